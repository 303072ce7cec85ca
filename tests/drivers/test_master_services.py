"""The CiA 402 master's service objects (:mod:`drivers.master`), each on its own, with no bus.

Every service is built on a :class:`~drivers.master.link.MasterLink` whose network, bus, SDO client and NMT master
are fakes written here: frames sent are recorded, SDO objects live in a dict that reads back what was written, time
passes only when the code sleeps. Where a service needs a drive to answer (the 402 commands, the stop, start-up), a
small scripted drive answers from the CiA 402 tables (the standard's statusword coding and transitions, written here,
not taken from the master). The master composed on the in-process bus is tested by tests/test_master_*.py.
"""

from __future__ import annotations

import logging
import struct
import threading
import uuid
from collections.abc import Callable
from types import SimpleNamespace
from typing import cast

import can
import canopen
import pytest
from canopen.objectdictionary import INTEGER8, UNSIGNED8, ObjectDictionary, ODRecord, ODVariable
from canopen.sdo import SdoAbortedError, SdoCommunicationError

from drivers.cia301 import NmtCommand, NmtState, SdoAbortCode
from drivers.cia402 import Obj, OperationMode, State402
from drivers.cia402_master import Cia402Drive
from drivers.config import DriveConfig
from drivers.drive import StopPath
from drivers.errors import (
    BadFrameError,
    ConfigError,
    DriveError,
    DriveFaultError,
    DriveNmtStateError,
    DriveTimeoutError,
    EmergencyError,
    FeedbackTimeoutError,
    HeartbeatLostError,
    ProtocolError,
    SdoError,
    StateTransitionError,
)
from drivers.heartbeat import HeartbeatMonitor
from drivers.inprocess import InProcessBus
from drivers.master.cyclic import CyclicPath
from drivers.master.emergency import EmcyConsumer
from drivers.master.inbox import Inbox
from drivers.master.link import MasterLink
from drivers.master.nmt_client import NmtClient
from drivers.master.plan import interpolation_time_period, pdo_plan, settings_rows
from drivers.master.safe_stop import SafeStop
from drivers.master.sdo_client import I8, I16, U16, U32, SdoClient
from drivers.master.startup import StartUp
from drivers.master.state402 import PowerStateCommands
from drivers.master.supervision import DriveSupervision
from drivers.network import DriveNetwork
from drivers.od import load_od

NODE = 3
CFG = DriveConfig(node_id=NODE, state_timeout=0.05, heartbeat_producer_ms=100, heartbeat_consumer_ms=500)
OD = load_od(None, NODE)
PERIOD = 0.001

#: CiA 402-2 statusword of each state (bits 0-3, 5, 6), independent of drivers.cia402's table
STATUSWORD = {
    State402.SWITCH_ON_DISABLED: 0x0040, State402.READY_TO_SWITCH_ON: 0x0021, State402.SWITCHED_ON: 0x0023,
    State402.OPERATION_ENABLED: 0x0027, State402.QUICK_STOP_ACTIVE: 0x0007, State402.FAULT: 0x0008,
}
#: CiA 402-2 transitions the scripted drive makes: (state, controlword) -> next state
TRANSITIONS = {
    (State402.SWITCH_ON_DISABLED, 0x06): State402.READY_TO_SWITCH_ON,
    (State402.READY_TO_SWITCH_ON, 0x07): State402.SWITCHED_ON,
    (State402.SWITCHED_ON, 0x0F): State402.OPERATION_ENABLED,
    (State402.OPERATION_ENABLED, 0x02): State402.QUICK_STOP_ACTIVE,
    (State402.FAULT, 0x80): State402.SWITCH_ON_DISABLED,
}


# --- fakes ------------------------------------------------------------------------------------------------------


class Clock:
    """A synchronous timebase: time passes only when the code sleeps."""

    synchronous = True

    def __init__(self) -> None:
        self.t = 0.0

    def now(self) -> float:
        return self.t

    def sleep(self, seconds: float) -> None:
        self.t += max(0.0, seconds)


class Bus:
    def __init__(self) -> None:
        self.sent: list[can.Message] = []
        self.error: Exception | None = None

    def send(self, message: can.Message, timeout: float | None = None) -> None:
        if self.error is not None:
            raise self.error
        self.sent.append(message)


class Net:
    """What the services use of a DriveNetwork: members' cycles, SYNC, cyclic subscriptions, the master heartbeat."""

    def __init__(self) -> None:
        self.bus = Bus()
        self.network = SimpleNamespace(send_lock=threading.Lock(), notifier=None)
        self.receiver = None
        self.members: list[Callable[[], None]] = []
        self.cyclic: dict[int, Callable[[int, bytearray, float], None]] = {}
        self.syncs = 0
        self.on_sync: Callable[[], None] = lambda: None
        self.heartbeats: list[tuple[int, float]] = []
        self.counts_on_echo = False  # the loop's SYNC (or a thread's), counted as sent

    @property
    def syncs_sent(self) -> int:
        """The network's count of SYNCs sent (``DriveNetwork.syncs_sent``: what a send returns)."""
        return self.syncs

    def sync(self, sample_time: float) -> None:
        for begin_cycle in self.members:
            begin_cycle()
        self.syncs += 1
        self.on_sync()

    def subscribe_cyclic(self, can_id: int, callback: Callable[[int, bytearray, float], None]) -> None:
        self.cyclic[can_id] = callback

    def unsubscribe_cyclic(self, can_id: int, callback: Callable[[int, bytearray, float], None]) -> None:
        del self.cyclic[can_id]

    def start_master_heartbeat(self, master_node_id: int, period: float) -> None:
        self.heartbeats.append((master_node_id, period))


