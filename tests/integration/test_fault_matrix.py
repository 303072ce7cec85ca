"""The fault matrix: every injectable fault against ``foilc-hil run``, one table, and the same table in the docs.

Each row of :data:`MATRIX` runs the CLI in this process (``foilc_hil.cli.main``) on the embedded emulator with
``--inject`` (trial 2 is hit; trial 1 runs clean), and checks:

- the documented outcome: the run rides the fault out (exit 0) with the expected counts in ``run --json`` and in
  the log's ``/ilc/trial``, or exits 1 with one line naming the fault and one JSON error document;
- the drive afterwards, read twice: the run's ``drive_stop`` (in the JSON document or the error document) and the
  emulated drive's own state, read from the emulator object after the run;
- the log: it opens in the standard ``mcap`` reader and every completed trial has its ``/ilc/trial`` record and
  all its ``/ilc/sample`` rows.

The expected counts come from the injection itself (one TPDO set dropped is one lost feedback; a seeded rate is
replayed here with the same generator), never from a run's output. Process faults (the emulator's process killed
or stopped, a third party's NMT over a real bus) run across processes in
``tests/crossprocess/test_fault_matrix_xproc.py``.

``docs/reliability.md`` holds the table :func:`markdown_table` makes from both matrices, between the markers
:data:`BEGIN` and :data:`END`; :func:`test_the_docs_hold_the_matrix` fails when they differ
(``python -m tests.integration.test_fault_matrix`` rewrites the doc's table).
"""

from __future__ import annotations

import enum
import json
import random
import sys
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import pytest
import yaml

from drivers.cia402 import State402
from drivers.drive import DISABLED_STATES
from drivers.faults import Injection, InjectKind, parse_injection
from foilc_hil.cli import main
from tests.support.bench import read_log, read_mcap

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[2]
DOC = ROOT / "docs" / "reliability.md"
BEGIN = "<!-- fault-matrix: generated from tests/integration/test_fault_matrix.py; do not edit by hand -->"
END = "<!-- fault-matrix: end -->"
NODE = 1
SAMPLES = 60  # 0.3 s trials at 5 ms
TRIALS = 2
#: the matrix's bench policy: one lost feedback tolerated, two in a row abort (each wait 4 x 0.1 s in lockstep)
LOST_FEEDBACK_TOLERATED = 1
STOPPED_STATES = DISABLED_STATES | {State402.QUICK_STOP_ACTIVE}


class Outcome(enum.StrEnum):
    RIDES_OUT = "rides it out"
    ABORTS = "exit 1"


class Stop(enum.StrEnum):
    CONFIRMED = "confirmed"
    NOT_CONFIRMED = "not confirmed"


@dataclass(frozen=True)
class Row:
    """One fault: what is injected, what must happen, and the words the docs' table uses for it."""

    fault: str  # the docs' words
    inject: str  # the --inject spec
    outcome: Outcome
    names: str = ""  # exit 1: text the one error line must contain (it names the fault)
    lost: int = 0  # rides out: lost feedbacks counted in trial 2 (from the injection)
    bad: int = 0  # rides out: bad frames counted in trial 2
    stop: Stop = Stop.CONFIRMED
    after: str = "disabled, read back"  # the docs' words for the drive afterwards
    policy: dict[str, Any] = field(default_factory=dict)  # bench.faults overrides for this row
    drive: dict[str, Any] = field(default_factory=dict)  # drive overrides for this row
    trials: int = TRIALS
    completed: int | None = 1  # exit 1: trials completed before the fault (None: at least 1, set by wall time)
    where: str = "in-process, embedded emulator"

    @property
    def how(self) -> str:
        return f"`--inject {self.inject}`"

    @property
    def kind(self) -> InjectKind:
        return parse_injection(self.inject).kind

    def outcome_text(self) -> str:
        if self.outcome is Outcome.RIDES_OUT:
            counts = f"lost_feedback {self.lost}, bad_frames {self.bad} in trial 2"
            return f"exit 0, counted ({counts})" if self.lost or self.bad else f"exit 0, nothing counted ({counts})"
        return f"exit 1, one line naming it (`{self.names}`)"

    def kept_text(self) -> str:
        if self.outcome is Outcome.RIDES_OUT:
            return "every trial, with its counts in `/ilc/trial`"
        if self.completed is None:
            return "every trial before the fault was noticed intact; the one it hit not logged"
        return "trial 1 intact; trial 2 (hit) not logged"


