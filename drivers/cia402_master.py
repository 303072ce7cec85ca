"""CiA 402 master over python-can + canopen: :class:`Cia402Drive`, the bench's :class:`~drivers.drive.Drive`.

Start-up follows what real CANopen masters do, using only standard objects, so any CiA 402 drive works:

0. Construction (``Cia402Drive.open``, or ``Cia402Drive.on_network`` for one of several drives sharing a
   :class:`~drivers.network.DriveNetwork`: one receive path, one SYNC, one master heartbeat per bus) is inert, like
   canopen's ``Network()``: no thread, nothing on the bus.
1. ``connect``: ``listen`` (Notifier, frame tap, heartbeat watchdog); NMT reset communication, wait for the
   boot-up, NMT pre-operational, read 0x1000 (must be a 402 device), 0x1018:1..4 and 0x6502 over SDO.
2. ``configure``: :meth:`Cia402Drive.preflight` first (mode in 0x6502, :func:`pdo_plan`: the PDOs and objects
   the drive's EDS has); start the master's heartbeat producer; for every RPDO/TPDO 1..4: disable it (COB-ID
   bit 31), and for those the plan uses: transmission type 1, mapping count 0, mapping entries, count, COB-ID
   enabled; then 0x6060 mode, 0x605A, 0x6007 (optional in CiA 402), 0x1006 (cycle period in us; optional in
   CiA 301), 0x60C2 (interpolation time period), 0x1017 (drive heartbeat), 0x1016:1 (drive watches the master;
   optional in CiA 301). An optional object the EDS lacks is not written (a warning and a plan note say so); one
   the EDS has but the drive refuses with "no object" is skipped with a warning. Read all of it back (0x6061 must
   show the mode); NMT start; wait for the operational heartbeat. Torque (0x6077) and position (0x6064) feedback
   are mapped only when the drive has them (then :class:`~drivers.drive.Feedback` has NaN torque / position 0).
3. ``enable``: controlword 0x06 / 0x07 / 0x0F through the RPDO, one SYNC each, until the TPDO statusword shows
   OPERATION_ENABLED.

Cyclic path (never SDO): ``set_target`` encodes the RPDO with a precomputed :class:`~drivers.pdo.PdoCodec` and
sends it; ``sync`` sends a prebuilt SYNC (DLC 0: no counter, so no drive needs 0x1019) and advances the master's
cycle counter; TPDOs are decoded on the Notifier thread and handed to ``wait_feedback`` through a condition
variable, or, with a :class:`~drivers.cyclic_rx.CyclicReceiver` (the realtime bench), received and decoded by
``wait_feedback`` itself on the control thread (same decoding, counters and errors; the Notifier still shows them
to the frame tap).

Waiting: every wait of the master (feedback, heartbeats, state changes, pacing) runs on the bus's timebase
(:func:`drivers.inprocess.timebase_of`). On a lockstep in-process bus (the embedded emulator) frames are delivered
inside ``send``, so nothing arrives by waiting: an unanswered SYNC is known when ``sync`` returns and
``wait_feedback`` raises :class:`~drivers.errors.FeedbackTimeoutError` at once, with no deadline; an SDO answer is
there or never comes (no response timeout); and time is the channel's simulated time, one cycle period per SYNC
(``sync`` advances it) plus the master's own pauses, so heartbeat supervision never reads a busy host as a lost
drive. On any other bus they are wall-clock waits.

Units: ``set_target`` takes plant units and sends ``round(value * scale)`` after clamping ``|value|`` to
``velocity_limit`` (CSV, PV; scale ``velocity_scale``) or ``torque_limit`` (CST; scale ``torque_scale``); feedback
is divided by the same scales. The shipped EDS counts velocity in 0.001 rpm, so a plant in rpm needs
``velocity_scale: 1000``, the ``DriveConfig`` default. Torque is per mille of rated torque (CiA 402).

Errors: EMCY -> :class:`~drivers.errors.EmergencyError` (code decoded), statusword fault bit ->
:class:`~drivers.errors.DriveFaultError`, no heartbeat for ``heartbeat_timeout_factor x 0x1017`` ->
:class:`~drivers.errors.HeartbeatLostError` (checked by ``wait_feedback`` and by a watchdog thread), no TPDO set
in time -> :class:`~drivers.errors.FeedbackTimeoutError`, SDO abort -> :class:`~drivers.errors.SdoError`
(abort code decoded), no SDO answer -> :class:`~drivers.errors.DriveTimeoutError`.
Before any of these but ``FeedbackTimeoutError`` leaves ``wait_feedback`` the master commands quick stop (controlword
0x02, target 0, one SYNC); one unanswered SYNC leaves the command as it was, for the caller to judge.
Received frames: a TPDO/EMCY/heartbeat of the drive that does not decode (wrong DLC, impossible statusword) is
counted in :attr:`Cia402Drive.stats` (``bad_frames``); with ``fatal_bad_frames`` (the default) it is also a
:class:`~drivers.errors.BadFrameError` (a run-time error, exit 1) raised by the next ``wait_feedback``, otherwise
it is only counted (a TPDO set left incomplete by it then simply never answers its SYNC). A frame with a COB-ID
nobody subscribed to (another node's traffic) is ignored and counted (``unknown_frames``).

NMT supervision: once the drive's heartbeat has reported OPERATIONAL after ``configure`` (the heartbeat is armed),
a heartbeat reporting any other NMT state while the master is operational is a
:class:`~drivers.errors.DriveNmtStateError` raised by the next ``wait_feedback``: a drive out of OPERATIONAL
ignores RPDOs, so the cyclic path no longer reaches it. The master's own NMT commands disarm the heartbeat first.

Thread safety
-------------
- Public methods are called from ONE control thread (the bench's). canopen's SDO client is not re-entrant.
- The Notifier thread runs the receive callbacks (TPDO, EMCY, heartbeat; with a cyclic receiver the TPDO callback
  runs on the control thread instead, inside ``wait_feedback`` and ``sync``). They touch only the state guarded by
  ``self._cv`` (a ``threading.Condition``): the current cycle's partial TPDO set, the latest feedback and the
  queue of pending errors. The control thread reads that state only under the same lock.
- The heartbeat watchdog thread only posts a pending error under ``self._cv``.
- Frames are sent under canopen's ``network.send_lock``, shared with canopen's own sends; python-can's
  periodic heartbeat task has its own lock (the interfaces' ``send`` is thread-safe).
- Frame listeners (:meth:`Cia402Drive.add_frame_listener`) run on the sending thread and the Notifier thread.
"""

from __future__ import annotations

import collections
import contextlib
import logging
import math
import struct
import threading
import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass

import can
import canopen
from canopen.nmt import NmtMaster
from canopen.objectdictionary import ObjectDictionary
from canopen.sdo import SdoAbortedError, SdoCommunicationError

from drivers.bus import FrameListener
from drivers.cia301 import (
    NMT_COB_ID,
    RPDO_BASES,
    TPDO_BASES,
    CobIdEntry,
    EmcyCode,
    FunctionCode,
    HeartbeatConsumerEntry,
    NmtCommand,
    NmtState,
    SdoAbortCode,
    check_node_id,
    cob_id,
    sdo_abort_text,
)
from drivers.cia402 import (
    ENABLE_PATH,
    SUPPORTED_MODE_BITS,
    Command402,
    IdentitySub,
    Obj,
    OperationMode,
    State402,
    Statusword,
    decode_state,
)
from drivers.config import DriveConfig
from drivers.cyclic_rx import CyclicReceiver
from drivers.drive import DISABLED_STATES, DeviceInfo, Drive, Feedback, StopPath, StopReport
from drivers.emcy import decode_emcy
from drivers.errors import (
    BadFrameError,
    ConfigError,
    DriveError,
    DriveFaultError,
    DriveNmtStateError,
    DriveTimeoutError,
    FeedbackTimeoutError,
    HeartbeatLostError,
    ProductError,
    ProtocolError,
    SdoError,
    StateTransitionError,
)
from drivers.heartbeat import HeartbeatMonitor
from drivers.inprocess import LockstepClock, timebase_of
from drivers.network import DriveNetwork
from drivers.od import load_od, mapped_variable
from drivers.pdo import MappedVariable, PdoCodec, PdoDirection, PdoLayout, data_frame

