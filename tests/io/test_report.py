"""report: plots, JSON and Markdown summaries from synthetic logs; truncated and bad logs."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from foilc_hil.cli import main
from foilc_hil.io.mcap_log import McapLogWriter

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"
N = 30
DESIGN = {"law": "foilc", "kp": 0.1, "r": 0.7, "gamma": 0.3, "certificates": {"spectral_radius": 0.61}}


def _write(path: Path, trials: int = 4, timing: bool = True, mimo: bool = False) -> list[float]:
    """A log whose trial k has error (0.5 ** k) * ones: SSE_k = N * 0.25 ** k. Returns the SSEs."""
    sses = []
    t = np.arange(N) * 0.01
    with McapLogWriter(path, config_yaml="trials: 4\n", design=DESIGN) as writer:
        cycle = 0
        for trial in range(1, trials + 1):
            e = 0.5**trial
            for i in range(N):
                reference = np.sin(t[i])
                if mimo:
                    writer.log_sample(
                        trial,
                        t[i],
                        [reference, -reference],
                        [reference - e, -reference - e],
                        [1.0, 2.0],
                        [e, e],
                        [e, e],
                        sample=i,
                    )
                else:
                    writer.log_sample(trial, t[i], reference, reference - e, 1.0 / trial, e, e, sample=i)
                if timing:
                    # lateness 0..99 us over the run (independent truth: percentiles of 0..99 are known)
                    writer.log_timing(cycle, trial, i, float(cycle % 100), 10000.0, 250.0, cycle % 100 == 99)
                    cycle += 1
            sse = N * e * e * (2 if mimo else 1)
            sses.append(sse)
            writer.log_trial({"trial": trial, "sse": sse, "rmse": e, "max_abs_error": e})
            writer.end_trial()
    return sses


@pytest.mark.slow
def test_report_writes_plots_and_summaries(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    log = tmp_path / "run.mcap"
    sses = _write(log, trials=4, timing=True)
    out = tmp_path / "report"
    assert main(["report", str(log), "--out", str(out), "--json"]) == 0
    document = json.loads(capsys.readouterr().out)
    assert document["plots"] == ["outputs.png", "control.png", "error.png", "sse.png", "timing.png"]
    for name in document["plots"]:
        assert (out / name).read_bytes()[:8] == PNG_MAGIC
    summary = json.loads((out / "summary.json").read_text())
    assert summary == {key: value for key, value in document.items() if key != "out"}
    assert [t["sse"] for t in summary["trials"]] == sses
    assert summary["completed_trials"] == 4 and summary["incomplete_trials"] == [] and not summary["truncated"]
    assert summary["design"]["certificates"] == {"spectral_radius": 0.61} and summary["design"]["kp"] == 0.1
    timing = summary["timing"]
    assert timing["cycles"] == 4 * N and timing["missed_deadlines"] == (4 * N) // 100
    values = np.array([c % 100 for c in range(4 * N)], dtype=float)
    # independent truth: order statistics by hand (linear interpolation between the two neighbours)
    ordered = np.sort(values)
    rank = 0.99 * (len(ordered) - 1)
    lo = int(np.floor(rank))
    expected_p99 = ordered[lo] + (rank - lo) * (ordered[lo + 1] - ordered[lo])
    assert timing["lateness_us"]["p99"] == pytest.approx(expected_p99)
    assert timing["lateness_us"]["max"] == 99.0
    markdown = (out / "summary.md").read_text()
    assert "| 4 |" in markdown and "spectral_radius" in markdown and "![sse](sse.png)" in markdown
    assert "Truncated" not in markdown


@pytest.mark.slow
def test_report_without_timing_and_with_vector_signals(tmp_path: Path) -> None:
    log = tmp_path / "mimo.mcap"
    _write(log, trials=2, timing=False, mimo=True)
    out = tmp_path / "r"
    assert main(["report", str(log), "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["timing"] is None and "timing.png" not in summary["plots"]
    assert (out / "outputs.png").read_bytes()[:8] == PNG_MAGIC


@pytest.mark.slow
def test_report_of_a_truncated_log_reports_what_it_has(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    log = tmp_path / "run.mcap"
    _write(log, trials=4)
    data = log.read_bytes()
    log.write_bytes(data[: int(len(data) * 0.6)])
    out = tmp_path / "r"
    assert main(["report", str(log), "--out", str(out), "--json"]) == 1  # partial: not the whole run
    captured = capsys.readouterr()
    document = json.loads(captured.out)
    assert document["truncated"] is True and document["damage"] and document["partial"] is True
    assert 1 <= document["completed_trials"] < 4
    assert len(captured.err.strip().splitlines()) == 1
    assert captured.err.startswith("foilc-hil report: partial: ") and "before its footer" in captured.err
    assert f"reported the {document['completed_trials']} trials read before it" in captured.err
    assert "Truncated log" in (out / "summary.md").read_text()
    assert (out / "sse.png").read_bytes()[:8] == PNG_MAGIC


def test_report_rejects_non_mcap_and_missing_logs(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(b"PK\x03\x04 zip, not mcap")
    assert main(["report", str(bad), "--out", str(tmp_path / "r")]) == 2
    err = capsys.readouterr().err
    assert "bad.mcap: not an MCAP file" in err and err.count("\n") == 1
    assert main(["report", str(tmp_path / "none.mcap"), "--out", str(tmp_path / "r")]) == 2
    assert "no such file" in capsys.readouterr().err


# --- labels, scales, notes, the comparison figure and the demo's verdict -----------------------------------------

CONFIG_RPM = (
    "drive: {mode: csv, velocity_unit: rpm}\nplant: {disturbance: {kind: step, amplitude: 1.0, start_trial: 3}}\n"
)


def _stepped_log(path: Path, law: str, trials: int = 4, *, rate: float = 0.5) -> None:
    """A log of a reference that steps to 400 at the first sample: sample 0's error is 400 in every trial (the
    unlearnable one), the rest decays as ``rate ** trial``; trial 1 runs u = 0 (error = reference)."""
    design = {**DESIGN, "law": law, "input_delay": 1}
    with McapLogWriter(path, config_yaml=CONFIG_RPM, design=design) as writer:
        for trial in range(1, trials + 1):
            errors = []
            for i in range(N):
                reference = 400.0
                error = reference if trial == 1 or i == 0 else 3.0 * rate**trial * (-1) ** i
                control = 0.0 if trial == 1 else 400.0 + (900.0 if i == 1 else 0.0)
                writer.log_sample(trial, (i + 1) * 0.01, reference, reference - error, control, error, error, sample=i)
                errors.append(error)
            e = np.array(errors)
            writer.log_trial({"trial": trial, "sse": float(e @ e), "rmse": float(np.sqrt(e @ e / N)),
                              "max_abs_error": float(np.abs(e).max()),
                              "rmse_learnable": float(np.sqrt(e[1:] @ e[1:] / (N - 1))),
                              "max_abs_error_learnable": float(np.abs(e[1:]).max())})
            writer.end_trial()


def test_labels_come_from_the_logged_design_and_config(tmp_path: Path) -> None:
    from foilc_hil.io.mcap_log import read_log
    from foilc_hil.logtools.report import log_context

    log = tmp_path / "f.mcap"
    _stepped_log(log, "foilc")
    context = log_context(read_log(log))
    assert (context.law, context.output_unit, context.input_unit) == ("FOILC", "rpm", "rpm")
    assert context.input_delay == 1 and context.disturbance_trial == 3


def test_neither_trial_1_nor_the_unlearnable_sample_sets_the_zoomed_scale() -> None:
    from foilc_hil.logtools.report import _zoomed_limits

    t = np.arange(5) * 0.1
    signals = {
        1: {"t": t, "error": np.full((5, 1), 400.0)},  # u = 0: the whole reference
        2: {"t": t, "error": np.array([[400.0], [2.0], [-1.0], [0.5], [0.0]])},
        3: {"t": t, "error": np.array([[400.0], [1.0], [-2.0], [0.25], [0.0]])},
    }
    signals_u = {trial: {"t": d["t"], "control": d["error"]} for trial, d in signals.items()}
    low, high = _zoomed_limits(signals_u, "control", 1) or (0.0, 0.0)
    assert -2.0 > low > -3.0 and 2.0 < high < 3.0  # the range of trials 2..3 after sample 0, plus 8 % padding


@pytest.mark.slow
def test_summary_has_learnable_metrics_certificate_tables_and_the_step_note(tmp_path: Path) -> None:
    log = tmp_path / "f.mcap"
    _stepped_log(log, "foilc")
    out = tmp_path / "r"
    assert main(["report", str(log), "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["trials"][1]["max_abs_error"] == 400.0
    assert summary["trials"][1]["max_abs_error_learnable"] == pytest.approx(3.0 * 0.25)
    assert len(summary["notes"]) == 2 and "starts with a step" in summary["notes"][0]
    assert "from 400 to 1300 rpm" in summary["notes"][1]  # the learned input's early swing, measured
    markdown = (out / "summary.md").read_text()
    assert "| certificate | value |" in markdown and "| spectral_radius | 0.61 |" in markdown
    assert "## Notes" in markdown and "learnable max abs error" in markdown


def test_no_step_note_when_the_reference_starts_where_the_axis_is(tmp_path: Path) -> None:
    from foilc_hil.io.mcap_log import read_log
    from foilc_hil.logtools.report import summarize

    log = tmp_path / "run.mcap"
    _write(log, trials=3, timing=False)  # sin reference from 0: the first error is like every other one
    assert summarize(read_log(log))["notes"] == []


@pytest.mark.slow
def test_the_comparison_figure_draws_both_laws(tmp_path: Path) -> None:
    from foilc_hil.logtools.report import write_comparison

    logs = {}
    for law, rate in (("foilc", 0.3), ("ioilc", 0.6)):
        logs[law] = tmp_path / f"{law}.mcap"
        _stepped_log(logs[law], law, rate=rate)
    path = write_comparison(logs, tmp_path / "comparison.png")
    assert path.read_bytes()[:8] == PNG_MAGIC


def test_the_demo_verdict_names_the_law_that_settles_first() -> None:
    from foilc_hil.commands.demo import converged_by, verdict

    def run(rmse: list[float]) -> dict[str, object]:
        return {"trials": [{"trial": k, "rmse_learnable": value} for k, value in enumerate(rmse, start=1)]}

    fast, slow = [100.0, 5.0, 4.8, 4.7, 9.0], [100.0, 30.0, 10.0, 4.9, 9.0]
    assert converged_by(run(fast)["trials"]) == 2  # type: ignore[arg-type]
    assert converged_by(run(slow)["trials"]) == 4  # type: ignore[arg-type]
    # still learning when the disturbance starts (trial 5): settled only when it reaches its level, trial 7
    assert converged_by(run([100.0, 80.0, 60.0, 40.0, 30.0, 10.0, 5.0])["trials"]) == 7  # type: ignore[arg-type]
    line = verdict({"foilc": run(fast), "ioilc": run(slow)})
    assert line.startswith("verdict: ") and "FOILC settles first" in line and "docs/paper-reproduction.md" in line
    together = verdict({"foilc": run([100.0, 6.0, 5.0]), "ioilc": run([100.0, 20.0, 5.0])})
    assert "FOILC learns more in its first learning trial" in together
    assert "both learn equally fast" in verdict({"foilc": run([100.0, 5.0]), "ioilc": run([100.0, 5.1])})


def test_trial_signals_are_the_logged_values_in_sample_order() -> None:
    from foilc_hil.logtools.report import trial_signals

    # scalars (one numpy conversion), vectors, ragged vectors padded with NaN, nulls as NaN, rows out of order
    rows = [
        {"trial": 2, "t": 0.2, "sample": 1, "reference": 1.5, "output": [1.0, 2.0], "control": [1.0], "error": None},
        {"trial": 2, "t": 0.1, "sample": 0, "reference": 0.5, "output": [3.0, None], "control": [2.0, 4.0],
         "error": 0.25},
        {"trial": 1, "t": 0.1, "sample": 0, "reference": 7.0, "output": [0.0, 0.0], "control": 9.0, "error": 1.0},
    ]
    signals = trial_signals(rows)
    assert list(signals) == [1, 2]
    nan = np.nan
    np.testing.assert_array_equal(signals[2]["t"], [0.1, 0.2])
    np.testing.assert_array_equal(signals[2]["reference"], [[0.5], [1.5]])
    np.testing.assert_array_equal(signals[2]["output"], [[3.0, nan], [1.0, 2.0]])
    np.testing.assert_array_equal(signals[2]["control"], [[2.0, 4.0], [1.0, nan]])
    np.testing.assert_array_equal(signals[2]["error"], [[0.25], [nan]])
    np.testing.assert_array_equal(signals[1]["control"], [[9.0]])


@pytest.mark.slow
def test_the_report_counts_the_frames_it_does_not_keep(tmp_path: Path) -> None:
    """``summary.json``'s frames by direction, from a read that only counts them, against a read that keeps every
    frame; a frame whose JSON is damaged stops the counting read where it stops the full one."""
    import can

    from foilc_hil.io.mcap_log import read_log
    from foilc_hil.io.schemas import TOPIC_CAN
    from foilc_hil.logtools.report import REPORT_TOPICS

    log = tmp_path / "frames.mcap"
    with McapLogWriter(log, config_yaml="trials: 1\n", design=DESIGN) as writer:
        for i in range(N):
            writer.log_frame(can.Message(arbitration_id=0x201, data=[i, 0]), "tx")
            for _ in range(1 + i % 3):  # 60 received against 30 sent
                writer.log_frame(can.Message(arbitration_id=0x181, data=[0, i]), "rx")
            writer.log_sample(1, i * 0.01, 1.0, 0.5, 0.0, 0.5, 0.5, sample=i)
        # documents another writer could have made (other key order, another direction): decoded, not matched
        writer._add(TOPIC_CAN, {"dir": "rx", "timestamp": 1.0, "id": 1, "extended": False, "dlc": 0, "data": ""}, 1)
        writer._add(TOPIC_CAN, {"timestamp": 1.0, "id": 1, "extended": False, "dlc": 0, "data": "", "dir": "sent"}, 2)
        writer.log_trial({"trial": 1, "sse": 1.0, "rmse": 1.0, "max_abs_error": 1.0})
        writer.end_trial()
    kept = read_log(log)
    counted = read_log(log, REPORT_TOPICS, count_frames=True)
    assert counted.frames == [] and len(counted.samples) == len(kept.samples) == N
    truth = {key: sum(f["dir"] == key for f in kept.frames) for key in ("tx", "rx", "sent")}
    assert truth == {"tx": N, "rx": 2 * N + 1, "sent": 1} == counted.frame_directions == kept.frame_directions
    out = tmp_path / "r"
    assert main(["report", str(log), "--out", str(out)]) == 0
    assert json.loads((out / "summary.json").read_text())["frames"] == truth
    # one frame's bytes damaged inside an uncompressed chunk: both reads stop at the same place, saying the same
    bad = tmp_path / "bad.mcap"
    with McapLogWriter(bad, config_yaml="trials: 1\n", design=DESIGN, compression="none") as writer:
        for i in range(N):
            writer.log_frame(can.Message(arbitration_id=0x181, data=[i]), "rx")
        writer.end_trial()
    data = bytearray(bad.read_bytes())
    where = data.index(b'"dir":"rx"', len(data) // 2)
    data[where:where + 1] = b"'"  # no longer JSON
    bad.write_bytes(bytes(data))
    full = read_log(bad)
    partial = read_log(bad, REPORT_TOPICS, count_frames=True)
    assert full.truncated and partial.truncated and partial.damage == full.damage
    assert partial.frame_directions == full.frame_directions
