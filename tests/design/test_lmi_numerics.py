"""LMI (31) numerics: solved on a balanced model with a relative margin and bounded multipliers, checked here by
eigenvalues computed with numpy/scipy on matrices this file builds itself; a gamma the re-check cannot confirm is
refused."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest
import scipy.linalg

from foilc_hil.config import load_config
from foilc_hil.design import lmi
from foilc_hil.design.certificate_record import LMI_RELATIVE_MARGIN_MIN, LmiChecks
from foilc_hil.design.json_fields import jsonable
from foilc_hil.design.lmi import SIGMA_BOUND, balance, lmi_matrix, roesser_model, solve_lmi
from foilc_hil.design.models import DiscreteModel, Uncertainty, uncertainty_vertices
from foilc_hil.design.pipeline import design_model
from foilc_hil.errors import LmiInfeasibleError

CONFIGS = Path(__file__).resolve().parents[2] / "configs"
RATE = 0.868


def _model(name: str, delay: int) -> tuple[DiscreteModel, Uncertainty]:
    return design_model(load_config(CONFIGS / name), input_delay=delay)


def _lifted_roesser(model: DiscreteModel, dA: np.ndarray, dB: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``Abar``, ``Bbar`` of the 2D model at one plant, written out here from the derivation (not the code)."""
    A, B, C = model.A + dA, model.B + dB, model.C
    n, p = model.n_states, model.n_outputs
    return np.block([[A, np.zeros((n, p))], [-C @ A, np.eye(p)]]), np.vstack([B, -C @ B])


@pytest.mark.parametrize(("name", "delay"), [("paper_sim.yaml", 0), ("paper_sim.yaml", 1), ("demo.yaml", 1)])
def test_solution_passes_independent_eigenvalue_checks(name: str, delay: int) -> None:
    model, uncertainty = _model(name, delay)
    solution = solve_lmi(model, uncertainty, tau=RATE, theta=RATE)
    n = model.n_states
    Q = scipy.linalg.block_diag(solution.Qb, solution.Qt)
    assert np.min(scipy.linalg.eigvalsh(Q)) > 0
    np.testing.assert_allclose(solution.P @ Q, solution.J, rtol=1e-9, atol=1e-9 * np.max(np.abs(solution.J)))
    rates = scipy.linalg.block_diag(RATE * np.linalg.inv(solution.Qb), RATE * np.linalg.inv(solution.Qt))
    plants = [(np.zeros_like(model.A), np.zeros_like(model.B)), *uncertainty_vertices(uncertainty)]
    for dA, dB in plants:  # Theorem 1's Lyapunov decrease at every vertex, from the model matrices
        Abar, Bbar = _lifted_roesser(model, dA, dB)
        Acl = Abar + Bbar @ solution.P
        assert np.max(scipy.linalg.eigvalsh(Acl.T @ np.linalg.solve(Q, Acl) - rates)) < 0
        assert np.max(np.abs(np.linalg.eigvals(Acl[:n, :n]))) < 1
    # the multipliers as solved are bounded and the margin relative to the solved matrix is the one imposed
    scaling = solution.checks.scaling
    assert scaling is not None and max(scaling.sigmas) <= SIGMA_BOUND * (1 + 1e-9)
    assert min(scaling.sigmas) > 0
    assert solution.checks.relative_margin > 0.3e-6  # imposed 1e-6, to the solver's tolerance
    assert solution.checks.Q_condition == pytest.approx(np.linalg.cond(Q), rel=1e-6)


