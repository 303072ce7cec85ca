"""Faults of the virtual drive: detection, EMCY + 0x603F + 0x1001, the 0x6007 reactions, clearing -- and the
master (``drivers.cia402_master.Cia402Drive``) turning each into a typed error with the drive left safe."""

from __future__ import annotations

import math
import struct
import time
from collections.abc import Iterator

import can
import pytest

from drivers.bus import open_bus
from drivers.cia301 import (
    SYNC_COB_ID,
    EmcyCode,
    ErrorRegister,
    FunctionCode,
    HeartbeatConsumerEntry,
    NmtCommand,
    NmtState,
    cob_id,
)
from drivers.cia402 import AbortConnectionOption, Obj, OperationMode, State402
from drivers.cia402_master import Cia402Drive
from drivers.config import DriveConfig
from drivers.drive import StopPath
from drivers.inprocess import LockstepClock, timebase_of
from foilc_hil.errors import DriveError, EmergencyError, HeartbeatLostError
from plant_emulator.config import PlantConfig, PmsmConfig
from plant_emulator.device import FaultKind
from plant_emulator.embedded import EmbeddedEmulator
from plant_emulator.settings import EmulatorConfig
from plant_emulator.supervision import MONITOR_PERIOD, STALL_POLLS
from tests.support.emulator_harness import ABORT_REACTIONS, AFTER_THE_RAMP, Harness

pytestmark = pytest.mark.timeout(90)

MASTER_ID = 127
COUNTS_PER_RPM = 1000


def _emcy(frame: bytes) -> tuple[int, int]:
    code, register = struct.unpack_from("<HB", frame)
    return code, register


def _enable_csv(h: Harness, target_counts: int = 0) -> None:
    """Operational, CSV, operation enabled through RPDO1 (controlword + target velocity) and SYNC."""
    h.start()
    for controlword in (0x06, 0x07, 0x0F):
        h.send(h.rpdo1, struct.pack("<Hi", controlword, target_counts))
        h.sync(wait_for=h.tpdo1)
    assert h.drive.state is State402.OPERATION_ENABLED


def _run(h: Harness, cycles: int, target_counts: int) -> None:
    for _ in range(cycles):
        h.send(h.rpdo1, struct.pack("<Hi", 0x0F, target_counts))
        h.sync(wait_for=h.tpdo1)
        if h.drive.state is not State402.OPERATION_ENABLED:
            return


def _check_latched(h: Harness, code: int, register_bits: int) -> None:
    frames = h.recorder.wait_count(h.emcy, 1)
    sent_code, register = _emcy(frames[-1])
    assert sent_code == code
    assert register & ErrorRegister.GENERIC and register & register_bits == register_bits
    assert h.node.sdo[Obj.ERROR_CODE].raw == code
    assert h.node.sdo[Obj.ERROR_REGISTER].raw == register


def _fault_reset_clears(h: Harness) -> None:
    before = h.recorder.count(h.emcy)
    h.node.sdo[Obj.CONTROLWORD].raw = 0x00
    h.node.sdo[Obj.CONTROLWORD].raw = 0x80  # rising edge of bit 7
    assert h.drive.state is State402.SWITCH_ON_DISABLED
    frames = h.recorder.wait_count(h.emcy, before + 1)
    assert _emcy(frames[-1]) == (EmcyCode.NO_ERROR, 0)  # the EMCY "error reset"
    assert h.node.sdo[Obj.ERROR_CODE].raw == 0
    assert h.node.sdo[Obj.ERROR_REGISTER].raw == 0


@pytest.mark.parametrize(
    ("kind", "code", "bits"),
    [
        (FaultKind.OVER_CURRENT, EmcyCode.OVER_CURRENT, ErrorRegister.CURRENT),
        (FaultKind.OVER_SPEED, EmcyCode.OVER_SPEED, ErrorRegister.DEVICE_PROFILE),
        (FaultKind.GENERIC, EmcyCode.GENERIC, 0),
    ],
)
def test_injected_faults_raise_emcy_and_fault(kind: FaultKind, code: int, bits: int) -> None:
    with Harness() as h:
        _enable_csv(h)
        h.drive.inject_fault(kind)
        _check_latched(h, code, bits)
        assert h.drive.state is State402.FAULT
        statusword = h.node.sdo[Obj.STATUSWORD].raw
        assert statusword & 0x4F == 0x08  # fault
        _fault_reset_clears(h)