class Sdo:
    """canopen's SDO client over a dict: objects read back what was written; ``hooks`` run after a download."""

    RESPONSE_TIMEOUT = 0.3

    def __init__(self, store: dict[tuple[int, int], bytes] | None = None) -> None:
        self.store = dict(store or {})
        self.fail: dict[tuple[int, int], Exception] = {}
        self.downloads: list[tuple[int, int, bytes]] = []
        self.hooks: dict[tuple[int, int], Callable[[bytes], None]] = {}
        self.keep: set[tuple[int, int]] = set()  # written, but the drive keeps its old value

    def upload(self, index: int, subindex: int) -> bytes:
        if (index, subindex) in self.fail:
            raise self.fail[index, subindex]
        if (index, subindex) not in self.store:
            raise SdoAbortedError(int(SdoAbortCode.NO_OBJECT))
        return self.store[index, subindex]

    def download(self, index: int, subindex: int, data: bytes) -> None:
        if (index, subindex) in self.fail:
            raise self.fail[index, subindex]
        self.downloads.append((index, subindex, bytes(data)))
        if (index, subindex) not in self.keep:
            self.store[index, subindex] = bytes(data)
        if (index, subindex) in self.hooks:
            self.hooks[index, subindex](bytes(data))


class NmtMaster:
    def __init__(self) -> None:
        self.commands: list[int] = []
        self.tracked: list[bytes] = []
        self.heartbeats: list[bytes] = []
        self.on_send: Callable[[int], None] = lambda code: None
        self.error: Exception | None = None

    def send_command(self, code: int) -> None:
        if self.error is not None:
            raise self.error
        self.commands.append(code)
        self.on_send(code)

    def on_command(self, can_id: int, data: bytearray, timestamp: float) -> None:
        self.tracked.append(bytes(data))

    def on_heartbeat(self, can_id: int, data: bytearray, timestamp: float) -> None:
        self.heartbeats.append(bytes(data))


class Rig:
    """The link on fakes, and every service, wired as Cia402Drive wires them.

    The heartbeat monitor waits on the wall clock (a wait for a heartbeat that never comes ends after its timeout,
    a few tens of ms here); with ``frozen_heartbeat_clock`` it runs on the fake clock instead, for a loss made by
    letting the fake time pass (nothing may wait on it then: that clock never moves by itself).
    """

    def __init__(self, cfg: DriveConfig = CFG, sdo: Sdo | None = None, *, frozen_heartbeat_clock: bool = False) -> None:
        self.net = Net()
        self.sdo_fake = sdo or Sdo()
        self.nmt_fake = NmtMaster()
        node = SimpleNamespace(sdo=self.sdo_fake, nmt=self.nmt_fake, object_dictionary=OD)
        self.link = MasterLink(cfg, cast(canopen.RemoteNode, node), cast(DriveNetwork, self.net), owns_network=True)
        self.clock = Clock()
        self.link.timebase = self.clock
        self.inbox = Inbox()
        self.sdo = SdoClient(self.link)
        self.supervision = DriveSupervision(self.link, self.inbox, forward=self.nmt_fake.on_heartbeat)
        if frozen_heartbeat_clock:
            self.supervision.monitor = HeartbeatMonitor(NODE, clock=self.clock.now)
        self.monitor = self.supervision.monitor
        self.nmt = NmtClient(self.link, self.monitor)
        self.cyclic = CyclicPath(self.link, self.inbox, self.monitor, sample_time=PERIOD)
        self.net.members.append(self.cyclic.begin_cycle)
        self.restored = 0
        self.power = PowerStateCommands(self.link, self.cyclic, self.sdo, self.inbox,
                                        restore_communication=self._restore)
        self.startup = StartUp(self.link, self.sdo, self.nmt, self.supervision, self.cyclic, self.inbox)
        self.stop = SafeStop(self.link, self.cyclic, self.power, self.nmt, self.monitor, self.sdo, self.inbox)

    def _restore(self) -> None:
        self.restored += 1

    def started(self, mode: OperationMode = OperationMode.CYCLIC_SYNC_VELOCITY) -> CyclicPath:
        """The cyclic path as ``configure`` leaves it: codecs of the plan installed, the drive operational."""
        plan = pdo_plan(mode, NODE, OD)
        self.cyclic.install(mode, plan.rpdos, plan.tpdos)
        self.link.connected = self.link.operational = True
        return self.cyclic

    def rpdos(self) -> list[tuple[int, int]]:
        """(controlword, target) of every RPDO sent (CiA 402: UNSIGNED16, then INTEGER32 velocity or INTEGER16
        torque)."""
        return [cast(tuple[int, int], struct.unpack("<Hi" if len(m.data) == 6 else "<Hh", bytes(m.data)))
                for m in self.net.bus.sent if m.arbitration_id == 0x200 + NODE]