def test_scaling_is_exact_and_gives_the_same_gain() -> None:
    """Unscaling a scaled solution is exact (powers of two): the original LMI matrix is the congruence
    ``Dg Ms Dg`` of the scaled one (same eigenvalue signs), and ``P = S Ps T^-1``."""
    model, uncertainty = _model("paper_sim.yaml", 1)
    roesser = roesser_model(model, uncertainty)
    scaling = balance(roesser)
    factors = np.concatenate([scaling.state, scaling.inputs, scaling.channels])
    assert np.all(np.log2(factors) == np.round(np.log2(factors)))
    scaled = scaling.apply(roesser)
    # Abar, Bbar of the scaled model built here from T and S
    T, S = np.diag(scaling.state), np.diag(scaling.inputs)
    np.testing.assert_array_equal(scaled.Abar, np.linalg.inv(T) @ roesser.Abar @ T)
    np.testing.assert_array_equal(scaled.Bbar, np.linalg.inv(T) @ roesser.Bbar @ S)
    solution = solve_lmi(model, uncertainty, tau=RATE, theta=RATE)
    Tb, Tt = T[: model.n_states, : model.n_states], T[model.n_states :, model.n_states :]
    Tinv = np.linalg.inv(T)
    values: dict[str, Any] = {
        "Qb": np.linalg.inv(Tb) @ solution.Qb @ np.linalg.inv(Tb),
        "Qt": np.linalg.inv(Tt) @ solution.Qt @ np.linalg.inv(Tt),
        "J": np.linalg.inv(S) @ solution.J @ Tinv,
        "sigmas": tuple(s / c**2 for s, c in zip(solution.sigmas, scaling.channels, strict=True)),
        "gamma": solution.gamma,
    }
    back = scaling.unscale(values)
    for key in ("Qb", "Qt", "J"):
        np.testing.assert_array_equal(back[key], getattr(solution, key))
    kwargs: dict[str, Any] = {"tau": RATE, "theta": RATE, "bmat": np.block}
    M = lmi_matrix(roesser, **{k: back[k] for k in ("Qb", "Qt", "J", "sigmas", "gamma")}, **kwargs)
    Ms = lmi_matrix(scaled, **{k: values[k] for k in ("Qb", "Qt", "J", "sigmas", "gamma")}, **kwargs)
    Dg = np.diag(scaling.congruence(roesser))
    np.testing.assert_allclose(M, Dg @ Ms @ Dg, rtol=1e-12, atol=1e-12 * np.max(np.abs(M)))
    assert np.max(np.linalg.eigvalsh(Ms)) < 0
    Ps = values["J"] @ np.linalg.inv(scipy.linalg.block_diag(values["Qb"], values["Qt"]))
    np.testing.assert_allclose(S @ Ps @ Tinv, solution.P, rtol=1e-9)
    closed = np.sort_complex(np.linalg.eigvals(roesser.Abar + roesser.Bbar @ solution.P))
    closed_scaled = np.sort_complex(np.linalg.eigvals(scaled.Abar + scaled.Bbar @ Ps))
    np.testing.assert_allclose(closed, closed_scaled, atol=1e-9)


def test_both_solvers_pass_the_recheck_and_agree_on_paper_sim() -> None:
    """Unscaled, SCS's paper_sim solution failed the re-check (largest eigenvalue +0.13) and only CLARABEL's
    passed; scaled, both pass with the same gamma."""
    model, uncertainty = _model("paper_sim.yaml", 0)
    clarabel = solve_lmi(model, uncertainty, tau=RATE, theta=RATE, solver="CLARABEL")
    scs = solve_lmi(model, uncertainty, tau=RATE, theta=RATE, solver="SCS")
    assert (clarabel.solver, scs.solver) == ("CLARABEL", "SCS") and not scs.checks.solver_failures
    assert scs.gamma == pytest.approx(clarabel.gamma, rel=1e-3)


def _scaled_solution(model: DiscreteModel, uncertainty: Uncertainty) -> tuple[Any, dict[str, Any]]:
    """The CLARABEL solution in the coordinates it was solved in."""
    solution = solve_lmi(model, uncertainty, tau=RATE, theta=RATE)
    scaling = balance(roesser_model(model, uncertainty))
    n = model.n_states
    T, S = scaling.state, scaling.inputs
    return scaling, {
        "Qb": solution.Qb / np.outer(T[:n], T[:n]),
        "Qt": solution.Qt / np.outer(T[n:], T[n:]),
        "J": solution.J / np.outer(S, T),
        "sigmas": tuple(s / c**2 for s, c in zip(solution.sigmas, scaling.channels, strict=True)),
        "gamma": solution.gamma,
    }


def _boundary_gamma(scaling: Any, roesser: Any, values: dict[str, Any]) -> float:
    """The gamma at which the LMI matrix at ``values`` stops being negative definite (bisection), as the check sees
    it: in the coordinates solved (``values``) and in the original ones (a sign at rounding level may differ)."""
    scaled = scaling.apply(roesser)

    def largest(gamma: float) -> float:
        planted = {**values, "gamma": gamma}
        solved = lmi_matrix(scaled, **planted, tau=RATE, theta=RATE, bmat=np.block)
        original = lmi_matrix(roesser, **scaling.unscale(planted), tau=RATE, theta=RATE, bmat=np.block)
        return max(float(np.max(np.linalg.eigvalsh(solved))), float(np.max(np.linalg.eigvalsh(original))))

    low, high = 0.0, values["gamma"]
    for _ in range(200):
        middle = (low + high) / 2
        if middle in (low, high):
            break
        low, high = (low, middle) if largest(middle) < 0 else (middle, high)
    assert largest(high) < 0 <= largest(low)
    return high


