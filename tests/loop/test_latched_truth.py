"""The truth of each cycle in a realtime run with SYNC from a clock, in one process (python-can ``virtual``).

A realtime emulator and ``run_rig`` on one ``virtual`` channel, the bench's loop stalled for four periods
(``stall@2+10``) while its SYNC clock goes on: the stalled command and the ones the loop sends catching up miss their
SYNC. The log must say so (``/ilc/sample.latched``: the previous command, from the bus), ``replay --verify`` must
hold it against the logged frames bit for bit, and the law must have learned from it (a changed ``latched`` changes
the next trial's commands). The cross-process version, with an independent receiver process and SIGSTOP, is
``tests/crossprocess/test_latched_crossprocess.py``.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterator
from pathlib import Path

import pytest

from foilc_hil.io.mcap_log import LogContents, read_log
from foilc_hil.io.schemas import METADATA_PDO_MAPPING
from foilc_hil.logtools.replay import verify_log
from foilc_hil.loop.rig import RunReport
from tests.support.stalled_run import SCALE, STALLED, stalled_config, stalled_run

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def run(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[RunReport, Path]]:
    out = tmp_path_factory.mktemp("latched") / "run.mcap"
    yield stalled_run(stalled_config(), out), out


def _as_sent(value: float) -> float:
    return round(value * SCALE) / SCALE


def test_a_stalled_loop_misses_its_sync_and_the_log_says_what_the_drive_latched(
    run: tuple[RunReport, Path],
) -> None:
    report, out = run
    timing = report.outcome.timing
    assert timing is not None and timing.sync_clock == "thread" and timing.missed_deadlines >= 1
    (stall,) = [r for r in report.injected if str(r.injection.kind) == "stall"]
    assert stall.started_at_sync is not None and stall.frames == 1
    rows = [s for s in read_log(out).samples if s["trial"] == 2]
    assert all("latched" in row for row in rows)
    # the stalled command went out four periods late: the drive held the command before it at the next SYNC
    assert rows[STALLED]["latched"] == _as_sent(rows[STALLED - 1]["control"])
    assert rows[STALLED]["latched"] != _as_sent(rows[STALLED]["control"])
    # where the deadline was met, latched is the command as sent
    met = [row for row in rows if row["latched"] == _as_sent(row["control"])]
    assert len(met) >= len(rows) // 2


def test_replay_verify_holds_latched_against_the_wire_bit_for_bit(run: tuple[RunReport, Path]) -> None:
    _, out = run
    contents = read_log(out)
    result = verify_log(contents)
    assert result.verified, result.first_divergence
    assert result.trials_checked == 2 and result.samples_checked == 2 * 40


def _tampered(contents: LogContents, trial: int, sample: int, *, wire: bool) -> LogContents:
    """``latched`` of one row changed: by one ulp where the wire holds it, by one count of the drive's target where
    only the law can see it (one ulp of the feedforward may round away in the law's sum)."""
    samples = [dict(row) for row in contents.samples]
    for row in samples:
        if row["trial"] == trial and row["sample"] == sample:
            row["latched"] = math.nextafter(row["latched"], math.inf) if wire else row["latched"] + 1.0 / SCALE
    metadata = dict(contents.metadata)
    if not wire:
        metadata.pop(METADATA_PDO_MAPPING)  # no wire to check: only the law can see it
    return dataclasses.replace(contents, samples=samples, metadata=metadata)


def test_a_latched_value_that_is_not_the_wire_is_found(run: tuple[RunReport, Path]) -> None:
    _, out = run
    result = verify_log(_tampered(read_log(out), 2, STALLED, wire=True))
    assert not result.verified and result.first_divergence is not None
    assert (result.first_divergence.trial, result.first_divergence.sample) == (2, STALLED)
    assert "latched" in result.first_divergence.reason


def test_the_law_learned_from_latched(run: tuple[RunReport, Path]) -> None:
    """Trial 1's latched one count off, with no wire to hold it against: trial 2's recomputed command differs,
    because u_{k-1} is what the drive latched."""
    _, out = run
    result = verify_log(_tampered(read_log(out), 1, 20, wire=False))
    assert not result.verified and result.first_divergence is not None
    assert (result.first_divergence.trial, result.first_divergence.sample) == (2, 20)
    assert result.first_divergence.reason == "command differs"
