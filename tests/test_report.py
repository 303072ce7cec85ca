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


def test_report_without_timing_and_with_vector_signals(tmp_path: Path) -> None:
    log = tmp_path / "mimo.mcap"
    _write(log, trials=2, timing=False, mimo=True)
    out = tmp_path / "r"
    assert main(["report", str(log), "--out", str(out)]) == 0
    summary = json.loads((out / "summary.json").read_text())
    assert summary["timing"] is None and "timing.png" not in summary["plots"]
    assert (out / "outputs.png").read_bytes()[:8] == PNG_MAGIC


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
