"""LMI (31) numerics: the margin is reported relative to the matrix's norm, recomputed here with numpy, and a
solution that holds only within rounding is labelled so (its gamma is not shown as confirmed)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from foilc_hil.config import load_config
from foilc_hil.design.lmi import lmi_matrix, roesser_model, solve_lmi
from foilc_hil.design.pipeline import design_model
from foilc_hil.design.record import LmiChecks, jsonable

pytestmark = pytest.mark.filterwarnings("ignore:Solution may be inaccurate")
CONFIGS = Path(__file__).resolve().parents[1] / "configs"


@pytest.mark.parametrize("name", ["paper_sim.yaml", "demo.yaml"])
def test_relative_margin_and_condition_are_recomputed(name: str) -> None:
    model, uncertainty = design_model(load_config(CONFIGS / name), input_delay=1)
    solution = solve_lmi(model, uncertainty, tau=0.868, theta=0.868)
    M = lmi_matrix(
        roesser_model(model, uncertainty),
        Qb=solution.Qb,
        Qt=solution.Qt,
        J=solution.J,
        sigmas=solution.sigmas,
        gamma=solution.gamma,
        tau=0.868,
        theta=0.868,
        bmat=np.block,
    )
    singular = np.linalg.svd(M, compute_uv=False)  # ||M||_2 by a second method (SVD, not eigenvalues)
    expected = -np.max(np.linalg.eigvalsh((M + M.T) / 2)) / singular[0]
    checks = solution.checks
    assert checks.relative_margin == pytest.approx(expected, rel=1e-6)
    Q = np.block([[solution.Qb, np.zeros((model.n_states, 1))], [np.zeros((1, model.n_states)), solution.Qt]])
    assert checks.Q_condition == pytest.approx(np.linalg.cond(Q), rel=1e-6)
    # the margin is absolute (synthesis.margin = 1e-6) against multipliers of 1e2..1e5: tiny relative to M
    assert checks.relative_margin < 1e-6 * max(solution.sigmas)


def test_paper_sim_lmi_holds_only_within_rounding_and_round_trips() -> None:
    model, uncertainty = design_model(load_config(CONFIGS / "paper_sim.yaml"))
    checks = solve_lmi(model, uncertainty, tau=0.868, theta=0.868).checks
    assert max(checks.sigmas) > 1e4 and checks.within_rounding
    assert jsonable(LmiChecks.from_json(jsonable(checks)).to_json()) == jsonable(checks)
