"""A virtual CiA 402 servo drive: canopen's ``LocalNode`` plus everything a real drive adds to it.

What canopen gives (and is used as is): the object dictionary from the EDS, the SDO server (expedited and
segmented transfers, abort codes for unknown objects / sub-indices / read-only objects / length mismatch), the
NMT slave with its heartbeat producer (0x1017), and the EMCY producer.

What this module adds, because ``LocalNode`` has none of it:

- a SYNC consumer (``LocalNode`` does not subscribe to SYNC at all);
- a PDO engine driven by the mapping in the OD (0x1400/0x1600 RPDO, 0x1800/0x1A00 TPDO), rebuilt whenever the
  master rewrites it over SDO, with transmission types 0 (acyclic synchronous), 1..240 (every n-th SYNC) and
  254/255 (event-driven; the event timer 0x18xx:05 is honoured, the inhibit time is not). The SYNC counter byte
  and the SYNC start value (0x18xx:06) are ignored: every SYNC counts;
- SDO write validation (range from the EDS limits, PDO mapping checks, supported modes) -- through
  ``LocalNode``'s write callbacks, which run before the value is stored and may raise ``SdoAbortedError``;
- a post-write hook (``_EmulatedNode.set_data``): canopen calls write callbacks *before* storing, but a PDO
  remap must be rebuilt *after* the new value is in the store, so ``set_data`` is overridden narrowly;
- the NMT reset services (canopen's ``NmtSlave`` only changes its state byte to 0 and stops there): reset node
  restores every object to its EDS default, reset communication only 0x1000..0x1FFF; both send the boot-up
  message and enter pre-operational. SDO requests are not answered in *stopped* (canopen would answer them);
- the CiA 402 power state machine (:mod:`plant_emulator.state_machine`), modes CSV / CST / PV, quick stop,
  faults with EMCY + 0x603F + 0x1001, the heartbeat consumer (0x1016) and 0x6007 abort-connection reactions;
- the physics: each cycle advances the plant from :mod:`plant_emulator.physics`.

Cycle order at SYNC *n* (lockstep; the one-cycle transport delay of a SYNC-driven loop, errata 6):

1. advance the physics by one cycle period with the command that was active during cycle *n-1*;
2. latch the synchronous RPDO values received since SYNC *n-1*: they become the active command;
3. sample the feedback and send the synchronous TPDOs.

So a target sent before SYNC *n* first moves the axis during cycle *n*, and its effect is first reported in the
TPDO of SYNC *n+1*. In realtime mode step 1 runs on the wall clock in its own thread (one cycle period per
tick, whether or not SYNC came); steps 2 and 3 run on SYNC.

Units: 0x60FF / 0x606C are counts of the EDS's velocity unit (0.001 rpm in the shipped EDS, 0x2000 = counts per
rpm); 0x6071 / 0x6077 are per mille of rated torque; 0x6064 is encoder increments (the PMSM's resolver counts).
The plant works in its own units; ``velocity_scale`` (counts per plant velocity unit) and ``torque_scale`` (per
mille per plant torque unit) convert, exactly as the master's ``drive.velocity_scale`` / ``drive.torque_scale``
do. A PMSM plant (rpm, N m) defaults to 0x2000 counts per rpm and ``1000 / rated_torque``.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import StrEnum
from pathlib import Path
from typing import Any

import can
import canopen
import numpy as np
from canopen import objectdictionary as cod
from canopen.sdo import SdoAbortedError

from drivers.cia301 import (
    SYNC_COB_ID,
    EmcyCode,
    ErrorRegister,
    FunctionCode,
    NmtCommand,
    NmtState,
    SdoAbortCode,
    check_node_id,
    cob_id,
)
from drivers.cia402 import (
    AbortConnectionOption,
    Command402,
    Controlword,
    Obj,
    OperationMode,
    QuickStopOption,
    State402,
)
from drivers.od import DEFAULT_EDS, load_od
from foilc_hil.errors import EdsError, InputError
from plant_emulator.physics.base import Plant
from plant_emulator.settings import EmulatorConfig
from plant_emulator.state_machine import MotionKind, PowerStateMachine

__all__ = [
    "DEFAULT_EDS",
    "FaultKind",
    "TimingMode",
    "VirtualDrive",
    "load_object_dictionary",
]

logger = logging.getLogger(__name__)


PDO_INVALID = 1 << 31  # COB-ID bit 31: PDO does not exist / is not valid
PDO_COB_MASK = 0x7FF
PDO_MAX_BITS = 64
PDO_CHANNELS = 512  # 0x1400..0x15FF / 0x1800..0x19FF
SYNC_TYPE_MAX = 240
TRANS_ACYCLIC = 0
TRANS_EVENT_TYPES = (254, 255)
HEARTBEAT_CONSUMER_NODE_SHIFT = 16
QUICK_STOP_OPTION_MAX = 8  # 0x605A: 0..8 are defined by CiA 402-2
VELOCITY_RESOLUTION_INDEX = 0x2000  # manufacturer object of the shipped EDS: counts of 0x606C per rpm
NOTIFIER_CYCLE = 0.1  # s the notifier blocks in recv(): bounds how long stop() waits (canopen default 1 s)
MONITOR_PERIOD = 0.002  # s, resolution of the heartbeat consumer / SYNC-loss / event-timer supervision
RAMP_SETTLE_TIME = 3.0  # s a finished quick-stop ramp waits at most for the axis to come to rest
SUPPORTED_MODES = frozenset(int(m) for m in OperationMode)
_COMMUNICATION_AREA = range(0x1000, 0x2000)
_PDO_MAPPING_AREAS = (range(0x1600, 0x1600 + PDO_CHANNELS), range(0x1A00, 0x1A00 + PDO_CHANNELS))
_PDO_AREAS = (
    range(0x1400, 0x1400 + PDO_CHANNELS),
    range(0x1600, 0x1600 + PDO_CHANNELS),
    range(0x1800, 0x1800 + PDO_CHANNELS),
    range(0x1A00, 0x1A00 + PDO_CHANNELS),
)


class TimingMode(StrEnum):
    """How the physics clock is driven."""

    LOCKSTEP = "lockstep"  # one cycle period per SYNC: deterministic, as fast as the bus allows
    REALTIME = "realtime"  # wall clock in its own thread: late/missing SYNC look as on hardware


class FaultKind(StrEnum):
    """Faults the drive detects (and tests can inject)."""

    OVER_CURRENT = "over-current"
    OVER_SPEED = "over-speed"
    HEARTBEAT_LOSS = "heartbeat-loss"
    SYNC_LOSS = "sync-loss"
    NMT_LEFT_OPERATIONAL = "nmt-left-operational"
    GENERIC = "generic"


# fault -> (EMCY error code, error register bits besides "generic")
FAULT_CODES: dict[FaultKind, tuple[EmcyCode, int]] = {
    FaultKind.OVER_CURRENT: (EmcyCode.OVER_CURRENT, ErrorRegister.CURRENT),
    FaultKind.OVER_SPEED: (EmcyCode.OVER_SPEED, ErrorRegister.DEVICE_PROFILE),
    FaultKind.HEARTBEAT_LOSS: (EmcyCode.HEARTBEAT_LOSS, ErrorRegister.COMMUNICATION),
    FaultKind.SYNC_LOSS: (EmcyCode.SYNC_LOSS, ErrorRegister.COMMUNICATION),
    FaultKind.NMT_LEFT_OPERATIONAL: (EmcyCode.COMMUNICATION, ErrorRegister.COMMUNICATION),
    FaultKind.GENERIC: (EmcyCode.GENERIC, 0),
}
_COMMUNICATION_FAULTS = frozenset({FaultKind.HEARTBEAT_LOSS, FaultKind.SYNC_LOSS, FaultKind.NMT_LEFT_OPERATIONAL})
# the power stage may produce torque in these states: an abort-connection event must act on them
_POWERED_STATES = frozenset({State402.OPERATION_ENABLED, State402.QUICK_STOP_ACTIVE})


def load_object_dictionary(node_id: int, eds: str | Path | None = None) -> cod.ObjectDictionary:
    """The drive's object dictionary from ``eds`` (default: the shipped ``configs/foilc_servo.eds``).

    Raises
    ------
    foilc_hil.errors.EdsError
        If the file is missing or malformed, or lacks an object the drive needs.
    """
    od = load_od(eds, node_id)
    source = str(eds) if eds is not None else str(DEFAULT_EDS)
    for index in (Obj.TARGET_VELOCITY, Obj.VELOCITY_ACTUAL_VALUE, Obj.PRODUCER_HEARTBEAT_TIME):
        if index not in od:
            raise EdsError(f"lacks object 0x{int(index):04X} ({index.name.lower()})", source=source)
    return od


# --------------------------------------------------------------------------------------------------------------
# PDO engine


@dataclass(frozen=True)
class MappedObject:
    """One mapped entry of a PDO: where its bytes sit in the frame and in the store."""

    index: int
    subindex: int
    offset: int  # byte offset in the frame
    size: int  # bytes


@dataclass
class PdoChannel:
    """One RPDO or TPDO as the OD currently configures it."""

    number: int  # 1-based
    cob_id: int
    valid: bool
    transmission_type: int
    event_timer_ms: int
    entries: tuple[MappedObject, ...]
    length: int  # bytes
    sync_count: int = 0
    pending: bytes | None = None  # RPDO: received since the last SYNC, latched at the next
    last_sent: bytes | None = None  # TPDO: for acyclic / event-driven change detection
    last_sent_time: float = 0.0

    @property
    def synchronous(self) -> bool:
        """Transmission types 0..240 act on SYNC."""
        return self.transmission_type <= SYNC_TYPE_MAX


@dataclass
class _HeartbeatWatch:
    """One entry of the heartbeat consumer 0x1016."""

    node_id: int
    timeout: float  # s
    deadline: float | None = None  # None until the first heartbeat arrives (CiA 301: then the watch starts)


# --------------------------------------------------------------------------------------------------------------
# the node


class _EmulatedNode(canopen.LocalNode):
    """``LocalNode`` with a post-store hook.

    canopen runs write callbacks *before* storing (so they can veto with an SDO abort), but the PDO engine and
    the state machine must see the value *in* the store. This override is the only change to canopen's
    behaviour.
    """

    def __init__(self, node_id: int, od: cod.ObjectDictionary, after_write: Callable[[int, int], None]) -> None:
        super().__init__(node_id, od)
        self._after_write = after_write

    def set_data(self, index: int, subindex: int, data: bytes, check_writable: bool = False) -> None:
        super().set_data(index, subindex, data, check_writable=check_writable)
        self._after_write(index, subindex)


@dataclass
class _Axis:
    """The drive's view of the motion: command, internal ramps and feedback, in drive units (counts)."""

    velocity: float = 0.0  # actual velocity, counts of 0x606C
    torque: float = 0.0  # actual torque, per mille
    position: float = 0.0  # actual position, counts of 0x6064
    profile_velocity: float = 0.0  # PV mode: the ramped internal set-point
    ramp_velocity: float = 0.0  # quick stop ramp set-point
    ramp_zero_time: float = 0.0  # s since the quick stop ramp reached zero
    torque_limited_cycles: int = 0
    internal_limit: bool = False
    cycles: int = 0


