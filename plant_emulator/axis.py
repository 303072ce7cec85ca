"""The drive's view of the motion, shared by the CiA 402 application and the physics tick (data only)."""

from __future__ import annotations

import math
from dataclasses import dataclass

__all__ = ["Axis", "Units", "toward"]


@dataclass
class Axis:
    """Command, internal ramps and feedback, in drive units (counts)."""

    velocity: float = 0.0  # actual velocity, counts of 0x606C
    torque: float = 0.0  # actual torque, per mille
    position: float = 0.0  # actual position, counts of 0x6064
    profile_velocity: float = 0.0  # PV mode: the ramped internal set-point
    ramp_velocity: float = 0.0  # quick stop ramp set-point
    ramp_zero_time: float = 0.0  # s since the quick stop ramp reached zero
    torque_limited_cycles: int = 0
    internal_limit: bool = False
    cycles: int = 0

    def start_ramp(self) -> None:
        """A quick stop begins: the ramp starts from the present velocity."""
        self.ramp_velocity = self.velocity
        self.ramp_zero_time = 0.0


@dataclass(frozen=True)
class Units:
    """Plant units <-> drive units, as the master's ``drive.velocity_scale`` / ``drive.torque_scale`` convert.

    Attributes
    ----------
    velocity_scale
        Counts of 0x60FF / 0x606C per plant velocity unit.
    torque_scale
        Per mille of rated torque per plant torque unit.
    """

    velocity_scale: float = 1.0
    torque_scale: float = 1.0

    def counts(self, plant_units: float) -> float:
        """Plant velocity units -> counts of 0x60FF/0x606C."""
        return plant_units * self.velocity_scale

    def plant_velocity(self, counts: float) -> float:
        """Counts of 0x60FF -> plant velocity units."""
        return counts / self.velocity_scale

    def plant_torque(self, per_mille: float) -> float:
        """Per mille of rated torque (0x6071) -> plant torque units."""
        return per_mille / self.torque_scale


def toward(value: float, target: float, max_step: float) -> float:
    """Move ``value`` toward ``target`` by at most ``max_step``."""
    if abs(target - value) <= max_step:
        return target
    return value + math.copysign(max_step, target - value)
