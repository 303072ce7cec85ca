"""Several CiA 402 drives on one bus (:class:`drivers.network.DriveNetwork`) against a multi-node embedded emulator.

One receive path, one SYNC per cycle, frames routed by COB-ID to the drive they belong to: each drive is enabled,
commanded and disabled on its own while the others keep their state.
"""

from __future__ import annotations

from collections.abc import Iterator

import can
import pytest

from drivers.bus import open_bus
from drivers.cia301 import SYNC_COB_ID
from drivers.cia402 import OperationMode, State402
from drivers.cia402_master import Cia402Drive
from drivers.config import DriveConfig
from drivers.inprocess import InProcessBus
from drivers.network import DriveNetwork
from foilc_hil.errors import ConfigError, InputError
from plant_emulator import cli as emulator_cli
from plant_emulator.config import PlantConfig
from plant_emulator.embedded import EmbeddedEmulator
from plant_emulator.settings import EmulatorConfig

PERIOD = 0.01
NODES = (1, 2, 3, 4)


@pytest.fixture
def emulator() -> Iterator[EmbeddedEmulator]:
    plant = PlantConfig(model="first_order", a=-1.23, b=1.68)
    with EmbeddedEmulator(plant, EmulatorConfig(), node_id=NODES, sample_time=PERIOD,
                          velocity_scale=1000.0) as started:
        yield started


@pytest.fixture
def network(emulator: EmbeddedEmulator) -> Iterator[DriveNetwork]:
    bus = open_bus(emulator.bus_config)
    assert isinstance(bus, InProcessBus)
    shared = DriveNetwork(bus)
    yield shared
    shared.close()
    bus.shutdown()


def _drives(network: DriveNetwork, nodes: tuple[int, ...] = NODES) -> list[Cia402Drive]:
    drives = []
    for node in nodes:
        cfg = DriveConfig(node_id=node, velocity_scale=1000.0)
        drive = Cia402Drive.on_network(network, cfg, sample_time=PERIOD)
        drive.connect()
        drive.configure(OperationMode.CYCLIC_SYNC_VELOCITY)
        drives.append(drive)
    return drives


def test_four_drives_share_one_receive_path_and_are_commanded_independently(
    network: DriveNetwork, emulator: EmbeddedEmulator
) -> None:
    drives = _drives(network)
    syncs: list[can.Message] = []
    network.tap.add_listener(lambda msg, direction: syncs.append(msg) if msg.arbitration_id == SYNC_COB_ID else None)
    drives[1].enable()  # node 2 only
    assert [emulator.by_node(n).state for n in NODES] == [
        State402.SWITCH_ON_DISABLED, State402.OPERATION_ENABLED, State402.SWITCH_ON_DISABLED,
        State402.SWITCH_ON_DISABLED]
    for drive in (drives[0], drives[2], drives[3]):
        drive.enable()
    targets = {1: 5.0, 2: -7.0, 3: 11.0, 4: 0.0}
    sent_before = len(syncs)
    for _ in range(30):
        for drive in drives:
            drive.set_target(targets[drive.node_id])
        drives[0].sync()  # one SYNC for every member
        feedback = [drive.wait_feedback(1.0) for drive in drives]
    assert len(syncs) - sent_before == 30
    assert len({drive.cycle for drive in drives}) == 1
    # each node got its own target (routing by COB-ID both ways): the emulated axes move apart, each towards the
    # sign of its own command, and the one commanded 0 stays at rest
    velocity = {drive.node_id: fb.velocity for drive, fb in zip(drives, feedback, strict=True)}
    assert velocity[1] > 0.5 and velocity[2] < -0.5 and velocity[3] > velocity[1]
    assert velocity[4] == pytest.approx(0.0, abs=1e-6)
    for node in NODES:  # the drive's own view (0.001 units) agrees with the master's decoded feedback
        assert emulator.by_node(node).snapshot().velocity / 1000.0 == pytest.approx(velocity[node], abs=2e-3)
    drives[2].disable()  # node 3 only
    assert [emulator.by_node(n).state for n in NODES] == [
        State402.OPERATION_ENABLED, State402.OPERATION_ENABLED, State402.SWITCH_ON_DISABLED,
        State402.OPERATION_ENABLED]
    reports = [drive.safe_stop() for drive in drives]
    assert all(report.confirmed for report in reports)
    assert all(emulator.by_node(n).state is State402.SWITCH_ON_DISABLED for n in NODES)
    assert drives[0].stats.unknown_frames == 0  # one shared counter: every frame had its subscriber
    for drive in drives:
        drive.close()


