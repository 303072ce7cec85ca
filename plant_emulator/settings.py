"""The ``emulator:`` section: how the virtual CiA 402 drive behaves (not what it drives -- that is ``plant:``)."""

from __future__ import annotations

from typing import Literal

from pydantic import Field

from drivers.realtime import RealtimeConfig
from drivers.schema import Section


class EmulatorRealtimeConfig(RealtimeConfig):
    """``emulator.realtime``: the host settings of the realtime clock plus its SYNC timing
    (:mod:`plant_emulator.sync_rx`, :meth:`plant_emulator.motion.AxisPhysics.run_realtime`)."""

    # seconds before (and after) the next SYNC is due during which the receive thread polls without blocking, so
    # a SYNC on time finds it awake; 0: it blocks in recv and the kernel wakes it (python-can's Notifier)
    sync_anticipation: float = Field(default=0.0002, ge=0, le=0.01)
    # the physics ticks this fraction of a period after the last SYNC, away from the SYNC's own handling (both take
    # the GIL and the drive's lock); None: on its own free-running grid
    tick_phase: float | None = Field(default=0.5, ge=0, lt=1)


class EmulatorConfig(Section):
    """Virtual drive settings.

    ``timing: lockstep`` advances the physics by one cycle period (0x1006, else ``sample_time``) per SYNC, so a
    run is deterministic and as fast as the bus allows; ``realtime`` runs the physics on the wall clock in its own
    thread, so a late or missing SYNC shows up as on hardware (stale feedback, SYNC-loss EMCY).
    """

    timing: Literal["lockstep", "realtime"] = "lockstep"
    seed: int = 0  # physics noise seed (the plant's own ``seed`` is added to it)
    eds: str | None = None  # object dictionary; None: the shipped configs/foilc_servo.eds
    # realtime: no SYNC for this many periods (0x1006) -> SYNC loss; 100 rides out a busy host's stalls
    # (docs/reliability.md, "Realtime 1 kHz") and still faults within 0.1 s of a real loss at 1 kHz
    sync_loss_cycles: float = Field(default=100.0, gt=1)
    torque_limit_fault_cycles: int = Field(default=200, ge=0)  # torque limited this long -> over-current; 0: never
    velocity_window: float = Field(default=10.0, ge=0)  # target reached window (drive velocity units), PV mode
    standstill_velocity: float = Field(default=1.0, ge=0)  # |v| below this ends a quick stop ramp (drive units)
    realtime: EmulatorRealtimeConfig = EmulatorRealtimeConfig()  # host settings and SYNC timing of the realtime clock
