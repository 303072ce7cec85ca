"""How a bench's clock is driven: :class:`TimingMode`, one value for both ends of the bus.

The master's loop (``bench.mode``) and the virtual drive (``emulator.timing``) each run in one of these modes; the
enum lives here, below both, so the loop names it without importing the emulator (``plant_emulator.device``
re-exports it under its old name).
"""

from __future__ import annotations

from enum import StrEnum

__all__ = ["TimingMode"]


class TimingMode(StrEnum):
    """How the physics clock is driven."""

    LOCKSTEP = "lockstep"  # one cycle period per SYNC: deterministic, as fast as the bus allows
    REALTIME = "realtime"  # wall clock in its own thread: late/missing SYNC look as on hardware
