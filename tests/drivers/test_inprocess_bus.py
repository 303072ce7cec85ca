"""The synchronous in-process transport (``drivers.inprocess``): delivery inside ``send``, order, no recursion,
senders in other threads, python-can's bus API (filters, ``recv``, periodic tasks) and the lockstep clock."""

from __future__ import annotations

import threading
import tomllib
import uuid
from collections.abc import Iterator
from pathlib import Path

import can
import canopen
import pytest

from drivers.bus import FrameTap, is_simulated_bus, open_bus
from drivers.config import BusConfig
from drivers.inprocess import (
    INTERFACE,
    WALL_CLOCK,
    InProcessBus,
    InProcessNotifier,
    LockstepClock,
    connect_network,
    subscribe_cyclic,
    timebase_of,
)

ROOT = Path(__file__).resolve().parents[2]


def frame(can_id: int, *data: int) -> can.Message:
    return can.Message(arbitration_id=can_id, data=bytes(data), is_extended_id=False)


class Recorder(can.Listener):
    """Records the frames it is given; optionally answers some of them on ``bus`` from inside the delivery."""

    def __init__(self, answer_on: can.BusABC | None = None, answers: dict[int, list[can.Message]] | None = None):
        self.frames: list[tuple[int, bytes]] = []
        self.threads: set[int] = set()
        self._bus = answer_on
        self._answers = answers or {}
        self.depth = 0
        self.max_depth = 0

    def on_message_received(self, msg: can.Message) -> None:
        self.depth += 1
        self.max_depth = max(self.max_depth, self.depth)
        self.frames.append((msg.arbitration_id, bytes(msg.data)))
        self.threads.add(threading.get_ident())
        if self._bus is not None:
            for answer in self._answers.get(msg.arbitration_id, []):
                self._bus.send(answer)
        self.depth -= 1


@pytest.fixture
def channel() -> Iterator[str]:
    yield f"test-inprocess-{uuid.uuid4().hex}"


def test_a_frame_is_delivered_before_send_returns_in_the_senders_thread(channel: str) -> None:
    with InProcessBus(channel) as master, InProcessBus(channel) as drive:
        seen = Recorder()
        notifier = InProcessNotifier(drive, [seen])
        try:
            master.send(frame(0x80))
            assert seen.frames == [(0x80, b"")]  # no waiting, no polling: it is there
            assert seen.threads == {threading.get_ident()}
            assert master.recv(0) is None  # the sender does not get its own frame back
        finally:
            notifier.stop()


def test_answers_sent_during_a_delivery_are_queued_in_order_not_recursive(channel: str) -> None:
    with InProcessBus(channel) as master, InProcessBus(channel) as drive:
        # the drive answers a SYNC with two TPDOs, and each TPDO makes the master's listener send an RPDO
        drive_side = Recorder(drive, {0x80: [frame(0x181, 1), frame(0x281, 2)]})
        master_side = Recorder(master, {0x181: [frame(0x201, 3)], 0x281: [frame(0x201, 4)]})
        notifiers = [InProcessNotifier(drive, [drive_side]), InProcessNotifier(master, [master_side])]
        try:
            master.send(frame(0x80))
            assert master_side.frames == [(0x181, b"\x01"), (0x281, b"\x02")]
            assert drive_side.frames == [(0x80, b""), (0x201, b"\x03"), (0x201, b"\x04")]
            assert drive_side.max_depth == 1 and master_side.max_depth == 1  # never re-entered
        finally:
            for notifier in notifiers:
                notifier.stop()


def test_a_sender_in_another_thread_pumps_its_own_frame(channel: str) -> None:
    with InProcessBus(channel) as master, InProcessBus(channel) as other, InProcessBus(channel) as drive:
        seen = Recorder()
        notifier = InProcessNotifier(drive, [seen])
        try:
            def send_many(bus: can.BusABC, can_id: int) -> None:
                for index in range(200):
                    bus.send(frame(can_id, index % 256))

            worker = threading.Thread(target=send_many, args=(other, 0x700))
            worker.start()
            send_many(master, 0x600)
            worker.join(timeout=30)
            assert not worker.is_alive()
            for can_id in (0x600, 0x700):  # nothing lost, each sender's frames in its order
                assert [data for cob, data in seen.frames if cob == can_id] == [bytes([i % 256]) for i in range(200)]
        finally:
            notifier.stop()