__all__ = ["Cia402Drive", "PdoPlan", "RxStats", "interpolation_time_period", "pdo_plan"]

logger = logging.getLogger(__name__)

CIA402_PROFILE = 402
"""Low 16 bits of 0x1000 for a CiA 402 drive."""

MASTER_HEARTBEATS_PER_CONSUMER_TIME = 4
"""The master beats this many times per drive consumer time (0x1016), so one lost or late frame never trips it."""
HEARTBEAT_WATCHDOG_POLL = 0.05  # s between checks of the drive's heartbeat deadline
FEEDBACK_POLL = 0.05  # s: a wait for feedback looks at the heartbeat deadline at least this often
#: s: with a cyclic receiver, a wait for feedback sees the Notifier's errors (EMCY, heartbeat) at least this often
#: (it blocks in recv, not on the condition they notify); short against the drive's reaction, long against 1 cycle
RECEIVE_POLL = 0.005

_REQUIRED_FEEDBACK = (Obj.STATUSWORD, Obj.VELOCITY_ACTUAL_VALUE)
"""Feedback every mode needs: the 402 state and the axis output."""
_OPTIONAL_FEEDBACK = (Obj.TORQUE_ACTUAL_VALUE, Obj.POSITION_ACTUAL_VALUE)
"""Feedback mapped when the drive has it (:class:`~drivers.drive.Feedback` has NaN torque / 0 position without)."""
PDO_PAYLOAD_BITS = 64  # a classic CAN PDO carries at most 8 bytes


_U8, _U16, _U32 = ("B", False), ("H", False), ("I", False)
_QUICK_STOP_GOAL = frozenset({State402.QUICK_STOP_ACTIVE, State402.SWITCH_ON_DISABLED, State402.FAULT})
_DISABLE_GOAL = frozenset({State402.SWITCH_ON_DISABLED, State402.FAULT})
_I8, _I16 = ("b", True), ("h", True)
_Setting = tuple[int, int, tuple[str, bool], int, bool]  # index, sub-index, (struct code, signed), value, optional


def interpolation_time_period(period: float) -> tuple[int, int]:
    """0x60C2 encoding of ``period`` seconds: ``(value, exponent)`` with ``period = value * 10**exponent``.

    The largest exponent (-1 .. -6) giving an exact integer ``1 <= value <= 255`` is chosen. Raises
    :class:`ConfigError` when none does (e.g. 0.3 ms needs value 3, exponent -4: fine; 1.2345 ms: none).
    """
    for exponent in range(-1, -7, -1):
        value = period / 10.0**exponent
        if 1 <= round(value) <= 255 and abs(value - round(value)) <= 1e-9 * value:
            return round(value), exponent
    raise ConfigError(f"{period} s is not expressible in 0x60C2 (1..255 x 10^-1..10^-6 s)", key="sample_time")


@dataclass(frozen=True, slots=True)
class PdoPlan:
    """The PDOs the master configures on one drive for one mode, and what it left out (and why).

    Attributes
    ----------
    rpdos, tpdos
        The layouts ``configure`` writes (numbers the drive's EDS has, in order).
    notes
        One line per optional object or PDO the drive lacks, e.g. ``"0x6077 not mapped: ..."``.
    """

    rpdos: tuple[PdoLayout, ...]
    tpdos: tuple[PdoLayout, ...]
    notes: tuple[str, ...] = ()


def _pdo_numbers(od: ObjectDictionary | None, communication: int, mapping: int) -> tuple[int, ...]:
    """PDO numbers 1..4 whose communication and mapping objects the EDS describes (all four without an EDS)."""
    numbers = range(1, len(TPDO_BASES) + 1)
    if od is None:
        return tuple(numbers)
    return tuple(n for n in numbers if communication + n - 1 in od and mapping + n - 1 in od)


def _pack_feedback(groups: list[list[MappedVariable]], slots: int) -> tuple[list[list[MappedVariable]], list[int]]:
    """The feedback groups in ``slots`` PDOs: one group per PDO while PDOs remain, else first fit in 8 bytes.

    Returns the PDO contents and the objects that fit nowhere (the caller decides whether they were optional).
    """
    if len(groups) <= slots:
        return groups, []
    bins: list[list[MappedVariable]] = [[] for _ in range(slots)]
    dropped: list[int] = []
    for variable in (v for group in groups for v in group):
        fit = next((b for b in bins if sum(v.bits for v in b) + variable.bits <= PDO_PAYLOAD_BITS), None)
        if fit is None:
            dropped.append(variable.index)
        else:
            fit.append(variable)
    return [b for b in bins if b], dropped


def pdo_plan(mode: OperationMode, node_id: int, od: ObjectDictionary | None) -> PdoPlan:
    """The RPDOs and TPDOs the master configures for ``mode`` on a drive described by ``od`` (standard objects).

    RPDO1 = controlword + target (0x60FF for CSV/PV, 0x6071 for CST); TPDO1 = statusword + velocity actual;
    TPDO2 = torque actual + position actual. All synchronous (transmission type 1), default COB-IDs. Only objects
    and PDOs the EDS has are used: a drive without 0x6077 or 0x6064 gets them left out (a note says so), one
    without TPDO2 gets what fits into TPDO1. What the mode truly needs -- controlword, target, statusword, velocity
    actual, an RPDO and a TPDO -- is refused with a :class:`~drivers.errors.DriveError` naming the object.
    """
    target = Obj.TARGET_TORQUE if mode is OperationMode.CYCLIC_SYNC_TORQUE else Obj.TARGET_VELOCITY
    needed = (Obj.CONTROLWORD, target, *_REQUIRED_FEEDBACK)
    if od is not None:
        lacking = [f"0x{int(index):04X} ({index.name.lower()})" for index in needed if index not in od]
        if lacking:
            raise DriveError(f"node {node_id}: the drive's EDS lacks {', '.join(lacking)}, which {mode.name} needs")
    rpdo_numbers = _pdo_numbers(od, Obj.RPDO_COMMUNICATION, Obj.RPDO_MAPPING)
    tpdo_numbers = _pdo_numbers(od, Obj.TPDO_COMMUNICATION, Obj.TPDO_MAPPING)
    for kind, numbers, base in (("RPDO", rpdo_numbers, Obj.RPDO_COMMUNICATION),
                                ("TPDO", tpdo_numbers, Obj.TPDO_COMMUNICATION)):
        if not numbers:
            raise DriveError(f"node {node_id}: the drive's EDS has no {kind} (0x{int(base):04X}.. with its mapping), "
                             f"which {mode.name} needs")
    notes = [f"0x{int(index):04X} ({index.name.lower()}) not mapped: the drive's EDS lacks it"
             for index in _OPTIONAL_FEEDBACK if od is not None and index not in od]
    present = [index for index in _OPTIONAL_FEEDBACK if od is None or index in od]
    groups = [[mapped_variable(od, index) for index in _REQUIRED_FEEDBACK]]
    if present:
        groups.append([mapped_variable(od, index) for index in present])
    contents, dropped = _pack_feedback(groups, len(tpdo_numbers))
    room = f"the drive's {len(tpdo_numbers)} TPDO(s) have no room left"
    notes += [f"0x{index:04X} not mapped: {room}" for index in dropped]
    rpdo = rpdo_numbers[0]
    rpdos = (PdoLayout(PdoDirection.RPDO, rpdo, cob_id(RPDO_BASES[rpdo - 1], node_id),
                       (mapped_variable(od, Obj.CONTROLWORD), mapped_variable(od, target))),)
    tpdos = tuple(PdoLayout(PdoDirection.TPDO, number, cob_id(TPDO_BASES[number - 1], node_id), tuple(variables))
                  for number, variables in zip(tpdo_numbers, contents, strict=False))
    return PdoPlan(rpdos, tpdos, tuple(notes))


_FAULT_BIT = int(Statusword.FAULT)  # a plain int: IntFlag's operators are Python code, and this is every cycle
_STATES: dict[int, State402] = {}
"""Statuswords seen so far and their 402 state (``decode_state`` is pure; a handful of words recur every cycle)."""


def _nmt_name(state: int) -> str:
    try:
        return NmtState(state).name
    except ValueError:
        return f"state 0x{state:02X}"


