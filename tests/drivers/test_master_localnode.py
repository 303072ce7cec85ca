"""The master drives a slave built ONLY from canopen's ``LocalNode`` + the EDS (no emulator code).

The slave is :class:`~tests.support.mini_servo.MiniServo`, a minimal CiA 402 responder: canopen's SDO server and
NMT slave, plus what canopen's ``LocalNode`` leaves to the application -- the boot-up after an NMT reset, RPDO
reception applied at SYNC, the 402 state machine (statusword follows controlword per the CiA 402-2 transition table),
TPDOs sent on SYNC from whatever mapping the master wrote, and the PDO-configuration rules of CiA 301 (mapping only
while the PDO is disabled, only PDO-mappable objects, EDS limits). The fault tests use it with its fault hooks.
"""

from __future__ import annotations

import re
import threading
import time
import uuid
from collections.abc import Iterator
from pathlib import Path

import can
import pytest

from drivers.cia301 import (
    RPDO_BASES,
    SdoAbortCode,
    cob_id,
)
from drivers.cia402 import (
    Command402,
    Obj,
    OperationMode,
    State402,
)
from drivers.cia402_master import Cia402Drive, interpolation_time_period
from drivers.od import DEFAULT_EDS
from drivers.pdo import PDO_DISABLED
from foilc_hil.errors import ConfigError, DriveError, DriveTimeoutError, SdoError
from tests.support.mini_servo import NODE_ID, VELOCITY_SCALE, MiniServo, drive_config, transition


@pytest.fixture
def channel() -> str:
    return f"test-master-{uuid.uuid4()}"


@pytest.fixture
def servo(channel: str) -> Iterator[MiniServo]:
    slave = MiniServo(channel)
    yield slave
    slave.close()


@pytest.fixture
def master_bus(channel: str) -> Iterator[can.BusABC]:
    bus = can.Bus(interface="virtual", channel=channel)
    yield bus
    bus.shutdown()


def test_full_cycle_against_a_localnode_slave(servo: MiniServo, master_bus: can.BusABC) -> None:
    drive = Cia402Drive.open(master_bus, drive_config(), sample_time=0.002)
    with drive:
        started = time.perf_counter()
        info = drive.connect()
        connected = time.perf_counter()
        drive.configure(OperationMode.CYCLIC_SYNC_VELOCITY)
        configured = time.perf_counter()
        drive.enable()
        enabled = time.perf_counter()
        print(
            f"\nvirtual bus timing: connect {1e3 * (connected - started):.1f} ms, "
            f"configure {1e3 * (configured - connected):.1f} ms, enable {1e3 * (enabled - configured):.1f} ms, "
            f"total {1e3 * (enabled - started):.1f} ms"
        )

        # identity comes from the EDS the LocalNode serves
        assert info.vendor_id == servo.value(Obj.IDENTITY, 1) == 0x464F494C
        assert info.serial == servo.value(Obj.IDENTITY, 4)
        assert info.device_type & 0xFFFF == 402
        assert OperationMode.CYCLIC_SYNC_VELOCITY in info.supported_modes

        # the slave holds what the master configured
        assert servo.value(Obj.MODES_OF_OPERATION) == OperationMode.CYCLIC_SYNC_VELOCITY
        assert servo.value(Obj.COMMUNICATION_CYCLE_PERIOD) == 2000
        assert servo.value(Obj.PRODUCER_HEARTBEAT_TIME) == 100
        assert servo.value(Obj.CONSUMER_HEARTBEAT_TIME, 1) == (127 << 16) | 200
        assert servo.value(0x1600, 0) == 2 and servo.value(0x1600, 2) == 0x60FF0020
        assert servo.value(0x1401, 1) & PDO_DISABLED  # RPDO2 (EDS default: target torque) switched off
        assert servo.state is State402.OPERATION_ENABLED
        assert servo.received_controlwords[-3:] == [0x06, 0x07, 0x0F]

        # cyclic: the set-point comes back as the velocity, scaled both ways, one SYNC each
        for k, target in enumerate([10.0, -2.5, 0.0015, 5000.0]):
            sent = drive.set_target(target)
            cycle = drive.sync()
            feedback = drive.wait_feedback(0.5)
            assert feedback.cycle == cycle
            assert feedback.state is State402.OPERATION_ENABLED
            assert feedback.velocity == pytest.approx(sent)
            assert servo.value(Obj.TARGET_VELOCITY) == round(sent * VELOCITY_SCALE)
            if k == 2:
                assert sent == pytest.approx(0.002)  # quantised to 0.001 rpm
            if k == 3:
                assert sent == 3000.0  # clamped to velocity_limit

        drive.quick_stop()
        assert servo.state is State402.QUICK_STOP_ACTIVE
        assert drive.last_feedback is not None and drive.last_feedback.velocity == 0.0
        drive.disable()
        assert servo.state is State402.SWITCH_ON_DISABLED
        assert servo.received_controlwords[-1] == Command402.DISABLE_VOLTAGE
        assert drive.stats.bad_frames == 0