def test_recv_filters_and_receive_own_messages(channel: str) -> None:
    with InProcessBus(channel, receive_own_messages=True) as master, InProcessBus(channel) as reader:
        reader.set_filters([{"can_id": 0x181, "can_mask": 0x7FF}])
        master.send(frame(0x80))
        master.send(frame(0x181, 9))
        received = reader.recv(0)
        assert received is not None and received.arbitration_id == 0x181 and bytes(received.data) == b"\x09"
        assert received.is_rx and received.channel == channel and received.timestamp > 0
        assert reader.recv(0) is None  # the SYNC was filtered out by python-can's BusABC.recv
        assert master.recv(0) is not None  # its own SYNC, as asked


def test_receivers_get_a_copy_not_the_senders_message(channel: str) -> None:
    with InProcessBus(channel) as master, InProcessBus(channel) as reader:
        message = frame(0x201, 1, 2)
        master.send(message)
        message.data[0] = 0xFF  # the sender reuses its message
        received = reader.recv(0)
        assert received is not None and bytes(received.data) == b"\x01\x02"


def test_the_received_copy_sets_every_slot_of_a_message(channel: str) -> None:
    sent = can.Message(arbitration_id=0x1ABCDE, is_extended_id=True, data=b"\x01\x02", is_fd=True,
                       bitrate_switch=True, error_state_indicator=True, channel="sender")
    with InProcessBus(channel) as master, InProcessBus(channel) as reader:
        master.send(sent)
        received = reader.recv(0)
    assert received is not None
    stamped = {"timestamp", "channel", "is_rx"}  # the receiver's own: when, where, which way
    for name in set(can.Message.__slots__) - {"__weakref__"} - stamped:
        assert getattr(received, name) == getattr(sent, name), name  # an unset slot raises AttributeError here
    assert received.channel == channel and received.is_rx and received.timestamp > 0


def test_a_listener_error_is_kept_and_ends_notification_like_pythoncans_thread(channel: str) -> None:
    class Broken(can.Listener):
        def on_message_received(self, msg: can.Message) -> None:
            raise RuntimeError("listener bug")

    with InProcessBus(channel) as master, InProcessBus(channel) as drive:
        notifier = InProcessNotifier(drive, [Broken()])
        try:
            master.send(frame(0x80))  # the sender is not hurt
            assert isinstance(notifier.exception, RuntimeError)
            master.send(frame(0x81))
            later = drive.recv(0)  # after the error, frames wait in the bus's queue, as with a dead reader thread
            assert later is not None and later.arbitration_id == 0x81
        finally:
            notifier.stop()


def test_one_notifier_per_bus_and_only_for_inprocess_buses(channel: str) -> None:
    with InProcessBus(channel) as bus, can.Bus(interface="virtual", channel=channel) as virtual:
        notifier = InProcessNotifier(bus, [])
        try:
            with pytest.raises(ValueError, match="multiple active Notifier"):
                InProcessNotifier(bus, [])
        finally:
            notifier.stop()
        with pytest.raises(TypeError, match="in-process buses only"):
            InProcessNotifier(virtual, [])


def test_channels_must_agree_on_lockstep_and_close_with_their_last_end(channel: str) -> None:
    with InProcessBus(channel) as first:
        with pytest.raises(ValueError, match="is lockstep"):
            InProcessBus(channel, lockstep=False)
        second = InProcessBus(channel)
        assert second.clock is first.clock
        second.shutdown()
        with pytest.raises(can.CanOperationError):
            second.send(frame(0x80))
    with InProcessBus(channel, lockstep=False) as fresh:  # the lockstep channel is gone with its last end
        assert fresh.clock is None and timebase_of(fresh) is WALL_CLOCK


def test_open_bus_builds_it_and_it_counts_as_simulated(channel: str) -> None:
    assert is_simulated_bus(INTERFACE)
    with open_bus(BusConfig(interface=INTERFACE, channel=channel)) as bus:
        assert isinstance(bus, InProcessBus)
        assert timebase_of(bus) is bus.clock and timebase_of(bus).synchronous