class ScriptedDrive:
    """Answers every SYNC of ``rig`` with its TPDO set, after applying the last RPDO's controlword (CiA 402 table);
    ``stuck`` ignores commands; ``mute`` answers nothing."""

    def __init__(self, rig: Rig, state: State402 = State402.SWITCH_ON_DISABLED) -> None:
        self.rig, self.state = rig, state
        self.stuck = self.mute = False
        self.previous = 0
        rig.net.on_sync = self.answer
        rig.sdo_fake.store[Obj.STATUSWORD, 0] = struct.pack("<H", STATUSWORD[state])
        rig.sdo_fake.hooks[Obj.CONTROLWORD, 0] = lambda data: self.command(struct.unpack("<H", data)[0])

    def command(self, controlword: int) -> None:
        rising = controlword & 0x80 and not self.previous & 0x80
        self.previous = controlword
        if not self.stuck:
            key = 0x80 if rising else controlword & 0x8F
            if controlword & 0x02 == 0 and self.state is not State402.FAULT:
                self.state = State402.SWITCH_ON_DISABLED  # disable voltage from anywhere but FAULT
            elif (self.state, key) in TRANSITIONS:
                self.state = TRANSITIONS[self.state, key]
        self.rig.sdo_fake.store[Obj.STATUSWORD, 0] = struct.pack("<H", STATUSWORD[self.state])

    def answer(self) -> None:
        rpdos = self.rig.rpdos()
        if rpdos:
            self.command(rpdos[-1][0])
        if self.mute:
            return
        tpdo = self.rig.net.cyclic
        tpdo[0x180 + NODE](0x180 + NODE, bytearray(struct.pack("<Hi", STATUSWORD[self.state], 1500)), 0.0)
        tpdo[0x280 + NODE](0x280 + NODE, bytearray(struct.pack("<hi", -250, 77)), 0.0)


# --- MasterLink -------------------------------------------------------------------------------------------------


def test_link_sends_under_the_lock_and_names_a_bus_failure() -> None:
    rig = Rig()
    rig.link.send(can.Message(arbitration_id=0x203, data=b"\x01"))
    assert [m.arbitration_id for m in rig.net.bus.sent] == [0x203]
    rig.net.bus.error = can.CanOperationError("bus off")
    with pytest.raises(DriveError, match="cannot send 0x203 on the bus: bus off"):
        rig.link.send(can.Message(arbitration_id=0x203, data=b"\x01"))


def test_link_requirements_say_what_is_missing() -> None:
    link = Rig().link
    with pytest.raises(DriveError, match="not connected"):
        link.require_connected()
    with pytest.raises(DriveError, match="not operational"):
        link.require_operational()
    link.closed = True
    with pytest.raises(DriveError, match="is closed"):
        link.require_connected()


# --- Inbox ------------------------------------------------------------------------------------------------------


def test_inbox_raises_bad_frames_only_when_fatal_and_counts_them_always() -> None:
    inbox = Inbox()
    inbox.post(ProtocolError("short"), bad_frame=True)
    assert inbox.bad_frames == 1 and isinstance(inbox.errors[0], BadFrameError) and str(inbox.errors[0]) == "short"
    inbox.fatal_bad_frames = False
    inbox.post(ProtocolError("short again"), bad_frame=True)
    assert inbox.bad_frames == 2 and len(inbox.errors) == 1


def test_inbox_reports_an_nmt_departure_once_unless_the_caller_had_it() -> None:
    inbox = Inbox()
    departure = DriveNmtStateError("left OPERATIONAL")
    inbox.post_departure(departure)
    assert inbox.pending_faults() == ("left OPERATIONAL",) and inbox.pending_faults() == ()
    inbox.post_departure(departure)
    inbox.errors.popleft()  # raised by a stop attempt, not to the caller: the report still says it
    assert inbox.pending_faults() == ("left OPERATIONAL",)
    inbox.post_departure(departure)
    inbox.errors.popleft()
    inbox.delivered(departure)  # the caller got it
    assert inbox.pending_faults() == ()


def test_inbox_heartbeat_fault_survives_until_the_fault_is_cleared() -> None:
    inbox = Inbox()
    inbox.post_heartbeat_fault(HeartbeatLostError("lost"))
    assert inbox.take_heartbeat_fault() and not inbox.errors and inbox.heartbeat_fault
    inbox.clear_fault()
    assert not inbox.take_heartbeat_fault()


# --- SdoClient --------------------------------------------------------------------------------------------------


def test_sdo_reads_and_writes_integers_little_endian_with_their_sign() -> None:
    rig = Rig(sdo=Sdo({(0x6061, 0): b"\xfe", (0x1017, 0): b"\x64\x00"}))
    assert rig.sdo.read(0x6061, 0, I8) == -2 and rig.sdo.read(0x1017, 0, U16) == 100
    rig.sdo.write(0x605A, 0, I16, -3)
    assert rig.sdo_fake.store[0x605A, 0] == b"\xfd\xff"
    assert rig.sdo.read_object(Obj.PRODUCER_HEARTBEAT_TIME) == 100  # typed by the EDS: UNSIGNED16
    rig.sdo.write_object(Obj.MODES_OF_OPERATION, 0, -1)  # INTEGER8 in the EDS
    assert rig.sdo_fake.store[Obj.MODES_OF_OPERATION, 0] == b"\xff"


def test_sdo_failures_are_typed_errors() -> None:
    rig = Rig(sdo=Sdo({(0x1000, 0): b"\x92\x01"}))
    with pytest.raises(SdoError) as short:
        rig.sdo.read(0x1000, 0, U32)
    assert short.value.abort_code == SdoAbortCode.LENGTH_TOO_LOW
    with pytest.raises(SdoError) as missing:
        rig.sdo.upload(0x2000, 0)
    assert missing.value.abort_code == SdoAbortCode.NO_OBJECT and missing.value.text  # decoded
    rig.sdo_fake.fail[0x1017, 0] = SdoCommunicationError("no response")
    with pytest.raises(DriveTimeoutError, match="no valid SDO response for 0x1017:00"):
        rig.sdo.read(0x1017, 0, U16)
    rig.sdo_fake.fail[0x6040, 0] = can.CanOperationError("tx queue full")
    with pytest.raises(DriveError, match="SDO download 0x6040:00 could not be sent"):
        rig.sdo.write(0x6040, 0, U16, 6)
    with pytest.raises(ConfigError, match="does not fit"):
        rig.sdo.write(0x6060, 0, I8, 300)
    assert rig.sdo_fake.downloads == []  # nothing sent for a value that does not fit


