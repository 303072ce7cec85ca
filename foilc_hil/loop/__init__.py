"""The trial loop: bench over CAN, scheduler, safety, the simulated drive."""