def test_the_can_interface_entry_point_names_the_bus_class() -> None:
    project = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
    target = project["project"]["entry-points"]["can.interface"][INTERFACE]
    module, _, name = target.partition(":")
    assert __import__(module, fromlist=[name]).__dict__[name] is InProcessBus


def test_frame_tap_reports_the_cause_before_its_answers(channel: str) -> None:
    with InProcessBus(channel) as master, InProcessBus(channel) as drive:
        tap = FrameTap()
        order: list[tuple[int, str]] = []
        tap.add_listener(lambda msg, direction: order.append((msg.arbitration_id, direction)))
        tap.attach(master)
        notifiers = [InProcessNotifier(drive, [Recorder(drive, {0x80: [frame(0x181, 1)]})]),
                     InProcessNotifier(master, [tap])]
        try:
            master.send(frame(0x80))
            assert order == [(0x80, "tx"), (0x181, "rx")]
        finally:
            tap.detach()
            for notifier in notifiers:
                notifier.stop()


def test_connect_network_starts_no_thread_on_an_inprocess_bus(channel: str) -> None:
    before = set(threading.enumerate())
    with InProcessBus(channel) as bus, InProcessBus(channel) as other:
        network = canopen.Network(bus)
        connect_network(network)
        notifier = network.notifier
        assert isinstance(notifier, InProcessNotifier)
        try:
            assert [t.name for t in threading.enumerate() if t not in before] == []
            got: list[bytes] = []
            network.subscribe(0x181, lambda can_id, data, timestamp: got.append(bytes(data)))
            other.send(frame(0x181, 5))
            assert got == [b"\x05"]
        finally:
            notifier.stop()


# --- the lockstep clock and periodic tasks ------------------------------------------------------------------------


def test_clock_fires_timers_in_due_order_at_their_due_time() -> None:
    clock = LockstepClock()
    fired: list[tuple[str, float]] = []
    clock.every(0.3, lambda: fired.append(("slow", clock.now())))
    fast = clock.every(0.25, lambda: fired.append(("fast", clock.now())))
    clock.advance_to(0.65)
    assert fired == [("fast", pytest.approx(0.25)), ("slow", pytest.approx(0.3)), ("fast", pytest.approx(0.5)),
                     ("slow", pytest.approx(0.6))]
    assert clock.now() == pytest.approx(0.65)
    fast.cancel()
    clock.sleep(0.3)
    assert fired[-1] == ("slow", pytest.approx(0.9)) and len(fired) == 5
    clock.advance_to(0.1)  # time never goes back
    assert clock.now() == pytest.approx(0.95)


def test_wait_until_lets_simulated_time_pass_only_as_far_as_needed() -> None:
    clock = LockstepClock()
    beats: list[float] = []
    clock.every(0.1, lambda: beats.append(clock.now()))
    assert clock.wait_until(lambda: len(beats) >= 3, timeout=1.0)
    assert clock.now() == pytest.approx(0.3)
    assert not clock.wait_until(lambda: False, timeout=0.25)
    assert clock.now() == pytest.approx(0.55)


def test_periodic_tasks_are_timers_on_the_clock_not_threads(channel: str) -> None:
    before = set(threading.enumerate())
    with InProcessBus(channel) as producer, InProcessBus(channel) as consumer:
        clock = producer.clock
        assert clock is not None
        task = producer.send_periodic(frame(0x77F, 5), 0.1)
        assert [t.name for t in threading.enumerate() if t not in before] == []
        first = consumer.recv(0)
        assert first is not None and bytes(first.data) == b"\x05"  # python-can's semantics: the first one at once
        assert consumer.recv(0) is None
        clock.sleep(0.25)
        assert [bytes(m.data) for m in iter(lambda: consumer.recv(0), None)] == [b"\x05", b"\x05"]
        assert isinstance(task, can.ModifiableCyclicTaskABC)
        task.modify_data(frame(0x77F, 4))
        clock.sleep(0.1)
        latest = consumer.recv(0)
        assert latest is not None and bytes(latest.data) == b"\x04"
        task.stop()
        clock.sleep(1.0)
        assert consumer.recv(0) is None