def test_configure_rejects_a_mode_the_drive_lacks(servo: MiniServo, master_bus: can.BusABC) -> None:
    servo.put(Obj.SUPPORTED_DRIVE_MODES, 0, 1 << 2)  # profile velocity only
    with Cia402Drive.open(master_bus, drive_config(), sample_time=0.002) as drive:
        drive.connect()
        with pytest.raises(ConfigError, match=r"drive\.mode.*does not support CYCLIC_SYNC_VELOCITY"):
            drive.configure(OperationMode.CYCLIC_SYNC_VELOCITY)


def test_sdo_abort_is_decoded(servo: MiniServo, master_bus: can.BusABC) -> None:
    # 0x6007 has HighLimit 3 in the EDS; the slave refuses 7 and the master names object and abort text
    with Cia402Drive.open(master_bus, drive_config(abort_connection_option=3), sample_time=0.002) as drive:
        drive.connect()
        with pytest.raises(SdoError) as caught:
            drive.write_object(Obj.ABORT_CONNECTION_OPTION, 0, 7)
        assert caught.value.abort_code == SdoAbortCode.VALUE_TOO_HIGH
        assert "0x6007:00" in str(caught.value) and "too high" in str(caught.value)
        with pytest.raises(SdoError) as read_only:
            drive.write_object(0x2000, 0, 1)
        assert read_only.value.abort_code == SdoAbortCode.READ_ONLY


def test_mapping_a_non_mappable_object_aborts(servo: MiniServo, master_bus: can.BusABC) -> None:
    with Cia402Drive.open(master_bus, drive_config(), sample_time=0.002) as drive:
        drive.connect()
        drive.write_object(0x1400, 1, cob_id(RPDO_BASES[0], NODE_ID) | PDO_DISABLED)
        with pytest.raises(SdoError) as caught:
            drive.write_object(0x1600, 1, 0x2001_0010)  # velocity loop gain: PDOMapping=0
        assert caught.value.abort_code == SdoAbortCode.CANNOT_MAP


def test_connect_without_boot_up_names_the_node(servo: MiniServo, master_bus: can.BusABC) -> None:
    servo.boot_up = False
    servo.stop_heartbeat()
    with (
        Cia402Drive.open(master_bus, drive_config(state_timeout=0.3), sample_time=0.002) as drive,
        pytest.raises(DriveTimeoutError, match=f"no boot-up from node {NODE_ID}"),
    ):
        drive.connect()


def _new_threads(before: set[threading.Thread]) -> list[str]:
    return [thread.name for thread in threading.enumerate() if thread not in before]


def test_construction_is_inert_and_close_is_safe_unconnected(channel: str, master_bus: can.BusABC) -> None:
    listener_bus = can.Bus(interface="virtual", channel=channel)
    before = set(threading.enumerate())
    drive = Cia402Drive.open(master_bus, drive_config(), sample_time=0.002)
    assert _new_threads(before) == []  # no Notifier, no heartbeat watchdog
    assert "send" not in vars(master_bus)  # the frame tap is not on the bus yet
    drive.close()
    drive.close()  # idempotent
    assert _new_threads(before) == []
    assert listener_bus.recv(timeout=0.05) is None  # nothing was sent
    listener_bus.shutdown()


def test_failed_connect_leaves_no_thread(servo: MiniServo, master_bus: can.BusABC) -> None:
    servo.boot_up = False
    servo.stop_heartbeat()
    before = set(threading.enumerate())
    drive = Cia402Drive.open(master_bus, drive_config(state_timeout=0.2), sample_time=0.002)
    with pytest.raises(DriveTimeoutError):
        drive.connect()
    assert _new_threads(before) == []  # the Notifier and the watchdog were stopped again
    assert "send" not in vars(master_bus)
    drive.close()
    assert _new_threads(before) == []


def test_responder_follows_the_402_table() -> None:
    # the responder's 402 table itself: the path the master walks, and disable voltage from anywhere
    assert transition(State402.SWITCH_ON_DISABLED, 0x06, 0) is State402.READY_TO_SWITCH_ON
    assert transition(State402.READY_TO_SWITCH_ON, 0x07, 0x06) is State402.SWITCHED_ON
    assert transition(State402.SWITCHED_ON, 0x0F, 0x07) is State402.OPERATION_ENABLED
    assert transition(State402.OPERATION_ENABLED, 0x02, 0x0F) is State402.QUICK_STOP_ACTIVE
    assert transition(State402.FAULT, 0x80, 0x80) is State402.FAULT  # no rising edge
    assert transition(State402.FAULT, 0x80, 0x00) is State402.SWITCH_ON_DISABLED


