"""``drivers.faults``: the injection spec and the fault-injecting bus, frame by frame.

The bus under test wraps :class:`PairBus`, a minimal in-memory ``can.BusABC`` written here (no python-can
interface behind it), to show that :class:`~drivers.faults.FaultyBus` needs nothing from the bus it wraps but
``send``, ``recv`` and ``shutdown``. Every expectation is derived from the injection (which SYNC, which frames), not
from a run of the bus.
"""

from __future__ import annotations

import collections
import random
import re
from collections.abc import Iterator
from typing import Any

import can
import numpy as np
import pytest

from drivers.cia301 import NMT_COB_ID, SYNC_COB_ID, FunctionCode, NmtCommand, cob_id
from drivers.faults import FaultyBus, Injection, InjectKind, Role, parse_injection, require_actions
from foilc_hil.errors import ConfigError, InputError

NODE = 1
RPDO1 = cob_id(FunctionCode.RPDO1, NODE)
TPDO1, TPDO2 = cob_id(FunctionCode.TPDO1, NODE), cob_id(FunctionCode.TPDO2, NODE)


class PairBus(can.BusABC):
    """One end of an in-memory link: what it sends lands in ``outbox``, what it receives comes from ``inbox``."""

    def __init__(self, inbox: collections.deque[can.Message], outbox: collections.deque[can.Message]) -> None:
        self.inbox, self.outbox = inbox, outbox
        self.channel_info = "pair"
        super().__init__(channel="pair")

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self.outbox.append(msg)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        return (self.inbox.popleft() if self.inbox else None), False


class Clock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def frame(can_id: int, data: bytes = b"\x01\x02\x03\x04") -> can.Message:
    return can.Message(arbitration_id=can_id, data=data, is_extended_id=False)


SYNC = frame(SYNC_COB_ID, b"")


@pytest.fixture
def link() -> Iterator[tuple[collections.deque[can.Message], collections.deque[can.Message], Any]]:
    """(to_bench, to_drive, make): ``make(*specs, role=..., **kwargs)`` wraps the bench's end in a FaultyBus."""
    to_bench: collections.deque[can.Message] = collections.deque()
    to_drive: collections.deque[can.Message] = collections.deque()
    made: list[FaultyBus] = []

    def make(*specs: str, role: Role = Role.MASTER, **kwargs: Any) -> FaultyBus:
        inbox, outbox = (to_bench, to_drive) if role is Role.MASTER else (to_drive, to_bench)
        bus = FaultyBus(PairBus(inbox, outbox), [parse_injection(s) for s in specs], node_id=NODE, role=role,
                        **kwargs)
        made.append(bus)
        return bus

    yield to_bench, to_drive, make
    for bus in made:
        bus.shutdown()


def received(bus: FaultyBus) -> list[can.Message]:
    out = []
    while (msg := bus.recv(0)) is not None:
        out.append(msg)
    return out


def ids(messages: Any) -> list[int]:
    return [m.arbitration_id for m in messages]


def test_a_window_starts_at_its_trial_and_cycle_and_lasts_count_syncs(link: Any) -> None:
    _, to_drive, make = link
    bus = make("drop-rpdo@2+1:count=2")
    bus.begin_trial(1)
    for _ in range(3):
        bus.send(SYNC)
        bus.send(frame(RPDO1))
    bus.begin_trial(2)
    for _ in range(4):  # cycles 0..3 of trial 2: the RPDOs of cycles 1 and 2 are lost
        bus.send(SYNC)
        bus.send(frame(RPDO1))
    assert ids(to_drive) == [SYNC_COB_ID, RPDO1] * 3 + [SYNC_COB_ID, RPDO1, SYNC_COB_ID, SYNC_COB_ID, SYNC_COB_ID,
                                                         RPDO1]
    (report,) = bus.reports()
    assert report.started_at_sync == 5 and report.frames == 2


def test_an_absolute_cycle_counts_syncs_from_the_first(link: Any) -> None:
    _, to_drive, make = link
    bus = make("drop-sync@c2")
    for _ in range(4):
        bus.send(SYNC)
    assert len(to_drive) == 3  # the third SYNC (cycle 2) was dropped