def _format(variable: MappedVariable) -> tuple[str, bool]:
    codes = {8: "b", 16: "h", 32: "i", 64: "q"}
    code = codes[variable.bits]
    return (code if variable.signed else code.upper()), variable.signed


@dataclass(frozen=True, slots=True)
class RxStats:
    """Counters of the receive side (read with :attr:`Cia402Drive.stats`)."""

    tpdo_frames: int
    emcy_frames: int
    heartbeat_frames: int
    bad_frames: int  # wrong DLC or impossible content: counted, and raised as BadFrameError when fatal
    unknown_frames: int  # COB-ID nobody subscribed to: ignored


class Cia402Drive(Drive):
    """A CiA 402 drive on a python-can bus, driven through canopen's SDO client and NMT master.

    Build it with :meth:`open` (a drive alone on its bus: it owns a private :class:`~drivers.network.DriveNetwork`)
    or :meth:`on_network` (one of several drives sharing a network's receive path, SYNC and master heartbeat).
    The bus belongs to the caller: :meth:`close` of a drive that owns its network releases the Notifier, the
    heartbeat producer and the frame tap, never the bus; a drive on a shared network only leaves it (the network's
    owner closes it).
    """

    def __init__(
        self,
        bus: can.BusABC,
        cfg: DriveConfig,
        *,
        sample_time: float,
        od: ObjectDictionary,
        network: DriveNetwork | None = None,
        receiver: CyclicReceiver | None = None,
    ) -> None:
        if not (sample_time > 0 and math.isfinite(sample_time)):
            raise ConfigError(f"must be a positive number of seconds, got {sample_time}", key="sample_time")
        if cfg.master_node_id == cfg.node_id:
            raise ConfigError(f"must differ from drive.node_id ({cfg.node_id}): both would send heartbeats on "
                              f"0x{cob_id(FunctionCode.HEARTBEAT, cfg.node_id):03X}", key="drive.master_node_id")
        self.cfg = cfg
        self.node_id = check_node_id(cfg.node_id)
        self.sample_time = sample_time
        self.od = od
        self._bus = bus
        if network is not None and network.bus is not bus:
            raise DriveError(f"node {cfg.node_id}: the shared network is on another bus")
        if network is not None and receiver is not None:
            raise DriveError(f"node {cfg.node_id}: a shared network has its own cyclic receiver (DriveNetwork)")
        self._owns_network = network is None
        # the tap and the Notifier start with listen(): construction starts nothing
        self._net = DriveNetwork(bus, receiver) if network is None else network
        self.network = self._net.network
        if self.node_id in self.network:
            raise ConfigError(f"node {self.node_id} is already on this bus's network", key="drive.node_id")
        self._listening = False
        self.node = canopen.RemoteNode(self.node_id, od)
        self._init_waits(bus)
        self.network.add_node(self.node)
        self._master_nmt: NmtMaster = self.node.nmt

        # state shared with the Notifier and watchdog threads: only under self._cv
        self._cv = threading.Condition(threading.RLock())
        self._lock = self._cv._lock  # type: ignore[attr-defined]  # the hot paths: see _begin_cycle
        self._cycle = 0
        self._parts: dict[int, tuple[int, ...]] = {}
        self._feedback: Feedback | None = None
        self._errors: collections.deque[ProductError] = collections.deque()
        self._tpdo_frames = self._emcy_frames = self._heartbeat_frames = self._bad_frames = 0
        self._heartbeat_fault = False
        #: a frame from the drive that does not decode is raised (BadFrameError) by the next wait_feedback; False:
        #: only counted in stats.bad_frames (the bench's ``bench.faults.bad_frame: count``)
        self.fatal_bad_frames = True
        # the drive left NMT OPERATIONAL (its heartbeat said so) and the error was not yet raised by wait_feedback:
        # the final stop reports it even when another error (e.g. the drive's own EMCY) ended the run first
        self._nmt_departure: DriveNmtStateError | None = None

        # control-thread state
        self._mode: OperationMode | None = None
        self._device_modes: tuple[OperationMode, ...] | None = None  # from 0x6502, read once
        self._cycle_period = sample_time
        self._rpdo: PdoLayout | None = None
        self._rpdo_codec: PdoCodec | None = None
        self._target_limits = (0, 0)
        self._tpdo_codecs: dict[int, PdoCodec] = {}
        self._feedback_at: dict[int, tuple[int, int]] = {}  # object index -> (TPDO COB-ID, slot)
        self._controlword = int(Command402.DISABLE_VOLTAGE)
        self._last_statusword = 0  # the statusword of the last state exchange (PDO or SDO)
        self._target_raw = 0
        self._operational = False
        self._connected = False  # a boot-up answered connect(): the drive is there to be stopped over SDO
        self._closed = False

        # canopen's EMCY consumer unpacks without a length check and would stop the callbacks of a short frame:
        # ours replaces it. canopen's NMT state tracking unpacks heartbeats and NMT commands unchecked too: ours
        # replace its subscriptions and pass it the well-formed frames only.
        emcy_cob = cob_id(FunctionCode.EMCY, self.node_id)
        self.network.unsubscribe(emcy_cob, self.node.emcy.on_emcy)
        self.network.subscribe(emcy_cob, self._on_emcy)
        heartbeat_cob = cob_id(FunctionCode.HEARTBEAT, self.node_id)
        self.network.unsubscribe(heartbeat_cob, self._master_nmt.on_heartbeat)
        self.network.subscribe(heartbeat_cob, self._on_heartbeat)
        self.network.unsubscribe(NMT_COB_ID, self._master_nmt.on_command)
        self.network.subscribe(NMT_COB_ID, self._on_nmt_command)
        self._net.join(self._begin_cycle)

    def _init_waits(self, bus: can.BusABC) -> None:
        """Every wait of the master runs on the bus's timebase (module docstring, "Waiting")."""
        self._timebase = timebase_of(bus)
        # on a synchronous bus the answer is in the queue when the request's send returns, or never comes
        self.node.sdo.RESPONSE_TIMEOUT = 0.0 if self._timebase.synchronous else self.cfg.sdo_timeout
        lockstep = self._timebase if isinstance(self._timebase, LockstepClock) else None
        self.heartbeat = HeartbeatMonitor(self.node_id, lockstep=lockstep)

    # --- construction -----------------------------------------------------------------------------------------

    @classmethod
    def open(cls, bus: can.BusABC, cfg: DriveConfig, *, sample_time: float,
             receiver: CyclicReceiver | None = None) -> Cia402Drive:
        """A master for drive ``cfg.node_id`` on ``bus`` with the EDS ``cfg.eds`` (default: the shipped one).

        ``receiver``: the TPDOs are received on the thread that waits for them (:mod:`drivers.cyclic_rx`; it
        stays the caller's, as the bus does). Raises :class:`~drivers.errors.EdsError` for a bad EDS. Nothing
        is sent until :meth:`connect`.
        """
        od = load_od(cfg.eds, cfg.node_id)
        return cls(bus, cfg, sample_time=sample_time, od=od, receiver=receiver)

    @classmethod
    def on_network(cls, network: DriveNetwork, cfg: DriveConfig, *, sample_time: float) -> Cia402Drive:
        """A master for drive ``cfg.node_id`` sharing ``network`` (its bus, receive path, SYNC, master heartbeat).

        Each drive keeps its own SDO client, NMT commands, PDO codecs, heartbeat supervision and errors: frames
        reach it by COB-ID through the network's one receive path. :meth:`sync` of any member sends the one SYNC
        and starts a new cycle on every member. Raises :class:`~drivers.errors.ConfigError` for a node id
        already on the network and :class:`~drivers.errors.EdsError` for a bad EDS.
        """
        od = load_od(cfg.eds, cfg.node_id)
        return cls(network.bus, cfg, sample_time=sample_time, od=od, network=network)

    # --- Drive: start-up --------------------------------------------------------------------------------------

    def connect(self) -> DeviceInfo:
        """NMT reset communication, wait for boot-up, NMT pre-operational, read identity (see module docstring).

        Starts the listening side first (:meth:`listen`). If the drive never answered (no boot-up), a failed connect
        stops it again, so no thread outlives the failure; once it answered, the listening side stays for
        :meth:`safe_stop` (the drive is there to be stopped) until :meth:`close`.
        """
        self.listen()
        try:
            return self._identify()
        except BaseException:
            if not self._connected:
                self._stop_listening()
            raise

    def listen(self) -> None:
        """Attach the frame tap, start the Notifier (canopen's listener, the tap, the counter) and the watchdog.

        :meth:`connect` calls it; commissioning, which talks SDO and NMT to a drive it must not reset, calls it
        instead. Idempotent; :meth:`close` stops it all.
        """
        self._require_open()
        if self._listening:
            return
        self._net.listen()
        self._listening = True
        if not self._timebase.synchronous:  # synchronous: time passes only in this thread, which checks anyway
            self.heartbeat.start_watchdog(self._on_heartbeat_lost, poll=HEARTBEAT_WATCHDOG_POLL)

    def _stop_listening(self) -> None:
        """Undo :meth:`listen` (safe when it never ran); a shared network keeps listening for the other drives."""
        self.heartbeat.stop_watchdog()
        self._listening = False
        if self._owns_network:
            self._net.close()

    def _identify(self) -> DeviceInfo:
        self._reset_communication()
        self._connected = True
        self._nmt(NmtCommand.ENTER_PRE_OPERATIONAL)
        device_type = self._read(Obj.DEVICE_TYPE, 0, _U32)
        if device_type & 0xFFFF != CIA402_PROFILE:
            raise DriveError(
                f"node {self.node_id} is not a CiA 402 drive: device type 0x{device_type:08X} (0x1000)"
            )
        identity = [self._read(Obj.IDENTITY, sub, _U32) for sub in IdentitySub]
        supported = self._supported_modes()
        self._device_modes = supported
        return DeviceInfo(
            node_id=self.node_id,
            vendor_id=identity[0],
            product_code=identity[1],
            revision=identity[2],
            serial=identity[3],
            device_type=device_type,
            nmt_state=NmtState.PRE_OPERATIONAL,
            supported_modes=supported,
        )

    def preflight(self, mode: OperationMode, cycle_period: float) -> PdoPlan:
        """What :meth:`configure` checks before it writes anything: the mode (0x6502), the PDOs the EDS allows
        (:func:`pdo_plan`), the settings it can encode; raises what ``configure`` would raise.

        ``commission enable`` runs it too, so a drive ``run`` would refuse is refused there as well. The plan's
        notes name the optional objects the drive lacks (also logged as warnings by ``configure``).
        """
        mode = OperationMode(mode)
        if not (cycle_period > 0 and math.isfinite(cycle_period)):
            raise ConfigError(f"must be a positive number of seconds, got {cycle_period}", key="cycle_period")
        supported = self._device_modes if self._device_modes is not None else self._supported_modes()
        if supported and mode not in supported:
            names = ", ".join(m.name for m in supported)
            raise ConfigError(f"node {self.node_id} does not support {mode.name} (0x6502 offers {names})",
                              key="drive.mode")
        plan = pdo_plan(mode, self.node_id, self.od)
        skipped = [f"0x{index:04X}:{sub:02X} not configured: the drive's EDS lacks it"
                   for index, sub, _, _, optional in self._settings(mode, cycle_period)
                   if optional and index not in self.od]
        return PdoPlan(plan.rpdos, plan.tpdos, (*plan.notes, *skipped))

    def configure(self, mode: OperationMode, cycle_period: float) -> None:
        """Configure PDOs, mode, timing and heartbeats over SDO, verify by reading back, then NMT start."""
        self._require_connected()
        mode = OperationMode(mode)
        plan = self.preflight(mode, cycle_period)
        for note in plan.notes:
            logger.warning("node %d: %s", self.node_id, note)
        self.heartbeat.disarm()
        self._operational = False
        self._nmt(NmtCommand.ENTER_PRE_OPERATIONAL)
        with self._cv:
            self._errors.clear()
            self._heartbeat_fault = False
            self._nmt_departure = None
        self._start_master_heartbeat()

        rpdos, tpdos = plan.rpdos, plan.tpdos
        for layouts, bases, direction in ((rpdos, RPDO_BASES, PdoDirection.RPDO),
                                          (tpdos, TPDO_BASES, PdoDirection.TPDO)):
            used = {layout.number: layout for layout in layouts}
            for number in range(1, len(bases) + 1):
                if number in used:
                    self._write_pdo(used[number])
                else:
                    self._disable_pdo(direction, number, cob_id(bases[number - 1], self.node_id))

        settings = self._settings(mode, cycle_period)
        written = [row for row in settings if (row[0] in self.od or not row[4]) and self._write_setting(row)]

        # read everything back: a drive may accept a write and keep another value
        for layout in (*rpdos, *tpdos):
            self._verify_pdo(layout)
        for index, sub, fmt, value, _ in written:
            self._expect(index, sub, fmt, value)
        self._wait_mode_display(mode)

        self._install_codecs(mode, rpdos, tpdos)
        self._mode = mode
        self._cycle_period = cycle_period
        self._controlword = int(Command402.DISABLE_VOLTAGE)
        self._target_raw = 0

        beats_before = self.heartbeat.beats
        self._nmt(NmtCommand.START)
        self._operational = True
        if self.cfg.heartbeat_producer_ms > 0:
            state = self.heartbeat.wait_for(
                lambda s: s == NmtState.OPERATIONAL,
                beats_before,
                timeout=self.cfg.state_timeout + 2 * self.cfg.heartbeat_producer_ms / 1000,
            )
            if state is None:
                raise DriveTimeoutError(
                    f"node {self.node_id} did not report NMT OPERATIONAL in its heartbeat after NMT start"
                )
            self.heartbeat.arm(self.cfg.heartbeat_timeout_factor * self.cfg.heartbeat_producer_ms / 1000)

    # --- Drive: CiA 402 state machine -------------------------------------------------------------------------

    def enable(self) -> None:
        """Controlword 0x06 / 0x07 / 0x0F until OPERATION_ENABLED (target held at 0)."""
        self._require_operational()
        self._target_raw = 0
        try:
            state = self._step(self._controlword).state
            for _ in range(len(State402) + 2):  # the path is at most 4 transitions; bounded against a looping drive
                if state is State402.OPERATION_ENABLED:
                    return
                if state is State402.FAULT:
                    raise DriveFaultError(
                        f"node {self.node_id} is in FAULT; fault_reset() first "
                        f"(statusword 0x{self._statusword():04X})"
                    )
                state = self._leave(state, ENABLE_PATH[state], goal=State402.OPERATION_ENABLED)
            raise StateTransitionError(
                f"node {self.node_id} never reached OPERATION_ENABLED (last state {state.name})"
            )
        except ProductError:
            self._fail_safe()
            raise

    def disable(self) -> None:
        """Disable voltage until SWITCH_ON_DISABLED (or FAULT, which disable voltage does not leave)."""
        self._require_connected()
        self._target_raw = 0
        self._drive_to(Command402.DISABLE_VOLTAGE, _DISABLE_GOAL, self.cfg.state_timeout)

    def quick_stop(self) -> None:
        """Quick stop until QUICK_STOP_ACTIVE, or SWITCH_ON_DISABLED (quick stop options 0..4, or not enabled)."""
        self._require_connected()
        self._target_raw = 0
        self._drive_to(Command402.QUICK_STOP, _QUICK_STOP_GOAL, self.cfg.state_timeout)

    def fault_reset(self) -> None:
        """Rising edge on controlword bit 7 until the drive leaves FAULT.

        After a heartbeat fault (EMCY 0x8130 from the drive, or the master lost the drive's heartbeat) the
        drive's communication is restored first: NMT reset communication, boot-up, and the last
        :meth:`configure` again (reset communication restores the drive's 0x1000..0x1FFF defaults).
        """
        self._require_connected()
        with self._cv:
            heartbeat_fault = self._heartbeat_fault
            self._errors.clear()
        if heartbeat_fault and self._mode is not None:
            mode, period = self._mode, self._cycle_period
            self.heartbeat.disarm()
            self._operational = False
            self._reset_communication()
            self.configure(mode, period)
        self._target_raw = 0
        self._command_state(int(Command402.DISABLE_VOLTAGE))  # bit 7 low first: the reset acts on the rising edge
        deadline = self._timebase.now() + self.cfg.state_timeout
        state = self._command_state(int(Command402.FAULT_RESET))
        while state in (State402.FAULT, State402.FAULT_REACTION_ACTIVE):
            if self._timebase.now() > deadline:
                self._command_state(int(Command402.DISABLE_VOLTAGE))
                raise StateTransitionError(
                    f"node {self.node_id} stuck in {state.name}: fault reset (controlword 0x80) for "
                    f"{self.cfg.state_timeout} s did not clear it"
                )
            state = self._command_state(int(Command402.FAULT_RESET))
        self._command_state(int(Command402.DISABLE_VOLTAGE))
        with self._cv:
            self._errors.clear()
            self._heartbeat_fault = False

    # --- Drive: cyclic path -----------------------------------------------------------------------------------

    def set_target(self, value: float) -> float:
        """Clamp to the mode's limit, scale, round and send RPDO1 (controlword + target); no SDO."""
        codec, rpdo = self._rpdo_codec, self._rpdo
        if self._closed or not self._operational or codec is None or rpdo is None:
            codec = self._require_codec()  # raises the reason (the checks above, inlined: this runs every cycle)
        cob = rpdo.cob_id if rpdo is not None else self._rpdo_cob()
        if not math.isfinite(value):
            raise DriveError(f"target {value} is not finite; not sent")
        cfg = self.cfg
        if self._mode is OperationMode.CYCLIC_SYNC_TORQUE:
            limit, scale = cfg.torque_limit, cfg.torque_scale
        else:
            limit, scale = cfg.velocity_limit, cfg.velocity_scale
        clamped = -limit if value < -limit else limit if value > limit else value
        low, high = self._target_limits
        raw = round(clamped * scale)
        raw = low if raw < low else high if raw > high else raw
        self._target_raw = raw
        self._send(data_frame(cob, codec.encode(self._controlword, raw)))
        return raw / scale

    def sync(self) -> int:
        """Send SYNC; TPDOs received from now on answer the returned cycle.

        On a synchronous bus one cycle period of simulated time passes since the previous SYNC first (the drive's
        and the master's heartbeat timers fire on the way), and the answering TPDOs are in when this returns.
        """
        if self._closed:  # _require_open's test, inlined: every cycle
            self._require_open()
        self._net.sync(self._cycle_period)
        return self._cycle  # only this thread changes it (in _begin_cycle, just now)

    def _begin_cycle(self) -> None:
        """The network is about to send SYNC: TPDOs received from now on answer the next cycle."""
        # the cyclic path takes the condition's lock itself: Condition.__enter__/__exit__ are Python-level wrappers
        # of it, calls every cycle that are all overhead (holding the lock is holding the condition)
        with self._lock:
            self._cycle += 1
            self._parts.clear()

    def wait_feedback(self, timeout: float) -> Feedback:
        """Block until the TPDO set answering the last SYNC arrived (see :class:`~drivers.drive.Drive`)."""
        try:
            return self._await_feedback(timeout, raise_on_fault=True)
        except FeedbackTimeoutError:
            # not a stop: the caller decides whether one unanswered SYNC is fatal (the bench counts a lost feedback
            # and holds the last good one); the drive keeps its last command meanwhile
            raise
        except (ProductError, can.CanError) as exc:
            with self._cv:
                if exc is self._nmt_departure:
                    self._nmt_departure = None  # the caller has it
            self._fail_safe()
            raise

    def safe_stop(self) -> StopReport:
        """Quick stop, zero target, disable voltage, confirmed by reading the drive's statusword; never raises.

        The paths of :class:`~drivers.drive.StopPath` are tried in order until one confirms a disabled power stage:
        the RPDO (only while the drive's heartbeat says OPERATIONAL: outside it a drive ignores RPDOs), an SDO
        write of 0x6040 (not in NMT STOPPED), NMT enter pre-operational then SDO (which also triggers the drive's
        own 0x6007 reaction), and last NMT reset node (an application reset switches the power stage off). The
        report says what was read back, or that nothing could be.
        """
        if self._closed or not self._connected:
            return StopReport(commanded=False, confirmed=False)
        attempts: list[str] = []
        statusword: int | None = None
        state: State402 | None = None
        for path in StopPath:
            self._target_raw = 0
            try:
                statusword = self._stop_via(path)
                state = decode_state(statusword)
            except Exception as exc:  # safe_stop never raises: every exit path calls it
                attempts.append(f"{path}: {exc}")
                logger.info("safe stop of node %d via %s failed: %s", self.node_id, path, exc)
                continue
            if state in DISABLED_STATES:
                report = StopReport(True, True, state, statusword, path, tuple(attempts), self._pending_faults())
                logger.info("%s", report.describe(self.node_id))
                return report
            attempts.append(f"{path}: drive still {state.name}")
        report = StopReport(True, False, state, statusword, None, tuple(attempts), self._pending_faults())
        logger.info("%s", report.describe(self.node_id))  # the caller has the report; the CLI says it in its one line
        return report

    def close(self) -> None:
        """NMT pre-operational and consumer heartbeat off (best effort), then release the Notifier, producer, tap."""
        if self._closed:
            return
        self.heartbeat.disarm()  # our own NMT command below is not a drive leaving OPERATIONAL
        if self._operational:
            try:
                self._nmt(NmtCommand.ENTER_PRE_OPERATIONAL)
                self._write(Obj.CONSUMER_HEARTBEAT_TIME, 1, _U32, 0)
            except Exception as exc:  # the drive may be gone; closing must still release everything
                logger.info("close: could not park node %d: %s", self.node_id, exc)
        self._operational = False
        self._closed = True
        self._net.leave(self._begin_cycle)
        self._stop_listening()

    def add_frame_listener(self, listener: FrameListener) -> None:
        """Call ``listener(message, "tx" | "rx")`` for every frame on the bus (on a shared network: every drive's);
        runs on the sending and the Notifier thread."""
        self._net.tap.add_listener(listener)

    # --- SDO access for commissioning (not for the cyclic path) ----------------------------------------------

    def sdo_upload(self, index: int, subindex: int) -> bytes:
        """Raw SDO upload (start-up and commissioning, never the cyclic path); failures as product errors."""
        with self._sdo_errors(index, subindex, "upload"):
            return bytes(self.node.sdo.upload(index, subindex))

    def sdo_download(self, index: int, subindex: int, data: bytes) -> None:
        """Raw SDO download (start-up and commissioning, never the cyclic path); failures as product errors."""
        with self._sdo_errors(index, subindex, "download"):
            self.node.sdo.download(index, subindex, data)

    def read_object(self, index: int, subindex: int = 0) -> int:
        """SDO upload of an integer object, typed by the EDS (or the CiA 402 standard); SdoError on abort."""
        variable = mapped_variable(self.od, index, subindex)
        return self._read(index, subindex, _format(variable))

    def write_object(self, index: int, subindex: int, value: int) -> None:
        """SDO download of an integer object, typed by the EDS (or the CiA 402 standard); SdoError on abort."""
        variable = mapped_variable(self.od, index, subindex)
        self._write(index, subindex, _format(variable), value)

    # --- observation ------------------------------------------------------------------------------------------

    @property
    def stats(self) -> RxStats:
        """Receive-side counters."""
        with self._cv:
            return RxStats(self._tpdo_frames, self._emcy_frames, self._heartbeat_frames, self._bad_frames,
                           self._net.unknown.count)

    @property
    def bad_frames(self) -> int:
        """Frames from the drive that did not decode (:attr:`RxStats.bad_frames`)."""
        with self._cv:
            return self._bad_frames

    @property
    def pdo_codecs(self) -> dict[int, PdoCodec]:
        """The configured PDO codecs by COB-ID (RPDO and TPDOs), e.g. for :func:`drivers.trace.describe_frame`."""
        codecs = dict(self._tpdo_codecs)
        if self._rpdo is not None and self._rpdo_codec is not None:
            codecs[self._rpdo.cob_id] = self._rpdo_codec
        return codecs

    @property
    def last_feedback(self) -> Feedback | None:
        """The latest complete feedback, whatever cycle it answered."""
        with self._cv:
            return self._feedback

    @property
    def controlword(self) -> int:
        """The controlword the master sends with every RPDO."""
        return self._controlword

    @property
    def cycle(self) -> int:
        """The master's SYNC counter."""
        with self._cv:
            return self._cycle

    # --- Notifier-thread callbacks (guarded by self._cv) ------------------------------------------------------

    def _on_tpdo(self, can_id: int, data: bytearray, timestamp: float) -> None:
        received = time.monotonic()
        codec = self._tpdo_codecs.get(can_id)
        if codec is None:
            return
        try:
            values = codec.decode(data)
        except ProtocolError as exc:
            self._post_error(exc, bad_frame=True)
            return
        with self._lock:
            self._tpdo_frames += 1
            self._parts[can_id] = values
            if len(self._parts) < len(self._tpdo_codecs):
                return
            try:
                feedback = self._assemble(received)
            except ProtocolError as exc:
                self._post_error(exc, bad_frame=True)  # self._cv is reentrant (an RLock)
            else:
                self._feedback = feedback
            if not self._timebase.synchronous:  # on a synchronous bus nobody waits: the answer is in before
                self._cv.notify_all()

    def _assemble(self, received: float) -> Feedback:
        """Feedback from the complete TPDO set of the current cycle (caller holds self._cv)."""
        parts = self._parts
        where = self._feedback_at
        cob, slot = where[Obj.STATUSWORD]
        statusword = parts[cob][slot]
        state = _STATES.get(statusword)
        if state is None:
            try:
                state = _STATES[statusword] = decode_state(statusword)
            except ValueError as exc:
                raise ProtocolError(f"node {self.node_id}: {exc}") from exc
        cob, slot = where[Obj.VELOCITY_ACTUAL_VALUE]
        velocity = parts[cob][slot]
        torque: float = math.nan  # NaN: not mapped
        position = 0  # 0: not mapped
        if Obj.TORQUE_ACTUAL_VALUE in where:
            cob, slot = where[Obj.TORQUE_ACTUAL_VALUE]
            torque = parts[cob][slot]
        if Obj.POSITION_ACTUAL_VALUE in where:
            cob, slot = where[Obj.POSITION_ACTUAL_VALUE]
            position = parts[cob][slot]
        return Feedback(
            cycle=self._cycle,
            statusword=statusword,
            state=state,
            velocity=velocity / self.cfg.velocity_scale,
            torque=torque / self.cfg.torque_scale,
            position=position,
            timestamp=received,
        )

    def _on_emcy(self, can_id: int, data: bytearray, timestamp: float) -> None:
        try:
            emergency = decode_emcy(data, time.monotonic())
        except ProtocolError as exc:
            self._post_error(exc, bad_frame=True)
            return
        with self._cv:
            self._emcy_frames += 1
            if emergency.is_reset:
                return
            if emergency.code == EmcyCode.HEARTBEAT_LOSS:
                self._heartbeat_fault = True
            self._errors.append(emergency.error())
            self._cv.notify_all()
        logger.warning("node %d: %s", self.node_id, emergency.error())

    def _on_heartbeat(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if len(data) != 1:
            self._post_error(ProtocolError(f"heartbeat of node {self.node_id} has DLC {len(data)}, not 1"),
                             bad_frame=True)
            return
        with self._cv:
            self._heartbeat_frames += 1
        before = self.heartbeat.last_state
        self.heartbeat.beat(data[0])
        state = self.heartbeat.last_state
        if (state is not None and state != NmtState.OPERATIONAL and before == NmtState.OPERATIONAL
                and self._operational and self.heartbeat.timeout > 0):
            departure = DriveNmtStateError(
                f"node {self.node_id} left NMT OPERATIONAL: its heartbeat reports {_nmt_name(state)} while the "
                "bench runs (a drive outside OPERATIONAL ignores RPDOs)")
            with self._cv:
                self._nmt_departure = departure
            self._post_error(departure)
        self._master_nmt.on_heartbeat(can_id, data, timestamp)

    def _on_nmt_command(self, can_id: int, data: bytearray, timestamp: float) -> None:
        if len(data) >= 2:  # command and node id; a drive ignores a shorter frame, and so does the tracking here
            self._master_nmt.on_command(can_id, data, timestamp)

    def _on_heartbeat_lost(self, error: HeartbeatLostError) -> None:
        self._post_error(error)
        with self._cv:
            self._heartbeat_fault = True

    def _post_error(self, error: ProductError, *, bad_frame: bool = False) -> None:
        with self._cv:
            if bad_frame:
                self._bad_frames += 1
                if not self.fatal_bad_frames:
                    return
                error = BadFrameError(str(error))
            self._errors.append(error)
            self._cv.notify_all()

    # --- cyclic helpers ---------------------------------------------------------------------------------------

    def _await_feedback(self, timeout: float, *, raise_on_fault: bool, raise_errors: bool = True) -> Feedback:
        receiver = self._net.receiver
        if receiver is not None:
            return self._receive_feedback(receiver, timeout, raise_on_fault=raise_on_fault, raise_errors=raise_errors)
        synchronous = self._timebase.synchronous
        deadline = time.monotonic() + timeout
        with self._lock:
            cycle = self._cycle
            while True:
                feedback = self._answer(cycle, raise_on_fault=raise_on_fault, raise_errors=raise_errors)
                if feedback is not None:
                    return feedback
                remaining = deadline - time.monotonic()
                if remaining <= 0 or synchronous:
                    raise self._no_answer(cycle, "on the synchronous bus" if synchronous else f"within {timeout:.3f} s")
                self._cv.wait(min(remaining, FEEDBACK_POLL))

    def _receive_feedback(self, receiver: CyclicReceiver, timeout: float, *, raise_on_fault: bool,
                          raise_errors: bool) -> Feedback:
        """:meth:`_await_feedback` with the TPDOs received on this thread (:mod:`drivers.cyclic_rx`).

        The lock is taken only to look at the shared state, never across a ``recv``: the Notifier thread posts its
        errors (EMCY, heartbeat) meanwhile, and they are seen after at most :data:`RECEIVE_POLL`.
        """
        start = time.monotonic()
        deadline = start + timeout
        spin_until = start + receiver.spin
        cycle = self._cycle  # only this thread changes it
        while True:
            with self._lock:
                feedback = self._answer(cycle, raise_on_fault=raise_on_fault, raise_errors=raise_errors)
            if feedback is not None:
                return feedback
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                if receiver.drain():  # frames already received count, as the Notifier would have dispatched them
                    continue
                with self._lock:
                    raise self._no_answer(cycle, f"within {timeout:.3f} s")
            receiver.poll(min(remaining, RECEIVE_POLL), spin_until)

    def _answer(self, cycle: int, *, raise_on_fault: bool, raise_errors: bool) -> Feedback | None:
        """This cycle's feedback if it is in, after raising what is pending (caller holds self._cv)."""
        if self._errors and raise_errors:
            raise self._errors.popleft()
        try:
            self.heartbeat.check()
        except HeartbeatLostError:
            self._heartbeat_fault = True
            raise
        feedback = self._feedback
        if feedback is not None and feedback.cycle == cycle:
            if raise_on_fault and feedback.statusword & _FAULT_BIT:
                raise DriveFaultError(
                    f"node {self.node_id} reports a fault: statusword 0x{feedback.statusword:04X} "
                    f"({feedback.state.name})"
                )
            return feedback
        return None

    def _no_answer(self, cycle: int, waited: str) -> DriveError:
        """The error of an unanswered SYNC: the receive thread's own failure if it stopped, else a timeout."""
        notifier = self.network.notifier
        if notifier is not None and notifier.exception is not None:
            return DriveError(f"the CAN receive thread stopped: {notifier.exception}")
        return FeedbackTimeoutError(f"no TPDO set from node {self.node_id} answered SYNC {cycle} {waited}")

    def _exchange_timeout(self) -> float:
        return min(self.cfg.state_timeout, max(0.2, 10 * self._cycle_period))

    def _step(self, controlword: int, *, ignore_errors: bool = False) -> Feedback:
        """One cycle with ``controlword``: RPDO, SYNC, feedback (paced at the cycle period)."""
        start = self._timebase.now()
        self._controlword = controlword
        codec = self._require_codec()
        self._send(data_frame(self._rpdo_cob(), codec.encode(controlword, self._target_raw)))
        self.sync()
        feedback = self._await_feedback(self._exchange_timeout(), raise_on_fault=False, raise_errors=not ignore_errors)
        self._timebase.sleep(self._cycle_period - (self._timebase.now() - start))
        return feedback

    def _leave(self, state: State402, command: Command402 | None, *, goal: State402) -> State402:
        """Repeat ``command`` until the drive leaves ``state``; StateTransitionError naming it otherwise."""
        controlword = self._controlword if command is None else int(command)
        deadline = self._timebase.now() + self.cfg.state_timeout
        while True:
            new_state = self._step(controlword).state
            if new_state is not state:
                return new_state
            if self._timebase.now() > deadline:
                what = f"controlword 0x{controlword:02X} ({command.name})" if command else "waiting"
                raise StateTransitionError(
                    f"node {self.node_id} stuck in {state.name}: {what} for {self.cfg.state_timeout} s did not "
                    f"leave it (wanted {goal.name})"
                )

    def _drive_to(self, command: Command402, goal: frozenset[State402], timeout: float, *,
                  ignore_errors: bool = False) -> None:
        """Send ``command`` until the drive is in one of ``goal`` (over PDO when operational, else SDO).

        ``ignore_errors``: errors the drive reported earlier (already raised to the caller, or about to be in the
        stop report) do not interrupt the exchange; a stop must go on through them.
        """
        deadline = self._timebase.now() + timeout
        while True:
            state = self._command_state(int(command), ignore_errors=ignore_errors)
            if state in goal:
                return
            if self._timebase.now() > deadline:
                names = " or ".join(sorted(s.name for s in goal))
                raise StateTransitionError(
                    f"node {self.node_id} stuck in {state.name}: controlword 0x{int(command):02X} "
                    f"({command.name}) for {timeout} s did not reach {names}"
                )

    def _command_state(self, controlword: int, *, ignore_errors: bool = False) -> State402:
        if self._operational and self._rpdo_codec is not None:
            feedback = self._step(controlword, ignore_errors=ignore_errors)
            self._last_statusword = feedback.statusword
            return feedback.state
        self._controlword = controlword
        self._write(Obj.CONTROLWORD, 0, _U16, controlword)
        self._timebase.sleep(self._cycle_period)
        statusword = self._read(Obj.STATUSWORD, 0, _U16)
        self._last_statusword = statusword
        try:
            return decode_state(statusword)
        except ValueError as exc:
            raise ProtocolError(f"node {self.node_id}: {exc}") from exc

    def _stop_via(self, path: StopPath) -> int:
        """Quick stop then disable voltage through ``path``; the statusword read back afterwards."""
        short = min(self.cfg.state_timeout, 0.5)
        nmt = self.heartbeat.last_state
        if path is StopPath.PDO:
            if not self._operational or self._rpdo_codec is None:
                raise DriveError("no PDO path (the drive was never started)")
            if nmt is not None and nmt != NmtState.OPERATIONAL:
                raise DriveError(f"the drive reports NMT {_nmt_name(nmt)}: it ignores RPDOs")
        else:
            self._operational = False  # from here on, commands go over SDO
            if path is StopPath.SDO and nmt == NmtState.STOPPED:
                raise DriveError("the drive reports NMT STOPPED: it answers no SDO")
            if path is StopPath.NMT_SDO:
                self._enter_nmt(NmtCommand.ENTER_PRE_OPERATIONAL, (NmtState.PRE_OPERATIONAL,), short)
            elif path is StopPath.NMT_RESET:
                self._enter_nmt(NmtCommand.RESET_NODE, (NmtState.INITIALISING, NmtState.PRE_OPERATIONAL),
                                self.cfg.state_timeout)
                return self._read(Obj.STATUSWORD, 0, _U16)  # the application reset itself disabled the power stage
        self._drive_to(Command402.QUICK_STOP, _QUICK_STOP_GOAL, short, ignore_errors=True)
        self._drive_to(Command402.DISABLE_VOLTAGE, _DISABLE_GOAL, short, ignore_errors=True)
        return self._last_statusword

    def _enter_nmt(self, command: NmtCommand, states: tuple[NmtState, ...], timeout: float) -> None:
        """Send NMT ``command`` and wait (bounded) for a heartbeat in one of ``states``; a missing heartbeat is
        not an error here: the SDO read that follows is what confirms."""
        self.heartbeat.disarm()
        beats_before = self.heartbeat.beats
        self._nmt(command)
        self.heartbeat.wait_for(lambda s: s in states, beats_before, timeout=timeout)

    def _pending_faults(self) -> tuple[str, ...]:
        """Errors the drive reported that nobody raised yet (e.g. an EMCY during the final stop)."""
        with self._cv:
            errors = list(self._errors)
            if self._nmt_departure is not None and self._nmt_departure not in errors:
                errors.append(self._nmt_departure)  # raised by a stop attempt, never to the caller: say it
            self._errors.clear()
            self._nmt_departure = None
        return tuple(str(error) for error in errors)

    def _fail_safe(self, command: Command402 = Command402.QUICK_STOP) -> None:
        """Best effort: command ``command`` with target 0 and apply it with one SYNC; never raises."""
        self._controlword = int(command)
        self._target_raw = 0
        if self._closed or self._rpdo_codec is None or not self._operational:
            return
        try:
            self._send(data_frame(self._rpdo_cob(), self._rpdo_codec.encode(self._controlword, 0)))
            self.sync()
        except Exception as exc:  # called while another error propagates; must not replace it
            logger.warning("could not command %s on node %d: %s", command.name, self.node_id, exc)

    def _send(self, message: can.Message) -> None:
        try:
            with self.network.send_lock:
                self._bus.send(message)
        except can.CanError as exc:
            raise DriveError(f"cannot send 0x{message.arbitration_id:03X} on the bus: {exc}") from exc

    def _statusword(self) -> int:
        feedback = self.last_feedback
        return feedback.statusword if feedback is not None else 0

    def _rpdo_cob(self) -> int:
        if self._rpdo is None:
            raise DriveError(f"node {self.node_id} is not configured; call configure() first")
        return self._rpdo.cob_id

    def _require_codec(self) -> PdoCodec:
        self._require_operational()
        if self._rpdo_codec is None:
            raise DriveError(f"node {self.node_id} is not configured; call configure() first")
        return self._rpdo_codec

    def _require_open(self) -> None:
        if self._closed:
            raise DriveError(f"drive {self.node_id} is closed")

    def _require_connected(self) -> None:
        self._require_open()
        if not self._connected:
            raise DriveError(f"node {self.node_id} is not connected; call connect() first")

    def _require_operational(self) -> None:
        self._require_open()
        if not self._operational:
            raise DriveError(f"node {self.node_id} is not operational; call configure() first")

    # --- start-up helpers (SDO / NMT) -------------------------------------------------------------------------

    def _nmt(self, command: NmtCommand) -> None:
        try:
            self._master_nmt.send_command(int(command))
        except can.CanError as exc:
            raise DriveError(f"cannot send NMT {command.name} to node {self.node_id}: {exc}") from exc

    def _reset_communication(self) -> None:
        beats_before = self.heartbeat.beats
        self._nmt(NmtCommand.RESET_COMMUNICATION)
        # boot-up (state 0) is what CiA 301 sends; a heartbeat in pre-operational also proves the reset is done
        state = self.heartbeat.wait_for(lambda s: s in (NmtState.INITIALISING, NmtState.PRE_OPERATIONAL),
                                        beats_before, timeout=self.cfg.state_timeout)
        if state is None:
            raise DriveTimeoutError(
                f"no boot-up from node {self.node_id} within {self.cfg.state_timeout} s after NMT reset "
                "communication: is the drive powered, on this bus, with this node id?"
            )

    def _start_master_heartbeat(self) -> None:
        if self.cfg.heartbeat_consumer_ms == 0:
            return
        period = self.cfg.heartbeat_consumer_ms / 1000 / MASTER_HEARTBEATS_PER_CONSUMER_TIME
        self._net.start_master_heartbeat(self.cfg.master_node_id, period)

    def settings(self, mode: OperationMode, cycle_period: float) -> list[tuple[int, int, int, bool]]:
        """The objects :meth:`configure` writes after the PDOs, in order, as ``(index, sub-index, value,
        optional)``: ``commission check`` reads them and ``commission info --dcf`` records them."""
        return [(index, sub, value, optional) for index, sub, _, value, optional in self._settings(mode, cycle_period)]

    def _settings(self, mode: OperationMode, cycle_period: float) -> list[_Setting]:
        """The objects ``configure`` writes after the PDOs, in order: (index, sub, format, value, optional)."""
        consumer = HeartbeatConsumerEntry(self.cfg.master_node_id, self.cfg.heartbeat_consumer_ms).encode()
        rows: list[_Setting] = [
            (Obj.MODES_OF_OPERATION, 0, _I8, int(mode), False),
            (Obj.QUICK_STOP_OPTION, 0, _I16, self.cfg.quick_stop_option, True),  # optional in CiA 402
            (Obj.ABORT_CONNECTION_OPTION, 0, _I16, self.cfg.abort_connection_option, True),  # optional
            (Obj.COMMUNICATION_CYCLE_PERIOD, 0, _U32, round(cycle_period * 1e6), True),  # optional in CiA 301
        ]
        if Obj.INTERPOLATION_TIME_PERIOD in self.od:  # cyclic synchronous modes take their cycle from here
            value, exponent = interpolation_time_period(cycle_period)
            rows += [
                (Obj.INTERPOLATION_TIME_PERIOD, 1, _U8, value, True),
                (Obj.INTERPOLATION_TIME_PERIOD, 2, _I8, exponent, True),
            ]
        rows += [
            (Obj.PRODUCER_HEARTBEAT_TIME, 0, _U16, self.cfg.heartbeat_producer_ms, False),
            (Obj.CONSUMER_HEARTBEAT_TIME, 1, _U32, consumer, True),  # optional: the drive then cannot watch us
        ]
        return rows

    def _write_setting(self, row: _Setting) -> bool:
        """Write one setting; an optional object the drive lacks is skipped (False) with a warning."""
        index, sub, fmt, value, optional = row
        try:
            self._write(index, sub, fmt, value)
        except SdoError as exc:
            if optional and exc.abort_code in (SdoAbortCode.NO_OBJECT, SdoAbortCode.NO_SUBINDEX):
                logger.warning("node %d lacks optional object 0x%04X:%02X; not configured", self.node_id, index, sub)
                return False
            raise
        return True

    def _supported_modes(self) -> tuple[OperationMode, ...]:
        try:
            bits = self._read(Obj.SUPPORTED_DRIVE_MODES, 0, _U32)
        except SdoError as exc:
            if exc.abort_code in (SdoAbortCode.NO_OBJECT, SdoAbortCode.NO_SUBINDEX):
                return ()  # 0x6502 is optional: any mode may be tried
            raise
        return tuple(mode for mode, bit in SUPPORTED_MODE_BITS.items() if bits & bit)

    def _write_pdo(self, layout: PdoLayout) -> None:
        """CiA 301 PDO reconfiguration: disable, transmission type, count 0, entries, count, enable."""
        com, mapping = layout.communication_index, layout.mapping_index
        self._write(com, 1, _U32, CobIdEntry(layout.cob_id, valid=False).encode())
        self._write(com, 2, _U8, int(layout.transmission_type))
        self._write(mapping, 0, _U8, 0)
        for sub, variable in enumerate(layout.variables, start=1):
            self._write(mapping, sub, _U32, variable.mapping_entry)
        self._write(mapping, 0, _U8, len(layout.variables))
        self._write(com, 1, _U32, layout.cob_id)

    def _disable_pdo(self, direction: PdoDirection, number: int, default_cob: int) -> None:
        layout = PdoLayout(direction, number, default_cob, ())
        try:
            self._write(layout.communication_index, 1, _U32, CobIdEntry(default_cob, valid=False).encode())
        except SdoError as exc:
            if exc.abort_code != SdoAbortCode.NO_OBJECT:
                raise  # the drive has fewer PDOs than four: nothing to disable

    def _verify_pdo(self, layout: PdoLayout) -> None:
        com, mapping = layout.communication_index, layout.mapping_index
        self._expect(com, 1, _U32, layout.cob_id, mask=0x9FFF_FFFF)  # bit 30 (RTR) is the drive's business
        self._expect(com, 2, _U8, int(layout.transmission_type))
        self._expect(mapping, 0, _U8, len(layout.variables))
        for sub, variable in enumerate(layout.variables, start=1):
            self._expect(mapping, sub, _U32, variable.mapping_entry)

    def _wait_mode_display(self, mode: OperationMode) -> None:
        deadline = self._timebase.now() + self.cfg.state_timeout
        while True:
            shown = self._read(Obj.MODES_OF_OPERATION_DISPLAY, 0, _I8)
            if shown == mode:
                return
            if self._timebase.now() > deadline:
                raise DriveError(
                    f"node {self.node_id}: 0x6061 shows mode {shown}, not {int(mode)} ({mode.name}) "
                    f"{self.cfg.state_timeout} s after writing 0x6060"
                )
            self._timebase.sleep(0.01)

    def _install_codecs(self, mode: OperationMode, rpdos: Iterable[PdoLayout], tpdos: Iterable[PdoLayout]) -> None:
        for cob in list(self._tpdo_codecs):
            self._net.unsubscribe_cyclic(cob, self._on_tpdo)
        rpdo = next(iter(rpdos))
        codec = rpdo.codec()
        target = codec.variables[1]
        tpdo_codecs = {layout.cob_id: layout.codec() for layout in tpdos}
        mapped = {variable.index for c in tpdo_codecs.values() for variable in c.variables}
        missing = [f"0x{index:04X}" for index in _REQUIRED_FEEDBACK if index not in mapped]
        if missing:
            raise DriveError(f"TPDO mapping lacks {', '.join(missing)}")
        # where each feedback object sits: (TPDO COB-ID, position in the decoded values); the last mapping wins
        feedback_at = {variable.index: (cob, slot) for cob, c in tpdo_codecs.items()
                       for slot, variable in enumerate(c.variables)}
        with self._cv:
            self._tpdo_codecs = tpdo_codecs
            self._feedback_at = feedback_at
            self._parts.clear()
            self._feedback = None
        self._rpdo, self._rpdo_codec = rpdo, codec
        self._target_limits = (target.minimum, target.maximum)
        for cob in tpdo_codecs:
            self._net.subscribe_cyclic(cob, self._on_tpdo)

    @contextlib.contextmanager
    def _sdo_errors(self, index: int, subindex: int, transfer: str) -> Iterator[None]:
        """canopen's SDO exceptions as the product's: an abort is an ``SdoError`` with its decoded meaning, no
        answer is a ``DriveTimeoutError`` naming the object, a frame that cannot be sent is a ``DriveError``."""
        try:
            yield
        except SdoAbortedError as exc:
            raise SdoError(index, subindex, exc.code, sdo_abort_text(exc.code)) from exc
        except SdoCommunicationError as exc:
            raise DriveTimeoutError(
                f"node {self.node_id}: no valid SDO response for 0x{index:04X}:{subindex:02X} within "
                f"{self.cfg.sdo_timeout} s ({exc}): is the drive on this bus with this node id?"
            ) from exc
        except can.CanError as exc:
            raise DriveError(f"SDO {transfer} 0x{index:04X}:{subindex:02X} could not be sent: {exc}") from exc

    def _read(self, index: int, subindex: int, fmt: tuple[str, bool]) -> int:
        code, signed = fmt
        size = struct.calcsize(code)
        data = self.sdo_upload(index, subindex)
        if len(data) < size:
            raise SdoError(index, subindex, int(SdoAbortCode.LENGTH_TOO_LOW),
                           f"answered {len(data)} bytes, expected {size}")
        return int.from_bytes(data[:size], "little", signed=signed)

    def _write(self, index: int, subindex: int, fmt: tuple[str, bool], value: int) -> None:
        code, _ = fmt
        try:
            data = struct.pack("<" + code, value)
        except struct.error as exc:
            raise ConfigError(f"0x{index:04X}:{subindex:02X} = {value} does not fit its type: {exc}") from exc
        self.sdo_download(index, subindex, data)

    def _expect(self, index: int, subindex: int, fmt: tuple[str, bool], value: int, *, mask: int = -1) -> None:
        read = self._read(index, subindex, fmt)
        if read & mask != value & mask:
            raise DriveError(
                f"node {self.node_id}: 0x{index:04X}:{subindex:02X} reads back {read} (0x{read:X}) after writing "
                f"{value} (0x{value:X})"
            )

