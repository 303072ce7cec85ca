"""Unit tests of ``plant_emulator/`` (rank 1): physics, the virtual drive's services, the embedded emulator."""
