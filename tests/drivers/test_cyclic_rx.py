"""The cyclic receive path of a realtime bench (:mod:`drivers.cyclic_rx`): TPDOs received on the waiting thread.

On python-can ``virtual`` (every bus object gets its own copy of each frame, as on ``udp_multicast`` and
``socketcan``), in one process: the receiver alone, a network's SYNC draining late answers into their own cycle, and
masters against a realtime emulator with and without it (same feedback, counters, frame tap and errors).
"""

from __future__ import annotations

import itertools
import time
from collections.abc import Iterator

import can
import pytest

from drivers.bus import open_bus
from drivers.cia402 import OperationMode, State402
from drivers.cia402_master import Cia402Drive
from drivers.config import BusConfig, DriveConfig
from drivers.cyclic_rx import CyclicReceiver, open_cyclic_receiver
from drivers.drive import Feedback
from drivers.network import DriveNetwork, received_elsewhere
from foilc_hil.errors import DriveFaultError, FeedbackTimeoutError
from plant_emulator.config import PlantConfig
from plant_emulator.embedded import EmbeddedEmulator
from plant_emulator.settings import EmulatorConfig

PERIOD = 0.01
_channels = itertools.count()


@pytest.fixture
def channel() -> str:
    return f"cyclic-rx-test-{next(_channels)}"


def _frame(can_id: int, data: bytes = b"\x01\x02") -> can.Message:
    return can.Message(arbitration_id=can_id, data=data, is_extended_id=False)


@pytest.mark.parametrize("spin", [0.0, 0.0005])
def test_the_receiver_dispatches_only_its_routes(channel: str, spin: float) -> None:
    sender = can.Bus(interface="virtual", channel=channel)
    receiver = CyclicReceiver(can.Bus(interface="virtual", channel=channel), spin)
    got: list[tuple[int, bytes]] = []
    try:
        receiver.route(0x181, lambda can_id, data, _: got.append((can_id, bytes(data))))
        for can_id in (0x080, 0x201, 0x181, 0x701):
            sender.send(_frame(can_id))
        spin_until = time.monotonic() + spin
        assert [receiver.poll(1.0, spin_until) for _ in range(4)] == [False, False, True, False]  # others dropped
        assert got == [(0x181, b"\x01\x02")]
        assert not receiver.poll(0.001, spin_until)  # nothing left
        assert receiver.frames == 1
        receiver.unroute(0x181)
        sender.send(_frame(0x181))
        assert not receiver.poll(0.001) and len(got) == 1
    finally:
        receiver.close()
        sender.shutdown()


def test_dispatch_until_tells_which_came_first_and_never_reads_past_a_sync(channel: str) -> None:
    """An RPDO's own echo against the next SYNC (a clock counted on its echoes): frames before either are dispatched,
    a SYNC first is kept for the next poll, an earlier echo of the same COB-ID is not taken for this one."""
    sender = can.Bus(interface="virtual", channel=channel)
    receiver = CyclicReceiver(can.Bus(interface="virtual", channel=channel))
    got: list[int] = []
    try:
        for can_id in (0x080, 0x201):
            receiver.route(can_id, lambda can_id, data, _: got.append(can_id))

        def echoes() -> int:
            return got.count(0x201)

        for can_id in (0x181, 0x201, 0x080, 0x201):  # an old echo, a SYNC, then this RPDO's echo
            sender.send(_frame(can_id))
        assert receiver.dispatch_until(lambda: echoes() >= 2, 0x080) is False  # the SYNC came first
        assert got == [0x201]  # the old echo dispatched, the SYNC kept
        assert receiver.poll(1.0) and got == [0x201, 0x080]  # the kept SYNC is the next frame
        assert receiver.dispatch_until(lambda: echoes() >= 2, 0x080) is True and got == [0x201, 0x080, 0x201]
        assert receiver.dispatch_until(lambda: echoes() >= 3, 0x080) is None  # not in yet: not known
    finally:
        receiver.close()
        sender.shutdown()


def test_a_sync_first_dispatches_the_answers_of_the_cycle_before(channel: str) -> None:
    """A TPDO in the queue when the next SYNC is sent arrived for the old cycle: it must not answer the new one."""
    bus = can.Bus(interface="virtual", channel=channel)
    drive_end = can.Bus(interface="virtual", channel=channel)
    network = DriveNetwork(bus, CyclicReceiver(can.Bus(interface="virtual", channel=channel)))
    assert network.receiver is not None
    cycle = [0]
    seen: list[int] = []
    network.join(lambda: cycle.__setitem__(0, cycle[0] + 1))
    def on_tpdo(can_id: int, data: bytearray, timestamp: float) -> None:
        seen.append(cycle[0])

    network.subscribe_cyclic(0x181, on_tpdo)
    try:
        assert network.network.subscribers[0x181] == [received_elsewhere]  # known to the Notifier, handled elsewhere
        network.sync(PERIOD)
        drive_end.send(_frame(0x181))  # late: nobody polled for it in cycle 1
        network.sync(PERIOD)
        assert seen == [1]
        network.unsubscribe_cyclic(0x181, on_tpdo)
        assert 0x181 not in network.network.subscribers and not network.receiver.routes
    finally:
        network.close()
        network.receiver.close()
        for end in (bus, drive_end):
            end.shutdown()


