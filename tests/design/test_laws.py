"""Learning laws against independent brute-force implementations and convergence theory."""

from __future__ import annotations

import itertools
from dataclasses import replace
from typing import Any

import numpy as np
import pytest

from foilc_hil.config import FractionalMemory, LawConfig, LawKind, QFilterConfig
from foilc_hil.design.certificate_record import Certificates
from foilc_hil.design.certificates import certify_as_given, certify_p_type
from foilc_hil.design.fractional import FractionalPD
from foilc_hil.design.lifted import LawStructure, LoopPlant
from foilc_hil.design.models import DiscreteModel, Uncertainty, augment_input_delay
from foilc_hil.design.pipeline import law_kind
from foilc_hil.design.qfilter import QFilter
from foilc_hil.errors import ConfigError, InputError
from foilc_hil.laws.learning import Foilc, Ioilc, PType, make_law
from tests.support.designs import p_type_design, plain_design

TS = 0.05


def _design(A, B, C, P, *, kp=0.3, r=0.7, law="foilc", input_delay=0, C_measured=None):
    return plain_design(
        A, B, C, P, kp=kp, r=r, law=law, sample_time=TS, input_delay=input_delay, C_measured=C_measured
    )


# A small 2-state, 2-output, 1-input plant (C invertible so x = C^-1 y).
A2 = np.array([[0.9, 0.1], [-0.05, 0.8]])
B2 = np.array([[0.05], [0.1]])
C2 = np.array([[1.0, 0.0], [0.5, 1.0]])
P2 = np.array([[0.4, -0.2, 0.3, 0.2]])


def _run_plant(A, B, C, x0, u_of, n, delay=0):
    """Independent loop: discrete plant, commands from ``u_of(t, y)``; returns feedback, outputs, commands."""
    x = np.array(x0, dtype=float)
    line = [np.zeros(B.shape[1]) for _ in range(delay)]
    feedback, outputs, commands = [], [], []
    for t in range(n):
        y = C @ x
        feedback.append(y)
        u = np.array(u_of(t, y), dtype=float)
        commands.append(u)
        line.append(u)
        x = A @ x + B @ line.pop(0)
        outputs.append(C @ x)
    return np.array(feedback), np.array(outputs), np.array(commands)


def _controllable_operator(kp, r, h, n, delay):
    """``diag(I_d, I + kp h^-r T)``, ``T`` the GL Toeplitz matrix from ``(-1)^j binom(r, j)`` (scipy.special)."""
    from scipy.linalg import block_diag, toeplitz
    from scipy.special import binom

    length = n - delay
    j = np.arange(length)
    weights = (-1.0) ** j * binom(r, j)
    return block_diag(np.eye(delay), np.eye(length) + kp * h**-r * toeplitz(weights, np.zeros(length)))


def _brute_force_foilc(A, B, C, P, kp, r, ref, trials, n, x0, delay=0, memory="controllable"):
    """The 2D law written out from eq. (21) with lists and a dense fractional matrix (no shared buffers)."""
    m = B.shape[1]
    if kp == 0:
        M = np.eye(n)
    elif memory == "trial":
        M = FractionalPD(kp, r, TS).matrix(n)
    else:
        M = _controllable_operator(kp, r, TS, n, delay)
    u_prev = np.zeros((n, m))
    x_prev = None
    E_prev = None
    all_commands = []
    for _ in range(trials):
        issued: list[np.ndarray] = []
        states: list[np.ndarray] = []

        def law(t, y, issued=issued, states=states, u_prev=u_prev, x_prev=x_prev, E_prev=E_prev):
            x_plant = np.linalg.solve(C, y) if C.shape[0] == C.shape[1] else np.linalg.pinv(C) @ y
            past = [issued[t - delay + j] if t - delay + j >= 0 else np.zeros(m) for j in range(delay)]
            x = np.concatenate([x_plant, *past]) if delay else x_plant
            states.append(x)
            if x_prev is None:
                u = u_prev[t].copy()
            else:
                lead = E_prev[t + delay] if t + delay < n else np.zeros(E_prev.shape[1])
                u = u_prev[t] + P[:, : x.size] @ (x - x_prev[t]) + P[:, x.size :] @ lead
            issued.append(u)
            return u

        _, outputs, commands = _run_plant(A, B, C, x0, law, n, delay)
        e = ref - outputs
        E_prev = M @ e
        x_prev = np.array(states)
        u_prev = commands
        all_commands.append(commands)
    return all_commands