INTERPOLATION_TIME_PERIOD_EDS = """
[60C2]
ParameterName=Interpolation time period
ObjectType=0x9
SubNumber=3

[60C2sub0]
ParameterName=Highest sub-index supported
ObjectType=0x7
DataType=0x0005
AccessType=ro
DefaultValue=2
PDOMapping=0

[60C2sub1]
ParameterName=Interpolation time period value
ObjectType=0x7
DataType=0x0005
AccessType=rw
DefaultValue=1
PDOMapping=0

[60C2sub2]
ParameterName=Interpolation time index
ObjectType=0x7
DataType=0x0002
AccessType=rw
DefaultValue=-3
PDOMapping=0
"""


def test_other_drive_without_optional_objects_but_with_0x60c2(channel: str, tmp_path: Path) -> None:
    """A different 402 drive: no 0x6007 / 0x605A (optional), but 0x60C2 for the cyclic modes."""
    text = DEFAULT_EDS.read_text(encoding="utf-8")
    for section in ("6007", "605A"):
        text = re.sub(rf"\[{section}\]\n(?:[^\[\n].*\n)*", "", text)  # the section up to its blank line
    eds = tmp_path / "other_drive.eds"
    eds.write_text(text + INTERPOLATION_TIME_PERIOD_EDS, encoding="utf-8")
    slave = MiniServo(channel, eds=eds)
    bus = can.Bus(interface="virtual", channel=channel)
    try:
        assert Obj.ABORT_CONNECTION_OPTION not in slave.node.object_dictionary
        with Cia402Drive.open(bus, drive_config(eds=str(eds)), sample_time=0.0005) as drive:
            drive.connect()
            drive.configure(OperationMode.CYCLIC_SYNC_TORQUE)
            assert (slave.value(0x60C2, 1), slave.value(0x60C2, 2)) == (5, -4)  # 5 x 10^-4 s
            assert slave.value(0x1600, 2) == 0x60710010  # CST maps target torque
            drive.enable()
            sent = drive.set_target(250.0)
            drive.sync()
            assert drive.wait_feedback(0.5).torque == sent == 250.0
    finally:
        bus.shutdown()
        slave.close()


@pytest.mark.parametrize(
    ("period", "encoded"),
    [(0.002, (2, -3)), (0.001, (1, -3)), (0.0005, (5, -4)), (0.3, (3, -1)), (0.000125, (125, -6)), (0.01, (1, -2))],
)
def test_interpolation_time_period(period: float, encoded: tuple[int, int]) -> None:
    value, exponent = interpolation_time_period(period)
    assert (value, exponent) == encoded
    assert value * 10.0**exponent == pytest.approx(period, rel=1e-12)


def test_interpolation_time_period_rejects_unencodable() -> None:
    with pytest.raises(ConfigError, match="0x60C2"):
        interpolation_time_period(0.0012345)


@pytest.mark.slow
def test_silent_sdo_server_is_a_timeout_naming_the_object(servo: MiniServo, master_bus: can.BusABC) -> None:
    with Cia402Drive.open(master_bus, drive_config(sdo_timeout=0.05), sample_time=0.002) as drive:
        drive.connect()
        servo.network.unsubscribe(servo.node.sdo.rx_cobid, servo.node.sdo.on_request)  # the SDO server goes quiet
        with pytest.raises(DriveTimeoutError, match=r"no valid SDO response for 0x6061:00 within 0.05 s"):
            drive.read_object(Obj.MODES_OF_OPERATION_DISPLAY)


def test_bus_with_a_foreign_notifier_is_refused_cleanly(master_bus: can.BusABC) -> None:
    notifier = can.Notifier(master_bus, [], timeout=0.05)
    try:
        with (
            Cia402Drive.open(master_bus, drive_config(), sample_time=0.002) as drive,
            pytest.raises(DriveError, match="cannot listen on the bus"),
        ):
            drive.connect()
        assert "send" not in vars(master_bus)  # the frame tap was taken off again
    finally:
        notifier.stop()


def test_master_and_drive_node_ids_must_differ(master_bus: can.BusABC) -> None:
    with pytest.raises(ConfigError, match=r"drive\.master_node_id: must differ from drive\.node_id"):
        Cia402Drive.open(master_bus, drive_config(master_node_id=NODE_ID), sample_time=0.002)