def test_over_speed_from_the_plant_limit_flag() -> None:
    """CST with rated torque and no load accelerates the axis past its speed limit."""
    pmsm = PmsmConfig(rated_speed=300.0, speed_limit=400.0)
    with Harness(PlantConfig(model="pmsm", pmsm=pmsm)) as h:
        h.node.sdo[Obj.MODES_OF_OPERATION].raw = OperationMode.CYCLIC_SYNC_TORQUE
        _enable_csv(h)
        rpdo2 = cob_id(FunctionCode.RPDO2, 3)  # default RPDO2: controlword + target torque
        for _ in range(200):
            h.send(rpdo2, struct.pack("<Hh", 0x0F, 1000))  # rated torque
            h.sync(wait_for=h.tpdo1)
            if h.drive.state is not State402.OPERATION_ENABLED:
                break
        _check_latched(h, EmcyCode.OVER_SPEED, ErrorRegister.DEVICE_PROFILE)
        assert h.drive.state is State402.FAULT
        _fault_reset_clears(h)


def test_sustained_torque_limit_is_an_over_current_fault() -> None:
    pmsm = PmsmConfig(rated_torque=0.05, torque_limit=0.05)
    settings = EmulatorConfig(torque_limit_fault_cycles=10)
    with Harness(PlantConfig(model="pmsm", pmsm=pmsm), settings=settings) as h:
        _enable_csv(h)
        h.send(h.rpdo1, struct.pack("<Hi", 0x0F, 2000 * COUNTS_PER_RPM))
        h.sync(wait_for=h.tpdo1)
        h.sync(wait_for=h.tpdo1)
        statusword = struct.unpack_from("<H", h.recorder.frames[h.tpdo1][-1])[0]
        assert statusword & (1 << 11)  # internal limit active while the torque is clipped
        _run(h, 30, target_counts=2000 * COUNTS_PER_RPM)
        _check_latched(h, EmcyCode.OVER_CURRENT, ErrorRegister.CURRENT)
        assert h.drive.state is State402.FAULT


@pytest.mark.parametrize(
    ("option", "state_after"),
    # one reaction in the inner loop (each case waits out a heartbeat consumer time), all four in `make test`
    [pytest.param(*reaction, marks=() if reaction[0] is AbortConnectionOption.FAULT else pytest.mark.slow)
     for reaction in ABORT_REACTIONS],
)
def test_heartbeat_loss_reacts_per_0x6007(option: int, state_after: State402) -> None:
    with Harness() as h:
        h.node.sdo[Obj.ABORT_CONNECTION_OPTION].raw = option
        h.node.sdo[Obj.CONSUMER_HEARTBEAT_TIME][1].raw = HeartbeatConsumerEntry(MASTER_ID, 300).encode()
        _enable_csv(h)
        h.send(cob_id(FunctionCode.HEARTBEAT, MASTER_ID), bytes([0x05]))  # the master's one and only beat
        time.sleep(0.05)
        assert h.recorder.count(h.emcy) == 0  # within the consumer time: nothing yet
        frames = h.recorder.wait_count(h.emcy, 1, timeout=2.0)
        assert _emcy(frames[0])[0] == EmcyCode.HEARTBEAT_LOSS
        assert h.node.sdo[Obj.ERROR_REGISTER].raw & ErrorRegister.COMMUNICATION
        _wait_for_state(h, AFTER_THE_RAMP.get(state_after, state_after))


def _wait_for_state(h: Harness, state: State402) -> None:
    """Liveness, not speed: the state is reached, however slowly the machine runs."""
    deadline = time.monotonic() + 30.0
    while h.drive.state is not state and time.monotonic() < deadline:
        time.sleep(0.01)
    assert h.drive.state is state