def test_sdo_read_back_compares_under_the_mask() -> None:
    rig = Rig(sdo=Sdo({(0x1800, 1): struct.pack("<I", 0x4000_0183)}))
    rig.sdo.expect(0x1800, 1, U32, 0x183, mask=0x9FFF_FFFF)  # bit 30 (RTR) ignored
    with pytest.raises(DriveError, match="reads back"):
        rig.sdo.expect(0x1800, 1, U32, 0x183)


def test_sdo_response_timeout_follows_the_timebase() -> None:
    rig = Rig()
    assert rig.sdo_fake.RESPONSE_TIMEOUT == 0.0  # synchronous: the answer is in when send returns, or never
    rig.link.timebase = SimpleNamespace(synchronous=False)
    SdoClient(rig.link)
    assert CFG.sdo_timeout == rig.sdo_fake.RESPONSE_TIMEOUT


# --- NmtClient --------------------------------------------------------------------------------------------------


def test_nmt_reset_waits_for_the_boot_up() -> None:
    rig = Rig()
    rig.nmt_fake.on_send = lambda code: rig.monitor.beat(0) if code == NmtCommand.RESET_COMMUNICATION else None
    rig.nmt.reset_communication()
    assert rig.nmt_fake.commands == [NmtCommand.RESET_COMMUNICATION]


def test_nmt_reset_without_boot_up_and_a_failed_send_are_errors() -> None:
    rig = Rig()
    with pytest.raises(DriveTimeoutError, match="no boot-up from node 3"):
        rig.nmt.reset_communication()
    rig.nmt_fake.error = can.CanOperationError("bus off")
    with pytest.raises(DriveError, match="cannot send NMT START to node 3"):
        rig.nmt.send(NmtCommand.START)


def test_nmt_enter_disarms_the_supervision_first() -> None:
    rig = Rig()
    rig.monitor.arm(1.0)
    rig.nmt_fake.on_send = lambda code: rig.monitor.beat(int(NmtState.PRE_OPERATIONAL))
    rig.nmt.enter(NmtCommand.ENTER_PRE_OPERATIONAL, (NmtState.PRE_OPERATIONAL,), timeout=0.05)
    assert rig.monitor.timeout == 0 and rig.nmt_fake.commands == [NmtCommand.ENTER_PRE_OPERATIONAL]


def test_nmt_tracking_sees_well_formed_commands_only() -> None:
    rig = Rig()
    rig.nmt.on_command(0, bytearray(b"\x01"), 0.0)
    rig.nmt.on_command(0, bytearray(b"\x01\x03"), 0.0)
    assert rig.nmt_fake.tracked == [b"\x01\x03"]


# --- DriveSupervision ------------------------------------------------------------------------------------------


def test_supervision_counts_forwards_and_flags_a_bad_heartbeat() -> None:
    rig = Rig()
    rig.supervision.on_heartbeat(0x703, bytearray(b"\x05"), 0.0)
    rig.supervision.on_heartbeat(0x703, bytearray(b"\x05\x00"), 0.0)
    assert rig.supervision.frames == 1 and rig.nmt_fake.heartbeats == [b"\x05"]
    assert rig.inbox.bad_frames == 1 and isinstance(rig.inbox.errors[0], BadFrameError)


def test_supervision_reports_a_departure_from_operational_only_while_running() -> None:
    rig = Rig()
    rig.supervision.on_heartbeat(0x703, bytearray(b"\x05"), 0.0)
    rig.supervision.on_heartbeat(0x703, bytearray(b"\x7f"), 0.0)  # not armed, not operational: nothing
    assert not rig.inbox.errors
    rig.link.operational = True
    rig.monitor.arm(1.0)
    rig.supervision.on_heartbeat(0x703, bytearray(b"\x05"), 0.0)
    rig.supervision.on_heartbeat(0x703, bytearray(b"\x04"), 0.0)
    error = rig.inbox.errors[0]
    assert isinstance(error, DriveNmtStateError) and "STOPPED" in str(error) and rig.inbox.nmt_departure is error


def test_supervision_check_raises_a_loss_and_flags_the_fault() -> None:
    rig = Rig(frozen_heartbeat_clock=True)
    rig.monitor.arm(0.5)
    rig.supervision.check()
    rig.clock.sleep(0.6)
    with pytest.raises(HeartbeatLostError):
        rig.supervision.check()
    assert rig.inbox.heartbeat_fault


def test_supervision_arms_once_operational_is_reported() -> None:
    rig = Rig()
    rig.monitor.beat(int(NmtState.OPERATIONAL))
    rig.supervision.confirm_operational(beats_before=0)
    assert rig.monitor.timeout == pytest.approx(CFG.heartbeat_timeout_factor * 0.1)
    silent = Rig(cfg=CFG.model_copy(update={"heartbeat_producer_ms": 10}))
    with pytest.raises(DriveTimeoutError, match="did not report NMT OPERATIONAL"):
        silent.supervision.confirm_operational(beats_before=0)
    no_heartbeat = Rig(cfg=CFG.model_copy(update={"heartbeat_producer_ms": 0}))
    no_heartbeat.supervision.confirm_operational(beats_before=0)
    assert no_heartbeat.monitor.timeout == 0