def _rate_losses(seed: int, rate: float, cycles: int, frames_per_set: int = 2) -> int:
    """Lost feedbacks a seeded TPDO drop rate makes: the SYNCs where at least one TPDO of the set is drawn."""
    rng = random.Random(seed)
    return sum(any(rng.random() < rate for _ in range(frames_per_set)) for _ in range(cycles))


RATE_SEED, RATE, RATE_CYCLES = 11, 0.05, SAMPLES

#: the in-process rows (faults a bus or the embedded emulator can make)
MATRIX: tuple[Row, ...] = (
    Row("SYNC dropped (one)", "drop-sync@2+20", Outcome.RIDES_OUT, lost=1),
    Row("RPDO dropped (a burst of 3)", "drop-rpdo@2+20:count=3", Outcome.RIDES_OUT),
    Row("TPDO set dropped (one)", "drop-tpdo@2+20", Outcome.RIDES_OUT, lost=1),
    Row(f"TPDOs dropped at random (rate {RATE}, seeded, one trial)",
        f"drop-tpdo@2:rate={RATE},seed={RATE_SEED},count={RATE_CYCLES}",
        Outcome.RIDES_OUT, lost=_rate_losses(RATE_SEED, RATE, RATE_CYCLES)),
    Row("TPDO sets dropped, one more than tolerated", f"drop-tpdo@2+20:count={LOST_FEEDBACK_TOLERATED + 1}",
        Outcome.ABORTS, names="consecutive SYNCs without feedback"),
    Row("TPDOs delayed 20 ms (10 cycles)", "delay@2+20:delay=0.02,count=10", Outcome.RIDES_OUT),
    Row("TPDOs reordered (10 cycles)", "reorder@2+20:count=10", Outcome.RIDES_OUT),
    Row("RPDOs reordered behind the next SYNC (10 cycles)", "reorder@2+20:frames=rpdo,count=10",
        Outcome.RIDES_OUT),
    Row("TPDOs duplicated (10 cycles)", "duplicate@2+20:count=10", Outcome.RIDES_OUT),
    Row("SYNC duplicated (one)", "duplicate@2+20:frames=sync", Outcome.RIDES_OUT),
    Row("wrong DLC on one TPDO set, `bad_frame: count`", "wrong-dlc@2+20", Outcome.RIDES_OUT, lost=1, bad=2),
    Row("wrong DLC on one TPDO set, `bad_frame: abort`", "wrong-dlc@2+20", Outcome.ABORTS, names="DLC",
        policy={"bad_frame": "abort"}),
    Row("a foreign node's TPDO1, heartbeat and EMCY (10 cycles)", "foreign-node@2:node=5,count=10",
        Outcome.RIDES_OUT),
    Row("bus silence, one cycle", "silence@2+20", Outcome.RIDES_OUT, lost=1),
    # lockstep: the loop sends SYNC itself, so a stall of its thread delays the next SYNC and nothing is missed
    # (with SYNC from a clock the command misses its SYNC: tests/loop/test_latched_truth.py and the netns test)
    Row("the loop thread stalled 5 ms (one cycle)", "stall@2+20:duration=0.005", Outcome.RIDES_OUT),
    # the drive's heartbeat consumer (0.4 s here) must trip well within the run's stop attempts (about 2 s)
    Row("bus silence to the end", "silence@2+20:count=0", Outcome.ABORTS,
        names="consecutive SYNCs without feedback", stop=Stop.NOT_CONFIRMED, drive={"heartbeat_consumer_ms": 400},
        after="the run cannot read it (said so); the drive's own heartbeat consumer disables it"),
    Row("NMT stop from a third party", "nmt-stop@2+20", Outcome.ABORTS, names="left NMT OPERATIONAL"),
    Row("NMT pre-operational from a third party", "nmt-pre-operational@2+20", Outcome.ABORTS,
        names="left NMT OPERATIONAL"),
    Row("emulator killed (stops responding)", "emulator-kill@2+20", Outcome.ABORTS,
        names="consecutive SYNCs without feedback", stop=Stop.NOT_CONFIRMED,
        after="dead: cannot be read, and the run says so"),
    Row("EMCY over-current", "emcy-over-current@2+20", Outcome.ABORTS, names="EMCY 0x2310",
        after="FAULT, read back"),
    Row("EMCY over-speed", "emcy-over-speed@2+20", Outcome.ABORTS, names="EMCY 0x8400", after="FAULT, read back"),
    # a heartbeat is missed only by the wall clock (0.8 s here), and lockstep trials are fast: many trials, so the
    # run still goes on when the master notices
    Row("the drive's heartbeat stops", "heartbeat-stop@2+20", Outcome.ABORTS, names="heartbeat of node 1 lost",
        drive={"heartbeat_timeout_factor": 8.0}, trials=200, completed=None),
    Row("plant input gain x3 (beyond the design's uncertainty)", "drift@2:factor=3", Outcome.RIDES_OUT),
)


