"""The in-process emulator behind ``--emulator embedded``: a virtual drive on its own ``virtual`` CAN channel.

>>> with EmbeddedEmulator(plant_cfg, EmulatorConfig(), node_id=1, sample_time=0.01) as emulator:  # doctest: +SKIP
...     bus = drivers.bus.open_bus(emulator.bus_config)   # the master's end of the same channel
"""

from __future__ import annotations

import uuid

import can

from drivers.config import BusConfig, DriveConfig
from plant_emulator.config import PlantConfig
from plant_emulator.device import VirtualDrive
from plant_emulator.physics import build_plant
from plant_emulator.settings import EmulatorConfig

__all__ = ["EmbeddedEmulator"]

CHANNEL_PREFIX = "foilc-hil-embedded"


class EmbeddedEmulator:
    """A :class:`~plant_emulator.device.VirtualDrive` on a fresh, unique ``virtual`` channel, as a context manager.

    Parameters
    ----------
    plant
        The ``plant:`` section (the physics).
    settings
        The ``emulator:`` section.
    node_id
        The drive's node id (the bench's ``drive.node_id``).
    sample_time
        Seconds per cycle until the master writes 0x1006.
    velocity_scale, torque_scale
        Plant units -> drive units; pass the bench's ``drive.velocity_scale`` / ``drive.torque_scale`` so both
        ends agree (None: the drive's defaults, see :class:`VirtualDrive`).

    Notes
    -----
    The seed of the physics is ``plant.seed + settings.seed``. The drive runs in canopen's notifier thread of
    its own bus (and, in realtime mode, a physics thread); :meth:`close` stops them and shuts its bus down.
    """

    def __init__(
        self,
        plant: PlantConfig,
        settings: EmulatorConfig,
        *,
        node_id: int,
        sample_time: float,
        velocity_scale: float | None = None,
        torque_scale: float | None = None,
    ) -> None:
        self.channel = f"{CHANNEL_PREFIX}-{uuid.uuid4().hex}"
        self.drive = VirtualDrive(
            build_plant(plant, seed=plant.seed + settings.seed),
            node_id=node_id,
            cycle_period=sample_time,
            settings=settings,
            velocity_scale=velocity_scale,
            torque_scale=torque_scale,
        )
        self._started = False

    @classmethod
    def for_drive(
        cls, plant: PlantConfig, settings: EmulatorConfig, drive: DriveConfig, *, sample_time: float
    ) -> EmbeddedEmulator:
        """The emulator matching the bench's ``drive:`` section (node id, velocity and torque scales)."""
        return cls(
            plant,
            settings,
            node_id=drive.node_id,
            sample_time=sample_time,
            velocity_scale=drive.velocity_scale,
            torque_scale=drive.torque_scale,
        )

    @property
    def bus_config(self) -> BusConfig:
        """Where the master connects: ``BusConfig(interface="virtual", channel=<this emulator's channel>)``."""
        return BusConfig(interface="virtual", channel=self.channel)

    def start(self) -> EmbeddedEmulator:
        """Open the drive's end of the channel and boot the drive (boot-up, pre-operational)."""
        if not self._started:
            self.drive.start(can.Bus(interface="virtual", channel=self.channel))
            self._started = True
        return self

    def close(self) -> None:
        """Stop the drive and shut its bus down."""
        if self._started:
            self.drive.stop()
            self._started = False

    def __enter__(self) -> EmbeddedEmulator:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()