def _run_law(law, A, B, C, ref, trials, n, x0, delay=0):
    all_commands = []
    for _ in range(trials):
        law.begin_trial()
        _, outputs, commands = _run_plant(A, B, C, x0, lambda t, y: law.command(t, y).copy(), n, delay)
        update = law.end_trial(ref, outputs)
        assert update.metrics.trial == law.trial
        all_commands.append(commands)
    return all_commands


def _reference(n, p):
    t = np.arange(1, n + 1) * TS
    return np.column_stack([np.sin(t * (k + 1)) for k in range(p)])


@pytest.mark.parametrize("memory", ["controllable", "trial"])
def test_foilc_matches_brute_force(memory: str) -> None:
    n = 40
    ref = _reference(n, 2)
    design = _design(A2, B2, C2, P2, kp=0.3, r=0.7)
    got = _run_law(Foilc(design, n, fractional_memory=memory), A2, B2, C2, ref, 4, n, x0=[0.1, -0.2])
    want = _brute_force_foilc(A2, B2, C2, P2, 0.3, 0.7, ref, 4, n, x0=[0.1, -0.2], memory=memory)
    for k in range(4):
        np.testing.assert_allclose(got[k], want[k], rtol=1e-12, atol=1e-12)
    assert np.any(got[-1] != 0)  # the law did learn something


@pytest.mark.parametrize("memory", ["controllable", "trial"])
def test_foilc_with_input_delay_matches_brute_force(memory: str) -> None:
    n, d = 30, 1
    ref = _reference(n, 2)
    augmented, _ = augment_input_delay(DiscreteModel(A2, B2, C2, TS), d)
    P = np.array([[0.4, -0.2, 0.1, 0.3, 0.2]])
    design = _design(
        augmented.A, augmented.B, augmented.C, P, kp=0.2, r=1.3, input_delay=d, C_measured=augmented.measured_output
    )
    got = _run_law(Foilc(design, n, fractional_memory=memory), A2, B2, C2, ref, 3, n, x0=[0.0, 0.0], delay=d)
    want = _brute_force_foilc(A2, B2, C2, P, 0.2, 1.3, ref, 3, n, x0=[0.0, 0.0], delay=d, memory=memory)
    for k in range(3):
        np.testing.assert_allclose(got[k], want[k], rtol=1e-12, atol=1e-12)


def test_ioilc_equals_foilc_with_kp_zero_bit_for_bit() -> None:
    n = 40
    ref = _reference(n, 2)
    ioilc = Ioilc(_design(A2, B2, C2, P2, kp=0.0, r=0.7, law="ioilc"), n)
    foilc = Foilc(_design(A2, B2, C2, P2, kp=0.0, r=0.7), n)
    with pytest.raises(InputError, match=r"design\.kp"):  # the law runs the design's kp: it sets none aside
        Ioilc(_design(A2, B2, C2, P2, kp=0.5, r=0.7), n)
    a = _run_law(ioilc, A2, B2, C2, ref, 4, n, x0=[0.1, 0.0])
    b = _run_law(foilc, A2, B2, C2, ref, 4, n, x0=[0.1, 0.0])
    for k in range(4):
        assert np.array_equal(a[k], b[k])
    # and kp matters: a FOILC with kp > 0 differs
    c = _run_law(Foilc(_design(A2, B2, C2, P2, kp=0.5, r=0.7), n), A2, B2, C2, ref, 4, n, x0=[0.1, 0.0])
    assert not np.array_equal(a[-1], c[-1])