# --- EmcyConsumer -----------------------------------------------------------------------------------------------


def test_emcy_becomes_a_typed_error_and_a_reset_code_only_a_count() -> None:
    inbox = Inbox()
    emcy = EmcyConsumer(NODE, inbox)
    emcy.on_emcy(0x83, bytearray(struct.pack("<HB5s", 0x2310, 0x03, b"")), 0.0)
    emcy.on_emcy(0x83, bytearray(struct.pack("<HB5s", 0x0000, 0x00, b"")), 0.0)
    assert emcy.frames == 2 and len(inbox.errors) == 1
    error = inbox.errors[0]
    assert isinstance(error, EmergencyError) and error.code == 0x2310 and error.register == 0x03
    assert not inbox.heartbeat_fault
    emcy.on_emcy(0x83, bytearray(struct.pack("<HB5s", 0x8130, 0x11, b"")), 0.0)
    assert inbox.heartbeat_fault
    emcy.on_emcy(0x83, bytearray(b"\x10\x23\x01"), 0.0)
    assert inbox.bad_frames == 1 and emcy.frames == 3


# --- CyclicPath -------------------------------------------------------------------------------------------------


def test_set_target_clamps_scales_and_sends_the_rpdo() -> None:
    rig = Rig()
    cyclic = rig.started()
    assert cyclic.set_target(12.3456) == pytest.approx(12.346)  # 0.001 rpm counts: rounded
    assert cyclic.set_target(-1e6) == -CFG.velocity_limit
    assert rig.rpdos() == [(0x00, 12346), (0x00, -3_000_000)]
    with pytest.raises(DriveError, match="not finite"):
        cyclic.set_target(float("nan"))
    torque = Rig()
    torque.started(OperationMode.CYCLIC_SYNC_TORQUE).set_target(5000.0)
    assert torque.rpdos() == [(0x00, int(CFG.torque_limit * CFG.torque_scale))]


def test_set_target_before_start_says_why() -> None:
    with pytest.raises(DriveError, match="not operational"):
        Rig().cyclic.set_target(1.0)


def test_sync_opens_a_cycle_and_the_tpdo_set_answers_it() -> None:
    rig = Rig()
    cyclic = rig.started()
    ScriptedDrive(rig, State402.OPERATION_ENABLED)
    assert cyclic.sync() == 1
    feedback = cyclic.wait_feedback(0.1)
    assert (feedback.cycle, feedback.state, feedback.statusword) == (1, State402.OPERATION_ENABLED, 0x0027)
    assert feedback.velocity == 1.5 and feedback.torque == -250 and feedback.position == 77
    assert cyclic.tpdo_frames == 2 and set(cyclic.pdo_codecs) == {0x203, 0x183, 0x283}


def test_an_unanswered_sync_is_a_timeout_and_no_stop() -> None:
    rig = Rig()
    cyclic = rig.started()
    ScriptedDrive(rig).mute = True
    cyclic.sync()
    with pytest.raises(FeedbackTimeoutError, match="answered SYNC 1 on the synchronous bus"):
        cyclic.wait_feedback(0.1)
    assert rig.rpdos() == [] and rig.net.syncs == 1  # the command is left as it was


def test_a_fault_in_the_feedback_stops_the_drive() -> None:
    rig = Rig()
    cyclic = rig.started()
    ScriptedDrive(rig, State402.FAULT)
    cyclic.sync()
    with pytest.raises(DriveFaultError, match="statusword 0x0008"):
        cyclic.wait_feedback(0.1)
    assert rig.rpdos() == [(0x02, 0)] and rig.net.syncs == 2  # quick stop, target 0, one SYNC


def test_pending_errors_and_a_lost_heartbeat_come_before_the_feedback() -> None:
    rig = Rig(frozen_heartbeat_clock=True)
    cyclic = rig.started()
    ScriptedDrive(rig, State402.OPERATION_ENABLED)
    rig.inbox.post(EmergencyError(0x2310, 3, "over-current"))
    cyclic.sync()
    with pytest.raises(EmergencyError):
        cyclic.wait_feedback(0.1)
    rig.monitor.arm(0.5)
    rig.clock.sleep(1.0)
    cyclic.sync()
    with pytest.raises(HeartbeatLostError):
        cyclic.wait_feedback(0.1)
    assert rig.inbox.heartbeat_fault


def test_a_tpdo_of_the_wrong_length_is_a_bad_frame() -> None:
    rig = Rig()
    cyclic = rig.started()
    cyclic.sync()
    cyclic.on_tpdo(0x183, bytearray(b"\x27\x00"), 0.0)
    assert rig.inbox.bad_frames == 1 and cyclic.feedback is None


# --- PowerStateCommands ---------------------------------------------------------------------------------------


def test_enable_walks_the_402_path_over_pdos() -> None:
    rig = Rig()
    rig.started()
    drive = ScriptedDrive(rig)
    rig.power.enable()
    assert drive.state is State402.OPERATION_ENABLED
    assert [word for word, _ in rig.rpdos()] == [0x00, 0x06, 0x07, 0x0F]  # current word first, then the path


def test_enable_of_a_faulted_drive_refuses_and_stops() -> None:
    rig = Rig()
    rig.started()
    ScriptedDrive(rig, State402.FAULT)
    with pytest.raises(DriveFaultError, match="fault_reset"):
        rig.power.enable()
    assert rig.rpdos()[-1] == (0x02, 0)


