"""Config sections owned by the CAN side: the bus and the drive under control."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, field_validator

from drivers.cia402 import OperationMode
from drivers.schema import Section

_OPERATION_MODES = {
    "csv": OperationMode.CYCLIC_SYNC_VELOCITY,
    "cst": OperationMode.CYCLIC_SYNC_TORQUE,
    "pv": OperationMode.PROFILE_VELOCITY,
}


class BusConfig(Section):
    """A python-can bus: ``can.Bus(interface=..., channel=..., bitrate=...)``.

    ``interface: embedded`` runs the plant emulator in-process on a ``virtual`` bus (the default where no bus is
    given, so every command works with no CAN hardware).
    """

    interface: str = "embedded"
    channel: str = "foilc-hil"
    bitrate: int | None = Field(default=None, gt=0)  # None: 1 Mbit/s for the bus-load check of run
    # the largest worst-case bus load (fraction of the bit rate) run accepts, computed before it starts
    load_limit: float = Field(default=0.7, gt=0, le=1)
    receive_own_messages: bool = False

    @field_validator("interface")
    @classmethod
    def _interface_named(cls, value: str) -> str:
        if not value.strip():
            raise ValueError("must name a python-can interface, e.g. socketcan, virtual, udp_multicast")
        return value


class DriveConfig(Section):
    """The CiA 402 drive: node, mode, limits, timing and supervision."""

    node_id: int = Field(default=1, ge=1, le=127)
    mode: Literal["csv", "cst", "pv"] = "csv"
    eds: str | None = None  # object dictionary of the drive; None: the shipped configs/foilc_servo.eds
    velocity_limit: float = Field(default=3000.0, gt=0)  # |target velocity| clamp, in velocity units (rpm)
    torque_limit: float = Field(default=1000.0, gt=0)  # |target torque| clamp, per mille of rated torque
    # Drive velocity counts (0x60FF/0x606C) per plant output unit. The shipped EDS counts 0.001 rpm (object
    # 0x2000), so 1000 makes the plant unit rpm; set 1 for a drive that counts whole rpm.
    velocity_scale: float = Field(default=1000.0, gt=0)
    torque_scale: float = Field(default=1.0, gt=0)  # plant input unit -> drive torque unit (0x6071)
    # the plant units after the scales above: axis labels of reports, signal units of the DBC (commission info --dbc)
    velocity_unit: str = Field(default="rpm", min_length=1, max_length=32)
    torque_unit: str = Field(default="permille", min_length=1, max_length=32)  # of rated torque (CiA 402)
    heartbeat_producer_ms: int = Field(default=100, ge=0, le=65535)  # the drive's 0x1017
    heartbeat_consumer_ms: int = Field(default=500, ge=0, le=65535)  # the drive's 0x1016:01, watching the master
    master_node_id: int = Field(default=127, ge=1, le=127)  # the id whose heartbeat the drive consumes
    heartbeat_timeout_factor: float = Field(default=3.0, gt=1)  # master declares loss after factor x 0x1017
    sdo_timeout: float = Field(default=0.5, gt=0)  # seconds
    state_timeout: float = Field(default=2.0, gt=0)  # seconds per 402 transition
    quick_stop_option: int = Field(default=2, ge=0, le=8)  # 0x605A
    abort_connection_option: int = Field(default=3, ge=0, le=3)  # 0x6007
    # map the mode's demand object (0x606B in CSV/PV, 0x6074 in CST) into a TPDO and count every sample whose echo
    # is not the command the bench knows the drive latched; off by default: it can cost a TPDO per cycle (bus load).
    # strict: a YAML 1, 3 or "yes" is a typo here, not a yes
    demand_echo: bool = Field(default=False, strict=True)

    @property
    def operation_mode(self) -> OperationMode:
        """The CiA 402 mode (0x6060) ``mode`` names: the one ``run`` configures and ``commission enable`` checks."""
        return _OPERATION_MODES[self.mode]