@dataclass
class DriveSnapshot:
    """What the drive shows at one instant (for tests and the emulator's own log)."""

    nmt_state: NmtState
    state: State402
    statusword: int
    mode: int
    velocity: int
    torque: int
    position: int
    error_code: int
    error_register: int
    cycles: int
    plant_time: float
    plant_output: list[float] = field(default_factory=list)


class VirtualDrive:
    """A CiA 402 servo drive on a python-can bus, driving a simulated plant.

    Parameters
    ----------
    plant
        The physics (:func:`plant_emulator.physics.build_plant`); output 0 is the velocity. A PMSM axis
        (``model == "pmsm"``) is switched between velocity and torque input with ``set_input_kind``.
    node_id
        CANopen node id (1..127).
    cycle_period
        Seconds per cycle when 0x1006 is 0 (the master normally writes 0x1006 at start-up).
    settings
        The ``emulator:`` section.
    od
        The object dictionary; default: loaded from ``settings.eds`` or the shipped EDS.
    velocity_scale, torque_scale
        Plant units -> drive units (0x60FF/0x606C physical unit; per mille of rated torque).

    Notes
    -----
    Call :meth:`start` with a bus; the drive takes the bus over (``stop`` shuts it down). All CAN callbacks run
    in canopen's notifier thread; the realtime physics thread and the supervision thread share one lock.
    """

    def __init__(
        self,
        plant: Plant,
        *,
        node_id: int = 1,
        cycle_period: float = 0.01,
        settings: EmulatorConfig | None = None,
        od: cod.ObjectDictionary | None = None,
        velocity_scale: float | None = None,
        torque_scale: float | None = None,
    ) -> None:
        if plant.n_inputs != 1:
            raise InputError(f"the virtual drive drives a single-input plant; this one has {plant.n_inputs}")
        if not (cycle_period > 0 and math.isfinite(cycle_period)):
            raise InputError(f"cycle_period must be positive, got {cycle_period!r}")
        for name, value in (("velocity_scale", velocity_scale), ("torque_scale", torque_scale)):
            if value is not None and not (value > 0 and math.isfinite(value)):
                raise InputError(f"{name} must be positive, got {value!r}")
        self.settings = settings if settings is not None else EmulatorConfig()
        self.node_id = check_node_id(node_id)
        self.plant = plant
        self.timing = TimingMode(self.settings.timing)
        self._default_cycle_period = float(cycle_period)
        self._is_pmsm = hasattr(plant, "set_input_kind")
        od = od if od is not None else load_object_dictionary(self.node_id, self.settings.eds)
        self.od = od
        if velocity_scale is not None:
            self._velocity_scale = float(velocity_scale)
        elif self._is_pmsm and VELOCITY_RESOLUTION_INDEX in od:
            resolution = od[VELOCITY_RESOLUTION_INDEX]
            default = resolution.default if isinstance(resolution, cod.ODVariable) else None
            self._velocity_scale = float(default) if isinstance(default, (int, float)) and default > 0 else 1.0
        else:
            self._velocity_scale = 1.0
        rated_torque = getattr(plant, "rated_torque", None)
        if torque_scale is not None:
            self._torque_scale = float(torque_scale)
        elif rated_torque is not None:
            self._torque_scale = 1000.0 / float(rated_torque)  # N m -> per mille of rated torque
        else:
            self._torque_scale = 1.0
        self.node = _EmulatedNode(self.node_id, od, self._after_write)
        self.node.add_write_callback(self._validate_write)
        self._lock = threading.RLock()
        self.machine = PowerStateMachine()
        self._axis = _Axis()
        self._rpdos: dict[int, PdoChannel] = {}  # by COB-ID
        self._tpdos: list[PdoChannel] = []
        self._subscribed_rpdo_ids: set[int] = set()
        self._heartbeat_watches: dict[int, _HeartbeatWatch] = {}
        self._sync_cob_id = SYNC_COB_ID
        self._last_sync: float | None = None
        self._sync_lost = False
        self._latched_errors: list[EmcyCode] = []
        self._fault_reset_bit = False
        self._network: canopen.Network | None = None
        self._running = False
        self._alive = False  # False after stop_responding(): every handler returns at once
        self._threads: list[threading.Thread] = []
        self._stop_event = threading.Event()
        self.sync_count = 0
        self.emcy_log: list[tuple[int, int]] = []  # (code, register) as sent, for tests and the CLI
        self.trace: Callable[[DriveSnapshot], None] | None = None  # called after every cycle, if set
        self._reset_application()

    # ---------------------------------------------------------------------------------------------------------
    # life cycle

    def start(self, bus: can.BusABC) -> None:
        """Join ``bus`` (taken over: :meth:`stop` shuts it down), send the boot-up message, enter pre-operational."""
        if self._running:
            raise RuntimeError("the virtual drive is already running")
        network = canopen.Network(bus)
        network.NOTIFIER_CYCLE = NOTIFIER_CYCLE
        network.connect()
        self._network = network
        network[self.node_id] = self.node
        # Replace canopen's SDO and NMT subscriptions with gated ones (no SDO in stopped, NMT resets handled).
        network.unsubscribe(self.node.sdo.rx_cobid, self.node.sdo.on_request)
        network.unsubscribe(FunctionCode.NMT, self.node.nmt.on_command)
        network.subscribe(self.node.sdo.rx_cobid, self._on_sdo_request)
        network.subscribe(FunctionCode.NMT, self._on_nmt_command)
        self._alive = True
        self._running = True
        self._stop_event.clear()
        with self._lock:
            self._subscribe_sync()
            self._rebuild_pdos()
            self._rebuild_heartbeat_consumer()
            self._boot()
        self._start_thread(self._supervise, "drive-supervision")
        if self.timing is TimingMode.REALTIME:
            self._start_thread(self._realtime_physics, "drive-physics")

    def stop(self) -> None:
        """Stop the threads, the heartbeat and the network (the bus is shut down)."""
        if not self._running:
            return
        self._running = False
        self._stop_event.set()
        for thread in self._threads:
            thread.join(timeout=2.0)
        self._threads.clear()
        self.node.nmt.stop_heartbeat()
        if self._network is not None:
            self._network.disconnect()
            self._network = None

    def __enter__(self) -> VirtualDrive:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _start_thread(self, target: Callable[[], None], name: str) -> None:
        thread = threading.Thread(target=target, name=f"{name}-{self.node_id}", daemon=True)
        self._threads.append(thread)
        thread.start()

    # ---------------------------------------------------------------------------------------------------------
    # fault injection (tests and the bench's fault tests)

    def inject_fault(self, kind: FaultKind | str) -> None:
        """Raise fault ``kind`` as the drive would detect it (EMCY, 0x603F, 0x1001, state reaction)."""
        fault = FaultKind(kind)
        with self._lock:
            if fault in _COMMUNICATION_FAULTS:
                self._communication_abort(fault)
            else:
                self._raise_fault(fault)
            self._publish_status()
            self._send_event_tpdos()

    def begin_trial(self, trial: int) -> None:
        """Start trial ``trial`` (1-based) of the physics: ``plant.reset(trial)``.

        The plant returns to its initial condition and its trial-dependent parts (the disturbance from
        ``plant.disturbance.start_trial`` on, per-trial noise and drift) follow ``trial``. The bench calls this
        between trials of an embedded run, when the axis has settled; a real drive has no such hook, so a
        cross-process run keeps one continuous trial-1 physics.
        """
        with self._lock:
            self.plant.reset(trial)
            y = np.asarray(self.plant.output(), dtype=float).reshape(-1)
            axis = self._axis
            axis.velocity = self._counts(float(y[0]))
            axis.profile_velocity = axis.ramp_velocity = axis.velocity
            plant_position = getattr(self.plant, "position_counts", None)
            axis.position = float(plant_position) if plant_position is not None else 0.0
            self._put(Obj.VELOCITY_ACTUAL_VALUE, axis.velocity)
            self._put(Obj.POSITION_ACTUAL_VALUE, axis.position)

    def stop_responding(self) -> None:
        """Simulate the drive dying: no heartbeat, no SDO answers, no PDOs, no physics, from now on."""
        with self._lock:
            self._alive = False
            self.node.nmt.stop_heartbeat()

    def send_emcy(self, code: int, register: int | None = None, data: bytes = b"") -> None:
        """Send an EMCY frame with ``code`` (and ``register``, default: the present 0x1001) without a state change."""
        with self._lock:
            reg = self._get(Obj.ERROR_REGISTER) if register is None else int(register)
            self._emcy(int(code), reg, data)

    # ---------------------------------------------------------------------------------------------------------
    # read-only views

    @property
    def state(self) -> State402:
        """The present CiA 402 state."""
        return self.machine.state

    @property
    def nmt_state(self) -> NmtState:
        """The present NMT state."""
        return NmtState(self.node.nmt._state)  # canopen keeps the state byte private

    @property
    def cycle_period(self) -> float:
        """Seconds per cycle: 0x1006 (microseconds) when set, else the constructor's ``cycle_period``."""
        micros = self._get(Obj.COMMUNICATION_CYCLE_PERIOD) if Obj.COMMUNICATION_CYCLE_PERIOD in self.od else 0
        return micros * 1e-6 if micros > 0 else self._default_cycle_period

    def snapshot(self) -> DriveSnapshot:
        """The drive's present state and feedback."""
        with self._lock:
            return DriveSnapshot(
                nmt_state=self.nmt_state,
                state=self.machine.state,
                statusword=self._get(Obj.STATUSWORD),
                mode=self._get(Obj.MODES_OF_OPERATION_DISPLAY),
                velocity=self._get(Obj.VELOCITY_ACTUAL_VALUE),
                torque=self._get(Obj.TORQUE_ACTUAL_VALUE) if Obj.TORQUE_ACTUAL_VALUE in self.od else 0,
                position=self._get(Obj.POSITION_ACTUAL_VALUE) if Obj.POSITION_ACTUAL_VALUE in self.od else 0,
                error_code=self._get(Obj.ERROR_CODE) if Obj.ERROR_CODE in self.od else 0,
                error_register=self._get(Obj.ERROR_REGISTER),
                cycles=self._axis.cycles,
                plant_time=float(self.plant.time),
                plant_output=[float(v) for v in np.asarray(self.plant.output()).reshape(-1)],
            )

    # ---------------------------------------------------------------------------------------------------------
    # object dictionary access

    def _var(self, index: int, subindex: int) -> cod.ODVariable:
        obj = self.od[index]
        if isinstance(obj, cod.ODVariable):
            return obj
        return obj[subindex]

    def _get(self, index: int, subindex: int = 0) -> Any:
        var = self._var(index, subindex)
        return var.decode_raw(self.node.get_data(index, subindex))

    def _put(self, index: int, value: int | float, subindex: int = 0) -> None:
        """Store a value the drive itself produces (no callbacks: it is not a write from the bus)."""
        if index not in self.od:
            return
        var = self._var(index, subindex)
        if var.data_type in cod.INTEGER_TYPES:
            bits = len(var)
            low, high = ((-(1 << (bits - 1)), (1 << (bits - 1)) - 1) if var.data_type in cod.SIGNED_TYPES
                         else (0, (1 << bits) - 1))
            value = min(max(round(value), low), high)
        self.node.data_store.setdefault(index, {})[subindex] = var.encode_raw(value)

    def _reset_store(self, area: range | None) -> None:
        """Every object in ``area`` (all when None) back to its EDS value, pre-encoded in the store."""
        store = self.node.data_store
        for index in list(store):
            if area is None or index in area:
                del store[index]
        for index in list(self.od.indices):
            if area is not None and index not in area:
                continue
            obj = self.od[index]
            variables = [obj] if isinstance(obj, cod.ODVariable) else list(obj.values())
            for var in variables:
                initial = var.value if var.value is not None else var.default
                if initial is None or var.data_type not in var.STRUCT_TYPES:
                    continue
                store.setdefault(var.index, {})[var.subindex] = var.encode_raw(initial)

    # ---------------------------------------------------------------------------------------------------------
    # NMT

    def _boot(self) -> None:
        """Boot-up message, then pre-operational with the heartbeat producer of 0x1017 (canopen's NmtSlave)."""
        nmt = self.node.nmt
        nmt.stop_heartbeat()
        nmt.send_command(NmtCommand.RESET_NODE)  # state 0: canopen sends the boot-up frame
        nmt.send_command(NmtCommand.ENTER_PRE_OPERATIONAL)  # 0 -> 127 starts the heartbeat per 0x1017

    def _reset_application(self) -> None:
        self._reset_store(None)
        self.machine = PowerStateMachine(quick_stop_option=self._quick_stop_option())
        self.machine.power_on()
        self._latched_errors.clear()
        self._fault_reset_bit = False
        self._publish_status()

    def _on_nmt_command(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if not self._alive or len(data) < 2:
            return
        command, target = data[0], data[1]
        if target not in (0, self.node_id):
            return
        with self._lock:
            if command == NmtCommand.RESET_NODE:
                self._reset_application()
                self._after_reset()
            elif command == NmtCommand.RESET_COMMUNICATION:
                self._reset_store(_COMMUNICATION_AREA)
                self._after_reset()
            else:
                was_operational = self.nmt_state is NmtState.OPERATIONAL
                self.node.nmt.on_command(can_id, data, timestamp)
                if self.nmt_state is not NmtState.OPERATIONAL:
                    for channel in self._rpdos.values():
                        channel.pending = None
                    # Why: outside OPERATIONAL no RPDO reaches the drive, so a master could no longer stop it over
                    # PDO. CiA 402 drives apply the abort-connection reaction (0x6007) when the NMT state leaves
                    # OPERATIONAL (NMT stop or pre-operational, by anyone) while the power stage is on.
                    if was_operational and self.machine.state in _POWERED_STATES:
                        self._communication_abort(FaultKind.NMT_LEFT_OPERATIONAL)
                        self._publish_status()

    def _after_reset(self) -> None:
        self._subscribe_sync()
        self._rebuild_pdos()
        self._rebuild_heartbeat_consumer()
        self._last_sync = None
        self._sync_lost = False
        self._boot()

    def _on_sdo_request(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if not self._alive or self.nmt_state is NmtState.STOPPED:
            return  # CiA 301: no SDO in stopped
        with self._lock:
            self.node.sdo.on_request(can_id, data, timestamp)

    # ---------------------------------------------------------------------------------------------------------
    # SDO write validation (before store) and reaction (after store)

    def _validate_write(self, index: int, subindex: int, od: cod.ODVariable, data: bytes, **_: Any) -> None:
        value: int | float | None = None
        if od.data_type in cod.NUMBER_TYPES and od.data_type in od.STRUCT_TYPES:
            decoded = od.decode_raw(bytes(data))
            assert isinstance(decoded, (int, float))  # numeric types decode to numbers
            value = decoded
            if od.min is not None and value < od.min:
                raise SdoAbortedError(SdoAbortCode.VALUE_TOO_LOW)
            if od.max is not None and value > od.max:
                raise SdoAbortedError(SdoAbortCode.VALUE_TOO_HIGH)
        if index == Obj.MODES_OF_OPERATION and value not in SUPPORTED_MODES:
            raise SdoAbortedError(SdoAbortCode.INVALID_VALUE)
        if any(index in area for area in _PDO_MAPPING_AREAS) and isinstance(value, int):
            if subindex == 0:
                self._check_mapping_length(index, value)
            elif value != 0:
                self._check_mappable(index, value)
        if index == Obj.QUICK_STOP_OPTION and isinstance(value, int) and not 0 <= value <= QUICK_STOP_OPTION_MAX:
            raise SdoAbortedError(SdoAbortCode.INVALID_VALUE)

    def _check_mappable(self, mapping_index: int, entry: int) -> None:
        index, subindex, bits = entry >> 16, (entry >> 8) & 0xFF, entry & 0xFF
        if index not in self.od:
            raise SdoAbortedError(SdoAbortCode.NO_OBJECT)
        obj = self.od[index]
        if not isinstance(obj, cod.ODVariable):
            if subindex not in obj:
                raise SdoAbortedError(SdoAbortCode.NO_SUBINDEX)
            obj = obj[subindex]
        if not obj.pdo_mappable:
            raise SdoAbortedError(SdoAbortCode.CANNOT_MAP)
        is_rpdo = mapping_index < 0x1800
        if (is_rpdo and not obj.writable) or (not is_rpdo and not obj.readable):
            raise SdoAbortedError(SdoAbortCode.CANNOT_MAP)
        if bits != len(obj):
            raise SdoAbortedError(SdoAbortCode.GENERAL_PARAMETER)

    def _check_mapping_length(self, mapping_index: int, count: int) -> None:
        total = 0
        for sub in range(1, count + 1):
            try:
                entry = self._get(mapping_index, sub)
            except (KeyError, SdoAbortedError):
                raise SdoAbortedError(SdoAbortCode.NO_SUBINDEX) from None
            self._check_mappable(mapping_index, entry)
            total += entry & 0xFF
        if total > PDO_MAX_BITS:
            raise SdoAbortedError(SdoAbortCode.PDO_TOO_LONG)

    def _after_write(self, index: int, subindex: int) -> None:
        """React to a value now in the store (from SDO or from an RPDO)."""
        if index == Obj.CONTROLWORD:
            self._apply_controlword(self._get(Obj.CONTROLWORD))
        elif index == Obj.MODES_OF_OPERATION:
            self._apply_mode(self._get(Obj.MODES_OF_OPERATION))
        elif index == Obj.QUICK_STOP_OPTION:
            self.machine.quick_stop_option = self._quick_stop_option()
        elif index == Obj.COB_ID_SYNC:
            self._subscribe_sync()
        elif index == Obj.CONSUMER_HEARTBEAT_TIME:
            self._rebuild_heartbeat_consumer()
        elif any(index in area for area in _PDO_AREAS):
            self._rebuild_pdos()

    # ---------------------------------------------------------------------------------------------------------
    # CiA 402

    def _quick_stop_option(self) -> int:
        if Obj.QUICK_STOP_OPTION not in self.od:
            return int(QuickStopOption.QUICK_STOP_RAMP_THEN_DISABLE)
        return int(self._get(Obj.QUICK_STOP_OPTION))

    def _apply_controlword(self, controlword: int) -> None:
        reset_bit = bool(controlword & Controlword.FAULT_RESET)
        rising = reset_bit and not self._fault_reset_bit
        self._fault_reset_bit = reset_bit
        before = self.machine.state
        after = self.machine.apply_controlword(controlword)
        if rising and (before is State402.FAULT or self._latched_errors):
            self._clear_errors()
        if after is State402.QUICK_STOP_ACTIVE and before is not State402.QUICK_STOP_ACTIVE:
            self._axis.ramp_velocity = self._axis.velocity
            self._axis.ramp_zero_time = 0.0
        if after is State402.OPERATION_ENABLED and before is not State402.OPERATION_ENABLED:
            self._axis.profile_velocity = self._axis.velocity  # PV ramps start where the axis is
        if after != before:
            self._publish_status()
            self._send_event_tpdos()

    def _apply_mode(self, mode: int) -> None:
        if mode in SUPPORTED_MODES:
            self._put(Obj.MODES_OF_OPERATION_DISPLAY, mode)
            self._axis.profile_velocity = self._axis.velocity
            self._publish_status()

    def _raise_fault(self, fault: FaultKind) -> None:
        code, register_bits = FAULT_CODES[fault]
        if self.machine.state is State402.FAULT and code in self._latched_errors:
            return
        self._latch_error(code, register_bits)
        self.machine.fault()
        # Fault reaction "disable drive": torque off at once, so the reaction is complete immediately (14).
        if self.machine.motion() is MotionKind.TORQUE_OFF:
            self.machine.ramp_finished()

    def _communication_abort(self, fault: FaultKind) -> None:
        """Heartbeat or SYNC loss, or NMT leaving OPERATIONAL: EMCY, then the 0x6007 reaction."""
        option = (int(self._get(Obj.ABORT_CONNECTION_OPTION)) if Obj.ABORT_CONNECTION_OPTION in self.od
                  else int(AbortConnectionOption.FAULT))
        if option == AbortConnectionOption.FAULT:
            self._raise_fault(fault)
            return
        code, register_bits = FAULT_CODES[fault]
        self._latch_error(code, register_bits)
        keep = self.machine.state
        if option == AbortConnectionOption.DISABLE_VOLTAGE:
            self.machine.apply_controlword(Command402.DISABLE_VOLTAGE)
        elif option == AbortConnectionOption.QUICK_STOP:
            self.machine.apply_controlword(Command402.QUICK_STOP)
            if self.machine.state is State402.QUICK_STOP_ACTIVE and keep is not State402.QUICK_STOP_ACTIVE:
                self._axis.ramp_velocity = self._axis.velocity
                self._axis.ramp_zero_time = 0.0

    def _latch_error(self, code: EmcyCode, register_bits: int) -> None:
        if code not in self._latched_errors:
            self._latched_errors.append(code)
        register = int(self._get(Obj.ERROR_REGISTER)) | ErrorRegister.GENERIC | register_bits
        self._put(Obj.ERROR_REGISTER, register)
        self._put(Obj.ERROR_CODE, int(code))
        self._emcy(int(code), register)

    def _clear_errors(self) -> None:
        self._latched_errors.clear()
        self._axis.torque_limited_cycles = 0
        self._put(Obj.ERROR_REGISTER, 0)
        self._put(Obj.ERROR_CODE, 0)
        self._emcy(EmcyCode.NO_ERROR, 0)

    def _emcy(self, code: int, register: int, data: bytes = b"") -> None:
        self.emcy_log.append((code, register))
        # CiA 301: a node in STOPPED sends no EMCY (the error stays latched in 0x1001/0x603F)
        if self._network is not None and self._alive and self.nmt_state is not NmtState.STOPPED:
            self.node.emcy.send(code, register, data)

    def _publish_status(self) -> None:
        mode = int(self._get(Obj.MODES_OF_OPERATION_DISPLAY))
        axis = self._axis
        target_reached = False
        if self.machine.state is State402.OPERATION_ENABLED and mode == OperationMode.PROFILE_VELOCITY:
            target = float(self._get(Obj.TARGET_VELOCITY))
            target_reached = abs(axis.velocity - target) <= self._counts(self.settings.velocity_window)
        elif self.machine.state is State402.QUICK_STOP_ACTIVE:
            target_reached = self.machine.ramp_done
        word = self.machine.statusword(mode, target_reached=target_reached, internal_limit=axis.internal_limit)
        self._put(Obj.STATUSWORD, word)

    # ---------------------------------------------------------------------------------------------------------
    # units

    def _counts(self, plant_units: float) -> float:
        """Plant velocity units -> counts of 0x60FF/0x606C."""
        return plant_units * self._velocity_scale

    def _plant_velocity_input(self, counts: float) -> float:
        return counts / self._velocity_scale

    def _plant_torque_input(self, per_mille: float) -> float:
        return per_mille / self._torque_scale

    # ---------------------------------------------------------------------------------------------------------
    # physics

    def _tick(self, dt: float) -> None:
        """Advance the plant one cycle with the active command; update feedback, limits, ramps."""
        axis = self._axis
        motion = self.machine.motion()
        mode = int(self._get(Obj.MODES_OF_OPERATION_DISPLAY))
        kind, u = "torque", 0.0
        if motion is MotionKind.FOLLOW_TARGET:
            if mode == OperationMode.CYCLIC_SYNC_TORQUE:
                kind = "torque"
                u = self._plant_torque_input(float(self._get(Obj.TARGET_TORQUE)))
            elif mode == OperationMode.PROFILE_VELOCITY:
                kind = "velocity"
                axis.profile_velocity = self._profile_step(axis.profile_velocity, dt)
                u = self._plant_velocity_input(axis.profile_velocity)
            else:
                kind = "velocity"
                u = self._plant_velocity_input(float(self._get(Obj.TARGET_VELOCITY)))
        elif motion in (MotionKind.QUICK_STOP_RAMP, MotionKind.HOLD_STANDSTILL):
            kind = "velocity"
            if motion is MotionKind.QUICK_STOP_RAMP:
                axis.ramp_velocity = _toward(axis.ramp_velocity, 0.0, self._quick_stop_deceleration() * dt)
            else:
                axis.ramp_velocity = 0.0
            u = self._plant_velocity_input(axis.ramp_velocity)
        if self._is_pmsm:
            self.plant.set_input_kind(kind)  # type: ignore[attr-defined]
        elif motion is MotionKind.TORQUE_OFF:
            u = 0.0
        y = np.asarray(self.plant.step(np.array([u]), dt), dtype=float).reshape(-1)
        axis.cycles += 1
        axis.velocity = self._counts(float(y[0]))
        plant_position = getattr(self.plant, "position_counts", None)
        if plant_position is not None:
            axis.position = float(plant_position)
        else:
            axis.position += float(y[0]) * dt  # no encoder in the model: the integral of the output
        plant_torque = getattr(self.plant, "torque", None)
        if plant_torque is not None:
            axis.torque = float(plant_torque) * self._torque_scale
        else:
            axis.torque = u * self._torque_scale if kind == "torque" else 0.0
        torque_limited = bool(getattr(self.plant, "torque_limited", False))
        over_speed = bool(getattr(self.plant, "over_speed", False))
        axis.internal_limit = torque_limited
        axis.torque_limited_cycles = axis.torque_limited_cycles + 1 if torque_limited else 0
        energised = motion is not MotionKind.TORQUE_OFF
        if energised and over_speed:
            self._raise_fault(FaultKind.OVER_SPEED)
        limit_cycles = self.settings.torque_limit_fault_cycles
        if energised and limit_cycles and axis.torque_limited_cycles >= limit_cycles:
            self._raise_fault(FaultKind.OVER_CURRENT)
        if motion is MotionKind.QUICK_STOP_RAMP and axis.ramp_velocity == 0.0:
            axis.ramp_zero_time += dt
            standstill = abs(axis.velocity) <= self._counts(self.settings.standstill_velocity)
            if standstill or axis.ramp_zero_time >= RAMP_SETTLE_TIME:
                self.machine.ramp_finished()
        self._put(Obj.VELOCITY_ACTUAL_VALUE, axis.velocity)
        self._put(Obj.TORQUE_ACTUAL_VALUE, axis.torque)
        self._put(Obj.POSITION_ACTUAL_VALUE, axis.position)
        self._publish_status()

    def _profile_step(self, current: float, dt: float) -> float:
        target = float(self._get(Obj.TARGET_VELOCITY))
        speeding_up = abs(target) > abs(current) and (target * current >= 0)
        index = Obj.PROFILE_ACCELERATION if speeding_up else Obj.PROFILE_DECELERATION
        rate = float(self._get(index)) if index in self.od else math.inf
        return _toward(current, target, rate * dt if rate > 0 else math.inf)

    def _quick_stop_deceleration(self) -> float:
        option = self.machine.quick_stop_option
        slow = option in (QuickStopOption.SLOW_DOWN_RAMP_THEN_DISABLE, QuickStopOption.SLOW_DOWN_RAMP_STAY)
        index = Obj.PROFILE_DECELERATION if slow else Obj.QUICK_STOP_DECELERATION
        rate = float(self._get(index)) if index in self.od else 0.0
        return rate if rate > 0 else math.inf

    def _realtime_physics(self) -> None:
        next_tick = time.perf_counter()
        while not self._stop_event.is_set():
            period = self.cycle_period
            next_tick += period
            delay = next_tick - time.perf_counter()
            if delay > 0:
                self._stop_event.wait(delay)
            elif delay < -10 * period:
                next_tick = time.perf_counter()  # fell far behind (debugger, overload): do not burst
            with self._lock:
                if self._alive:
                    self._tick(period)
                    self._emit_trace()

    # ---------------------------------------------------------------------------------------------------------
    # SYNC and PDOs

    def _subscribe_sync(self) -> None:
        network = self._network
        if network is None:
            return
        if self._sync_cob_id in network.subscribers and self._on_sync in network.subscribers[self._sync_cob_id]:
            network.unsubscribe(self._sync_cob_id, self._on_sync)
        if Obj.COB_ID_SYNC in self.od:
            self._sync_cob_id = int(self._get(Obj.COB_ID_SYNC)) & PDO_COB_MASK
        network.subscribe(self._sync_cob_id, self._on_sync)

    def _on_sync(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if not self._alive:
            return
        with self._lock:
            self.sync_count += 1
            self._last_sync = time.monotonic()
            self._sync_lost = False
            if self.timing is TimingMode.LOCKSTEP:
                self._tick(self.cycle_period)  # (1) physics with the command that was active
            if self.nmt_state is not NmtState.OPERATIONAL:
                if self.timing is TimingMode.LOCKSTEP:
                    self._emit_trace()
                return
            for channel in self._rpdos.values():  # (2) latch the RPDOs received since the last SYNC
                if channel.pending is not None:
                    data_now, channel.pending = channel.pending, None
                    self._store_rpdo(channel, data_now)
            self._publish_status()
            for tpdo in self._tpdos:  # (3) sample and send
                if not tpdo.valid:
                    continue
                if tpdo.transmission_type == TRANS_ACYCLIC:
                    self._send_tpdo(tpdo, only_if_changed=True)
                elif tpdo.synchronous:
                    tpdo.sync_count += 1
                    if tpdo.sync_count >= tpdo.transmission_type:
                        tpdo.sync_count = 0
                        self._send_tpdo(tpdo, only_if_changed=False)
            self._send_event_tpdos()
            if self.timing is TimingMode.LOCKSTEP:
                self._emit_trace()

    def _emit_trace(self) -> None:
        if self.trace is not None:
            self.trace(self.snapshot())

    def _on_rpdo(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if not self._alive or self.nmt_state is not NmtState.OPERATIONAL:
            return
        with self._lock:
            channel = self._rpdos.get(can_id)
            if channel is None or not channel.valid:
                return
            if len(data) < channel.length:
                self._emcy(EmcyCode.PDO_LENGTH, int(self._get(Obj.ERROR_REGISTER)))
                return
            if channel.synchronous:
                channel.pending = bytes(data)  # takes effect at the next SYNC
            else:
                self._store_rpdo(channel, bytes(data))

    def _store_rpdo(self, channel: PdoChannel, data: bytes) -> None:
        store = self.node.data_store
        touched: list[tuple[int, int]] = []
        for entry in channel.entries:
            store.setdefault(entry.index, {})[entry.subindex] = data[entry.offset:entry.offset + entry.size]
            touched.append((entry.index, entry.subindex))
        # mode first, so a controlword in the same frame acts in the new mode
        touched.sort(key=lambda key: key[0] != Obj.MODES_OF_OPERATION)
        for index, subindex in touched:
            if index in (Obj.CONTROLWORD, Obj.MODES_OF_OPERATION):
                self._after_write(index, subindex)

    def _pack_tpdo(self, channel: PdoChannel) -> bytes:
        store = self.node.data_store
        return b"".join(store[entry.index][entry.subindex] for entry in channel.entries)

    def _send_tpdo(self, channel: PdoChannel, *, only_if_changed: bool) -> None:
        payload = self._pack_tpdo(channel)
        if only_if_changed and payload == channel.last_sent:
            return
        channel.last_sent = payload
        channel.last_sent_time = time.monotonic()
        if self._network is not None:
            self._network.send_message(channel.cob_id, payload)

    def _send_event_tpdos(self, *, timer_only: bool = False) -> None:
        if self._network is None or not self._alive or self.nmt_state is not NmtState.OPERATIONAL:
            return
        now = time.monotonic()
        for tpdo in self._tpdos:
            if not tpdo.valid or tpdo.transmission_type not in TRANS_EVENT_TYPES:
                continue
            timer_due = tpdo.event_timer_ms > 0 and now - tpdo.last_sent_time >= tpdo.event_timer_ms / 1000
            if timer_due:
                self._send_tpdo(tpdo, only_if_changed=False)
            elif not timer_only:
                self._send_tpdo(tpdo, only_if_changed=True)

    def _read_channel(self, communication: int, mapping: int, number: int, default_base: int) -> PdoChannel:
        raw_cob = int(self._get(communication, 1))
        trans = int(self._get(communication, 2))
        event_timer = 0
        com_obj = self.od[communication]
        if not isinstance(com_obj, cod.ODVariable) and 5 in com_obj:
            event_timer = int(self._get(communication, 5))
        count = int(self._get(mapping, 0))
        entries: list[MappedObject] = []
        offset = 0
        for sub in range(1, count + 1):
            value = int(self._get(mapping, sub))
            index, subindex, bits = value >> 16, (value >> 8) & 0xFF, value & 0xFF
            size = bits // 8
            entries.append(MappedObject(index, subindex, offset, size))
            offset += size
        cob = raw_cob & PDO_COB_MASK
        if cob == 0 and number <= len(_DEFAULT_PDO_BASES):
            cob = default_base + self.node_id
        return PdoChannel(
            number=number,
            cob_id=cob,
            valid=not raw_cob & PDO_INVALID,
            transmission_type=trans,
            event_timer_ms=event_timer,
            entries=tuple(entries),
            length=offset,
        )

    def _rebuild_pdos(self) -> None:
        rpdos: dict[int, PdoChannel] = {}
        tpdos: list[PdoChannel] = []
        for n in range(PDO_CHANNELS):
            number = n + 1
            base_r = _DEFAULT_PDO_BASES[n][1] if n < len(_DEFAULT_PDO_BASES) else 0
            base_t = _DEFAULT_PDO_BASES[n][0] if n < len(_DEFAULT_PDO_BASES) else 0
            if Obj.RPDO_COMMUNICATION + n in self.od and Obj.RPDO_MAPPING + n in self.od:
                channel = self._read_channel(Obj.RPDO_COMMUNICATION + n, Obj.RPDO_MAPPING + n, number, base_r)
                old = self._rpdos.get(channel.cob_id)
                if old is not None and old.number == number and old.entries == channel.entries:
                    channel.pending = old.pending
                rpdos[channel.cob_id] = channel
            if Obj.TPDO_COMMUNICATION + n in self.od and Obj.TPDO_MAPPING + n in self.od:
                tpdos.append(
                    self._read_channel(Obj.TPDO_COMMUNICATION + n, Obj.TPDO_MAPPING + n, number, base_t)
                )
        self._rpdos = {cob: ch for cob, ch in rpdos.items() if ch.valid}
        self._tpdos = tpdos
        network = self._network
        if network is None:
            return
        wanted = set(self._rpdos)
        for cob in self._subscribed_rpdo_ids - wanted:
            network.unsubscribe(cob, self._on_rpdo)
        for cob in wanted - self._subscribed_rpdo_ids:
            network.subscribe(cob, self._on_rpdo)
        self._subscribed_rpdo_ids = wanted

    # ---------------------------------------------------------------------------------------------------------
    # heartbeat consumer and supervision

    def _rebuild_heartbeat_consumer(self) -> None:
        network = self._network
        for watch in self._heartbeat_watches.values():
            if network is not None:
                network.unsubscribe(cob_id(FunctionCode.HEARTBEAT, watch.node_id), self._on_heartbeat)
        self._heartbeat_watches = {}
        if Obj.CONSUMER_HEARTBEAT_TIME not in self.od:
            return
        record = self.od[Obj.CONSUMER_HEARTBEAT_TIME]
        subs = [] if isinstance(record, cod.ODVariable) else [s for s in record.subindices if s > 0]
        for sub in subs:
            value = int(self._get(Obj.CONSUMER_HEARTBEAT_TIME, sub))
            node, millis = (value >> HEARTBEAT_CONSUMER_NODE_SHIFT) & 0x7F, value & 0xFFFF
            if node == 0 or millis == 0:
                continue
            self._heartbeat_watches[node] = _HeartbeatWatch(node_id=node, timeout=millis / 1000)
            if network is not None:
                network.subscribe(cob_id(FunctionCode.HEARTBEAT, node), self._on_heartbeat)

    def _on_heartbeat(self, can_id: int, data: bytearray, timestamp: float) -> None:
        watch = self._heartbeat_watches.get(can_id - FunctionCode.HEARTBEAT)
        if watch is not None and self._alive:
            watch.deadline = time.monotonic() + watch.timeout

    def _supervise(self) -> None:
        while not self._stop_event.wait(MONITOR_PERIOD):
            if not self._alive:
                continue
            now = time.monotonic()
            with self._lock:
                for watch in self._heartbeat_watches.values():
                    if watch.deadline is not None and now > watch.deadline:
                        watch.deadline = None  # wait for the next heartbeat before watching again
                        self._communication_abort(FaultKind.HEARTBEAT_LOSS)
                        self._publish_status()
                        self._send_event_tpdos()
                if (
                    self.timing is TimingMode.REALTIME
                    and self._last_sync is not None
                    and not self._sync_lost
                    and self.nmt_state is NmtState.OPERATIONAL
                    and now - self._last_sync > self.settings.sync_loss_cycles * self.cycle_period
                ):
                    self._sync_lost = True
                    self._communication_abort(FaultKind.SYNC_LOSS)
                    self._publish_status()
                    self._send_event_tpdos()
                self._send_event_tpdos(timer_only=True)


_DEFAULT_PDO_BASES = (
    (FunctionCode.TPDO1, FunctionCode.RPDO1),
    (FunctionCode.TPDO2, FunctionCode.RPDO2),
    (FunctionCode.TPDO3, FunctionCode.RPDO3),
    (FunctionCode.TPDO4, FunctionCode.RPDO4),
)


def _toward(value: float, target: float, max_step: float) -> float:
    """Move ``value`` toward ``target`` by at most ``max_step``."""
    if abs(target - value) <= max_step:
        return target
    return value + math.copysign(max_step, target - value)

