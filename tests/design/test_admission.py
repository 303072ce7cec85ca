"""One rule for every law (``foilc_hil.design.admission``): a P-type, NOILC or gradient design whose certified 2-norm is
above one is rescaled or refused (exit 3, one line), never handed out as it is; the rescaled design is checked here
against dense maps built from the plant's numbers, and the law that runs applies the rescaled update."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from foilc_hil.cli import main
from foilc_hil.config import Config, load_config
from foilc_hil.design.admission import admit
from foilc_hil.design.certificate_record import CertificateAction
from foilc_hil.design.pipeline import build_design
from foilc_hil.errors import ConfigError, ConvergenceCertificateError
from foilc_hil.laws.learning import make_law
from tests.support.lifted_reference import config_plants

pytestmark = pytest.mark.slow

CONFIGS = Path(__file__).resolve().parents[2] / "configs"
#: paper_sim's plant on a 3 s trial (300 samples): long enough that its lifted laws feel the low frequencies.
LONG = {
    "reference.profile": "piecewise",
    "reference.segments": [{"duration": 2.0, "start": 1.0}, {"duration": 1.0, "start": 0.0}],
}
#: |dA| up to 0.009 on A = 0.988: a vertex's DC gain 2.3 times the model's, the other's 0.6 times. The lifted laws,
#: designed on the model, are not monotonic at that vertex (||T|| 1.3 to 2.3); a smaller step is.
WIDE = {"plant.uncertainty.G1": 0.009}
N = 301  # 300 learnable samples behind the CAN loop's delay
#: P-type's map is above one at any length with three times the DC-deadbeat gain: a 0.8 s trial is enough.
SHORT = {
    "reference.profile": "piecewise",
    "reference.segments": [{"duration": 0.5, "start": 1.0}, {"duration": 0.3, "start": 0.0}],
}
N_SHORT = 81


def _config(**overrides: Any) -> Config:
    return load_config(CONFIGS / "paper_sim.yaml", {**LONG, **WIDE, **overrides})


def _one_step(design: Any, config: Config, error: np.ndarray) -> np.ndarray:
    """``u_2 - u_1`` after a first trial with error ``error`` (zero input, zero output): the law's update."""
    law = make_law(design, config.law, N)
    law.begin_trial()
    for t in range(N):
        law.command(t, np.zeros(1))
    law.end_trial(error, np.zeros(N))
    law.begin_trial()
    return np.array([law.command(t, np.zeros(1))[0] for t in range(N)])


@pytest.mark.parametrize("law", ["noilc", "gradient"])
def test_a_lifted_law_not_certified_monotonic_is_rescaled(law: str) -> None:
    config = _config()
    design = build_design(config, law, N, input_delay=1)
    certificates = design.certificates
    assert certificates is not None
    assert certificates.action is CertificateAction.RESCALE and certificates.rescale_criterion == "monotonic"
    scale = certificates.gain_scale
    assert 0 < scale < 1 and design.gain_scale == scale
    assert certificates.designed.norm_2 > 1 and certificates.monotonic
    model, plants = config_plants(config, 1, N)
    G, d = plants[0], model.input_delay
    if law == "noilc":
        assert certificates.noilc is not None and certificates.noilc.scale == scale
        weights = certificates.noilc
        unscaled = np.linalg.solve(weights.q * G.T @ G + weights.r * np.eye(N - d), weights.q * G.T)
    else:
        assert certificates.gradient is not None
        assert certificates.gradient.step_relative == pytest.approx(scale, rel=1e-12)
        unscaled = G.T / np.linalg.svd(G, compute_uv=False)[0] ** 2
        assert certificates.gradient.beta == pytest.approx(scale / np.linalg.norm(G, 2) ** 2, rel=1e-9)
    # the truth, dense: the unscaled law is not monotonic at some plant, the scaled one is at all (certificate above)
    before = [np.linalg.norm(np.eye(N - d) - G_v @ unscaled, 2) for G_v in plants]
    after = [np.linalg.norm(np.eye(N - d) - scale * G_v @ unscaled, 2) for G_v in plants]
    assert max(before) > 1
    assert max(after) < 1 and max(after) <= certificates.norm_2 * (1 + 1e-9)
    # ... and the law that runs applies the scaled update
    error = np.linspace(1.0, -0.5, N)
    np.testing.assert_allclose(_one_step(design, config, error)[: N - d], scale * unscaled @ error[d:], rtol=1e-9,
                               atol=1e-12 * float(np.max(np.abs(unscaled @ error[d:]))))