def test_law_is_deterministic_and_command_is_read_only() -> None:
    n = 30
    ref = _reference(n, 2)
    runs = [_run_law(Foilc(_design(A2, B2, C2, P2), n), A2, B2, C2, ref, 3, n, x0=[0.3, 0.1]) for _ in range(2)]
    for k in range(3):
        assert np.array_equal(runs[0][k], runs[1][k])
    law = Foilc(_design(A2, B2, C2, P2), n)
    law.begin_trial()
    u = law.command(0, np.zeros(2))
    with pytest.raises(ValueError):
        u[0] = 1.0


def test_sequence_errors() -> None:
    n = 10
    law = Foilc(_design(A2, B2, C2, P2), n)
    with pytest.raises(InputError, match="begin_trial"):
        law.command(0, np.zeros(2))
    law.begin_trial()
    law.command(0, np.zeros(2))
    with pytest.raises(InputError, match="out of order"):
        law.command(2, np.zeros(2))
    with pytest.raises(InputError, match="1 of 10"):
        law.end_trial(np.zeros(n), np.zeros((n, 2)))


def test_state_reconstruction_needs_full_column_rank() -> None:
    C = np.array([[1.0, 1.0]])
    design = _design(A2, B2, C, np.array([[0.1, 0.1, 0.1]]))
    with pytest.raises(ConfigError, match=r"plant\.c"):
        Foilc(design, 10)


def test_restore_runs_the_given_feedforward_unchanged() -> None:
    n = 20
    ref = _reference(n, 2)
    law = Foilc(_design(A2, B2, C2, P2), n)
    _run_law(law, A2, B2, C2, ref, 2, n, x0=[0.2, 0.0])
    best = np.linspace(0.0, 1.0, n)
    law.restore(best)
    commands = _run_law(law, A2, B2, C2, ref, 1, n, x0=[0.2, 0.0])[0]
    np.testing.assert_array_equal(commands[:, 0], best)


# --- P-type -------------------------------------------------------------------------------------------------


