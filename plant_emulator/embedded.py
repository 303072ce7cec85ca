"""The in-process emulator behind ``--emulator embedded``: a virtual drive on its own in-process CAN channel.

In lockstep (the emulator's default timing) the channel is python-can interface ``inprocess``
(:mod:`drivers.inprocess`): synchronous delivery in the sender's thread, simulated time, no thread on either end.
A realtime emulator ticks its physics on the wall clock in a thread, so it gets a python-can ``virtual`` channel.

>>> with EmbeddedEmulator.for_drive(plant, EmulatorConfig(), drive, sample_time=0.01) as emulator:  # doctest: +SKIP
...     bus = drivers.bus.open_bus(emulator.bus_config)   # the master's end of the same channel
"""

from __future__ import annotations

import uuid
from collections.abc import Sequence
from typing import Protocol

from drivers.bus import open_bus
from drivers.config import BusConfig, DriveConfig
from drivers.errors import InputError
from drivers.inprocess import INTERFACE as INPROCESS_INTERFACE
from drivers.timing import TimingMode
from plant_emulator.config import PlantConfig
from plant_emulator.device import VirtualDrive
from plant_emulator.physics import build_plant
from plant_emulator.settings import EmulatorConfig

__all__ = ["BenchDocument", "EmbeddedEmulator"]

CHANNEL_PREFIX = "foilc-hil-embedded"


class BenchDocument(Protocol):
    """The parts of the bench's whole config (``foilc_hil.config.Config``, layer 3) the emulator reads."""

    @property
    def plant(self) -> PlantConfig: ...

    @property
    def emulator(self) -> EmulatorConfig: ...

    @property
    def drive(self) -> DriveConfig: ...

    @property
    def sample_time(self) -> float: ...


class EmbeddedEmulator:
    """One or several :class:`~plant_emulator.device.VirtualDrive` on one channel, as a context manager.

    Parameters
    ----------
    plant
        The ``plant:`` section (the physics).
    settings
        The ``emulator:`` section.
    node_id
        The drive's node id (the bench's ``drive.node_id``), or several: one virtual drive per node id, all on the
        one channel, each answering every SYNC (the drive of the ``k``-th node id has the physics seed
        ``plant.seed + settings.seed + k``, so the first is the single-node emulator's).
    sample_time
        Seconds per cycle until the master writes 0x1006.
    velocity_scale, torque_scale
        Plant units -> drive units; pass the bench's ``drive.velocity_scale`` / ``drive.torque_scale`` so both
        ends agree (None: the drive's defaults, see :class:`VirtualDrive`).
    channel
        The channel name; default: a fresh unique name.
    threaded
        Use a python-can ``virtual`` channel (Notifier threads, the wall clock) in lockstep too. A bus wrapper on
        the master's side (:class:`drivers.faults.FaultyBus`, the bench's ``inject:``) needs it: it sees frames
        through the wrapped bus's ``send`` and ``recv``, while the in-process channel hands them straight to the
        receiving end's listeners.

    Notes
    -----
    The seed of the physics is ``plant.seed + settings.seed``. In lockstep the drive runs in the threads that
    send to it (the master's); in realtime in canopen's notifier thread of its own ``virtual`` bus and a physics
    thread. :meth:`close` stops the drives and shuts their buses down. Each drive has its own end of the channel
    (a :class:`~plant_emulator.device.VirtualDrive` takes its bus over); the channel is still the one bus.
    Build it from the bench's whole config with :meth:`from_config`, or from its sections with :meth:`for_drive`.
    """

    def __init__(
        self,
        plant: PlantConfig,
        settings: EmulatorConfig,
        *,
        node_id: int | Sequence[int],
        sample_time: float,
        velocity_scale: float | None = None,
        torque_scale: float | None = None,
        channel: str | None = None,
        threaded: bool = False,
    ) -> None:
        self.channel = channel if channel is not None else f"{CHANNEL_PREFIX}-{uuid.uuid4().hex}"
        self.threaded = threaded
        node_ids = (node_id,) if isinstance(node_id, int) else tuple(node_id)
        if not node_ids or len(set(node_ids)) != len(node_ids):
            raise InputError(f"node ids must be distinct and at least one, got {list(node_ids)}")
        self.drives = tuple(
            VirtualDrive(
                build_plant(plant, seed=plant.seed + settings.seed + k),
                node_id=node,
                cycle_period=sample_time,
                settings=settings,
                velocity_scale=velocity_scale,
                torque_scale=torque_scale,
            )
            for k, node in enumerate(node_ids)
        )
        self.drive = self.drives[0]
        self._started = False

    @classmethod
    def for_drive(
        cls,
        plant: PlantConfig,
        settings: EmulatorConfig,
        drive: DriveConfig,
        *,
        sample_time: float,
        channel: str | None = None,
        threaded: bool = False,
    ) -> EmbeddedEmulator:
        """The emulator matching the bench's ``drive:`` section (node id, velocity and torque scales)."""
        return cls(
            plant,
            settings,
            node_id=drive.node_id,
            sample_time=sample_time,
            velocity_scale=drive.velocity_scale,
            torque_scale=drive.torque_scale,
            channel=channel,
            threaded=threaded,
        )

    @classmethod
    def from_config(cls, config: BenchDocument, *, channel: str | None = None,
                    threaded: bool = False) -> EmbeddedEmulator:
        """The emulator for the bench's whole config: its ``plant``, ``emulator``, ``drive`` and ``sample_time``."""
        return cls.for_drive(config.plant, config.emulator, config.drive, sample_time=config.sample_time,
                             channel=channel, threaded=threaded)

    @property
    def device(self) -> VirtualDrive:
        """The virtual drive (same as :attr:`drive`)."""
        return self.drive

    @property
    def bus_config(self) -> BusConfig:
        """Where the master connects: ``inprocess`` (lockstep) or ``virtual`` (realtime, or :attr:`threaded`), on this
        emulator's channel."""
        wall_clock = self.threaded or self.drive.timing is TimingMode.REALTIME
        return BusConfig(interface="virtual" if wall_clock else INPROCESS_INTERFACE, channel=self.channel)

    def by_node(self, node_id: int) -> VirtualDrive:
        """The virtual drive with ``node_id``; KeyError when none has it."""
        for drive in self.drives:
            if drive.node_id == node_id:
                return drive
        raise KeyError(node_id)

    def begin_trial(self, trial: int) -> None:
        """Start trial ``trial`` of every drive's physics (see :meth:`VirtualDrive.begin_trial`)."""
        for drive in self.drives:
            drive.begin_trial(trial)

    def start(self) -> EmbeddedEmulator:
        """Open each drive's end of the channel and boot the drives (boot-up, pre-operational)."""
        if not self._started:
            self._started = True
            try:
                for drive in self.drives:
                    drive.start(open_bus(self.bus_config))
            except BaseException:
                self.close()
                raise
        return self

    def close(self) -> None:
        """Stop the drives and shut their buses down."""
        if self._started:
            for drive in self.drives:
                drive.stop()
            self._started = False

    def __enter__(self) -> EmbeddedEmulator:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()