def test_a_drive_that_does_not_move_is_a_state_transition_error() -> None:
    rig = Rig()
    rig.started()
    ScriptedDrive(rig).stuck = True
    with pytest.raises(StateTransitionError, match="stuck in SWITCH_ON_DISABLED"):
        rig.power.enable()


def test_commands_go_over_sdo_when_the_drive_is_not_operational() -> None:
    rig = Rig()
    rig.link.connected = True
    drive = ScriptedDrive(rig, State402.OPERATION_ENABLED)
    rig.power.quick_stop()
    assert drive.state is State402.QUICK_STOP_ACTIVE and rig.power.last_statusword == 0x0007
    assert (Obj.CONTROLWORD, 0, b"\x02\x00") in rig.sdo_fake.downloads and rig.rpdos() == []


def test_fault_reset_restores_communication_after_a_heartbeat_fault() -> None:
    rig = Rig()
    rig.started()
    drive = ScriptedDrive(rig, State402.FAULT)
    rig.inbox.post_heartbeat_fault(HeartbeatLostError("lost"))
    rig.power.fault_reset()
    assert rig.restored == 1 and drive.state is State402.SWITCH_ON_DISABLED and not rig.inbox.heartbeat_fault
    assert [word for word, _ in rig.rpdos()] == [0x00, 0x80, 0x00]  # bit 7 low, the rising edge, low again


# --- SafeStop ---------------------------------------------------------------------------------------------------


def test_no_drive_answered_connect_nothing_to_stop() -> None:
    report = Rig().stop.run()
    assert not report.commanded and not report.confirmed


def test_stop_skips_the_pdo_path_of_a_drive_outside_operational() -> None:
    rig = Rig()
    rig.started()
    drive = ScriptedDrive(rig, State402.OPERATION_ENABLED)
    rig.monitor.beat(int(NmtState.PRE_OPERATIONAL))
    rig.inbox.post(EmergencyError(0x2310, 3, "over-current"))
    report = rig.stop.run()
    assert report.confirmed and report.via is StopPath.SDO and drive.state is State402.SWITCH_ON_DISABLED
    assert len(report.attempts) == 1 and "ignores RPDOs" in report.attempts[0]
    assert report.faults == ("EMCY 0x2310 (over-current), error register 0x03",)
    assert not rig.link.operational  # from then on, commands go over SDO


def test_stop_over_pdos_confirms_from_the_tpdo() -> None:
    rig = Rig()
    rig.started()
    ScriptedDrive(rig, State402.OPERATION_ENABLED)
    report = rig.stop.run()
    assert report.confirmed and report.via is StopPath.PDO and report.statusword == 0x0040


def test_stop_never_raises_when_every_path_fails() -> None:
    rig = Rig()
    rig.started()
    ScriptedDrive(rig, State402.OPERATION_ENABLED).mute = True
    rig.sdo_fake.fail[Obj.CONTROLWORD, 0] = SdoCommunicationError("no response")
    rig.sdo_fake.fail[Obj.STATUSWORD, 0] = SdoCommunicationError("no response")
    report = rig.stop.run()
    assert report.commanded and not report.confirmed and report.state is None
    assert [line.split(":")[0] for line in report.attempts] == [str(path) for path in StopPath]


# --- StartUp and the plan ---------------------------------------------------------------------------------------


def identity_store() -> dict[tuple[int, int], bytes]:
    store: dict[tuple[int, int], bytes] = {(Obj.DEVICE_TYPE, 0): struct.pack("<I", 0x0002_0192)}
    store |= {(Obj.IDENTITY, sub): struct.pack("<I", 10 * sub) for sub in (1, 2, 3, 4)}
    store[Obj.SUPPORTED_DRIVE_MODES, 0] = struct.pack("<I", 1 << 8)  # csv only
    return store


def booting(rig: Rig) -> Rig:
    """The drive answers a reset with its boot-up and NMT start with an operational heartbeat; 0x6061 shows 0x6060."""
    states = {NmtCommand.RESET_COMMUNICATION: NmtState.INITIALISING, NmtCommand.START: NmtState.OPERATIONAL}
    rig.nmt_fake.on_send = lambda code: rig.monitor.beat(int(states[NmtCommand(code)])) if code in states else None
    rig.sdo_fake.hooks[Obj.MODES_OF_OPERATION, 0] = lambda data: rig.sdo_fake.store.__setitem__(
        (Obj.MODES_OF_OPERATION_DISPLAY, 0), data)
    return rig


def test_identify_reads_the_identity_after_the_boot_up() -> None:
    rig = booting(Rig(sdo=Sdo(identity_store())))
    info = rig.startup.identify()
    assert (info.vendor_id, info.product_code, info.revision, info.serial) == (10, 20, 30, 40)
    assert info.supported_modes == (OperationMode.CYCLIC_SYNC_VELOCITY,) and rig.link.connected
    assert rig.nmt_fake.commands == [NmtCommand.RESET_COMMUNICATION, NmtCommand.ENTER_PRE_OPERATIONAL]


def test_identify_refuses_a_device_that_is_not_a_402_drive() -> None:
    rig = booting(Rig(sdo=Sdo({**identity_store(), (Obj.DEVICE_TYPE, 0): struct.pack("<I", 0x0000_0191)})))
    with pytest.raises(DriveError, match="not a CiA 402 drive"):
        rig.startup.identify()


