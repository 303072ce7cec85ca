"""The ``Drive`` interface the bench uses, and the values it returns.

One cycle of the bench in lockstep is ``set_target(u)`` -> ``sync()`` -> ``wait_feedback(timeout)``: the RPDO
carrying the set-point goes out first, the SYNC makes the drive apply it and answer with its TPDOs, and
:meth:`Drive.wait_feedback` returns the :class:`Feedback` answering that SYNC. Every exit path calls
:meth:`Drive.safe_stop` (the context manager does), which never raises.

:class:`drivers.cia402_master.Cia402Drive` is the CiA 402 implementation over python-can + canopen.
"""

from __future__ import annotations

import enum
import math
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from types import TracebackType
from typing import TypeVar

import can

from drivers.cia301 import NmtState
from drivers.cia402 import OperationMode, State402

__all__ = ["DISABLED_STATES", "DeviceInfo", "Drive", "Feedback", "StopPath", "StopReport"]

DriveT = TypeVar("DriveT", bound="Drive")

# states in which the power stage produces no torque: a stop is confirmed when the drive reports one of them
DISABLED_STATES = frozenset({
    State402.NOT_READY_TO_SWITCH_ON,
    State402.SWITCH_ON_DISABLED,
    State402.READY_TO_SWITCH_ON,
    State402.SWITCHED_ON,
    State402.FAULT,
})


@enum.unique
class StopPath(enum.StrEnum):
    """The channel through which a stop was commanded and its result read back, in the order they are tried."""

    PDO = "pdo"  # RPDO controlword, statusword from the TPDO answering the SYNC
    SDO = "sdo"  # SDO write of 0x6040, SDO read of 0x6041
    NMT_SDO = "nmt+sdo"  # NMT enter pre-operational (SDO works again, the drive's 0x6007 reaction), then SDO
    NMT_RESET = "nmt-reset"  # NMT reset node (application reset: power stage off), then an SDO read of 0x6041


@dataclass(frozen=True)
class StopReport:
    """What :meth:`Drive.safe_stop` reached, read back from the drive, not assumed.

    Attributes
    ----------
    commanded
        False when no drive ever answered ``connect()``: nothing was enabled, nothing needed stopping.
    confirmed
        The drive's statusword was read after the stop and shows a disabled power stage (:data:`DISABLED_STATES`).
    state, statusword
        The last state read back, or None when none could be read.
    via
        The path that reached the confirmed state, or None.
    attempts
        One line per path tried that did not confirm, saying why.
    faults
        Errors the drive reported that had not been raised when the stop began (e.g. an EMCY after the last
        trial): a run that otherwise succeeded must not hide them.
    """

    commanded: bool
    confirmed: bool
    state: State402 | None = None
    statusword: int | None = None
    via: StopPath | None = None
    attempts: tuple[str, ...] = ()
    faults: tuple[str, ...] = ()

    def describe(self, node_id: int) -> str:
        """One sentence for the user: the truth about the drive's state after the stop."""
        if not self.commanded:
            return f"node {node_id}: no drive answered connect(); nothing to stop"
        if self.confirmed and self.state is not None and self.statusword is not None:
            return (f"drive {node_id} confirmed disabled: {self.state.name} (statusword 0x{self.statusword:04X}, "
                    f"read via {self.via})")
        seen = (f"last state read {self.state.name} (statusword 0x{self.statusword:04X})"
                if self.state is not None and self.statusword is not None else "its state could not be read")
        tried = "; ".join(self.attempts) or "no stop path was available"
        return f"drive {node_id} NOT confirmed disabled: {seen}; tried: {tried}"

    def to_json(self) -> dict[str, object]:
        """The report as the ``drive_stop`` object of ``run --json``."""
        return {
            "commanded": self.commanded,
            "confirmed": self.confirmed,
            "state": self.state.name if self.state is not None else None,
            "statusword": self.statusword,
            "via": str(self.via) if self.via is not None else None,
            "attempts": list(self.attempts),
            "faults": list(self.faults),
        }


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
    demand
        The demand echo (``drive.demand_echo``): 0x606B (CSV, PV) divided by ``DriveConfig.velocity_scale``, or
        0x6074 (CST) divided by ``DriveConfig.torque_scale`` -- the target the drive latched at the SYNC this set
        answers, in the units of :meth:`Drive.set_target`'s return; NaN: not mapped.
    """

    cycle: int
    statusword: int
    state: State402
    velocity: float
    torque: float
    position: int
    timestamp: float
    demand: float = math.nan


@dataclass(frozen=True)
class DeviceInfo:
    """What :meth:`Drive.connect` learned about the drive (identity object 0x1018, 0x1000, 0x6502).

    Attributes
    ----------
    node_id
        The drive's CANopen node id.
    vendor_id, product_code, revision, serial
        The identity object 0x1018:1..4.
    device_type
        0x1000 (its low 16 bits: the device profile, 402 for a drive).
    nmt_state
        The NMT state the drive reported after connect (pre-operational).
    supported_modes
        The CiA 402 modes 0x6502 lists.
    """

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
        its boot-up and read its identity. Constructing a drive starts nothing (no thread, no frame): threads and
        listeners start here, and a connect that no drive answered leaves none behind."""

    @abstractmethod
    def configure(self, mode: OperationMode) -> None:
        """Configure PDOs, mode, cycle period (the drive's sample time, given once, when it was made), heartbeats
        and stop options over SDO, verify by reading back, then start the node (NMT operational)."""

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
        """The feedback answering the last SYNC, waiting at most ``timeout`` seconds.

        Raises ``FeedbackTimeoutError`` when no feedback answered in time: the drive keeps its last command (one
        unanswered SYNC is the caller's to judge). ``EmergencyError``, ``DriveFaultError``, ``HeartbeatLostError``,
        ``DriveNmtStateError`` and ``BadFrameError`` leave the drive commanded to stop."""

    @property
    def bad_frames(self) -> int:
        """Frames received from the drive that did not decode, so far (0 for a drive without a bus)."""
        return 0

    @abstractmethod
    def safe_stop(self) -> StopReport:
        """Never raises: quick stop, zero target, disable, escalating through the paths of :class:`StopPath`
        until the drive's own statusword confirms a disabled power stage; the report says what was reached."""

    @abstractmethod
    def close(self) -> None:
        """Release the bus resources the drive object holds (not the bus itself); safe on a never-connected
        drive and when called twice."""

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