@pytest.mark.slow
def test_a_lost_master_in_lockstep_ends_the_quick_stop_on_the_drives_own_clock() -> None:
    """Lockstep on a wall-clock bus, the axis moving, the master gone (no heartbeat, no SYNC): the drive's 0x6007
    quick stop ramps the axis down and, with 0x605A = 2, ends in SWITCH ON DISABLED with its power stage off --
    it no longer waits for SYNCs that never come (before: QUICK STOP ACTIVE, powered, for good)."""
    with Harness() as h:
        h.node.sdo[Obj.ABORT_CONNECTION_OPTION].raw = AbortConnectionOption.QUICK_STOP
        h.node.sdo[Obj.CONSUMER_HEARTBEAT_TIME][1].raw = HeartbeatConsumerEntry(MASTER_ID, 300).encode()
        _enable_csv(h)
        h.send(cob_id(FunctionCode.HEARTBEAT, MASTER_ID), bytes([0x05]))
        _run(h, 40, target_counts=300 * COUNTS_PER_RPM)  # the axis speeds up towards 300 rpm
        assert abs(h.drive.snapshot().velocity) > 50 * COUNTS_PER_RPM
        h.recorder.wait_count(h.emcy, 1, timeout=10.0)
        _wait_for_state(h, State402.SWITCH_ON_DISABLED)
        assert abs(h.drive.snapshot().velocity) < 20 * COUNTS_PER_RPM  # ramped down, not cut off at speed


class _SteppedClock:
    """The supervision's clock, moved only by the test: SYNC-loss timing independent of the machine's load."""

    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


@pytest.mark.slow
def test_sync_loss_in_realtime_mode() -> None:
    settings = EmulatorConfig(timing="realtime", sync_loss_cycles=20)
    with Harness(settings=settings) as h:
        # The supervision thread keeps polling, but on this clock: a slow SYNC while enabling, or a starved thread,
        # cannot make or hide a loss. Steps of a quarter period stay under the stall threshold (STALL_POLLS polls),
        # so no poll (the thread's or ours) takes a step for a stalled process.
        clock = _SteppedClock()
        h.drive.supervisor.clock = clock
        h.node.sdo[Obj.ABORT_CONNECTION_OPTION].raw = AbortConnectionOption.FAULT
        _enable_csv(h)
        cycles = h.drive.snapshot().cycles
        step = h.drive.physics.cycle_period / 4
        assert step < STALL_POLLS * MONITOR_PERIOD
        for _ in range(4 * 20 - 1):  # 19.75 periods without SYNC: not yet a loss
            clock.now += step
            h.drive.supervisor.poll()
        assert h.drive.state is State402.OPERATION_ENABLED and h.recorder.count(h.emcy) == 0
        for _ in range(2):  # 20.25 periods: the loss, reported once
            clock.now += step
            h.drive.supervisor.poll()
        assert h.drive.state is State402.FAULT
        frames = h.recorder.wait_count(h.emcy, 1)
        assert _emcy(frames[0])[0] == EmcyCode.SYNC_LOSS
        # the physics goes on by the wall clock without SYNC (waited for, however slowly the machine runs)
        deadline = time.monotonic() + 30.0
        while h.drive.snapshot().cycles <= cycles + 5 and time.monotonic() < deadline:
            time.sleep(0.01)
        assert h.drive.snapshot().cycles > cycles + 5


def test_lockstep_has_no_sync_loss() -> None:
    with Harness() as h:
        _enable_csv(h)
        time.sleep(0.2)
        assert h.recorder.count(h.emcy) == 0
        assert h.drive.state is State402.OPERATION_ENABLED