def test_preflight_refuses_a_mode_the_drive_does_not_offer() -> None:
    rig = booting(Rig(sdo=Sdo(identity_store())))
    rig.startup.identify()
    with pytest.raises(ConfigError, match="does not support CYCLIC_SYNC_TORQUE") as refused:
        rig.startup.preflight(OperationMode.CYCLIC_SYNC_TORQUE)
    assert refused.value.key == "drive.mode"
    without_6502 = Rig(sdo=Sdo({}))
    assert without_6502.startup.supported_modes() == ()  # optional: any mode may be tried


def test_configure_writes_the_plan_reads_it_back_and_starts_the_drive() -> None:
    rig = booting(Rig(sdo=Sdo(identity_store())))
    rig.startup.identify()
    rig.startup.configure(OperationMode.CYCLIC_SYNC_VELOCITY)
    plan = pdo_plan(OperationMode.CYCLIC_SYNC_VELOCITY, NODE, OD)
    for layout in (*plan.rpdos, *plan.tpdos):
        store = rig.sdo_fake.store
        assert struct.unpack("<I", store[layout.communication_index, 1])[0] == layout.cob_id  # enabled
        assert [struct.unpack("<I", store[layout.mapping_index, sub])[0]
                for sub in range(1, len(layout.variables) + 1)] == [v.mapping_entry for v in layout.variables]
    assert struct.unpack("<I", rig.sdo_fake.store[0x1402, 1])[0] >> 31 == 1  # an unused RPDO: disabled
    assert rig.sdo_fake.store[Obj.PRODUCER_HEARTBEAT_TIME, 0] == struct.pack("<H", 100)
    assert rig.link.operational and rig.cyclic.mode is OperationMode.CYCLIC_SYNC_VELOCITY and rig.monitor.timeout > 0
    assert rig.nmt_fake.commands[-1] == NmtCommand.START and rig.net.heartbeats == [(127, 0.5 / 4)]


@pytest.mark.parametrize(("index", "subindex", "held"), [
    (Obj.PRODUCER_HEARTBEAT_TIME, 0, struct.pack("<H", 1000)),  # a setting
    (Obj.TPDO_MAPPING, 2, struct.pack("<I", 0x6077_0010)),  # a PDO mapping entry
])
def test_configure_refuses_a_value_the_drive_did_not_keep(index: int, subindex: int, held: bytes) -> None:
    rig = booting(Rig(sdo=Sdo(identity_store())))
    rig.sdo_fake.store[index, subindex] = held
    rig.sdo_fake.keep.add((index, subindex))
    rig.startup.identify()
    with pytest.raises(DriveError, match=f"0x{index:04X}:{subindex:02X} reads back"):
        rig.startup.configure(OperationMode.CYCLIC_SYNC_VELOCITY)
    assert not rig.link.operational


def test_configure_skips_an_optional_object_the_drive_refuses(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING, logger="drivers.cia402_master")
    rig = booting(Rig(sdo=Sdo(identity_store())))
    rig.sdo_fake.fail[Obj.QUICK_STOP_OPTION, 0] = SdoAbortedError(int(SdoAbortCode.NO_OBJECT))
    rig.startup.identify()
    rig.startup.configure(OperationMode.CYCLIC_SYNC_VELOCITY)
    assert "lacks optional object 0x605A:00" in caplog.text and rig.link.operational


def test_interpolation_time_period_is_exact_or_refused() -> None:
    assert interpolation_time_period(0.001) == (1, -3)
    assert interpolation_time_period(0.0003) == (3, -4)
    assert interpolation_time_period(0.25) == (25, -2)
    with pytest.raises(ConfigError, match="not expressible"):
        interpolation_time_period(0.0012345)


def test_the_plan_maps_the_mode_s_target_and_packs_a_drive_with_one_tpdo() -> None:
    cst = pdo_plan(OperationMode.CYCLIC_SYNC_TORQUE, NODE, OD)
    assert [v.index for v in cst.rpdos[0].variables] == [Obj.CONTROLWORD, Obj.TARGET_TORQUE]
    one_tpdo = load_od(None, NODE)
    for n in (1, 2, 3):
        del one_tpdo[Obj.TPDO_COMMUNICATION + n]
    plan = pdo_plan(OperationMode.CYCLIC_SYNC_VELOCITY, NODE, one_tpdo)
    assert len(plan.tpdos) == 1 and sum(v.bits for v in plan.tpdos[0].variables) <= 64
    assert [v.index for v in plan.tpdos[0].variables] == [Obj.STATUSWORD, Obj.VELOCITY_ACTUAL_VALUE,
                                                          Obj.TORQUE_ACTUAL_VALUE]
    assert plan.notes == ("0x6064 not mapped: the drive's 1 TPDO(s) have no room left",)
    lacking = load_od(None, NODE)
    del lacking[Obj.VELOCITY_ACTUAL_VALUE]
    with pytest.raises(DriveError, match="lacks 0x606C"):
        pdo_plan(OperationMode.CYCLIC_SYNC_VELOCITY, NODE, lacking)


