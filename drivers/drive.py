"""The ``Drive`` interface the bench uses, and the values it returns.

One cycle of the bench in lockstep is ``set_target(u)`` -> ``sync()`` -> ``wait_feedback(timeout)``: the RPDO
carrying the set-point goes out first, the SYNC makes the drive apply it and answer with its TPDOs, and
:meth:`Drive.wait_feedback` returns the :class:`Feedback` answering that SYNC. Every exit path calls
:meth:`Drive.safe_stop` (the context manager does), which never raises.

:class:`drivers.cia402_master.Cia402Drive` is the CiA 402 implementation over python-can + canopen.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from types import TracebackType
from typing import TypeVar

import can

from drivers.cia301 import NmtState
from drivers.cia402 import OperationMode, State402

__all__ = ["DeviceInfo", "Drive", "Feedback"]

DriveT = TypeVar("DriveT", bound="Drive")


@dataclass(frozen=True, slots=True)
class Feedback:
    """The drive's answer to one SYNC (its TPDO set), in plant units.

    Attributes
    ----------
    cycle
        Master's SYNC counter this feedback answers (the value :meth:`Drive.sync` returned).
    statusword
        0x6041.
    state
        The CiA 402 state the statusword shows.
    velocity
        0x606C divided by ``DriveConfig.velocity_scale``.
    torque
        0x6077 divided by ``DriveConfig.torque_scale``.
    position
        0x6064, raw increments.
    timestamp
        ``time.monotonic()`` when the last TPDO of the set was received.
    """

    cycle: int
    statusword: int
    state: State402
    velocity: float
    torque: float
    position: int
    timestamp: float


@dataclass(frozen=True)
class DeviceInfo:
    """What :meth:`Drive.connect` learned about the drive (identity object 0x1018, 0x1000, 0x6502)."""

    node_id: int
    vendor_id: int
    product_code: int
    revision: int
    serial: int
    device_type: int
    nmt_state: NmtState
    supported_modes: tuple[OperationMode, ...]


class Drive(ABC):
    """A servo drive the bench commands cyclically. Methods are called from one control thread."""

    @abstractmethod
    def connect(self) -> DeviceInfo:
        """Bring the drive's communication to a known state (NMT reset communication, pre-operational), wait for
        its boot-up and read its identity."""

    @abstractmethod
    def configure(self, mode: OperationMode, cycle_period: float) -> None:
        """Configure PDOs, mode, cycle period, heartbeats and stop options over SDO, verify by reading back, then
        start the node (NMT operational)."""

    @abstractmethod
    def enable(self) -> None:
        """Walk the CiA 402 state machine to OPERATION_ENABLED; raises ``StateTransitionError`` naming where it
        stuck."""

    @abstractmethod
    def disable(self) -> None:
        """Disable voltage: to SWITCH_ON_DISABLED from any state (a faulted drive stays in FAULT)."""

    @abstractmethod
    def quick_stop(self) -> None:
        """Command quick stop; returns when the drive is in QUICK_STOP_ACTIVE or SWITCH_ON_DISABLED."""

    @abstractmethod
    def fault_reset(self) -> None:
        """Clear a fault (rising edge on controlword bit 7), restoring communication first after a heartbeat
        fault."""

    @abstractmethod
    def set_target(self, value: float) -> float:
        """Send the set-point (plant units) with the current controlword; return the value actually sent after
        clamping and quantisation. Never uses SDO."""

    @abstractmethod
    def sync(self) -> int:
        """Send one SYNC; return its cycle counter."""

    @abstractmethod
    def wait_feedback(self, timeout: float) -> Feedback:
        """The feedback answering the last SYNC. Raises ``FeedbackTimeoutError``, ``EmergencyError``,
        ``DriveFaultError``, ``HeartbeatLostError`` or ``ProtocolError``; each leaves the drive commanded to stop."""

    @abstractmethod
    def safe_stop(self) -> None:
        """Best effort, never raises: quick stop, zero target, disable."""

    @abstractmethod
    def close(self) -> None:
        """Release the bus resources the drive object holds (not the bus itself)."""

    @abstractmethod
    def add_frame_listener(self, listener: Callable[[can.Message, str], None]) -> None:
        """Call ``listener(message, "tx" | "rx")`` for every frame on the bus from now on."""

    def __enter__(self: DriveT) -> DriveT:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        traceback: TracebackType | None,
    ) -> None:
        try:
            self.safe_stop()
        finally:
            self.close()
