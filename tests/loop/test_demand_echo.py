"""The drive's demand echo in a realtime run with SYNC from a clock, in one process (python-can ``virtual``), issue 28.

The set-up of ``test_latched_truth.py`` with ``drive.demand_echo: true``: the loop stalls for four periods
(``stall@2+10``) while its SYNC clock goes on, so some commands miss their SYNC and ``latched`` is not ``control``
there. The drive's echo (0x606B in TPDO3) says what it latched, and it must agree with the bench's ``latched`` on
every sample (``demand_mismatches`` 0), which ``replay --verify`` recounts from ``/can``. An emulator made to echo the
previous command is caught (mismatches counted, and the wire agrees), and a log whose count was changed fails
``replay --verify``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from pathlib import Path

import pytest

from drivers.cia402 import Obj
from foilc_hil.io.mcap_log import LogContents, read_log
from foilc_hil.logtools.replay import verify_log
from foilc_hil.loop.rig import RunReport
from plant_emulator.motion import AxisPhysics
from tests.support.stalled_run import SCALE, stalled_config, stalled_run

pytestmark = pytest.mark.slow


def _run(out: Path) -> RunReport:
    return stalled_run(stalled_config(**{"drive.demand_echo": True}), out)


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[RunReport, Path]]:
    out = tmp_path_factory.mktemp("echo") / "run.mcap"
    yield _run(out), out


@pytest.fixture(scope="module")
def wrong_echo(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[RunReport, Path]]:
    """A drive that echoes the command it latched at the SYNC before (a stale demand register)."""
    publish = AxisPhysics.publish_demand
    previous: dict[int, int] = {}

    def stale(self: AxisPhysics) -> None:
        latched = int(self.node.read(Obj.TARGET_VELOCITY))
        publish(self)
        self.node.produce(Obj.VELOCITY_DEMAND_VALUE, previous.get(id(self), 0))
        previous[id(self)] = latched

    out = tmp_path_factory.mktemp("echo-wrong") / "run.mcap"
    with pytest.MonkeyPatch.context() as patch:
        patch.setattr(AxisPhysics, "publish_demand", stale)
        report = _run(out)
    yield report, out


def _as_sent(value: float) -> float:
    return round(value * SCALE) / SCALE


def test_the_echo_agrees_with_latched_although_commands_were_missed(run: tuple[RunReport, Path]) -> None:
    report, out = run
    contents = read_log(out)
    rows = [s for s in contents.samples if s["trial"] == 2]
    missed = [row for row in rows if row["latched"] != _as_sent(row["control"])]
    assert missed, "the stall made no command miss its SYNC: the test shows nothing"
    mapping = contents.metadata["foilc_hil.pdo_mapping"]
    assert str(int(Obj.VELOCITY_DEMAND_VALUE)) in str(mapping)  # the echo is mapped (TPDO3) and on the wire
    assert [trial["demand_mismatches"] for trial in contents.trials] == [0, 0]
    assert report.outcome.demand_mismatches == 0
    assert report.to_json()["faults"]["demand_mismatches"] == 0


def test_replay_verify_recounts_the_echo_from_the_wire(run: tuple[RunReport, Path]) -> None:
    _, out = run
    result = verify_log(read_log(out))
    assert result.verified, result.first_divergence
    assert result.trials_checked == 2


def _with_count(contents: LogContents, trial: int, count: int) -> LogContents:
    trials = [dict(record) for record in contents.trials]
    for record in trials:
        if record["trial"] == trial:
            record["demand_mismatches"] = count
    return dataclasses.replace(contents, trials=trials)


def test_a_changed_count_fails_replay_verify(run: tuple[RunReport, Path]) -> None:
    _, out = run
    result = verify_log(_with_count(read_log(out), 2, 1))
    assert not result.verified and result.first_divergence is not None
    assert result.first_divergence.trial == 2
    assert "demand_mismatches" in result.first_divergence.reason


def test_a_wrong_echo_is_counted_and_the_wire_agrees(wrong_echo: tuple[RunReport, Path]) -> None:
    report, out = wrong_echo
    contents = read_log(out)
    counts = [trial["demand_mismatches"] for trial in contents.trials]
    # trial 1 of a P-type law commands its zero feedforward throughout (the previous command is the same); trial 2's
    # commands change from sample to sample
    assert counts[1] > 0, counts
    assert report.outcome.demand_mismatches == sum(counts)
    result = verify_log(contents)  # the count is what the wire shows: the log is true to a faulty drive
    assert result.verified, result.first_divergence
    assert not verify_log(_with_count(contents, 2, 0)).verified