def bench_document(policy: dict[str, Any], drive: dict[str, Any] | None = None, trials: int = TRIALS
                   ) -> dict[str, Any]:
    """The matrix's config: the paper's first-order axis, two 60-sample trials at 5 ms, a tight lockstep policy."""
    return {
        "plant": {"model": "first_order", "a": -1.23, "b": 1.68, "c": 1.0},
        "reference": {
            "profile": "piecewise",
            "segments": [{"duration": 0.15, "start": 0.0, "end": 30.0}, {"duration": 0.15, "start": 30.0}],
        },
        "sample_time": 0.005,
        "trials": trials,
        "tuning": {"kp": 0.2, "r": 0.5},
        "drive": {
            "node_id": NODE,
            "mode": "csv",
            "velocity_scale": 1000.0,
            "velocity_limit": 500.0,
            # 3 s: a stalled test machine is not a lost heartbeat (at load 8-10 a row lost it after 1.67 s with
            # 1.5 s here, and the drive's consumer tripped alike), and a silent bus trips the feedback watchdog
            # (2 x 0.4 s) first; the heartbeat row sets its own
            "heartbeat_timeout_factor": 30.0,
            # the drive's watch on the master: 3 s outlasts such a stall; the dead-bus row, where the drive must
            # disable itself during the run's stop attempts (about 2 s), sets 0.4 s
            "heartbeat_consumer_ms": 3000,
            # the defaults for SDO (0.5 s) and the state transitions, bounded to 1 s: commissioning on a loaded
            # machine needs the time, and a dead drive's last stop step waits this long for a boot-up
            "state_timeout": 1.0,
            **(drive or {}),
        },
        "bench": {
            "settle_time": 0.02,
            "settle_tolerance": 0.05,
            "watchdog_cycles": 4,
            "faults": {"lost_feedback": LOST_FEEDBACK_TOLERATED, **policy},
        },
    }


@pytest.fixture(scope="module")
def one_design() -> Iterator[dict[tuple[str, int], Any]]:
    """Designs made once per (law, samples): every row has the same plant, so the design is not what is tested."""
    yield {}


@pytest.fixture
def emulators(monkeypatch: pytest.MonkeyPatch, one_design: dict[tuple[str, int], Any]) -> list[Any]:
    """Every embedded emulator a run creates (to read its drive's state afterwards); designs shared across rows."""
    from foilc_hil.design import pipeline
    from plant_emulator.embedded import EmbeddedEmulator

    created: list[Any] = []
    original = EmbeddedEmulator.from_config.__func__  # type: ignore[attr-defined]

    def recording(cls: type[EmbeddedEmulator], config: Any, **kwargs: Any) -> EmbeddedEmulator:
        emulator = original(cls, config, **kwargs)
        created.append(emulator)
        return emulator

    design = pipeline.build_design

    def shared_design(config: Any, law: str, n_samples: int, **kwargs: Any) -> Any:
        if (law, n_samples) not in one_design:
            one_design[(law, n_samples)] = design(config, law, n_samples, **kwargs)
        return one_design[(law, n_samples)]

    monkeypatch.setattr(EmbeddedEmulator, "from_config", classmethod(recording))
    # the pipeline's attribute, which the bench reads at each call: a name bound at another module's import (the
    # rig's, imported during the first row) would keep the shared design after this test (the next test's axes
    # all got the first axis's design)
    monkeypatch.setattr(pipeline, "build_design", shared_design)
    return created


