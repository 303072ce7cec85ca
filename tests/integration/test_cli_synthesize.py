"""``foilc-hil synthesize``: JSON per the interface, exit codes 0 / 2 / 3."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import yaml

from foilc_hil.cli import main
from foilc_hil.design.record import Design

pytestmark = pytest.mark.filterwarnings("ignore:Solution may be inaccurate")

INTERFACE_KEYS = {
    "A", "B", "C", "G1", "H1", "G2", "H2", "P", "Qb", "Qt", "gamma", "tau", "theta", "kp", "r", "sample_time",
    "certificates",
}  # fmt: skip


def _config(tmp_path: Path, **sections: object) -> Path:
    document: dict[str, object] = {
        "plant": {"a": -1.23, "b": 1.68, "c": 1.0},
        "sample_time": 0.01,
        # A short trial keeps the lifted certificates quick: 1 s = 100 samples.
        "reference": {"profile": "piecewise", "segments": [{"duration": 1.0, "start": 1.0}]},
        "tuning": {"kp": 0.05, "r": 0.8},
    }
    document.update(sections)
    path = tmp_path / "config.yaml"
    path.write_text(yaml.safe_dump(document), encoding="utf-8")
    return path


def _run(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    code = main(list(argv))
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_json_document_has_the_interface_keys(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = _run(capsys, "synthesize", "--config", str(_config(tmp_path)), "--json", "--tau", "0.8")
    assert code == 0, err
    document = json.loads(out)
    assert set(document) >= INTERFACE_KEYS
    assert document["tau"] == 0.8 and document["theta"] == 0.868
    assert document["kp"] == 0.05 and document["r"] == 0.8
    assert np.array(document["P"]).shape == (1, 2)
    certificates = document["certificates"]
    assert certificates["spectral_radius"] < 1 and certificates["norm_2"] < 1
    assert certificates["n_samples"] == 100
    # The filter breaks the LMI gain at Ts = 0.01 (weight 1 + kp h^-r ~ 3): the default rescales it.
    assert certificates["designed"]["spectral_radius"] > 1
    assert 0 < document["gain_scale"] < 1
    design = Design.from_json(document)
    assert design.to_json() == document


def test_ioilc_uses_kp_zero_and_input_delay_augments(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = _config(tmp_path)
    code, out, err = _run(capsys, "synthesize", "--config", str(path), "--json", "--law", "ioilc", "--input-delay", "1")
    assert code == 0, err
    document = json.loads(out)
    assert document["kp"] == 0.0 and document["law"] == "ioilc"
    assert document["input_delay"] == 1
    assert np.array(document["A"]).shape == (2, 2)
    assert np.array(document["P"]).shape == (1, 3)
    assert document["C_measured"] == [[1.0, 0.0]]


def test_text_output(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = _run(capsys, "synthesize", "--config", str(_config(tmp_path)))
    assert code == 0
    assert "spectral radius" in out and "gamma" in out


def test_refused_filter_exits_3(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = _config(tmp_path, synthesis={"on_divergent_filter": "refuse"})
    code, out, err = _run(capsys, "synthesize", "--config", str(path), "--json")
    assert code == 3
    assert json.loads(out)["error"]["type"] == "ConvergenceCertificateError"
    assert json.loads(out)["error"]["kind"] == "infeasible"
    assert "not certified" in err and len(err.strip().splitlines()) == 1


def test_infeasible_lmi_exits_3(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # dB up to 3 B (B ~ 0.0167 at Ts = 0.01): the input gain can vanish or flip sign, nothing learns robustly.
    plant = {"a": -1.23, "b": 1.68, "c": 1.0, "uncertainty": {"G2": 0.05, "H2": 1.0}}
    code, _, err = _run(capsys, "synthesize", "--config", str(_config(tmp_path, plant=plant)), "--json")
    assert code == 3
    assert "LMI (31) infeasible" in err


@pytest.mark.parametrize(
    ("argv", "needle"),
    [
        (["--tau", "1.5"], "synthesis.tau"),
        (["--input-delay", "-1"], "--input-delay"),
    ],
)
def test_bad_input_exits_2(tmp_path: Path, capsys: pytest.CaptureFixture[str], argv: list[str], needle: str) -> None:
    code, _, err = _run(capsys, "synthesize", "--config", str(_config(tmp_path)), *argv)
    assert code == 2
    assert needle in err


def test_bad_uncertainty_names_the_key(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    plant = {"a": -1.23, "b": 1.68, "c": 1.0, "uncertainty": {"G1": 0.1}}
    code, _, err = _run(capsys, "synthesize", "--config", str(_config(tmp_path, plant=plant)))
    assert code == 2
    assert "plant.uncertainty.H1" in err


@pytest.mark.slow
def test_exact_tightens_the_certificate_of_a_q_filtered_law(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``--exact`` (``synthesis.exact_certificates``): the same map, a bound no looser than the fast one's, and the
    method says it is the structured exact test."""
    config = tmp_path / "q.yaml"
    config.write_text("plant: {model: first_order, a: -1.23, b: 1.68, c: 1.0}\nreference: {profile: eq49}\n"
                      "sample_time: 0.01\nlaw: {kind: p-type, q_filter: {cutoff: 40.0, order: 2}}\n", encoding="utf-8")

    def plants(*extra: str) -> list[dict[str, object]]:
        assert main(["synthesize", "--config", str(config), "--json", *extra]) == 0
        document = json.loads(capsys.readouterr().out)
        return list(document["design"]["certificates"]["plants"] if "design" in document
                    else document["certificates"]["plants"])

    fast, exact = plants(), plants("--exact")
    assert len(fast) == len(exact)
    for quick, tight in zip(fast, exact, strict=True):
        assert float(tight["norm_2"]) <= float(quick["norm_2"])  # type: ignore[arg-type]
        assert "structured exact" in str(tight["norm_2_method"])
        assert "structured exact" not in str(quick["norm_2_method"])