def test_settings_rows_encode_the_cycle_and_the_heartbeats() -> None:
    def rows(od: ObjectDictionary) -> dict[tuple[int, int], tuple[int, bool]]:
        return {(index, sub): (value, optional) for index, sub, _, value, optional in
                settings_rows(CFG, od, OperationMode.CYCLIC_SYNC_VELOCITY, 0.002)}

    shipped = rows(OD)
    assert shipped[Obj.MODES_OF_OPERATION, 0] == (9, False)
    assert shipped[Obj.COMMUNICATION_CYCLE_PERIOD, 0] == (2000, True)
    assert shipped[Obj.CONSUMER_HEARTBEAT_TIME, 1] == ((127 << 16) | 500, True)
    assert Obj.INTERPOLATION_TIME_PERIOD not in OD and (Obj.INTERPOLATION_TIME_PERIOD, 1) not in shipped
    with_60c2 = load_od(None, NODE)
    record = ODRecord("Interpolation time period", Obj.INTERPOLATION_TIME_PERIOD)
    for sub, data_type in ((1, UNSIGNED8), (2, INTEGER8)):
        member = ODVariable(f"sub {sub}", Obj.INTERPOLATION_TIME_PERIOD, sub)
        member.data_type = data_type
        record.add_member(member)
    with_60c2.add_object(record)
    assert rows(with_60c2)[Obj.INTERPOLATION_TIME_PERIOD, 1] == (2, True)  # 2 x 10^-3 s
    assert rows(with_60c2)[Obj.INTERPOLATION_TIME_PERIOD, 2] == (-3, True)



# --- the composition --------------------------------------------------------------------------------------------


def test_a_closed_drive_leaves_its_network_s_cycle() -> None:
    """Cia402Drive joins and leaves its network with one and the same bound method (a fresh one per access never
    compared identical, so a closed drive stayed a member and kept counting SYNCs)."""
    with InProcessBus(f"test-services-{uuid.uuid4().hex}") as bus:
        network = DriveNetwork(bus)
        first, second = (Cia402Drive.on_network(network, DriveConfig(node_id=node), sample_time=PERIOD)
                         for node in (1, 2))
        network.sync(PERIOD)
        assert (first.cycle, second.cycle) == (1, 1)
        first.close()
        network.sync(PERIOD)
        assert (first.cycle, second.cycle) == (1, 2)
        second.close()
        network.close()


def test_the_first_complete_tpdo_set_of_a_cycle_is_its_answer() -> None:
    """A set that straddled the SYNC (its TPDO2 and demand echo after it) completes with the cycle's own TPDO1; the
    cycle's own set, whole a moment later, must not replace that first answer: ``replay --verify`` takes the first
    complete set, so the loop, reading whenever its thread looks, must find the same."""
    rig = Rig()
    plan = pdo_plan(OperationMode.CYCLIC_SYNC_VELOCITY, NODE, OD, demand_echo=True)
    cyclic = rig.cyclic
    cyclic.install(OperationMode.CYCLIC_SYNC_VELOCITY, plan.rpdos, plan.tpdos)
    rig.link.connected = rig.link.operational = True
    tpdo1, tpdo2, tpdo3 = (0x180 + NODE, 0x280 + NODE, 0x380 + NODE)
    assert [layout.cob_id for layout in plan.tpdos] == [tpdo1, tpdo2, tpdo3]
    cyclic.sync()
    cyclic.on_tpdo(tpdo2, bytearray(6), 0.0)  # the previous SYNC's set, late
    cyclic.on_tpdo(tpdo3, bytearray(struct.pack("<i", 111)), 0.0)
    cyclic.on_tpdo(tpdo1, bytearray(struct.pack("<Hi", 0x1237, 500)), 0.0)  # this cycle's: the set completes
    cyclic.on_tpdo(tpdo2, bytearray(6), 0.0)
    cyclic.on_tpdo(tpdo3, bytearray(struct.pack("<i", 222)), 0.0)
    feedback = cyclic.wait_feedback(0.1)
    assert feedback.demand == 111 / CFG.velocity_scale and feedback.velocity == 500 / CFG.velocity_scale
    assert cyclic.tpdo_frames == 5  # every frame counted, answered or not
    cyclic.sync()  # the next cycle takes its own set again
    cyclic.on_tpdo(tpdo1, bytearray(struct.pack("<Hi", 0x1237, 600)), 0.0)
    cyclic.on_tpdo(tpdo2, bytearray(6), 0.0)
    cyclic.on_tpdo(tpdo3, bytearray(struct.pack("<i", 333)), 0.0)
    assert cyclic.wait_feedback(0.1).demand == 333 / CFG.velocity_scale


class _LateOnce(ScriptedDrive):
    """Leaves the first ``misses`` SYNCs unanswered (a loaded host's late answer), then answers every one."""

    def __init__(self, rig: Rig, misses: int) -> None:
        super().__init__(rig)
        self.misses = misses

    def answer(self) -> None:
        self.mute = self.misses > 0
        self.misses -= 1
        super().answer()


def test_enable_sends_an_unanswered_exchange_again_within_the_state_timeout() -> None:
    cfg = DriveConfig(node_id=NODE, state_timeout=0.3, heartbeat_producer_ms=100, heartbeat_consumer_ms=500)
    rig = Rig(cfg)
    rig.clock.synchronous = False  # the wall clock's behaviour: an answer may come while the master waits
    rig.started()
    drive = _LateOnce(rig, misses=1)
    rig.power.enable()  # the first SYNC went unanswered for the exchange's 0.2 s; the same controlword again
    assert drive.state is State402.OPERATION_ENABLED
    assert [word for word, _ in rig.rpdos()][:2] == [0x00, 0x00]  # the unanswered exchange, sent once more
    rig = Rig(cfg)
    rig.clock.synchronous = False
    rig.started()
    _LateOnce(rig, misses=10**6)  # a mute drive: still a lost feedback, after state_timeout's worth of tries
    with pytest.raises(FeedbackTimeoutError, match="answered SYNC 2 "):
        rig.power.enable()