@pytest.mark.slow
def test_send_emcy_and_stop_responding() -> None:
    with Harness() as h:
        h.drive.send_emcy(0xFF01, 0x80)
        assert _emcy(h.recorder.wait_count(h.emcy, 1)[0]) == (0xFF01, 0x80)
        assert h.drive.state is State402.SWITCH_ON_DISABLED  # a bare EMCY changes no state
        h.node.sdo[Obj.PRODUCER_HEARTBEAT_TIME].raw = 20
        h.drive.stop_responding()
        heartbeat = cob_id(FunctionCode.HEARTBEAT, 3)
        time.sleep(0.05)
        beats = h.recorder.count(heartbeat)
        time.sleep(0.15)
        assert h.recorder.count(heartbeat) == beats  # dead: no heartbeat
        h.node.sdo.RESPONSE_TIMEOUT = 0.2
        with pytest.raises(Exception, match="No SDO response"):
            h.node.sdo.upload(0x1000, 0)


# --- the master's view -----------------------------------------------------------------------------------------


_MASTER_BUSES: list[can.BusABC] = []


@pytest.fixture(autouse=True)
def _shut_master_buses() -> Iterator[None]:
    """The bus belongs to the caller, not to the master: shut the ones :func:`_master` opened."""
    yield
    while _MASTER_BUSES:
        _MASTER_BUSES.pop().shutdown()


def _master(emulator: EmbeddedEmulator, **drive: float) -> Cia402Drive:
    cfg = DriveConfig.model_validate(
        {"node_id": 2, "heartbeat_producer_ms": 50, "heartbeat_consumer_ms": 200, **drive}
    )
    bus = open_bus(emulator.bus_config)
    _MASTER_BUSES.append(bus)
    master = Cia402Drive.open(bus, cfg, sample_time=0.01)
    master.connect()
    master.configure(OperationMode.CYCLIC_SYNC_VELOCITY)
    master.enable()
    for _ in range(3):
        master.set_target(100.0)
        master.sync()
        master.wait_feedback(1.0)
    return master


def _cycle_until_error(master: Cia402Drive, cycles: int = 50) -> DriveError:
    for _ in range(cycles):
        try:
            master.set_target(100.0)
            master.sync()
            master.wait_feedback(1.0)
        except DriveError as exc:
            return exc
    raise AssertionError("the master saw no error")


@pytest.mark.parametrize(
    ("kind", "code"),
    [
        (FaultKind.OVER_CURRENT, EmcyCode.OVER_CURRENT),
        (FaultKind.OVER_SPEED, EmcyCode.OVER_SPEED),
        (FaultKind.SYNC_LOSS, EmcyCode.SYNC_LOSS),
        (FaultKind.HEARTBEAT_LOSS, EmcyCode.HEARTBEAT_LOSS),
    ],
)
def test_master_surfaces_each_fault_as_typed_error(kind: FaultKind, code: int) -> None:
    plant = PlantConfig(model="pmsm")
    with EmbeddedEmulator(plant, EmulatorConfig(), node_id=2, sample_time=0.01, velocity_scale=1000.0) as emulator:
        master = _master(emulator, velocity_scale=1000.0, abort_connection_option=1)
        try:
            emulator.drive.inject_fault(kind)
            error = _cycle_until_error(master)
            assert isinstance(error, EmergencyError)
            assert error.code == code
            assert emulator.drive.state in (State402.FAULT, State402.SWITCH_ON_DISABLED,
                                            State402.QUICK_STOP_ACTIVE)  # not enabled: safe
            assert emulator.drive.state is State402.FAULT  # 0x6007 = 1: every one of these is a fault
            master.fault_reset()
            assert emulator.drive.state is State402.SWITCH_ON_DISABLED
            assert emulator.drive.snapshot().error_code == 0
            assert emulator.drive.emcy_log[-1] == (EmcyCode.NO_ERROR, 0)
        finally:
            master.safe_stop()
            master.close()


def test_master_detects_a_dead_drive() -> None:
    plant = PlantConfig(model="pmsm")
    with EmbeddedEmulator(plant, EmulatorConfig(), node_id=2, sample_time=0.01, velocity_scale=1000.0) as emulator:
        # short SDO/state timeouts: the final stop walks every path against a drive that answers none of them
        master = _master(emulator, velocity_scale=1000.0, sdo_timeout=0.2, state_timeout=0.5)
        try:
            emulator.drive.stop_responding()
            error = _cycle_until_error(master, cycles=20)
            assert isinstance(error, (HeartbeatLostError, DriveError))
            assert not isinstance(error, EmergencyError)
        finally:
            master.safe_stop()
            master.close()