@pytest.mark.parametrize("law", ["noilc", "gradient", "p-type"])
def test_refuse_exits_3_with_one_line_naming_the_bound(law: str, tmp_path: Path,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    document = yaml.safe_load((CONFIGS / "paper_sim.yaml").read_text(encoding="utf-8"))
    segments = (SHORT if law == "p-type" else LONG)["reference.segments"]
    document["reference"] = {"profile": "piecewise", "segments": segments}
    document["plant"]["uncertainty"]["G1"] = 0.009
    document["synthesis"]["on_divergent_filter"] = "refuse"
    document["law"] = {"kind": law, "p_type_gain": 2.2}  # P-type: three times the DC-deadbeat gain
    path = tmp_path / "refuse.yaml"
    path.write_text(yaml.safe_dump(document), encoding="utf-8")
    code = main(["synthesize", "--config", str(path), "--json"])
    captured = capsys.readouterr()
    assert code == 3
    assert json.loads(captured.out)["error"]["type"] == "ConvergenceCertificateError"
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and "not certified to converge monotonically" in lines[0]
    assert f"{law}: worst-case induced 2-norm" in lines[0] and "on_divergent_filter=refuse" in lines[0]


@pytest.mark.parametrize("law", ["noilc", "gradient", "p-type"])
def test_no_scale_fixes_an_input_gain_that_flips_sign(law: str) -> None:
    """``|dB|`` up to 1.2 B: at a vertex the input gain has the other sign, and no step of any size learns there."""
    config = _config(**{"plant.uncertainty.G2": 0.02, **(SHORT if law == "p-type" else {})})
    with pytest.raises(ConvergenceCertificateError, match="no scale of the learning gain"):
        build_design(config, law, N_SHORT if law == "p-type" else N, input_delay=1)


def test_a_p_type_gain_above_the_monotonic_range_is_rescaled() -> None:
    """``law.p_type_gain: 2.2`` (three times DC-deadbeat) on the nominal uncertainty: rescaled, and the scaled gain
    is what the design records and certifies; the dense maps agree."""
    config = load_config(CONFIGS / "paper_sim.yaml", {**SHORT, "law.p_type_gain": 2.2})
    design = build_design(config, "p-type", N_SHORT, input_delay=1)
    certificates = design.certificates
    assert certificates is not None and certificates.p_type is not None
    assert certificates.action is CertificateAction.RESCALE and certificates.monotonic
    gamma = float(design.p2[0, 0])
    assert gamma == pytest.approx(2.2 * certificates.gain_scale, rel=1e-12)
    assert float(certificates.p_type.gain[0, 0]) == gamma
    _, plants = config_plants(config, 1, N_SHORT)
    size = plants[0].shape[0]
    assert max(np.linalg.norm(np.eye(size) - 2.2 * G_v, 2) for G_v in plants) > 1
    after = max(np.linalg.norm(np.eye(size) - gamma * G_v, 2) for G_v in plants)
    assert after < 1 and after <= certificates.norm_2 * (1 + 1e-9)


def test_asymptotic_only_hands_out_a_convergent_design_as_it_is() -> None:
    """``synthesis.require_monotonic: false``: the same P-type gain converges (spectral radius below one), so it
    runs as configured, said to be not monotonic."""
    config = load_config(
        CONFIGS / "paper_sim.yaml", {**SHORT, "law.p_type_gain": 2.2, "synthesis.require_monotonic": False}
    )
    design = build_design(config, "p-type", N_SHORT, input_delay=1)
    certificates = design.certificates
    assert certificates is not None
    assert certificates.action is CertificateAction.NONE and float(design.p2[0, 0]) == 2.2
    assert certificates.asymptotic and not certificates.monotonic and certificates.norm_2 > 1


def test_an_unknown_policy_is_refused_before_any_certificate_is_computed() -> None:
    """``admit`` names the field of an unknown policy (exit 2) and never evaluates the gain."""
    evaluated: list[float] = []

    def evaluate(scale: float) -> Any:
        evaluated.append(scale)
        raise AssertionError("evaluated an unknown policy's gain")

    with pytest.raises(ConfigError) as caught:
        admit(evaluate, law="p-type", policy="shrink", require_monotonic=False, growth_horizon=10)  # type: ignore[arg-type]
    assert caught.value.key == "synthesis.on_divergent_filter" and "'shrink'" in str(caught.value)
    assert caught.value.exit_code == 2 and evaluated == []
