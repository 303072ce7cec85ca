"""LMI (31) synthesis: the derived Roesser model, solutions re-checked in numpy, MIMO, infeasibility."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from foilc_hil.config import FractionalMemory, LawKind
from foilc_hil.design.lifted import LawStructure
from foilc_hil.design.lmi import (
    lmi_matrix,
    roesser_model,
    solve_lmi,
    synthesize,
    verify_lmi_solution,
)
from foilc_hil.design.models import DiscreteModel, Uncertainty, augment_input_delay, discretize, uncertainty_vertices
from foilc_hil.errors import LmiInfeasibleError
from plant_emulator.linear import ContinuousModel

pytestmark = pytest.mark.filterwarnings("ignore:Solution may be inaccurate")


def _paper_plant(ts: float, method: str = "zoh") -> DiscreteModel:
    return discretize(ContinuousModel(np.array([[-1.23]]), np.array([[1.68]]), np.array([[1.0]])), ts, method)  # type: ignore[arg-type]


def _mimo() -> DiscreteModel:
    rng = np.random.default_rng(7)
    a = rng.standard_normal((3, 3)) - 2 * np.eye(3)
    b = rng.standard_normal((3, 2))
    c = b.T + 0.1 * rng.standard_normal((2, 3))  # C B well conditioned: both outputs are learnable
    return discretize(ContinuousModel(a, b, c), 0.05)


def test_roesser_model_matches_a_trial_to_trial_simulation() -> None:
    """(dx(t+1), e_k(t+1)) = (Abar + Bbar P)(dx(t), e_{k-1}(t+1)) for the law r = P (dx, e_{k-1}(t+1)) (kp = 0).

    Independent of the derivation: simulate two trials of the plant in plain numpy and compare.
    """
    model = _mimo()
    rng = np.random.default_rng(1)
    P = rng.standard_normal((2, 5)) * 0.3
    roesser = roesser_model(model, Uncertainty.none(3, 2))
    Acl = roesser.Abar + roesser.Bbar @ P
    n_samples = 12
    reference = rng.standard_normal((n_samples + 1, 2))
    # Trial k-1: arbitrary input, record x and e.
    u_prev = rng.standard_normal((n_samples, 2))
    x_prev = np.zeros((n_samples + 1, 3))
    for t in range(n_samples):
        x_prev[t + 1] = model.A @ x_prev[t] + model.B @ u_prev[t]
    e_prev = reference - x_prev @ model.C.T
    # Trial k with the 2D law.
    x = np.zeros((n_samples + 1, 3))
    for t in range(n_samples):
        dx = x[t] - x_prev[t]
        u = u_prev[t] + P @ np.concatenate([dx, e_prev[t + 1]])
        x[t + 1] = model.A @ x[t] + model.B @ u
    e = reference - x @ model.C.T
    for t in range(n_samples):
        state = np.concatenate([x[t] - x_prev[t], e_prev[t + 1]])
        following = np.concatenate([x[t + 1] - x_prev[t + 1], e[t + 1]])
        np.testing.assert_allclose(Acl @ state, following, atol=1e-10)


@pytest.mark.parametrize(("ts", "method"), [(0.01, "zoh"), (0.001, "zoh"), (0.01, "euler")])
def test_paper_plant_solution_rechecked_in_numpy(ts: float, method: str) -> None:
    model = _paper_plant(ts, method)
    unc = Uncertainty.none(1, 1)
    solution = solve_lmi(model, unc, tau=0.868, theta=0.868)
    assert solution.checks.lmi_max_eigenvalue < 0
    # Rebuild the LMI matrix here and check it directly.
    roesser = roesser_model(model, unc)
    M = lmi_matrix(
        roesser,
        Qb=solution.Qb,
        Qt=solution.Qt,
        J=solution.J,
        sigmas=solution.sigmas,
        gamma=solution.gamma,
        tau=0.868,
        theta=0.868,
        bmat=np.block,
    )
    np.testing.assert_allclose(M, M.T, atol=1e-12)
    assert np.max(np.linalg.eigvalsh(M)) < 0
    Q = np.block([[solution.Qb, np.zeros((1, 1))], [np.zeros((1, 1)), solution.Qt]])
    np.testing.assert_allclose(solution.P @ Q, solution.J, rtol=1e-9, atol=1e-9)
    Acl = roesser.Abar + roesser.Bbar @ solution.P
    rates = np.diag([0.868 / solution.Qb[0, 0], 0.868 / solution.Qt[0, 0]])
    assert np.max(np.linalg.eigvalsh(Acl.T @ np.linalg.inv(Q) @ Acl - rates)) < 0
    assert solution.gamma > 0


def test_euler_and_zoh_give_different_designs() -> None:
    zoh = solve_lmi(_paper_plant(0.05, "zoh"), Uncertainty.none(1, 1), tau=0.868, theta=0.868)
    euler = solve_lmi(_paper_plant(0.05, "euler"), Uncertainty.none(1, 1), tau=0.868, theta=0.868)
    assert abs(zoh.P[0, 0] - euler.P[0, 0]) > 1e-3


def test_mimo_dimensions() -> None:
    model = _mimo()
    unc = Uncertainty(0.01 * np.eye(3), np.eye(3), 0.01 * model.B, np.eye(2))
    solution = solve_lmi(model, unc, tau=0.868, theta=0.868)
    assert solution.P.shape == (2, 5)
    assert solution.Qb.shape == (3, 3) and solution.Qt.shape == (2, 2)
    assert solution.checks.vertices_checked > 0
    assert solution.checks.trial_radius < 1 and solution.checks.time_radius < 1


def test_uncertain_plant_is_robust_at_every_vertex() -> None:
    model = _paper_plant(0.01)
    unc = Uncertainty(
        np.array([[0.1 * model.A[0, 0]]]), np.array([[1.0]]), np.array([[0.2 * model.B[0, 0]]]), np.array([[1.0]])
    )
    solution = solve_lmi(model, unc, tau=0.868, theta=0.868)
    vertices = list(uncertainty_vertices(unc))
    assert len(vertices) == 4
    p1, p2 = solution.P[:, :1], solution.P[:, 1:]
    for dA, dB in vertices:
        assert abs(1.0 - (model.B + dB)[0, 0] * p2[0, 0]) < 1.0
        assert abs((model.A + dA + (model.B + dB) @ p1)[0, 0]) < 1.0


def test_delay_augmented_design_is_feasible_with_uncertainty() -> None:
    base = _paper_plant(0.01)
    unc = Uncertainty(np.array([[0.05 * base.A[0, 0]]]), np.array([[1.0]]), np.array([[0.0]]), np.array([[1.0]]))
    model, padded = augment_input_delay(base, 1, unc)
    solution = solve_lmi(model, padded, tau=0.868, theta=0.868)
    assert solution.P.shape == (1, 3)
    assert solution.checks.lmi_max_eigenvalue < 0


def test_verification_catches_a_wrong_solution() -> None:
    model = _paper_plant(0.01)
    unc = Uncertainty.none(1, 1)
    solution = solve_lmi(model, unc, tau=0.868, theta=0.868)
    values = {
        "Qb": solution.Qb,
        "Qt": solution.Qt,
        "J": -solution.J,  # flips the gain: the LMI no longer holds
        "sigmas": solution.sigmas,
        "gamma": solution.gamma,
    }
    with pytest.raises(LmiInfeasibleError, match="LMI"):
        verify_lmi_solution(model, unc, values, tau=0.868, theta=0.868)


def test_unlearnable_plant_is_infeasible() -> None:
    # C B = 0: the input never reaches the next output, so the trial-direction block is I whatever p2 is.
    model = DiscreteModel(np.array([[0.5, 0.1], [0.0, 0.5]]), np.array([[0.0], [1.0]]), np.array([[1.0, 0.0]]), 0.01)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with pytest.raises(LmiInfeasibleError, match=r"tau=0\.868"):
            solve_lmi(model, Uncertainty.none(2, 1), tau=0.868, theta=0.868)


def test_sign_indefinite_input_uncertainty_is_infeasible() -> None:
    model = _paper_plant(0.01)
    # |dB| up to 3 B: B + dB can vanish or change sign, no gain can learn for all of them.
    unc = Uncertainty(np.zeros((1, 1)), np.zeros((1, 1)), np.array([[3.0 * model.B[0, 0]]]), np.array([[1.0]]))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        with pytest.raises(LmiInfeasibleError):
            solve_lmi(model, unc, tau=0.868, theta=0.868)


def test_scs_solver_is_recorded() -> None:
    solution = solve_lmi(_paper_plant(0.01), Uncertainty.none(1, 1), tau=0.868, theta=0.868, solver="SCS")
    assert solution.solver in ("SCS", "CLARABEL")
    assert solution.checks.lmi_max_eigenvalue < 0


def test_synthesize_returns_a_design_with_certificates() -> None:
    model = _paper_plant(0.01)
    design = synthesize(model, None, LawStructure(0.3, 1.0, model.sample_time, 200), kind=LawKind.IOILC)
    assert design.law == "ioilc" and design.kp == 0.0  # IOILC certifies kp = 0 whatever it is given
    assert design.certificates is not None and design.certificates.lmi is not None
    assert design.certificates.spectral_radius < 1
    assert design.certificates.lmi.solver == "CLARABEL"
    assert design.gain_scale == 1.0
    np.testing.assert_array_equal(design.P, design.certificates.lmi.P_lmi)


def test_synthesize_certifies_the_fractional_memory_the_law_runs() -> None:
    """d = 0, a large e(0) weight: the Caputo correction column (memory "trial") changes the certificate's 2-norm;
    the design records which operator it certified, and the law built from it must match."""
    from foilc_hil.laws.learning import Foilc

    model = _paper_plant(0.01)
    designs = {
        memory: synthesize(
            model, None, LawStructure(0.37, 0.13, model.sample_time, 200, fractional_memory=memory),
            require_monotonic=False,
        )
        for memory in FractionalMemory
    }
    certificates = {memory: design.certificates for memory, design in designs.items()}
    for memory, design in designs.items():
        assert design.certificates is not None and design.certificates.fractional_memory == memory
        Foilc(design, 200, fractional_memory=memory)  # consistent: accepted
    trial, controllable = certificates[FractionalMemory.TRIAL], certificates[FractionalMemory.CONTROLLABLE]
    assert trial is not None and controllable is not None
    # Same LMI gain; the operators differ only by the e(0) correction column, which the first input moves.
    assert trial.designed.norm_2 > controllable.designed.norm_2
    assert controllable.monotonic is True
