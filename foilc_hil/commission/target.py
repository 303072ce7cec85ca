"""Where commissioning talks to: a python-can bus given by ``--bus``, or the embedded emulator.

``--bus INTERFACE:CHANNEL`` opens that bus with :func:`drivers.bus.open_bus`. Without it (``--emulator embedded``,
the default), :class:`CommissionTarget` starts one :class:`plant_emulator.embedded.EmbeddedEmulator` per emulated
node id, all on one private in-process channel (unique per process), and opens the master's side of that channel,
so every command works on a fresh machine. The emulated drives take their plant, physics seed and timing from the config
(``plant:``, ``emulator:``; a config that names no plant gets the default PMSM axis) and the same unit scales as
the master (``drive.velocity_scale`` / ``drive.torque_scale``), as ``foilc-hil run --emulator embedded`` does.
"""

from __future__ import annotations

import uuid
from collections.abc import Sequence
from contextlib import ExitStack
from dataclasses import dataclass, field
from types import TracebackType
from typing import TYPE_CHECKING, Any

import can

from drivers.bus import open_bus
from drivers.cia301 import check_node_id
from drivers.config import BusConfig
from foilc_hil.errors import InputError, ProtocolError

if TYPE_CHECKING:
    from foilc_hil.config import Config
    from plant_emulator.device import VirtualDrive

__all__ = ["CommissionTarget", "PerNodeResult", "parse_node_list"]


@dataclass(frozen=True)
class PerNodeResult:
    """A commissioning action on several nodes (``--node-id 1,2,3,4``): each node's own document, in node order."""

    action: str
    documents: tuple[dict[str, Any], ...]

    def to_json(self) -> dict[str, Any]:
        return {"action": self.action, "nodes": list(self.documents)}


def parse_node_list(text: str, *, option: str) -> tuple[int, ...]:
    """``"1,5,9"`` or ``"1-4,9"`` -> node ids; :class:`InputError` naming ``option`` for anything else."""
    nodes: list[int] = []
    for part in text.split(","):
        part = part.strip()
        if not part:
            continue
        low_text, dash, high_text = part.partition("-")
        try:
            low = int(low_text, 0)
            high = int(high_text, 0) if dash else low
        except ValueError:
            raise InputError(f"{option}: {part!r} is not a node id or a range like 1-127") from None
        if low > high:
            raise InputError(f"{option}: range {part!r} is empty (low > high)")
        try:
            check_node_id(low)
            check_node_id(high)
        except ProtocolError as exc:
            raise InputError(f"{option}: {exc}") from None
        nodes.extend(range(low, high + 1))
    if not nodes:
        raise InputError(f"{option}: no node ids given")
    return tuple(sorted(set(nodes)))


@dataclass
class CommissionTarget:
    """A bus to commission on, owning the emulated drives when there is no real one.

    Parameters
    ----------
    config
        The resolved config (``drive:`` and ``sample_time`` for the master; ``plant:``/``emulator:`` for the
        embedded emulator).
    bus
        The ``--bus`` settings; ``None`` or ``interface: embedded``: the embedded emulator.
    emulated_nodes
        Node ids of the emulated drives (default: ``config.drive.node_id``). Ignored on a real bus.
    emulator_config
        The config whose ``plant:``/``emulator:`` the embedded drives run (default: ``config``).

    Use as a context manager; :attr:`bus` is the master's python-can bus while open.
    """

    config: Config
    bus_config: BusConfig | None = None
    emulated_nodes: Sequence[int] = ()
    emulator_config: Config | None = None
    drives: list[VirtualDrive] = field(default_factory=list)  # the emulated drives (embedded only)
    _bus: can.BusABC | None = None
    _channel: str = ""
    _stack: ExitStack = field(default_factory=ExitStack)

    @property
    def embedded(self) -> bool:
        """True when the commands talk to the in-process emulator."""
        return self.bus_config is None or self.bus_config.interface == "embedded"

    @property
    def bus(self) -> can.BusABC:
        """The master's bus (only while the target is open)."""
        if self._bus is None:
            raise RuntimeError("the commissioning target is not open")
        return self._bus

    @property
    def description(self) -> str:
        """``interface:channel`` of the bus; for the emulator, ``embedded`` and how many drives it emulates (its
        channel's name is an internal, per-process unique one: nothing a user can join)."""
        if self.embedded:
            return f"embedded ({len(self.drives)} emulated drive(s), in this process)"
        assert self.bus_config is not None
        return f"{self.bus_config.interface}:{self.bus_config.channel}"

    def __enter__(self) -> CommissionTarget:
        try:
            if self.embedded:
                self._channel = f"foilc-commission-{uuid.uuid4()}"
                bus_cfg = self._start_emulators()  # the emulators' channel
            else:
                assert self.bus_config is not None
                self._channel = self.bus_config.channel
                bus_cfg = self.bus_config
            bus = open_bus(bus_cfg)
            self._stack.callback(bus.shutdown)
            self._bus = bus
        except BaseException:
            self._stack.close()
            raise
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        self._bus = None
        self._stack.close()

    def _start_emulators(self) -> BusConfig:
        from plant_emulator.embedded import EmbeddedEmulator

        source = self.emulator_config if self.emulator_config is not None else self.config
        nodes = tuple(self.emulated_nodes) or (self.config.drive.node_id,)
        plant_cfg = source.plant
        if plant_cfg.model == "first_order" and all(
            value is None for value in (plant_cfg.a, plant_cfg.b, plant_cfg.num, plant_cfg.den)
        ):
            # a config that names no plant: emulate the default PMSM axis, as the test harness does
            plant_cfg = plant_cfg.model_copy(update={"model": "pmsm"})
        for node_id in nodes:
            emulator = EmbeddedEmulator(
                plant_cfg,
                source.emulator,
                node_id=node_id,
                sample_time=self.config.sample_time,
                velocity_scale=self.config.drive.velocity_scale,
                torque_scale=self.config.drive.torque_scale,
                channel=self._channel,
            )
            self._stack.enter_context(emulator)
            self.drives.append(emulator.drive)
        return emulator.bus_config
