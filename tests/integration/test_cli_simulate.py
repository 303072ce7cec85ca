"""``foilc-hil simulate``: JSON shape and exit codes, through the real CLI entry point."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from foilc_hil.cli import main

CONFIG = """
plant: {a: -1.23, b: 1.68, c: 1.0}
reference:
  profile: piecewise
  segments: [{duration: 1.0, start: 1.0}]
sample_time: 0.05
trials: 3
law: {kind: p-type, p_type_gain: 0.5}
"""


def _write(tmp_path: Path, text: str = CONFIG) -> Path:
    path = tmp_path / "c.yaml"
    path.write_text(text, encoding="utf-8")
    return path


def test_json_document(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["simulate", "--config", str(_write(tmp_path)), "--trials", "4", "--json"])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    document = json.loads(captured.out)
    assert document["law"] == "p-type"
    assert [t["trial"] for t in document["trials"]] == [1, 2, 3, 4]
    for trial in document["trials"]:
        assert set(trial) == {
            "trial", "sse", "rmse", "max_abs_error", "rmse_learnable", "max_abs_error_learnable", "noise_floor"
        }
    assert document["trials"][0]["noise_floor"] is None  # nothing to compare trial 1 with
    assert all(trial["noise_floor"] > 0 for trial in document["trials"][1:])  # the law still moves the error
    # the reference is 1 on every sample and trial 1 runs u = 0 from rest: e = 1 everywhere
    assert document["trials"][0]["sse"] == pytest.approx(20.0)
    assert document["trials"][-1]["sse"] < document["trials"][0]["sse"]


def test_law_option_and_text_output(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["simulate", "--config", str(_write(tmp_path)), "--law", "p-type", "--trials", "2"])
    out = capsys.readouterr().out
    assert code == 0
    assert out.startswith("p-type: 2 trial(s)")


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--config", "/nonexistent/c.yaml"], "no such file"),
        (["--law", "pid"], "invalid choice"),
        (["--trials", "0"], "trials"),
    ],
)
def test_usage_errors_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str], args: list[str], message: str) -> None:
    base = ["simulate", "--config", str(_write(tmp_path))]
    code = main([*base, *args, "--json"])
    err = capsys.readouterr().err
    assert code == 2
    assert message in err
    assert "Traceback" not in err and err.count("\n") == 1


def test_bad_sample_time_names_the_key(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = _write(tmp_path, CONFIG.replace("sample_time: 0.05", "sample_time: 0.3"))
    code = main(["simulate", "--config", str(path), "--json"])
    assert code == 2
    assert "sample_time" in capsys.readouterr().err


def test_divergence_exits_1_with_document(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # the gain is certified (rescaled) on the model; the plant's real input gain is ten times the model's
    mismodelled = "plant: {a: -1.23, b: 1.68, c: 1.0, variation: {b: {kind: sine, amplitude: 15.0, frequency: 0.001, " \
        "phase: 1.5707963}}}"
    path = _write(tmp_path, CONFIG.replace("p_type_gain: 0.5", "p_type_gain: 500.0").replace(
        "plant: {a: -1.23, b: 1.68, c: 1.0}", mismodelled))
    code = main(["simulate", "--config", str(path), "--trials", "20", "--json"])
    captured = capsys.readouterr()
    assert code == 1
    document = json.loads(captured.out)
    assert "diverged" in document["stopped"]
    assert 1 <= len(document["trials"]) < 20
    assert "diverged" in captured.err


def test_foilc_runs_through_tuning_free_synthesis(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    text = CONFIG.replace("law: {kind: p-type, p_type_gain: 0.5}", "tuning: {kp: 0.2, r: 0.5}")
    code = main(["simulate", "--config", str(_write(tmp_path, text)), "--trials", "3", "--json"])
    captured = capsys.readouterr()
    assert code == 0, captured.err
    document = json.loads(captured.out)
    assert document["law"] == "foilc"
    assert document["design"]["kp"] == 0.2 and document["design"]["r"] == 0.5
    assert "spectral_radius" in document["certificates"]
    sse = [t["sse"] for t in document["trials"]]
    assert sse[0] == pytest.approx(20.0)  # trial 1 measures the plant under u = 0
    assert sse[2] < sse[0]
