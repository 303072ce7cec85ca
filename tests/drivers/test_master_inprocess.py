"""The CiA 402 master and the embedded emulator on the synchronous in-process transport, in lockstep.

What the transport promises the bench: no thread on either end, an unanswered SYNC known when ``sync`` returns
(no deadline), and supervision on lockstep time, so a host that stalls is not a drive that died.
"""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator

import pytest

from drivers.bus import open_bus
from drivers.cia402 import OperationMode, State402
from drivers.cia402_master import Cia402Drive
from drivers.config import DriveConfig
from drivers.inprocess import InProcessBus, LockstepClock
from foilc_hil.errors import DriveTimeoutError, FeedbackTimeoutError, HeartbeatLostError
from plant_emulator.config import PlantConfig
from plant_emulator.embedded import EmbeddedEmulator
from plant_emulator.settings import EmulatorConfig

PERIOD = 0.01
NODE = 3


@pytest.fixture
def emulator() -> Iterator[EmbeddedEmulator]:
    plant = PlantConfig(model="first_order", a=-1.23, b=1.68)
    with EmbeddedEmulator(plant, EmulatorConfig(), node_id=NODE, sample_time=PERIOD,
                          velocity_scale=1000.0) as started:
        yield started


@pytest.fixture
def bus(emulator: EmbeddedEmulator) -> Iterator[InProcessBus]:
    opened = open_bus(emulator.bus_config)
    assert isinstance(opened, InProcessBus)
    yield opened
    opened.shutdown()


def _clock(bus: InProcessBus) -> LockstepClock:
    assert bus.clock is not None
    return bus.clock


def _enabled_master(bus: InProcessBus, **drive: float) -> Cia402Drive:
    cfg = DriveConfig.model_validate({"node_id": NODE, "velocity_scale": 1000.0, **drive})
    master = Cia402Drive.open(bus, cfg, sample_time=PERIOD)
    master.connect()
    master.configure(OperationMode.CYCLIC_SYNC_VELOCITY)
    master.enable()
    return master


def test_a_lockstep_run_has_no_thread_on_either_end(bus: InProcessBus) -> None:
    before = set(threading.enumerate())
    master = _enabled_master(bus)
    try:
        for _ in range(20):
            master.set_target(10.0)
            master.sync()
            assert master.wait_feedback(1.0).state is State402.OPERATION_ENABLED
        # no Notifier, heartbeat, watchdog or supervision thread (an earlier test's thread may end meanwhile)
        assert [t.name for t in threading.enumerate() if t not in before] == []
    finally:
        master.safe_stop()
        master.close()


def test_sync_advances_lockstep_time_by_one_period(bus: InProcessBus, emulator: EmbeddedEmulator) -> None:
    master = _enabled_master(bus)
    try:
        clock = _clock(bus)
        master.sync()  # from a SYNC on: the next one is one period later
        master.wait_feedback(1.0)
        start, physics = clock.now(), emulator.drive.snapshot().plant_time
        for _ in range(25):
            master.sync()
            master.wait_feedback(1.0)
        assert clock.now() - start == pytest.approx(25 * PERIOD)
        assert emulator.drive.snapshot().plant_time - physics == pytest.approx(25 * PERIOD)  # the drive agrees
    finally:
        master.safe_stop()
        master.close()


def test_an_unanswered_sync_is_known_at_once_without_a_deadline(
    bus: InProcessBus, emulator: EmbeddedEmulator, monkeypatch: pytest.MonkeyPatch
) -> None:
    master = _enabled_master(bus)
    try:
        monkeypatch.setattr(emulator.drive.pdos, "send_synchronous", lambda: None)  # no TPDO set from now on
        master.sync()
        clock = _clock(bus)
        before = clock.now()
        # an hour of allowance: a wait of any kind would stall the test (and pytest-timeout would fail it)
        with pytest.raises(FeedbackTimeoutError, match=r"answered SYNC \d+ on the synchronous bus"):
            master.wait_feedback(3600.0)
        assert clock.now() == before  # no simulated time passed either
    finally:
        master.safe_stop()
        master.close()


def test_a_stalled_host_is_not_a_lost_heartbeat_but_a_dead_drive_is_on_time(
    bus: InProcessBus, emulator: EmbeddedEmulator
) -> None:
    # 0x1017 = 20 ms, lost after 3 x 20 ms = 60 ms of lockstep time
    master = _enabled_master(bus, heartbeat_producer_ms=20, heartbeat_timeout_factor=3.0)
    try:
        for _ in range(3):  # the host stalls for longer than the heartbeat timeout, three times
            time.sleep(0.1)
            master.sync()
            master.wait_feedback(1.0)
        emulator.drive.stop_responding()
        lost: HeartbeatLostError | None = None
        for _ in range(100):
            master.sync()
            try:
                master.wait_feedback(1.0)
            except HeartbeatLostError as exc:
                lost = exc
                break
            except FeedbackTimeoutError:
                continue  # the dead drive answers no SYNC either; the heartbeat decides
        assert lost is not None
        silence = float(str(lost).split("none for ")[1].split(" s")[0])
        # found at the first SYNC after the deadline: more than 60 ms, at most one period more, of lockstep time
        assert 0.06 < silence <= 0.06 + PERIOD + 1e-9, silence
    finally:
        master.safe_stop()
        master.close()


def test_no_sdo_answer_is_known_without_waiting_for_the_response_timeout(bus: InProcessBus) -> None:
    cfg = DriveConfig.model_validate({"node_id": NODE + 1, "sdo_timeout": 3600.0, "state_timeout": 3600.0})
    master = Cia402Drive.open(bus, cfg, sample_time=PERIOD)  # a node id nobody answers to
    try:
        master.listen()
        with pytest.raises(DriveTimeoutError, match=r"no valid SDO response for 0x1000:00"):
            master.read_object(0x1000)
    finally:
        master.close()


def test_no_boot_up_is_a_wait_in_lockstep_time(bus: InProcessBus) -> None:
    cfg = DriveConfig.model_validate({"node_id": NODE + 1, "state_timeout": 5.0})
    master = Cia402Drive.open(bus, cfg, sample_time=PERIOD)
    try:
        start = _clock(bus).now()
        with pytest.raises(DriveTimeoutError, match=r"no boot-up from node 4 within 5\.0 s"):
            master.connect()
        assert _clock(bus).now() - start == pytest.approx(5.0)  # the whole allowance passed, as simulated time
    finally:
        master.close()