def test_nmt_reset_node_restores_the_abort_option() -> None:
    """Reset node from any master restores the OD: the EMCY-free restart the master's fault_reset relies on."""
    with Harness() as h:
        h.node.sdo[Obj.ABORT_CONNECTION_OPTION].raw = 0
        h.nmt(NmtCommand.RESET_NODE)
        assert h.node.sdo[Obj.ABORT_CONNECTION_OPTION].raw == 3  # EDS default


def test_short_rpdo_is_refused_with_emcy() -> None:
    with Harness() as h:
        h.start()
        h.send(h.rpdo1, struct.pack("<H", 0x06))  # RPDO1 maps 6 bytes; 2 arrive
        h.sync(wait_for=h.tpdo1)
        frames = h.recorder.wait_count(h.emcy, 1)
        assert _emcy(frames[0])[0] == EmcyCode.PDO_LENGTH
        assert h.drive.state is State402.SWITCH_ON_DISABLED  # the frame was not applied


# --- NMT leaving OPERATIONAL, and the master's confirmed stop ------------------------------------------------


@pytest.mark.parametrize("command", [NmtCommand.STOP, NmtCommand.ENTER_PRE_OPERATIONAL])
@pytest.mark.parametrize(
    ("option", "state_after"),
    # one reaction per command in the inner loop, all four in `make test`
    [pytest.param(*reaction, marks=() if reaction[0] is AbortConnectionOption.FAULT else pytest.mark.slow)
     for reaction in ABORT_REACTIONS],
)
def test_leaving_operational_reacts_per_0x6007(command: NmtCommand, option: int, state_after: State402) -> None:
    """Outside OPERATIONAL no RPDO reaches the drive: the drive applies its abort-connection reaction itself."""
    with Harness() as h:
        h.node.sdo[Obj.ABORT_CONNECTION_OPTION].raw = option
        _enable_csv(h, target_counts=100_000)
        h.nmt(command)
        # the reaction entered at once, or (quick stop) already ramped on the drive's own clock
        assert h.drive.state in (state_after, AFTER_THE_RAMP.get(state_after, state_after))
        _wait_for_state(h, AFTER_THE_RAMP.get(state_after, state_after))
        if option != AbortConnectionOption.NO_ACTION:
            assert h.drive.snapshot().error_code == EmcyCode.COMMUNICATION
            if command is NmtCommand.ENTER_PRE_OPERATIONAL:  # no EMCY from a STOPPED node (CiA 301)
                frames = h.recorder.wait_count(h.emcy, 1)
                assert _emcy(frames[-1])[0] == EmcyCode.COMMUNICATION


@pytest.mark.parametrize("command", [NmtCommand.STOP, NmtCommand.ENTER_PRE_OPERATIONAL])
def test_master_stop_is_confirmed_when_the_pdo_path_is_gone(command: NmtCommand) -> None:
    """A third party takes the drive out of OPERATIONAL; the drive itself does nothing (0x6007 = 0). The master's
    stop escalates past the dead PDO path and confirms the disabled state by reading the statusword over SDO."""
    plant = PlantConfig(model="pmsm")
    with EmbeddedEmulator(plant, EmulatorConfig(), node_id=2, sample_time=0.01, velocity_scale=1000.0) as emulator:
        master = _master(emulator, velocity_scale=1000.0, abort_connection_option=0)
        try:
            bus = open_bus(emulator.bus_config)
            try:
                bus.send(can.Message(arbitration_id=0, data=[int(command), 2], is_extended_id=False))
                # the drive's next heartbeat (0x1017 = 50 ms of lockstep time) tells the master
                clock = timebase_of(bus)
                assert isinstance(clock, LockstepClock)
                assert clock.wait_until(lambda: master.heartbeat.last_state != NmtState.OPERATIONAL, timeout=1.0)
            finally:
                bus.shutdown()
            assert emulator.drive.state is State402.OPERATION_ENABLED  # 0x6007 = 0: still enabled, no PDO path
            report = master.safe_stop()
            assert report.commanded and report.confirmed, report
            assert report.via in (StopPath.SDO, StopPath.NMT_SDO)
            assert report.attempts and report.attempts[0].startswith("pdo:")
            assert emulator.drive.state is State402.SWITCH_ON_DISABLED
            assert report.state is State402.SWITCH_ON_DISABLED
            assert "confirmed disabled" in report.describe(2) and "NOT" not in report.describe(2)
        finally:
            master.close()