def test_closing_a_shared_drive_leaves_the_others_running(network: DriveNetwork) -> None:
    first, second = _drives(network, (1, 2))
    second.enable()
    first.close()  # leaves the network; the receive path stays for node 2
    assert network.listening
    second.set_target(3.0)
    second.sync()
    assert second.wait_feedback(1.0).state is State402.OPERATION_ENABLED
    assert second.safe_stop().confirmed
    second.close()


def test_a_node_joins_a_network_once(network: DriveNetwork) -> None:
    Cia402Drive.on_network(network, DriveConfig(node_id=2), sample_time=PERIOD)
    with pytest.raises(ConfigError, match="node 2 is already on this bus's network"):
        Cia402Drive.on_network(network, DriveConfig(node_id=2), sample_time=PERIOD)


def test_one_master_heartbeat_per_bus(network: DriveNetwork) -> None:
    network.start_master_heartbeat(127, 0.05)
    network.start_master_heartbeat(127, 0.05)  # the second member: nothing new
    with pytest.raises(ConfigError, match=r"drive\.master_node_id"):
        network.start_master_heartbeat(100, 0.05)


def test_the_emulator_refuses_repeated_node_ids() -> None:
    with pytest.raises(InputError, match="distinct"):
        EmbeddedEmulator(PlantConfig(model="first_order"), EmulatorConfig(), node_id=(1, 1), sample_time=PERIOD)


@pytest.mark.parametrize(("node_ids", "said"), [("1,1", "repeats a node id"), ("1,200", "200 is outside 1..127"),
                                                 ("1,x", "not a comma-separated list")])
def test_the_emulator_cli_refuses_bad_node_lists(node_ids: str, said: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exited:
        emulator_cli.main(["--bus", "inprocess:unused", "--node-id", node_ids])
    assert exited.value.code == 2
    err = capsys.readouterr().err
    assert said in err and len(err.strip().splitlines()) == 1


def test_the_emulator_cli_refuses_injection_into_several_nodes(capsys: pytest.CaptureFixture[str]) -> None:
    assert emulator_cli.main(["--bus", "inprocess:unused", "--node-id", "1,2", "--inject", "emulator-kill@c5"]) == 2
    assert "give one --node-id" in capsys.readouterr().err


@pytest.mark.slow
@pytest.mark.timeout(60)
def test_two_realtime_drives_share_one_notifier_thread() -> None:
    """The threaded receive path: a realtime emulator (python-can ``virtual``, wall clock), one Notifier for both."""
    import threading
    import time

    from drivers.realtime import NOTIFIER_THREAD_PREFIX

    def notifiers() -> set[threading.Thread]:
        return {t for t in threading.enumerate() if t.name.startswith(NOTIFIER_THREAD_PREFIX)}

    plant = PlantConfig(model="first_order", a=-1.23, b=1.68)
    with EmbeddedEmulator(plant, EmulatorConfig(timing="realtime"), node_id=(5, 6), sample_time=PERIOD,
                          velocity_scale=1000.0) as emulator:
        bus = open_bus(emulator.bus_config)
        network = DriveNetwork(bus)
        drives: list[Cia402Drive] = []
        try:
            before = notifiers()
            drives = _drives(network, (5, 6))
            assert len(notifiers() - before) == 1  # the master's end: one receive thread for both drives
            for drive in drives:
                drive.enable()
            for _ in range(20):
                drives[0].set_target(20.0)
                drives[1].set_target(-20.0)
                drives[0].sync()
                feedback = [drive.wait_feedback(1.0) for drive in drives]
                time.sleep(PERIOD)  # realtime: the physics ticks on the wall clock, one SYNC per period
            assert feedback[0].velocity > 0 > feedback[1].velocity
            assert all(drive.safe_stop().confirmed for drive in drives)
        finally:
            for drive in drives:
                drive.close()
            network.close()
            bus.shutdown()