def test_a_planted_unconfirmed_gamma_is_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    """A solver answer whose gamma makes the LMI hold only within rounding (largest eigenvalue < 0, but by less
    than 1e-10 of the norm) and one whose gamma is too small are both refused: no gamma is returned."""
    model, uncertainty = _model("paper_sim.yaml", 0)
    scaling, values = _scaled_solution(model, uncertainty)
    scaled = scaling.apply(roesser_model(model, uncertainty))
    boundary = _boundary_gamma(scaling, roesser_model(model, uncertainty), values)
    M = lmi_matrix(scaled, **{**values, "gamma": boundary}, tau=RATE, theta=RATE, bmat=np.block)
    spectrum = np.linalg.eigvalsh(M)
    assert 0 < -np.max(spectrum) / np.max(np.abs(spectrum)) < LMI_RELATIVE_MARGIN_MIN  # negative, within rounding
    for planted, reason in ((boundary, "within rounding"), (0.5 * boundary, "not < 0")):
        answer = ("optimal", {**values, "gamma": planted})
        monkeypatch.setattr(lmi, "_solve_once", lambda *args, answer=answer: answer)
        with pytest.raises(LmiInfeasibleError, match=reason):
            solve_lmi(model, uncertainty, tau=RATE, theta=RATE)
    honest = ("optimal", values)  # the control: the solver's own gamma is confirmed
    monkeypatch.setattr(lmi, "_solve_once", lambda *args: honest)
    assert solve_lmi(model, uncertainty, tau=RATE, theta=RATE).gamma == values["gamma"]


def test_checks_round_trip_through_json() -> None:
    checks = solve_lmi(*_model("demo.yaml", 1), tau=RATE, theta=RATE).checks
    assert checks.scaling is not None and not checks.within_rounding
    assert jsonable(LmiChecks.from_json(jsonable(checks)).to_json()) == jsonable(checks)


@pytest.mark.parametrize(("name", "delay"), [("paper_sim.yaml", 0), ("demo.yaml", 1), ("scara_4axis.yaml", 1)])
def test_the_standard_form_is_the_lmi_matrix_at_every_point(name: str, delay: int) -> None:
    """``F0 + sum x_i F_i`` (what cvxpy solves) against :func:`lmi_matrix` of the same values, at random points;
    ``x`` is packed here from the documented order (upper triangles of Qb and Qt, J by rows, sigmas, gamma)."""
    model, uncertainty = _model(name, delay)
    scaled = balance(roesser_model(model, uncertainty)).apply(roesser_model(model, uncertainty))
    form = lmi.standard_form(scaled, RATE, 0.9)
    n, p, m, c = scaled.n_states, scaled.n_outputs, scaled.Bbar.shape[1], len(scaled.channels)
    assert c > 0  # the uncertainty channels are in the matrix
    rng = np.random.default_rng(delay)
    for _ in range(5):
        Qb, Qt = rng.standard_normal((n, n)), rng.standard_normal((p, p))
        Qb, Qt = Qb + Qb.T, Qt + Qt.T
        J, sigmas, gamma = rng.standard_normal((m, n + p)), rng.uniform(0.1, 2.0, c), float(rng.uniform(0.5, 3))
        x = np.concatenate([Qb[np.triu_indices(n)], Qt[np.triu_indices(p)], J.ravel(), sigmas, [gamma]])
        direct = lmi_matrix(scaled, Qb=Qb, Qt=Qt, J=J, sigmas=list(sigmas), gamma=gamma, tau=RATE, theta=0.9,
                            bmat=np.block)
        np.testing.assert_allclose(form.matrix(x), direct, rtol=0, atol=1e-12 * np.max(np.abs(direct)))
        unpacked = form.unpack(x)
        np.testing.assert_array_equal(unpacked["Qb"], Qb)
        np.testing.assert_array_equal(unpacked["Qt"], Qt)
        np.testing.assert_array_equal(unpacked["J"], J)
        assert unpacked["sigmas"] == tuple(sigmas) and unpacked["gamma"] == gamma