def run_row(row: Row, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> tuple[int, dict[str, Any], list[str]]:
    config = tmp_path / "matrix.yaml"
    config.write_text(yaml.safe_dump(bench_document(row.policy, row.drive, row.trials)), encoding="utf-8")
    out = tmp_path / "run.mcap"
    code = main(["run", "--config", str(config), "--emulator", "embedded", "--inject", row.inject,
                 "--out", str(out), "--quiet", "--json"])
    captured = capsys.readouterr()
    return code, json.loads(captured.out), captured.err.strip().splitlines()


def check_log(path: Path, completed: int | None, most: int) -> list[dict[str, Any]]:
    """The log opens in the standard reader; ``completed`` trials (None: 1 to ``most``), each with its record and
    every sample row."""
    topics = read_log(path)
    trials = topics.get("/ilc/trial", [])
    count = len(trials) if completed is None and 1 <= len(trials) <= most else completed
    assert [t["trial"] for t in trials] == list(range(1, (count or 0) + 1))
    samples = topics.get("/ilc/sample", [])
    for record in trials:
        rows = sorted(s["sample"] for s in samples if s["trial"] == record["trial"])
        assert rows == list(range(SAMPLES)), f"trial {record['trial']} is not intact"
    return trials


@pytest.mark.parametrize("row", MATRIX, ids=[row.inject for row in MATRIX])
def test_fault_matrix_row(
    row: Row, tmp_path: Path, capsys: pytest.CaptureFixture[str], emulators: list[Any]
) -> None:
    code, document, err = run_row(row, tmp_path, capsys)
    (emulator,) = emulators
    drive_state = emulator.drive.state
    if row.outcome is Outcome.RIDES_OUT:
        assert code == 0, err
        stop = document["drive_stop"]
        assert document["faults"]["trials"] == [
            {"lost_feedback": 0, "bad_frames": 0}, {"lost_feedback": row.lost, "bad_frames": row.bad}
        ]
        (injected,) = document["faults"]["injected"]
        assert injected["kind"] == row.kind and injected["started_at_sync"] is not None and injected["frames"] > 0
        trials = check_log(tmp_path / "run.mcap", row.trials, row.trials)
        assert [(t["lost_feedback"], t["bad_frames"]) for t in trials] == [(0, 0), (row.lost, row.bad)]
        _, metadata = read_mcap(tmp_path / "run.mcap")  # what was injected is logged with the config
        logged = yaml.safe_load(metadata["foilc_hil.config"]["yaml"])["inject"]
        assert [Injection.model_validate(entry) for entry in logged] == [parse_injection(row.inject)]
    else:
        assert code == 1
        assert len(err) == 1 and err[0].startswith("foilc-hil run: ") and row.names in err[0], err
        stop = document["error"]["drive_stop"]
        assert row.names in document["error"]["message"]
        check_log(tmp_path / "run.mcap", row.completed, row.trials - 1)
    said = f"drive {NODE} confirmed disabled" if row.stop is Stop.CONFIRMED else f"drive {NODE} NOT confirmed"
    assert stop["confirmed"] is (row.stop is Stop.CONFIRMED)
    if row.outcome is Outcome.ABORTS:
        assert said in err[0], err[0]
    if row.stop is Stop.CONFIRMED:
        assert State402[stop["state"]] in DISABLED_STATES
        assert drive_state in DISABLED_STATES  # the emulator's own state agrees with what the run read back
    elif row.kind is InjectKind.EMULATOR_KILL:
        assert stop["state"] is None and not emulator.drive.node.alive  # dead: nothing to read, and said so
    else:
        assert stop["state"] is None
        assert drive_state in STOPPED_STATES  # the drive protected itself (its heartbeat consumer, 0x6007)


def test_an_unknown_kind_or_a_bad_option_is_exit_2_naming_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    config = tmp_path / "matrix.yaml"
    config.write_text(yaml.safe_dump(bench_document({})), encoding="utf-8")
    for spec, named in (("drop-everything@2", "kind"), ("drop-tpdo@2:rate=2", "rate"), ("drop-tpdo", "KIND@WHEN"),
                        ("drop-sync@2:frames=tpdo", "frames")):
        code = main(["run", "--config", str(config), "--inject", spec, "--out", str(tmp_path / "x.mcap"), "--json"])
        captured = capsys.readouterr()
        assert code == 2, spec
        lines = captured.err.strip().splitlines()
        assert len(lines) == 1 and "--inject" in lines[0] and named in lines[0], lines
        assert json.loads(captured.out)["error"]["exit_code"] == 2
    assert not (tmp_path / "x.mcap").exists()


def test_emulator_kinds_need_the_embedded_emulator(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    document = bench_document({})
    document["inject"] = [{"kind": "emulator-kill", "trial": 2}]
    config = tmp_path / "matrix.yaml"
    config.write_text(yaml.safe_dump(document), encoding="utf-8")
    code = main(["run", "--config", str(config), "--bus", "virtual:nobody-here", "--out", str(tmp_path / "x.mcap")])
    lines = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert len(lines) == 1 and "inject[0].kind" in lines[0] and "plant-emulator --inject" in lines[0], lines


def markdown_table(rows: tuple[Any, ...]) -> str:
    """The docs' table: fault x where x injection x outcome x drive afterwards x log kept."""
    lines = [
        "| fault | injected with | where tested | outcome | drive afterwards | log kept |",
        "|---|---|---|---|---|---|",
    ]
    for row in rows:
        lines.append(f"| {row.fault} | {row.how} | {row.where} | {row.outcome_text()} | {row.after} | "
                     f"{row.kept_text()} |")
    return "\n".join(lines)


def all_rows() -> tuple[Any, ...]:
    from tests.crossprocess.test_fault_matrix_xproc import XPROC_MATRIX
    from tests.support.fault_rows import TESTED_ELSEWHERE

    return (*MATRIX, *XPROC_MATRIX, *TESTED_ELSEWHERE)


def test_every_row_tested_elsewhere_names_a_test_that_exists() -> None:
    import ast

    from tests.support.fault_rows import TESTED_ELSEWHERE

    for row in TESTED_ELSEWHERE:
        file, function = row.test.split("::")
        tree = ast.parse((Path(__file__).resolve().parents[1] / file).read_text(encoding="utf-8"))
        names = {node.name for node in ast.walk(tree) if isinstance(node, ast.FunctionDef)}
        assert function in names, f"{row.fault}: {row.test} does not exist"


def doc_table(text: str) -> str:
    start, end = text.find(BEGIN), text.find(END)
    assert 0 <= start < end, f"{DOC.name} has no fault-matrix markers"
    return text[start + len(BEGIN):end].strip()


def test_the_docs_hold_the_matrix() -> None:
    assert doc_table(DOC.read_text(encoding="utf-8")) == markdown_table(all_rows()), (
        "docs/reliability.md's fault table differs from the matrix: run `python -m tests.integration.test_fault_matrix`"
    )


def test_every_kind_has_a_row() -> None:
    covered = {row.kind for row in all_rows() if getattr(row, "inject", "")}
    assert covered == set(InjectKind), f"kinds without a row: {sorted(set(InjectKind) - covered)}"


def _write_doc() -> None:
    text = DOC.read_text(encoding="utf-8")
    start, end = text.index(BEGIN) + len(BEGIN), text.index(END)
    DOC.write_text(text[:start] + "\n" + markdown_table(all_rows()) + "\n" + text[end:], encoding="utf-8")


if __name__ == "__main__":
    _write_doc()
    sys.exit(0)
