"""``foilc-hil demo``: both laws run at once in worker processes, each with its log, report and the comparison;
the workers' progress reaches the parent's one view."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from foilc_hil.cli import main
from foilc_hil.io.mcap_log import read_log
from foilc_hil.progress import ProgressEvent, QueueProgress, RichRunsProgress

ROOT = Path(__file__).resolve().parents[2]


@pytest.mark.slow
def test_demo_runs_both_laws_and_writes_their_logs_reports_and_the_comparison(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    document = yaml.safe_load((ROOT / "configs" / "demo.yaml").read_text(encoding="utf-8"))
    # 1200 samples at 1 ms: the demo's axis and laws, shorter trials (below 2000 samples the designs certify by
    # dense SVDs, slower than the long trials' operator path)
    document["reference"]["time_scale"] = 0.2
    config = tmp_path / "demo.yaml"
    config.write_text(yaml.safe_dump(document), encoding="utf-8")
    out = tmp_path / "out"
    assert main(["demo", "--config", str(config), "--out", str(out), "--trials", "2", "--json"]) == 0
    summary = json.loads(capsys.readouterr().out)
    assert sorted(summary["laws"]) == ["foilc", "ioilc"] and summary["comparison"] == str(out / "comparison.png")
    assert (out / "comparison.png").stat().st_size > 0
    for law, run in summary["laws"].items():
        assert run["law"] == law and run["log"] == str(out / f"demo-{law}.mcap")
        logged = read_log(run["log"])
        assert [trial["trial"] for trial in logged.trials] == [1, 2]
        # the document's metrics are the log's: each law ran in its own process, on its own emulator
        assert [trial["sse"] for trial in run["trials"]] == [trial["sse"] for trial in logged.trials]
        assert (Path(run["report"]) / "sse.png").is_file()
        assert run["drive_stop"]["confirmed"] is True
    assert summary["laws"]["foilc"]["trials"][1]["sse"] != summary["laws"]["ioilc"]["trials"][1]["sse"]


class _ListQueue(list[tuple[str, ProgressEvent, tuple[object, ...]]]):
    def put(self, item: tuple[str, ProgressEvent, tuple[object, ...]]) -> None:
        self.append(item)


def test_a_workers_progress_reaches_the_parents_view(capsys: pytest.CaptureFixture[str]) -> None:
    events = _ListQueue()
    worker = QueueProgress(events, "IOILC")
    worker.begin_trial(3, 30, 6000)
    worker.advance(3000)
    worker.end_trial(3, 12.5, 0.25, 1.75)
    worker.note("settling")
    worker.close()
    assert [event for _, event, _ in events] == [ProgressEvent.BEGIN_TRIAL, ProgressEvent.ADVANCE,
                                                 ProgressEvent.END_TRIAL, ProgressEvent.NOTE]
    view = RichRunsProgress(["FOILC", "IOILC"], "demo")
    for item in events:
        view.handle(*item)
    view.close()
    shown = capsys.readouterr().err
    assert "IOILC: settling" in shown
    row = next(line for line in shown.splitlines() if "12.5" in line)
    assert "IOILC" in row and "0.25" in row and "1.75" in row