def test_master_stop_of_a_silent_drive_is_reported_unconfirmed() -> None:
    plant = PlantConfig(model="pmsm")
    with EmbeddedEmulator(plant, EmulatorConfig(), node_id=2, sample_time=0.01, velocity_scale=1000.0) as emulator:
        master = _master(emulator, velocity_scale=1000.0, sdo_timeout=0.1, state_timeout=0.3)
        try:
            emulator.drive.stop_responding()
            report = master.safe_stop()
            assert report.commanded and not report.confirmed
            assert [line.split(":")[0] for line in report.attempts] == [str(path) for path in StopPath]
            assert "NOT confirmed disabled" in report.describe(2)
        finally:
            master.close()


def _loaded_z_axis(brake_torque: float) -> PlantConfig:
    """The SCARA z axis of configs/scara_4axis.yaml: 0.2 N m of load on 6e-4 kg m^2, in the emulator's hands."""
    pmsm = PmsmConfig(inertia=6.0e-4, velocity_kp=0.05, velocity_ki=0.25, velocity_setpoint_weight=1.0,
                      brake_torque=brake_torque)
    return PlantConfig.model_validate({"model": "pmsm", "pmsm": pmsm.model_dump(),
                                       "disturbance": {"kind": "constant", "amplitude": 0.2}})


def _power_up_then_enable(h: Harness, idle_cycles: int) -> None:
    """``idle_cycles`` SYNCs of physics while the drive waits disabled (the realtime emulator's ticks before the
    master enables it, on the lockstep clock here), then enable CSV and hold target 0 for 40 cycles."""
    h.sync()
    assert h.drive.state is State402.SWITCH_ON_DISABLED
    for _ in range(idle_cycles):
        h.send(SYNC_COB_ID, b"")
    h.sync()  # settles: every SYNC above has been handled
    h.start()
    for controlword in (0x06, 0x07, 0x0F):
        h.send(h.rpdo1, struct.pack("<Hi", controlword, 0))
        h.sync(wait_for=h.tpdo1)
    _run(h, 40, 0)


def test_a_disabled_axis_under_load_is_held_by_its_brake_and_enables_without_over_speed() -> None:
    """Two seconds disabled under a load that would take the free axis past its speed limit in 1.3 s: the closed
    holding brake keeps it at rest, and the drive enables and holds it at 0 rpm without a fault."""
    with Harness(_loaded_z_axis(brake_torque=0.5), cycle_period=0.0025) as h:
        _power_up_then_enable(h, idle_cycles=800)
        assert h.drive.state is State402.OPERATION_ENABLED
        assert h.drive.emcy_log == []
        assert abs(h.drive.plant.output()[0]) < 100.0  # rpm: the velocity loop took the load over from the brake


def test_without_a_brake_the_load_runs_the_disabled_axis_away_and_enable_trips_over_speed() -> None:
    """The cause of the realtime four-axis run's over-speed EMCY: with no brake the unpowered axis accelerates
    under its load before the master enables it, and enabling a drive on an axis past its speed limit trips."""
    with Harness(_loaded_z_axis(brake_torque=0.0), cycle_period=0.0025) as h:
        _power_up_then_enable(h, idle_cycles=800)
        assert h.drive.plant.state()[1] > 3600.0 * 2 * math.pi / 60  # rad/s: past the speed limit, disabled
        _check_latched(h, EmcyCode.OVER_SPEED, ErrorRegister.DEVICE_PROFILE)
        assert h.drive.state is State402.FAULT