def test_a_seeded_rate_drops_the_frames_its_generator_draws(link: Any) -> None:
    to_bench, _, make = link
    bus = make("drop-tpdo@c0:rate=0.3,seed=7,count=0")
    rng = random.Random(7)
    expected = []
    for _ in range(50):
        bus.send(SYNC)
        to_bench.extend([frame(TPDO1), frame(TPDO2), frame(cob_id(FunctionCode.HEARTBEAT, NODE), b"\x05")])
        expected += [cob for cob in (TPDO1, TPDO2) if rng.random() >= 0.3]
        expected.append(cob_id(FunctionCode.HEARTBEAT, NODE))  # not a TPDO: never drawn, never dropped
    assert ids(received(bus)) == expected
    assert 0 < bus.reports()[0].frames < 100


def test_duplicate_and_wrong_dlc_hit_the_received_tpdos(link: Any) -> None:
    to_bench, _, make = link
    bus = make("duplicate@c0", "wrong-dlc@c1")
    bus.send(SYNC)
    to_bench.extend([frame(TPDO1), frame(RPDO1)])
    assert ids(received(bus)) == [TPDO1, TPDO1, RPDO1]
    bus.send(SYNC)
    to_bench.append(frame(TPDO1, b"\x01\x02\x03\x04"))
    (short,) = received(bus)
    assert bytes(short.data) == b"\x01\x02\x03" and short.dlc == 3


def test_reorder_sends_a_held_rpdo_behind_the_next_frame(link: Any) -> None:
    _, to_drive, make = link
    bus = make("reorder@c0:frames=rpdo")
    bus.send(SYNC)
    bus.send(frame(RPDO1))
    assert ids(to_drive) == [SYNC_COB_ID]
    bus.send(SYNC)  # the next frame out: the RPDO follows it, one cycle late
    assert ids(to_drive) == [SYNC_COB_ID, SYNC_COB_ID, RPDO1]


def test_delay_holds_a_frame_until_it_is_due(link: Any) -> None:
    to_bench, _, make = link
    clock = Clock()
    bus = make("delay@c0:delay=0.05", clock=clock)
    bus.send(SYNC)
    to_bench.append(frame(TPDO1))
    assert received(bus) == []
    clock.now += 0.049
    assert received(bus) == []
    clock.now += 0.002
    assert ids(received(bus)) == [TPDO1]


def test_silence_lets_nothing_through_either_way_and_ends(link: Any) -> None:
    to_bench, to_drive, make = link
    bus = make("silence@c0:count=2")
    sdo = frame(cob_id(FunctionCode.SDO_RX, NODE))
    for _ in range(2):
        bus.send(SYNC)
        bus.send(sdo)
        to_bench.append(frame(TPDO1))
        assert received(bus) == []
    assert list(to_drive) == []
    bus.send(SYNC)
    to_bench.append(frame(TPDO1))
    assert ids(to_drive) == [SYNC_COB_ID] and ids(received(bus)) == [TPDO1]


@pytest.mark.parametrize(("kind", "command"), [("nmt-stop", NmtCommand.STOP),
                                               ("nmt-pre-operational", NmtCommand.ENTER_PRE_OPERATIONAL)])
def test_a_third_partys_nmt_reaches_the_drive_from_either_side(link: Any, kind: str, command: NmtCommand) -> None:
    to_bench, to_drive, make = link
    master = make(f"{kind}@c1")
    master.send(SYNC)
    master.send(SYNC)
    assert ids(to_drive) == [SYNC_COB_ID, SYNC_COB_ID, NMT_COB_ID]  # out on the bus, after the SYNC it starts at
    assert list(to_drive[-1].data) == [int(command), NODE]
    drive = make(f"{kind}@c0", role=Role.DRIVE)  # the drive's own bus: it comes in
    to_drive.clear()
    to_drive.append(SYNC)
    got = received(drive)
    assert ids(got) == [SYNC_COB_ID, NMT_COB_ID] and list(got[1].data) == [int(command), NODE]
    assert list(to_bench) == []