def _first_order(ts: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    a, b = -1.23, 1.68
    ad = np.exp(a * ts)
    return np.array([[ad]]), np.array([[b * (ad - 1.0) / a]]), np.array([[1.0]])


def _p_type_certificates(A: np.ndarray, B: np.ndarray, C: np.ndarray, n: int, gain: np.ndarray) -> Certificates:
    """The certificates of the P-type design with gain ``gain`` (the design pipeline's P-type step)."""
    model = DiscreteModel(A, B, C, 0.1)
    design = certify_p_type(
        model, Uncertainty.none(1, 1), gain, LawStructure(0.0, 1.0, 0.1, n), require_monotonic=False
    )
    np.testing.assert_array_equal(design.p1, 0.0)  # P = (0 Gamma)
    np.testing.assert_array_equal(design.p2, gain)
    assert design.certificates is not None
    return design.certificates


def test_p_type_default_gain_converges_monotonically() -> None:
    n = 60
    A, B, C = _first_order(0.1)
    law = PType(p_type_design(A, B, C, sample_time=0.1), n)
    cert = _p_type_certificates(A, B, C, n, law.gain)
    assert cert.p_type is not None and cert.p_type.frequency_bound < 1.0
    assert cert.norm_2 <= cert.p_type.frequency_bound + 1e-9  # the symbol bounds the lifted norm
    assert cert.monotonic
    # the classic 1 / (C B) has spectral radius 0 but is NOT monotonic on this slow plant sampled fast
    deadbeat = _p_type_certificates(A, B, C, n, np.array([[1.0 / float((C @ B)[0, 0])]]))
    assert deadbeat.spectral_radius < 1e-12 and deadbeat.norm_2 > 1.0
    assert not deadbeat.monotonic and deadbeat.action == "none"  # reported, never rescaled
    ref = np.ones(n)
    norms = []
    for _ in range(12):
        law.begin_trial()
        _, outputs, _ = _run_plant(A, B, C, [0.0], lambda t, y: law.command(t, y).copy(), n)
        norms.append(float(np.linalg.norm(law.end_trial(ref, outputs).error)))
    assert all(b < a for a, b in itertools.pairwise(norms)), norms
    assert norms[-1] < 0.5 * norms[0]


def _lifted_plant(A: np.ndarray, B: np.ndarray, C: np.ndarray, n_samples: int) -> np.ndarray:
    """SISO ``u[0..N-1] -> y[1..N]``: entry ``(i, j)`` is ``C A^(i-j) B`` for ``j <= i``."""
    markov = [float((C @ np.linalg.matrix_power(A, k) @ B)[0, 0]) for k in range(n_samples)]
    lag = np.subtract.outer(np.arange(n_samples), np.arange(n_samples))
    return np.where(lag >= 0, np.asarray(markov)[np.clip(lag, 0, None)], 0.0)


def test_p_type_update_matches_lifted_formula() -> None:
    n = 25
    A, B, C = _first_order(0.1)
    gamma = 0.7
    law = PType(p_type_design(A, B, C, gamma, sample_time=0.1), n)
    G = _lifted_plant(A, B, C, n)
    ref = np.sin(np.arange(1, n + 1) * 0.3)
    e = ref.copy()  # trial 1 runs u = 0 from rest: y = 0
    for _ in range(4):
        law.begin_trial()
        _, outputs, _ = _run_plant(A, B, C, [0.0], lambda t, y: law.command(t, y).copy(), n)
        got = law.end_trial(ref, outputs).error[:, 0]
        np.testing.assert_allclose(got, e, atol=1e-12)
        e = (np.eye(n) - gamma * G) @ e


# --- Q-filter -----------------------------------------------------------------------------------------------


def test_q_filter_matrix_is_its_operator() -> None:
    q = QFilter(cutoff=5.0, order=3, sample_time=0.01)
    rng = np.random.default_rng(1)
    u = rng.standard_normal(200)
    np.testing.assert_allclose(q.matrix(200) @ u, q.apply(u), rtol=1e-12, atol=1e-12)
    two = rng.standard_normal((200, 2))
    np.testing.assert_allclose(q.apply(two)[:, 1], q.apply(two[:, 1]), rtol=1e-13, atol=1e-13)


def test_q_filter_is_zero_phase_low_pass() -> None:
    ts = 0.01
    q = QFilter(cutoff=20.0, order=2, sample_time=ts)
    t = np.arange(2000) * ts
    slow = np.sin(1.0 * t)
    fast = np.sin(200.0 * t)
    filtered = q.apply(slow + fast)
    middle = slice(300, 1700)
    np.testing.assert_allclose(filtered[middle], slow[middle], atol=2e-3)  # no delay, no attenuation
    with pytest.raises(ConfigError, match="cutoff"):
        QFilter(cutoff=400.0, order=2, sample_time=ts)  # above Nyquist (314 rad/s)


@pytest.mark.parametrize(
    ("cutoff", "order", "ts", "n"),
    [(20.0, 2, 0.01, 300), (5.0, 4, 0.01, 300), (2.0, 1, 0.01, 200), (50.0, 8, 0.005, 400), (100.0, 6, 0.001, 800)],
)
def test_q_filter_never_amplifies(cutoff: float, order: int, ts: float, n: int) -> None:
    """||Q||_2 <= 1: a Q-filter with a larger norm can break monotonic convergence (filtfilt's padding did)."""
    Q = QFilter(cutoff=cutoff, order=order, sample_time=ts).matrix(n)
    assert np.linalg.norm(Q, 2) <= 1.0 + 1e-12
    np.testing.assert_allclose(Q, Q.T, atol=1e-12)  # H^T H: symmetric ...
    assert np.min(np.linalg.eigvalsh((Q + Q.T) / 2)) >= -1e-12  # ... positive semidefinite


def test_make_law_with_q_filter_stores_filtered_feedforward() -> None:
    n = 80
    section = QFilterConfig(cutoff=10.0, order=2)
    design = replace(_design(A2, B2, C2, P2, kp=0.0), q_filter=QFilter.of(section, TS))
    law = make_law(design, LawConfig(q_filter=section), n)
    assert law.q_filter is design.q_filter  # the design's filter, not one built again
    ref = _reference(n, 2)
    commands = _run_law(law, A2, B2, C2, ref, 2, n, x0=[0.2, 0.1])
    assert law.q_filter is not None
    np.testing.assert_allclose(law.feedforward[:, 0], law.q_filter.apply(commands[-1][:, 0]), atol=1e-14)
    with pytest.raises(ConfigError, match=r"law\.kind"):
        law_kind("pid")


@pytest.mark.parametrize("memory", ["controllable", "trial"])
@pytest.mark.parametrize("delay", [0, 1, 2])
def test_law_obeys_the_certificates_lifted_error_map(delay: int, memory: str) -> None:
    """A second, independent derivation: the certificates' dense trial map T predicts the law's error updates."""
    from foilc_hil.design.error_map import dense_error_map

    n = 25
    A, B, C = _first_order(0.1)
    model, _ = augment_input_delay(DiscreteModel(A, B, C, 0.1), delay)
    P = np.hstack([np.full((1, model.n_states), -0.4), [[3.0]]])
    P[0, 0] = -5.0
    design = plain_design(
        model.A, model.B, model.C, P, kp=0.15, r=0.6, sample_time=0.1, input_delay=delay,
        C_measured=model.measured_output,
    )
    law = Foilc(design, n, fractional_memory=memory)
    ref = np.sin(np.arange(1, n + 1) * 0.2) + 0.5
    errors = []
    for _ in range(4):
        law.begin_trial()
        _, outputs, _ = _run_plant(A, B, C, [0.3], lambda t, y: law.command(t, y).copy(), n, delay)
        errors.append(law.end_trial(ref, outputs).error[:, 0])
    if memory == "trial":
        F = FractionalPD(0.15, 0.6, 0.1).matrix(n)
    else:
        F = _controllable_operator(0.15, 0.6, 0.1, n, delay)
    T = dense_error_map(model.A, model.B, model.measured_output, design.p1, design.p2, F, lead=delay)
    for k in range(1, 3):
        np.testing.assert_allclose(errors[k + 1] - errors[k], T @ (errors[k] - errors[k - 1]), atol=1e-10)
    assert np.linalg.norm(errors[2] - errors[1]) > 1e-3  # the check is not vacuous
    # The certificate's fast map is the same operator as the law's (fractional_memory passed through).
    from foilc_hil.design.error_map import lifted_error_map
    from foilc_hil.design.lifted import law_filter_matrix

    np.testing.assert_allclose(law_filter_matrix(0.15, 0.6, 0.1, n, delay, memory), F, atol=1e-12)
    fast = lifted_error_map(
        LoopPlant(model.A, model.B, model.measured_output, design.p1, design.p2),
        LawStructure(0.15, 0.6, 0.1, n, delay, FractionalMemory(memory)),
    )
    np.testing.assert_allclose(fast.to_dense(), T[delay:, delay:], atol=1e-10)


# --- saturation-aware learning ----------------------------------------------------------------------------------


def _saturated_run(law, A, B, C, ref, trials, n, limit):
    """The plant only ever receives clamp(u, -limit, limit) (the drive saturates); returns feedforwards, RMSEs."""
    feedforwards, rmses = [], []
    for _ in range(trials):
        law.begin_trial()
        _, outputs, _ = _run_plant(A, B, C, [0.0], lambda t, y: np.clip(law.command(t, y), -limit, limit), n)
        update = law.end_trial(ref, outputs)
        feedforwards.append(law.feedforward.copy())
        rmses.append(update.metrics.rmse)
    return feedforwards, rmses


@pytest.mark.parametrize("kind", ["foilc", "p-type"])
def test_law_with_limits_learns_from_what_is_applied(kind: str) -> None:
    """A reference the saturated actuator cannot reach (DC gain b/|a| = 1.37, limit 0.5, reference 1)."""
    ts, n, limit, trials = 0.1, 40, 0.5, 30
    A, B, C = _first_order(ts)
    ref = np.ones((n, 1))
    model = DiscreteModel(A, B, C, ts)
    P = np.array([[-0.5, 0.8 / float(B[0, 0])]])
    design = _design(model.A, model.B, model.C, P, kp=0.05, r=0.6)

    def build(limits):
        if kind == "p-type":
            return PType(p_type_design(A, B, C, 0.8 / float(B[0, 0]), sample_time=ts), n, limits=limits)
        return Foilc(design, n, limits=limits)

    clamped_ff, clamped_rmse = _saturated_run(build((-limit, limit)), A, B, C, ref, trials, n, limit)
    free_ff, _ = _saturated_run(build(None), A, B, C, ref, trials, n, limit)
    for ff in clamped_ff:
        assert np.max(np.abs(ff)) <= limit  # the stored feedforward never exceeds the limit
    assert max(clamped_rmse) <= clamped_rmse[0] * 1.0001  # the error does not blow up over the trials
    # After learning, the law commands the limit where the reference is out of reach (it learned saturation).
    assert np.max(clamped_ff[-1]) == limit
    # Without limits the unclamped feedforward winds up far past what the drive can apply (the defect fixed).
    assert np.max(free_ff[-1]) > 5 * limit


def test_limits_are_validated_and_logged() -> None:
    design = _design(A2, B2, C2, P2)
    with pytest.raises(InputError, match="limits"):
        Foilc(design, 10, limits=(1.0, -1.0))
    law = make_law(design, LawConfig(), 10, limits=(-2.0, 3.0))
    assert law.limits == (-2.0, 3.0)
    assert law.state_dict()["limits"] == [-2.0, 3.0]
    law.begin_trial()
    assert float(law.command(0, np.array([0.0, 0.0]))[0]) == 0.0


def test_law_refuses_a_design_certified_for_another_fractional_memory() -> None:
    plain = _design(A2, B2, C2, P2)
    trial = LawStructure(plain.kp, plain.r, TS, 10, fractional_memory=FractionalMemory.TRIAL)
    certificates = certify_as_given(plain.model, plain.uncertainty, plain.P, trial, require_monotonic=False)
    design = plain_design(A2, B2, C2, P2, kp=plain.kp, r=plain.r, sample_time=TS, certificates=certificates)
    with pytest.raises(ConfigError, match=r"law\.fractional_memory"):
        Foilc(design, 10)  # default "controllable": the certificate would not be of this law
    assert Foilc(design, 10, fractional_memory="trial").fractional_memory == "trial"
    with pytest.raises(ConfigError, match=r"law\.fractional_memory"):
        Foilc(_design(A2, B2, C2, P2), 10, fractional_memory="whole")
    # IOILC has no fractional operator: any recorded memory is fine
    assert Ioilc(replace(design, law=LawKind.IOILC, kp=0.0), 10).kp == 0.0


@pytest.mark.parametrize("law", ["foilc", "ioilc", "p-type"])
def test_make_law_compiles_the_step_for_its_own_argument_types(law: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """The law's step overload is resolved when the law is built, for the types it passes (a design's gain is a
    read-only array, which kernels.warm_up's arguments are not): a realtime run's first trial compiled it (0.6 s
    without SYNC on a fresh install)."""
    from foilc_hil.laws import learning

    resolved: list[tuple[str, ...]] = []

    def recording(arguments: Any) -> Any:
        resolved.append(tuple(str(learning.law_step.typeof_pyval(value)) for value in arguments))
        return law_step_for(arguments)

    law_step_for = learning.law_step_for
    monkeypatch.setattr(learning, "law_step_for", recording)
    # each law's own design: IOILC's has kp = 0, P-type's P = (0 Gamma)
    P = np.hstack([np.zeros((1, 2)), P2[:, 2:]]) if law == "p-type" else P2
    built = make_law(_design(A2, B2, C2, P, kp=0.3 if law == "foilc" else 0.0, law=law), LawConfig(), 10)
    assert len(resolved) == 1  # before any trial
    built.begin_trial()
    assert resolved[1] == resolved[0]  # the trial's types are those resolved at construction