def test_the_in_process_transport_has_no_second_receiver() -> None:
    assert open_cyclic_receiver(BusConfig(interface="inprocess", channel="x"), 0.0) is None


@pytest.fixture
def emulator() -> Iterator[EmbeddedEmulator]:
    """A realtime emulator on python-can ``virtual`` (wall clock), two drives."""
    plant = PlantConfig(model="first_order", a=-1.23, b=1.68)
    with EmbeddedEmulator(plant, EmulatorConfig(timing="realtime"), node_id=(5, 6), sample_time=PERIOD,
                          velocity_scale=1000.0) as started:
        yield started


def _masters(emulator: EmbeddedEmulator, receiver: CyclicReceiver | None) -> tuple[DriveNetwork, list[Cia402Drive]]:
    network = DriveNetwork(open_bus(emulator.bus_config), receiver)
    drives = []
    for node in (5, 6):
        drive = Cia402Drive.on_network(network, DriveConfig(node_id=node, velocity_scale=1000.0), sample_time=PERIOD)
        drive.connect()
        drive.configure(OperationMode.CYCLIC_SYNC_VELOCITY)
        drives.append(drive)
    return network, drives


def _given_no_time(drive: Cia402Drive) -> Feedback:
    """``wait_feedback(0.0)`` until the answer is in: a wait given no time returns an answer already received."""
    for _ in range(1000):
        try:
            return drive.wait_feedback(0.0)
        except FeedbackTimeoutError:
            time.sleep(0.01)
    raise AssertionError(f"node {drive.node_id}: no answer was ever found by a wait given no time")


def _close(network: DriveNetwork, drives: list[Cia402Drive]) -> None:
    for drive in drives:
        drive.close()
    network.close()
    if network.receiver is not None:
        network.receiver.close()
    network.bus.shutdown()


@pytest.mark.slow
@pytest.mark.parametrize("path", ["notifier", "loop", "loop-spin"])
def test_both_receive_paths_give_the_same_feedback_counters_and_log(emulator: EmbeddedEmulator, path: str) -> None:
    receiver = None if path == "notifier" else open_cyclic_receiver(emulator.bus_config, 0.001 * (path == "loop-spin"))
    network, drives = _masters(emulator, receiver)
    logged: list[tuple[int, str]] = []
    drives[0].add_frame_listener(lambda msg, direction: logged.append((msg.arbitration_id, direction)))
    # node 6's heartbeat may come before drive 6 is on the network (the emulator runs on the wall clock): unknown
    # then, rightly; from here on every frame on the bus has a subscriber
    unknown_before = drives[0].stats.unknown_frames
    try:
        for drive in drives:
            drive.enable()
        # at least 20 cycles, and until both axes move (the emulator's physics runs on the wall clock: a loaded host
        # may give it fewer ticks than SYNCs at first); liveness, not speed
        for count in range(500):
            drives[0].set_target(20.0)
            drives[1].set_target(-20.0)
            cycle = drives[0].sync()
            feedback = [drive.wait_feedback(1.0) for drive in drives]
            if count >= 20 and feedback[0].velocity > 0 > feedback[1].velocity:
                break
        assert [f.cycle for f in feedback] == [cycle, cycle]
        drives[0].sync()
        assert _given_no_time(drives[1]).cycle == _given_no_time(drives[0]).cycle == cycle + 1
        assert feedback[0].velocity > 0 > feedback[1].velocity
        assert all(f.state is State402.OPERATION_ENABLED for f in feedback)
        stats = drives[0].stats
        assert stats.tpdo_frames >= 20 and stats.bad_frames == 0 and stats.unknown_frames == unknown_before
        tpdo = drives[0].pdo_codecs.keys() - {0x205}  # node 5's TPDOs (its RPDO is 0x205)
        assert any(can_id in tpdo and direction == "rx" for can_id, direction in logged)  # the tap still logs them
        if receiver is not None:
            assert receiver.frames >= stats.tpdo_frames  # every TPDO of both drives came this way
        assert all(drive.safe_stop().confirmed for drive in drives)
    finally:
        _close(network, drives)


@pytest.mark.slow
@pytest.mark.parametrize("loop", [False, True])
def test_a_drive_fault_is_raised_by_the_wait_on_either_path(emulator: EmbeddedEmulator, loop: bool) -> None:
    network, drives = _masters(emulator, open_cyclic_receiver(emulator.bus_config, 0.0) if loop else None)
    try:
        for drive in drives:
            drive.enable()
        drives[0].sync()
        for drive in drives:
            drive.wait_feedback(1.0)
        emulator.by_node(5).inject_fault("over-current")
        with pytest.raises(DriveFaultError):  # the EMCY (Notifier thread) or the fault bit (this thread)
            for _ in range(50):
                drives[0].sync()
                drives[0].wait_feedback(1.0)
        assert drives[1].wait_feedback(1.0).state is State402.OPERATION_ENABLED  # the other axis is untouched
    finally:
        _close(network, drives)