def test_periodic_task_duration_bounds_it(channel: str) -> None:
    with InProcessBus(channel) as producer, InProcessBus(channel) as consumer:
        assert producer.clock is not None
        producer.send_periodic(frame(0x700, 1), 0.1, duration=0.25)
        producer.clock.sleep(1.0)
        assert len(list(iter(lambda: consumer.recv(0), None))) == 3  # at 0, 0.1 and 0.2 s


class _Subscriber:
    """A canopen subscriber callback that records what it was called with."""

    def __init__(self) -> None:
        self.calls: list[tuple[int, bytes]] = []

    def __call__(self, can_id: int, data: bytearray, timestamp: float) -> None:
        self.calls.append((can_id, bytes(data)))


def _feed(channel: str, routed: bool) -> tuple[_Subscriber, list[tuple[int, bytes, str]], list[int], canopen.Network]:
    """A canopen network on an in-process end, its PDO COB-ID subscribed with or without a direct route, fed the
    same frames; returns the subscriber, what the frame tap saw, what canopen's node scanner saw, the notifier."""
    sender = InProcessBus(channel)
    network = canopen.Network(InProcessBus(channel))
    tap = FrameTap()
    seen: list[tuple[int, bytes, str]] = []
    tap.add_listener(lambda msg, direction: seen.append((msg.arbitration_id, bytes(msg.data), direction)))
    network.listeners.insert(0, tap)  # type: ignore[arg-type]
    connect_network(network)
    subscriber = _Subscriber()
    if routed:
        subscribe_cyclic(network, 0x181, subscriber, observer=tap.on_message_received)
    else:
        network.subscribe(0x181, subscriber)
    for msg in (frame(0x181, 1, 2), frame(0x701, 5), frame(0x181, 3, 4),
                can.Message(arbitration_id=0x181, is_remote_frame=True, is_extended_id=False)):
        sender.send(msg)
    scanned = list(network.scanner.nodes)
    sender.shutdown()
    return subscriber, seen, scanned, network


def test_a_direct_route_delivers_what_canopens_notify_does(channel: str) -> None:
    generic, generic_seen, generic_scanned, generic_network = _feed(channel, routed=False)
    routed, routed_seen, _, network = _feed(f"{channel}-routed", routed=True)
    notifier, generic_notifier = network.notifier, generic_network.notifier
    assert isinstance(notifier, InProcessNotifier) and isinstance(generic_notifier, InProcessNotifier)
    assert 0x181 in notifier.routes and 0x181 not in generic_notifier.routes
    assert routed.calls == generic.calls == [(0x181, b"\x01\x02"), (0x181, b"\x03\x04")]  # the RTR is not data
    assert routed_seen == generic_seen  # the tap sees every frame, in order, the remote frame included
    assert len(routed_seen) == 4 and generic_scanned == [1]  # the heartbeat 0x701 still reaches the scanner
    for each in (notifier, generic_notifier):
        each.stop()
    for bus in (network.bus, generic_network.bus):
        assert bus is not None
        bus.shutdown()
    assert notifier.routes == {}  # routes live as long as their notifier


def test_a_route_error_is_kept_like_a_listener_error(channel: str) -> None:
    with InProcessBus(channel) as master, InProcessBus(channel) as drive:
        network = canopen.Network(drive)
        connect_network(network)

        def broken(can_id: int, data: bytearray, timestamp: float) -> None:
            raise RuntimeError("subscriber bug")

        subscribe_cyclic(network, 0x80, broken)
        master.send(frame(0x80))  # the sender is not hurt
        notifier = network.notifier
        assert notifier is not None and isinstance(notifier.exception, RuntimeError)
        notifier.stop()


def test_subscribe_cyclic_is_plain_subscribe_off_the_inprocess_transport() -> None:
    network = canopen.Network(can.Bus(interface="virtual", channel=f"test-route-{uuid.uuid4().hex}"))
    try:
        subscriber = _Subscriber()
        subscribe_cyclic(network, 0x181, subscriber)  # not listening, and not in-process: no route anywhere
        assert network.subscribers[0x181] == [subscriber]
    finally:
        assert network.bus is not None
        network.bus.shutdown()
