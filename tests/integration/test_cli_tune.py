"""``foilc-hil tune`` through the CLI: JSON document, exit codes 0/2/3, one-line errors."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from foilc_hil.cli import main

REPO = Path(__file__).resolve().parents[2]


def _write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "tune.yaml"
    path.write_text(text, encoding="utf-8")
    return path


PAPER_PLANT = "plant: {a: -1.23, b: 1.68, c: 1}\n"
DELAYED_PLANT = "plant: {a: -1.23, b: 1.68, c: 1, delay: 0.01}\n"


@pytest.mark.slow
def test_json_success_with_cli_overrides(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    config = _write(tmp_path, DELAYED_PLANT)
    code = main(["tune", "--config", str(config), "--crossover", "70", "--phase-margin", "70", "--json"])
    out, err = capsys.readouterr()
    assert code == 0, err
    document = json.loads(out)
    assert {"K", "kp", "r", "crossover", "phase_margin_deg", "plant", "achieved"} <= set(document)
    assert set(document["plant"]) == {"num", "den", "delay"}
    assert set(document["achieved"]) == {"crossover", "phase_margin_deg"}
    assert document["crossover"] == 70.0 and document["phase_margin_deg"] == 70.0
    assert document["K"] == 1.0 and document["kp"] > 0 and 0 < document["r"] < 2
    assert document["achieved"]["crossover"] == pytest.approx(70.0, rel=1e-4)
    assert document["achieved"]["phase_margin_deg"] == pytest.approx(70.0, abs=0.01)
    assert document["checks"]["python_control"]["agrees_with_sweep"] is True
    # the document is the spec evaluated independently: |L(j wc)| = 1 with the printed numbers
    num, den, delay = document["plant"]["num"], document["plant"]["den"], document["plant"]["delay"]
    s = 70j
    loop = (
        document["K"]
        * (1 + document["kp"] * s ** document["r"])
        * (num[0] / (den[0] * s + den[1]))
        * complex(math.cos(-delay * 70), math.sin(-delay * 70))
    )
    assert abs(loop) == pytest.approx(1.0, rel=1e-6)


@pytest.mark.slow
def test_flat_phase_flag_solves_k(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    config = _write(tmp_path, DELAYED_PLANT + "tuning: {crossover: 70, phase_margin_deg: 70}\n")
    assert main(["tune", "--config", str(config), "--flat-phase", "--json"]) == 0
    document = json.loads(capsys.readouterr().out)
    assert document["flat_phase"] is True
    assert document["K"] != 1.0
    assert document["checks"]["warnings"]  # this design does not roll off; the tuner says so


@pytest.mark.slow
def test_text_output_is_a_summary(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    config = _write(tmp_path, DELAYED_PLANT + "tuning: {crossover: 70, phase_margin_deg: 70}\n")
    assert main(["tune", "--config", str(config)]) == 0
    out = capsys.readouterr().out
    assert "kp =" in out and "phase margin deg" in out and "agrees" in out


def test_paper_literal_spec_exits_3_with_reason(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    config = _write(tmp_path, PAPER_PLANT + "tuning: {crossover: 70, phase_margin_deg: 70}\n")
    for extra in ([], ["--flat-phase"]):
        assert main(["tune", "--config", str(config), "--json", *extra]) == 3
        out, err = capsys.readouterr()
        assert json.loads(out)["error"]["exit_code"] == 3  # one JSON document even on failure
        assert len(err.strip().splitlines()) == 1
        assert err.startswith("foilc-hil tune: the plant's phase at wc=70 rad/s is -88.99 deg")
        assert "Traceback" not in err


@pytest.mark.parametrize(
    ("text", "args", "fragment"),
    [
        (PAPER_PLANT, [], "tuning.crossover: is required"),
        (PAPER_PLANT, ["--crossover", "70"], "tuning.phase_margin_deg: is required"),
        (PAPER_PLANT, ["--crossover", "-1", "--phase-margin", "40"], "tuning.crossover"),
        (PAPER_PLANT, ["--crossover", "10", "--phase-margin", "200"], "tuning.phase_margin_deg"),
        ("plant: {a: -1.23}\n", ["--crossover", "10", "--phase-margin", "40"], "plant"),
        ("plant: {a: -1.23, b: 1.68, c: 1, delay: -1}\n", [], "plant.delay"),
        ("tuning: [\n", [], "line"),
    ],
)
def test_bad_config_exits_2_one_line(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], text: str, args: list[str], fragment: str
) -> None:
    config = _write(tmp_path, text)
    assert main(["tune", "--config", str(config), "--json", *args]) == 2
    out, err = capsys.readouterr()
    error = json.loads(out)["error"]  # one JSON document even on failure, naming the same place
    assert error["exit_code"] == 2 and fragment in error["message"]
    assert len(err.strip().splitlines()) == 1
    assert fragment in err
    assert "Traceback" not in err


def test_missing_file_and_bad_option_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["tune", "--config", str(tmp_path / "nope.yaml")]) == 2
    assert "no such file" in capsys.readouterr().err
    assert main(["tune", "--config", str(tmp_path / "x.yaml"), "--crossover", "fast"]) == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1


def test_direct_pair_reports_achieved_margin(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    config = _write(tmp_path, DELAYED_PLANT + "tuning: {kp: 0.5, r: 0.6}\n")
    assert main(["tune", "--config", str(config), "--json"]) == 0
    document = json.loads(capsys.readouterr().out)
    assert document["mode"] == "direct"
    assert document["kp"] == 0.5 and document["r"] == 0.6
    assert document["achieved"]["crossover"] == document["crossover"] > 0
    assert document["checks"]["python_control"]["agrees_with_sweep"] is True


def test_shipped_feasible_example(capsys: pytest.CaptureFixture[str]) -> None:
    config = REPO / "configs" / "tune_feasible_example.yaml"
    assert main(["tune", "--config", str(config), "--json"]) == 0
    document = json.loads(capsys.readouterr().out)
    assert document["achieved"]["phase_margin_deg"] == pytest.approx(document["phase_margin_deg"], abs=0.01)
