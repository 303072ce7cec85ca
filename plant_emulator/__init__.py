"""Plant physics (shared by offline simulation and the emulator) and a virtual CiA 402 servo drive."""
