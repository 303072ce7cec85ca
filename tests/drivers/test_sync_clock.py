"""SYNC from a clock (:mod:`drivers.sync_clock`, :meth:`drivers.network.DriveNetwork.start_clock`).

The producer thread's policy on a fake clock (deadlines, one late SYNC after a stall and no burst, its records);
then a master on python-can ``virtual`` against a realtime emulator in this process, whose commands are made late by
stalling the control thread: what the master says each SYNC latched is held against an independent bus object that
reconstructs it from the SYNC and RPDO frames it sees, in the order the bus delivered them.
"""

from __future__ import annotations

import contextlib
import itertools
import threading
import time
from collections.abc import Callable, Iterator

import can
import pytest

from drivers.bus import open_bus
from drivers.cia301 import SYNC_COB_ID
from drivers.cia402 import OperationMode
from drivers.cia402_master import Cia402Drive
from drivers.config import BusConfig, DriveConfig
from drivers.cyclic_rx import open_cyclic_receiver
from drivers.errors import DriveError, FeedbackTimeoutError
from drivers.network import DriveNetwork
from drivers.sync_clock import SyncProducer
from plant_emulator.config import PlantConfig
from plant_emulator.embedded import EmbeddedEmulator
from plant_emulator.settings import EmulatorConfig

PERIOD = 0.01
SCALE = 1000.0
NODE = 5
RPDO = 0x200 + NODE


class FakeClock:
    """A clock that moves by ``tick`` on every read and by the time slept; ``stall_at`` adds a stall to one sleep."""

    def __init__(self, tick: float = 1e-6) -> None:
        self.now = 100.0
        self.tick = tick
        self.sleeps = 0
        self.stalls: dict[int, float] = {}

    def __call__(self) -> float:
        self.now += self.tick
        return self.now

    def sleep(self, seconds: float) -> None:
        self.sleeps += 1
        self.now += seconds + self.stalls.get(self.sleeps, 0.0)


def _produce(clock: FakeClock, count: int, spin: float = 0.0002) -> tuple[SyncProducer, list[tuple[int, float]]]:
    """Run a producer on ``clock`` until it sent ``count`` SYNCs; the (number, time) of each send."""
    sent: list[tuple[int, float]] = []
    done = threading.Event()
    producer: SyncProducer

    def send(stamp: Callable[[int], None]) -> int:
        number = len(sent) + 1
        stamp(number)
        sent.append((number, clock.now))
        if number == count:
            producer._stopped.set()  # no further SYNC: the thread ends at its next look
            done.set()
        return number

    producer = SyncProducer(send, PERIOD, spin_margin=spin, clock=clock, sleep=clock.sleep)
    producer.start(t0=200.0)
    assert done.wait(10.0)
    producer.stop()
    return producer, sent


def test_the_producer_sends_on_its_deadlines_and_records_each_sync() -> None:
    clock = FakeClock()
    producer, sent = _produce(clock, 6)
    assert [number for number, _ in sent] == [1, 2, 3, 4, 5, 6]
    for number, at in sent:
        due = 200.0 + (number - 1) * PERIOD
        assert due <= at < due + 1e-3  # never before its deadline; spun to it (each read moves 1 us)
        record = producer.record(number)
        assert record is not None and record.due == due and record.skipped == 0 and record.sent == pytest.approx(at)
        assert producer.next_due(number) == pytest.approx(due + PERIOD)
    assert producer.record(7) is None and producer.skipped == 0 and producer.error is None


def test_after_a_stall_one_late_sync_goes_out_and_the_passed_slots_are_skipped() -> None:
    clock = FakeClock()
    clock.stalls = {4: 3.4 * PERIOD}  # the 4th sleep (before SYNC 4) wakes 3.4 periods late
    producer, sent = _produce(clock, 7)
    times = [at for _, at in sent]
    # SYNC 4 goes out at once on waking, for the latest slot passed (slot 6: slots 3, 4, 5 skipped); SYNC 5 is on
    # the grid again, one period after that slot: no burst of catch-up SYNCs
    late = producer.record(4)
    assert late is not None and late.skipped == 3 and late.due == pytest.approx(200.0 + 6 * PERIOD)
    assert times[3] - times[2] == pytest.approx(4.4 * PERIOD, abs=1e-3)
    assert times[4] - late.due == pytest.approx(PERIOD, abs=1e-3)
    assert min(b - a for a, b in itertools.pairwise(times[3:])) > 0.5 * PERIOD
    assert producer.skipped == 3


@pytest.fixture
def emulator() -> Iterator[EmbeddedEmulator]:
    plant = PlantConfig(model="first_order", a=-1.23, b=1.68)
    with EmbeddedEmulator(plant, EmulatorConfig(timing="realtime"), node_id=(NODE,), sample_time=PERIOD,
                          velocity_scale=SCALE) as started:
        yield started


