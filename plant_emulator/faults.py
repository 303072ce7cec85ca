"""The emulator's side of fault injection: what each emulator kind of :mod:`drivers.faults` does to a drive.

:func:`emulator_actions` maps the kinds of :data:`drivers.faults.EMULATOR_KINDS` to actions on one
:class:`~plant_emulator.device.VirtualDrive`; a :class:`drivers.faults.FaultyBus` calls them at the SYNC their
injection starts. The bench passes them for the embedded emulator; ``plant-emulator --inject`` for its own drive.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from drivers.faults import Injection, InjectKind
from plant_emulator.application import FaultKind
from plant_emulator.device import VirtualDrive
from plant_emulator.physics.base import Plant

__all__ = ["InputGainDrift", "emulator_actions"]


class InputGainDrift:
    """A plant whose input gain is multiplied by ``factor``: the drift of ``b`` (first order) or of the torque or
    velocity gain (PMSM) beyond the design's uncertainty. Everything else is the wrapped plant's."""

    def __init__(self, plant: Plant, factor: float) -> None:
        self._plant = plant
        self.factor = float(factor)

    def step(self, u: np.ndarray, dt: float) -> np.ndarray:
        """The wrapped plant's step with ``factor * u``."""
        return self._plant.step(self.factor * np.asarray(u, dtype=float), dt)

    def __getattr__(self, name: str) -> Any:
        # Why delegate: the drive reads optional attributes (position, torque, limits, set_input_kind) by name.
        return getattr(self._plant, name)


def emulator_actions(drive: VirtualDrive) -> dict[InjectKind, Callable[[Injection], None]]:
    """The emulator kinds' actions on ``drive``."""

    def drift(injection: Injection) -> None:
        # one attribute swap: a physics tick reads the plant once, so it sees the old plant or the new one
        drive.physics.plant = InputGainDrift(drive.physics.plant, injection.factor)

    return {
        InjectKind.EMULATOR_KILL: lambda injection: drive.stop_responding(),
        InjectKind.EMCY_OVER_CURRENT: lambda injection: drive.inject_fault(FaultKind.OVER_CURRENT),
        InjectKind.EMCY_OVER_SPEED: lambda injection: drive.inject_fault(FaultKind.OVER_SPEED),
        InjectKind.HEARTBEAT_STOP: lambda injection: drive.node.nmt.stop_heartbeat(),
        InjectKind.DRIFT: drift,
    }