def test_a_foreign_node_talks_to_the_bench_at_every_sync(link: Any) -> None:
    _, _, make = link
    bus = make("foreign-node@c0:node=5,count=2")
    foreign = [cob_id(FunctionCode.TPDO1, 5), cob_id(FunctionCode.HEARTBEAT, 5), cob_id(FunctionCode.EMCY, 5)]
    for _ in range(3):
        bus.send(SYNC)
    assert ids(received(bus)) == foreign * 2


def test_an_emulator_action_runs_once_at_its_sync_with_the_bus_free(link: Any) -> None:
    _, to_drive, make = link
    calls: list[tuple[int, bool]] = []
    holder: list[FaultyBus] = []

    def action(injection: Injection) -> None:
        lock = holder[0]._lock
        free = lock.acquire(blocking=False)  # an action may take the emulator's lock: never under the bus's
        if free:
            lock.release()
        calls.append((len(to_drive), free))

    bus = make("emulator-kill@c2", actions={InjectKind.EMULATOR_KILL: action})
    holder.append(bus)
    for _ in range(5):
        bus.send(SYNC)
    assert calls == [(2, True)]  # before the third SYNC went out


def test_emulator_kinds_need_their_action(link: Any) -> None:
    _, _, make = link
    with pytest.raises(InputError, match=re.escape("inject[0].kind: 'drift' acts on the embedded emulator")):
        make("drift@2")
    with pytest.raises(ConfigError, match="must differ"):
        make("foreign-node@2:node=1")
    require_actions([parse_injection("drift@2")], emulator=True)  # with an emulator: fine


def test_shutdown_sends_what_is_held_and_shuts_the_wrapped_bus(link: Any) -> None:
    _, to_drive, make = link
    bus = make("reorder@c0:frames=rpdo")
    bus.send(SYNC)
    bus.send(frame(RPDO1))
    inner = bus._inner
    bus.shutdown()
    assert ids(to_drive) == [SYNC_COB_ID, RPDO1] and inner._is_shutdown


@pytest.mark.parametrize(
    ("spec", "expected"),
    [
        ("drop-tpdo@2+10:count=3", (InjectKind.DROP_TPDO, 2, 10, 3)),
        ("silence@c500:count=0", (InjectKind.SILENCE, None, 500, 0)),
        ("emulator-kill@4", (InjectKind.EMULATOR_KILL, 4, 0, 1)),
    ],
)
def test_specs_parse(spec: str, expected: tuple[Any, ...]) -> None:
    injection = parse_injection(spec)
    assert (injection.kind, injection.trial, injection.cycle, injection.count) == expected


@pytest.mark.parametrize(
    ("spec", "named"),
    [("drop-tpdo", "KIND@WHEN"), ("drop-tpdo@x", "WHEN"), ("nothing@2", "kind"), ("drop-tpdo@2:rate=0", "rate"),
     ("drop-tpdo@2:count", "KEY=VALUE"), ("drop-sync@2:frames=rpdo", "frames"), ("delay@0", "trial")],
)
def test_bad_specs_name_the_problem(spec: str, named: str) -> None:
    with pytest.raises(ConfigError) as caught:
        parse_injection(spec)
    assert "--inject" in str(caught.value) and named in str(caught.value)


def test_drift_multiplies_the_plants_input() -> None:
    from plant_emulator.config import PlantConfig
    from plant_emulator.faults import InputGainDrift
    from plant_emulator.physics import build_plant

    config = PlantConfig(model="first_order", a=-1.23, b=1.68, c=1.0)
    drifted, reference = InputGainDrift(build_plant(config, seed=0), 3.0), build_plant(config, seed=0)
    drifted.reset(1)
    reference.reset(1)
    for u in (1.0, -2.0, 0.5):
        assert np.array_equal(drifted.step(np.array([u]), 0.01), reference.step(np.array([3.0 * u]), 0.01))
    assert drifted.time == reference.time


def test_plant_emulator_refuses_a_trial_in_its_inject(capsys: pytest.CaptureFixture[str]) -> None:
    from plant_emulator.cli import main

    code = main(["--bus", "virtual:nobody", "--inject", "emulator-kill@2+5"])
    lines = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(lines) == 1 and "has no trials" in lines[0] and "KIND@cCYCLE" in lines[0], lines