def _reconstruct(frames: list[tuple[int, bytes]]) -> list[int | None]:
    """What the drive latched at each SYNC the independent bus object saw: the last RPDO target before it."""
    latched: list[int | None] = []
    last: int | None = None
    for can_id, data in frames:
        if can_id == RPDO:
            last = int.from_bytes(data[2:6], "little", signed=True)  # controlword (16 bits), target velocity (32)
        elif can_id == SYNC_COB_ID:
            latched.append(last)
    return latched


@pytest.mark.slow
def test_what_the_master_says_each_sync_latched_is_what_the_bus_shows(emulator: EmbeddedEmulator) -> None:
    bus_cfg: BusConfig = emulator.bus_config
    witness = can.Bus(interface="virtual", channel=bus_cfg.channel)  # the independent observer
    network = DriveNetwork(open_bus(bus_cfg), open_cyclic_receiver(bus_cfg, 0.0))
    drive = Cia402Drive.on_network(network, DriveConfig(node_id=NODE, velocity_scale=SCALE), sample_time=PERIOD)
    frames: list[tuple[int, bytes]] = []
    said: list[tuple[int, int]] = []  # (SYNC number, the latched target the master says, raw)
    missed: list[tuple[int, bool]] = []  # (SYNC number of the command's cycle, the master's missed flag)
    try:
        drive.connect()
        drive.configure(OperationMode.CYCLIC_SYNC_VELOCITY)
        drive.enable()
        assert drive.start_clock(spin_margin=0.0005) == "thread"
        number = network.syncs_sent
        for k in range(30):
            seen = network.await_sync(number, 1.0)
            number = seen.number
            said.append((number, round(drive.latched * SCALE)))
            with contextlib.suppress(FeedbackTimeoutError):  # the next SYNC came first: the bench's to count
                drive.wait_feedback(1.0)
            if k in (8, 9, 20):
                time.sleep(5 * PERIOD)  # the control thread alone stalls: the clock goes on
            drive.set_target(float(k + 1))  # a distinct target per cycle, so the wire tells them apart
            missed.append((number, drive.rpdo_sync_count > number))
        drive.stop_clock()
        time.sleep(2 * PERIOD)
        while (msg := witness.recv(0.0)) is not None:
            frames.append((msg.arbitration_id, bytes(msg.data)))
    finally:
        drive.close()
        network.close()
        assert network.receiver is not None
        network.receiver.close()
        network.bus.shutdown()
        witness.shutdown()
    latched = _reconstruct(frames)
    # the witness saw every SYNC from the network's first on: its j-th (from 1) is the network's SYNC j
    on_wire = dict(enumerate(latched, start=1))
    assert said and all(on_wire[n] == value for n, value in said), (said, on_wire)
    # a command missed its deadline iff the SYNC after its own came before it on the bus
    wire_missed = {n: on_wire[n + 1] != (k + 1) * SCALE for k, (n, _) in enumerate(missed) if n + 1 in on_wire}
    assert len(wire_missed) >= len(missed) - 1
    assert all(wire_missed[n] == flag for n, flag in missed if n in wire_missed)
    assert sum(flag for _, flag in missed) >= 2  # the stalls did make commands late (never a timing figure)


def test_await_sync_without_a_clock_and_a_clock_without_a_receiver_are_refused(emulator: EmbeddedEmulator) -> None:
    network = DriveNetwork(open_bus(emulator.bus_config))
    try:
        with pytest.raises(DriveError, match="receiver"):
            network.start_clock(PERIOD, {})
        with pytest.raises(DriveError, match="not running"):
            network.await_sync(0, 0.01)
    finally:
        network.close()
        network.bus.shutdown()


def test_on_socketcan_the_kernels_broadcast_manager_sends_sync() -> None:
    """python-can's ``send_periodic`` on ``socketcan:vcan0`` (the kernel's BCM holds the period) and the SYNCs read
    back from the loop's own socket. Runs where a ``vcan0`` exists; this test machine's kernel has no SocketCAN (no
    AF_CAN), so here it is skipped with python-can's reason."""
    cfg = BusConfig(interface="socketcan", channel="vcan0")
    try:
        bus = open_bus(cfg)
    except DriveError as exc:
        pytest.skip(f"socketcan:vcan0 cannot be opened here: {str(exc).splitlines()[0]}")
    network = DriveNetwork(bus, open_cyclic_receiver(cfg, 0.0))
    try:
        clock = network.start_clock(PERIOD, {})
        assert clock.name == "bcm" and clock.record(1) is None
        seen = [network.await_sync(number, 1.0) for number in range(network.syncs_seen, network.syncs_seen + 5)]
        assert [s.number for s in seen] == list(range(seen[0].number, seen[0].number + 5))
        assert all(b.time > a.time for a, b in itertools.pairwise(seen))  # each from its own echo's timestamp
        network.stop_clock()
        assert network.clock is None
    finally:
        network.close()
        assert network.receiver is not None
        network.receiver.close()
        bus.shutdown()
