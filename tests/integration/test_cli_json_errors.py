"""``--json`` failures: exactly one JSON document on stdout for every exit path (1, 2, 3), with any partial result.

The mid-run failure with partial results (trials done, the stop, the log) is in
``tests/integration/test_bench_faults.py`` (``test_drive_fault_mid_trial``); exit 3 in
``tests/integration/test_cli_synthesize.py`` (``test_refused_filter_exits_3``).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest

from foilc_hil.cli import main

# the P-type gain is certified (rescaled) on the model; the plant's real input gain is ten times the model's
DIVERGING = """
plant: {a: -1.23, b: 1.68, c: 1.0, variation: {b: {kind: sine, amplitude: 15.0, frequency: 0.001, phase: 1.5707963}}}
reference: {profile: piecewise, segments: [{duration: 1.0, start: 1.0}]}
sample_time: 0.05
trials: 6
law: {kind: p-type, p_type_gain: 5.0}
"""


def _run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, dict[str, Any], str]:
    code = main(list(argv))
    captured = capsys.readouterr()
    lines = [line for line in captured.out.splitlines() if line.strip()]
    assert lines, f"nothing on stdout (stderr: {captured.err!r})"
    document = json.loads(captured.out)  # exactly one document: json.loads refuses trailing data
    return code, document, captured.err


@pytest.mark.parametrize(
    "argv",
    [
        ["run", "--json"],  # --out missing
        ["simulate", "--json", "--no-such-option"],
        ["commission", "--json", "teleport"],
    ],
)
def test_usage_errors_print_a_document(capsys: pytest.CaptureFixture[str], argv: list[str]) -> None:
    code, document, err = _run(capsys, *argv)
    assert code == 2
    assert document["error"]["exit_code"] == 2 and document["error"]["kind"] == "usage"
    assert err.count("\n") == 1 and "error" in err  # the one line naming the problem stays on stderr


def test_help_prints_no_error_document(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["run", "--help", "--json"]) == 0
    assert '"error"' not in capsys.readouterr().out


def test_a_config_error_names_the_key_in_the_document(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    config = tmp_path / "c.yaml"
    config.write_text(DIVERGING.replace("sample_time: 0.05", "sample_time: -1"), encoding="utf-8")
    code, document, _ = _run(capsys, "simulate", "--config", str(config), "--json")
    assert code == 2
    assert document["error"]["key"] == "sample_time" and document["error"]["source"] == str(config)
    assert document["error"]["kind"] == "usage"


def test_a_finished_but_failed_command_has_its_result_and_the_error(capsys: pytest.CaptureFixture[str],
                                                                     tmp_path: Path) -> None:
    config = tmp_path / "c.yaml"
    config.write_text(DIVERGING, encoding="utf-8")
    code, document, err = _run(capsys, "simulate", "--config", str(config), "--json")
    assert code == 1
    assert document["stopped"] and document["trials"]  # the partial result: the trials before the stop
    assert document["error"]["exit_code"] == 1 and document["error"]["kind"] == "runtime_failure"
    assert document["error"]["message"] in err
