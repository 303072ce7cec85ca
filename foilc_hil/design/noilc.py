"""Norm-optimal ILC (Amann–Owens): the baseline an ILC engineer compares a new law with, in its state-space form.

Each trial minimises ``||e_k||_Q^2 + ||u_k - u_{k-1}||_R^2`` on the lifted plant, which gives

    u_k = u_{k-1} + L e_{k-1},    L = (G^T Q G + R)^-1 G^T Q,

with ``G`` the lifted nominal plant from the inputs ``u[0..N-d-1]`` to the error samples they can move,
``e[d..N-1]`` (block lower-triangular Toeplitz with blocks ``C_measured A^(j + d) B``; the first ``d`` samples never
change and the last ``d`` inputs move nothing, as for every law here). ``Q = q I``, ``R = r I``.

The state-space form
--------------------
``L`` is never formed. ``G`` is the causal system ``xi_(i+1) = A_p xi_i + B_p u_i``, ``y_i = C_p A_p xi_i + C_p B_p
u_i`` of the plant without its delay states (:func:`plant_realization`; ``d`` samples of delay are the shift the
lifted map already accounts for), and ``M = q G^T G + r I`` factors through the finite-horizon Riccati recursion
of the LQ problem ``min q ||G du||^2 + r ||du||^2`` (:func:`foilc_hil.design.lifted_kernel.noilc_riccati`, run
backward from ``P_L = 0``: the terminal condition of the finite trial): ``M = F^T W F`` with ``F du = du + K x``
(``x`` the nominal model's state under ``du``), lower triangular with unit diagonal. So

    L = Fi Fi^T q G^T,   Fi = F^-1 R_W^-1   (W_i = R_W,i^T R_W,i),

and the update ``L e`` is one backward pass (the costate of ``G Fi``: ``q (G Fi)^T e``) and one forward pass
(``Fi``: the Riccati feedback ``du_i = -K_i x_i + v_i``), ``O(N n^3)`` (:class:`LiftedUpdate`). It is the dense
update to rounding: ``tests/design/test_baselines.py`` checks it against the normal equations.

Certificates
------------
The trial-to-trial error map is ``T = I - G_v s L`` at each plant ``G_v`` (nominal and uncertainty vertices; ``s``
the update's scale, 1 unless :mod:`foilc_hil.design.admission` had to shrink it); with a Q-filter the input map
``M = Q_f - L S G_y`` instead. On the nominal plant ``T = r (q G G^T + r I)^-1`` is symmetric with eigenvalues
``r / (r + q sigma_i^2)`` in ``(0, 1)``: monotonic by construction; the vertices measure its robustness.

* Trials of up to :data:`DENSE_LIMIT` samples: ``T`` dense, its exact spectral radius and 2-norm
  (:func:`~foilc_hil.design.map_norms.matrix_certificate`, method ``dense``).
* Longer trials: ``T`` as a :class:`~foilc_hil.design.trial_operator.TrialOperator` (``3 n`` states), its 2-norm
  from above by the structured Cholesky test of its dilation and bisection (:data:`STRUCTURED_METHOD`: exact to the
  bisection's ``1e-10`` and a rounding margin, ``O(N n^3)`` per test). Its spectral radius is bounded by that
  norm, and when that is not below one by the 2-norm of a similar map, ``X = I - s q (G Fi)^T G_v Fi`` (the
  spectrum of ``I - G_v L`` is that of ``I - L G_v``, similar to ``X`` through ``Fi``; on the nominal plant ``X`` is
  symmetric and its norm the exact radius); where neither is below one the radius says "inconclusive at bound X".
* With a Q-filter, the input map ``M = Q_f - L_full G_y`` on all ``N`` inputs the same way: dense up to
  :data:`DENSE_LIMIT`, structured beyond (the filter's state-space form, ``Q_f = H^T H`` zero-phase or ``H``
  causal, from :meth:`~foilc_hil.design.qfilter.QFilter.realization`; a filter without one is certified densely up
  to :data:`Q_FILTER_DENSE_LIMIT` samples, and "inconclusive" beyond); its spectral radius bounded by its 2-norm,
  "inconclusive at bound X" where that is not below one.

The weight ``r`` is set relative to the plant, ``r = r_relative ||G||_2^2 q`` (``law.noilc.r_relative``), so one
default fits plants of any gain: the direction of the largest plant gain contracts by
``r_relative / (1 + r_relative)`` per trial. ``||G||_2`` comes from the same structured test, bisected to
``1e-13`` (:func:`plant_norm`).

Module order: after :mod:`foilc_hil.design.trial_operator` and :mod:`foilc_hil.design.admission`, before
:mod:`foilc_hil.design.gradient`.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from foilc_hil.config import DivergentFilterPolicy, FractionalMemory, LawKind, NoilcConfig
from foilc_hil.design.admission import admit
from foilc_hil.design.certificate_record import (
    BoundClaim,
    Bounds,
    CertificateAction,
    CertificateMethod,
    Certificates,
    MonotoneVerdict,
    NoilcWeights,
    PlantCertificate,
    Proof,
)
from foilc_hil.design.certificates import ScaledVerdict
from foilc_hil.design.lifted import LawStructure, dense_block_toeplitz, markov_blocks
from foilc_hil.design.map_norms import CONTRACTION_LIMIT, matrix_certificate
from foilc_hil.design.models import DiscreteModel, Uncertainty, uncertainty_vertices
from foilc_hil.design.record import Design
from foilc_hil.design.trial_operator import TrialOperator
from foilc_hil.errors import InputError
from foilc_hil.progress import as_step

__all__ = [
    "DENSE_LIMIT",
    "STRUCTURED_METHOD",
    "LiftedDesign",
    "LiftedUpdate",
    "Realization",
    "certify_lifted",
    "certify_noilc",
    "lifted_plant",
    "noilc_gain",
    "noilc_update",
    "noilc_weights",
    "plant_norm",
    "plant_operator",
    "plant_realization",
    "trial_map",
]

#: ``r`` recorded by a NOILC design: the law has no fractional term.
UNUSED_ORDER = 1.0
#: Up to this many learnable samples the trial maps are certified densely (exact eigenvalues and SVD, a few
#: milliseconds); beyond, by the structured test, cheaper already at a few hundred samples.
DENSE_LIMIT = 150
#: How the structured test computes a norm (module notes); a certificate's ``norm_2_method`` names it with the bracket.
STRUCTURED_METHOD = "structured exact, Cholesky test of the dilation through the state-space form"
#: ``spectral_radius_method`` when the 2-norm bounds the radius.
BY_NORM = "upper bound: the induced 2-norm"
#: ``spectral_radius_method`` when the 2-norm of the similar map bounds it (module notes).
BY_SIMILAR = "upper bound: the induced 2-norm of a similar map"
#: Largest trial whose Q-filter input map is certified densely when the filter has no state-space form.
Q_FILTER_DENSE_LIMIT = 2000
#: Lanczos steps of :meth:`_PlantMaps.estimate`.
ESTIMATE_STEPS = 6
#: Relative width of :func:`plant_norm`'s bisection: the weights and the step come from it.
PLANT_NORM_TOLERANCE = 1e-13


@dataclass(frozen=True)
class Realization:
    """The causal system of a lifted plant ``G``: ``xi_(i+1) = A xi_i + B u_i``, ``y_i = C xi_i + D u_i``."""

    A: np.ndarray
    B: np.ndarray
    C: np.ndarray
    D: np.ndarray


def _delay_free(A: np.ndarray, B: np.ndarray, C_measured: np.ndarray, lead: int) -> Realization | None:
    """The plant block of a model augmented by ``lead`` delay states (:func:`~foilc_hil.design.models.
    augment_input_delay`'s layout, every uncertainty vertex's too), or ``None`` if ``(A, B)`` is not laid out so."""
    n, m = B.shape
    plant = n - lead * m
    if plant < 1 or np.any(C_measured[:, plant:]) or np.any(A[:plant, plant + m :]):
        return None
    shift = np.zeros((lead * m, n))
    for slot in range(lead - 1):
        shift[slot * m : (slot + 1) * m, plant + (slot + 1) * m : plant + (slot + 2) * m] = np.eye(m)
    newest = np.zeros((n, m))
    newest[n - m :] = np.eye(m)
    if not (np.array_equal(A[plant:], shift) and np.array_equal(B, newest)):
        return None
    A_p, B_p, C_p = A[:plant, :plant], A[:plant, plant : plant + m], C_measured[:, :plant]
    return Realization(A_p, B_p, C_p @ A_p, C_p @ B_p)


def plant_realization(A: np.ndarray, B: np.ndarray, C_measured: np.ndarray, lead: int) -> Realization:
    """The causal system whose lifted matrix is :func:`lifted_plant` (blocks ``C_measured A^(j + lead) B``).

    For a delay-augmented model the plant block alone (its ``lead`` delay states are the shift the lifted map
    already makes: ``C_measured A^(j + lead) B = C_p A_p^j B_p``), so the map has the plant's order; otherwise
    ``(A, B, C' A, C' B)`` with ``C' = C_measured A^lead``.
    """
    A, B, C_measured = (np.asarray(X, dtype=float) for X in (A, B, C_measured))
    if lead:
        reduced = _delay_free(A, B, C_measured, lead)
        if reduced is not None:
            return reduced
    ahead = C_measured @ np.linalg.matrix_power(A, lead)
    return Realization(A, B, ahead @ A, ahead @ B)


def plant_operator(A: np.ndarray, B: np.ndarray, C_measured: np.ndarray, n_samples: int, lead: int) -> TrialOperator:
    """``G`` of :func:`lifted_plant` as a :class:`~foilc_hil.design.trial_operator.TrialOperator` (``O(L)``)."""
    length = _length(n_samples, lead)
    system = plant_realization(A, B, C_measured, lead)
    return TrialOperator.causal(system.A, system.B, system.C, system.D, length)


def _length(n_samples: int, lead: int) -> int:
    length = n_samples - lead
    if length < 1:
        raise InputError(f"n_samples: must exceed the input delay {lead}, got {n_samples}")
    return length


def lifted_plant(A: np.ndarray, B: np.ndarray, C_measured: np.ndarray, n_samples: int, lead: int) -> np.ndarray:
    """``G`` (``(L p) x (L m)``, ``L = N - lead``): inputs ``u[0..L-1]`` to the errors they move, ``y[lead..N-1]``
    (dense: the small trials' certificates and the tests)."""
    return dense_block_toeplitz(markov_blocks(A, B, C_measured, lead, _length(n_samples, lead)))


def plant_norm(model: DiscreteModel, n_samples: int) -> float:
    """``||G||_2`` of the lifted nominal plant for trials of ``n_samples``: the structured test bisected to
    :data:`PLANT_NORM_TOLERANCE` (the middle of the final bracket)."""
    G = plant_operator(model.A, model.B, model.measured_output, n_samples, model.input_delay)
    square = G if G.shape[0] == G.shape[1] else G.transpose().product(G)
    bound = square.norm_bound(PLANT_NORM_TOLERANCE)
    if not math.isfinite(bound.upper):
        raise InputError("plant: the lifted plant's norm overflows over one trial")
    return bound.estimate if square is G else math.sqrt(bound.estimate)


@dataclass(frozen=True, eq=False)
class LiftedUpdate:
    """The learning update ``du[0..L-1] = right (left e[d..N-1])`` of a lifted law, ``L = right left``.

    NOILC: ``left = s q (G Fi)^T`` (the costate pass), ``right = Fi`` (the Riccati feedback pass); gradient ILC:
    ``left = beta G^T``, ``right = I``. ``I - left G_v right`` is then similar to ``I - L G_v``, whose spectrum is
    that of the trial map ``I - G_v L`` (the spectral radius bound of the module notes).
    """

    left: TrialOperator
    right: TrialOperator

    @property
    def length(self) -> int:
        """``L``, samples of the update."""
        return self.left.length

    def apply(self, error: np.ndarray) -> np.ndarray:
        """``du = L e`` for ``e`` of shape ``(L, p)``: ``(L, m)``."""
        return self.right.apply(self.left.apply(error))

    def operator(self) -> TrialOperator:
        """``L`` as one operator."""
        return self.right.product(self.left)

    def dense(self) -> np.ndarray:
        """``L`` as a dense ``(L m) x (L p)`` matrix."""
        length, p = self.length, self.left.shape[1]
        unit = np.eye(length * p).reshape(length, p, length * p)
        return np.asarray(self.apply(unit).reshape(-1, length * p))


def noilc_weights(model: DiscreteModel, config: NoilcConfig, n_samples: int) -> NoilcWeights:
    """The absolute weights of ``law.noilc`` on ``model`` for trials of ``n_samples`` (module notes)."""
    scale = plant_norm(model, n_samples) ** 2
    return NoilcWeights(q=config.q, r=config.r_relative * scale * config.q, r_relative=config.r_relative)


def noilc_update(model: DiscreteModel, weights: NoilcWeights, n_samples: int) -> LiftedUpdate:
    """``weights.scale L``, ``L = (q G^T G + r I)^-1 q G^T``, in the state-space form (module notes)."""
    from foilc_hil.design.lifted_kernel import noilc_riccati

    length = _length(n_samples, model.input_delay)
    system = plant_realization(model.A, model.B, model.measured_output, model.input_delay)
    A, B, C, D = (np.ascontiguousarray(X, dtype=float) for X in (system.A, system.B, system.C, system.D))
    gains, inverses = noilc_riccati(A, B, C, D, weights.q, weights.r, length)
    # any S with S S^T = W^-1 factors M^-1 = F^-1 W^-1 F^-T = Fi Fi^T with Fi = F^-1 S: the Cholesky factor of W^-1
    root = np.linalg.cholesky(inverses)
    closed = np.ascontiguousarray(system.A - system.B @ gains)
    driven = np.ascontiguousarray(system.B @ root)

    def causal(C: np.ndarray, D: np.ndarray) -> TrialOperator:
        m = root.shape[2]
        return TrialOperator(
            closed, driven, np.ascontiguousarray(C), np.zeros((length, 0, 0)), np.zeros((length, 0, m)),
            np.zeros((length, C.shape[1], 0)), np.ascontiguousarray(D),
        )

    # Fi: x_(i+1) = (A - B K_i) x_i + B S_i v_i, du_i = -K_i x_i + S_i v_i. G Fi runs the plant on du from the same
    # zero state, so its state IS x (the plant's state under du): one state, output (C - D K_i) x_i + D S_i v_i.
    Fi = causal(-gains, root)
    plant_fi = causal(system.C - system.D @ gains, system.D @ root)
    return LiftedUpdate(plant_fi.transpose().scaled(weights.q * weights.scale), Fi)


def noilc_gain(model: DiscreteModel, weights: NoilcWeights, n_samples: int) -> np.ndarray:
    """``weights.scale L`` as a dense ``(L m) x (L p)`` matrix (the robustness draws' dense maps)."""
    return noilc_update(model, weights, n_samples).dense()


def trial_map(
    A: np.ndarray, B: np.ndarray, model: DiscreteModel, gain: np.ndarray, law: LawStructure
) -> tuple[np.ndarray, str]:
    """The dense map the law runs on at plant ``(A, B)``: the error map, or with a Q-filter the input map."""
    n, lead = law.n_samples, law.lead
    C = model.measured_output
    if law.q_filter is None:
        return np.eye(gain.shape[1]) - lifted_plant(A, B, C, n, lead) @ gain, "error"
    m, p = model.n_inputs, model.n_outputs
    # u_k = Q_f u_{k-1} + L_full e_{k-1}, e = y_r - G_y u: L_full acts on e[lead:] and fills u[:N-lead].
    full = np.zeros((n * m, n * p))
    full[: (n - lead) * m, lead * p :] = gain
    G_y = dense_block_toeplitz(markov_blocks(A, B, C, 0, n))
    return np.kron(law.q_filter, np.eye(m)) - full @ G_y, "input (Q-filter)"


def _q_filter_operator(q_filter: object, n_samples: int, channels: int) -> TrialOperator | None:
    """The law's Q-filter on the trial as a trial operator, each channel filtered alike: ``H^T H`` (zero phase) or
    ``H`` (causal) with ``H`` the state-space form of one pass; ``None`` when the filter has none."""
    realization = getattr(getattr(q_filter, "filter", None), "realization", None)
    if realization is None:
        return None
    system = realization()
    eye = np.eye(channels)
    H = TrialOperator.causal(
        np.kron(eye, system.A), np.kron(eye, system.B), np.kron(eye, system.C), np.kron(eye, system.D), n_samples
    )
    return H if str(getattr(q_filter, "phase", "zero")) == "causal" else H.transpose().product(H)


def _padded(X: TrialOperator, total: int) -> TrialOperator:
    """``X`` on the first ``X.length`` samples of a trial of ``total``, zero on the rest (inputs and outputs)."""
    extra = total - X.length

    def grow(Y: np.ndarray) -> np.ndarray:
        return np.ascontiguousarray(np.concatenate([Y, np.zeros((extra, *Y.shape[1:]))]))

    return TrialOperator(*(grow(Y) for Y in (X.Af, X.Bf, X.Cf, X.Ab, X.Bb, X.Cb, X.D)))


class _PlantMaps:
    """The trial maps of a lifted law at one plant ``(A, B)``, for every scale ``s`` of its update ``L``.

    The maps are affine in ``s`` -- ``I - s G_v L`` (error map), ``Q_f - s L_full G_y`` (input map with a Q-filter),
    ``I - s left G_v right`` (similar to the error map) -- so their ``s``-free parts are composed once, here, and a
    scale costs a sum, not a product of operators. Short trials take the dense path (module notes).
    """

    def __init__(
        self, update: LiftedUpdate, model: DiscreteModel, A: np.ndarray, B: np.ndarray, law: LawStructure,
        shared: _Shared,
    ) -> None:
        self.update, self.model, self.A, self.B, self.law, self.shared = update, model, A, B, law, shared

    @property
    def dense(self) -> bool:
        """Whether the trial is short enough for dense maps (:data:`DENSE_LIMIT`)."""
        return self.law.n_samples - self.law.lead <= DENSE_LIMIT

    @functools.cached_property
    def plant(self) -> TrialOperator:
        """``G_v``."""
        return plant_operator(self.A, self.B, self.model.measured_output, self.law.n_samples, self.law.lead)

    @functools.cached_property
    def step(self) -> TrialOperator:
        """``G_v L`` (no Q-filter) or ``L_full G_y`` padded to the whole trial (with one)."""
        if self.law.q_filter is None:
            return self.plant.product(self.shared.operator)
        return _padded(self.shared.operator.product(self.plant), self.law.n_samples)

    @functools.cached_property
    def similar_step(self) -> TrialOperator:
        """``left G_v right`` (module notes: the spectrum of the error map)."""
        return self.update.left.product(self.plant.product(self.update.right))

    def trial(self, scale: float) -> TrialOperator | None:
        """The map at ``scale``; ``None`` when the Q-filter has no state-space form."""
        first = self.shared.first
        return None if first is None else first.plus(self.step.scaled(-scale))

    def certificate(self, scale: float) -> PlantCertificate:
        """Spectral radius and 2-norm at ``scale``, with what they prove (module notes)."""
        trial = None if self.dense else self.trial(scale)
        if self.dense or (trial is None and self.law.n_samples <= Q_FILTER_DENSE_LIMIT):
            entry = matrix_certificate(*trial_map(self.A, self.B, self.model, scale * self.shared.dense_gain, self.law))
            verdict = _verdict(entry.norm_2, entry.norm_2)
            exact = BoundClaim.EXACT if entry.norm_2_method == "dense" else BoundClaim.UPPER
            return replace(entry, proof=Proof(exact, exact, verdict, CertificateMethod.DENSE))
        kind = "error" if self.law.q_filter is None else "input (Q-filter)"
        if trial is None:
            method = "inconclusive at bound inf (a Q-filter without a state-space form, on a long trial)"
            proof = Proof(BoundClaim.UPPER, BoundClaim.UPPER, MonotoneVerdict.INCONCLUSIVE, CertificateMethod.DENSE)
            return PlantCertificate("", kind, math.inf, math.inf, method, method, proof=proof)
        bound = trial.norm_bound(decide_at=CONTRACTION_LIMIT)
        norm, radius, method = bound.upper, bound.upper, BY_NORM
        if not norm < 1.0 and self.law.q_filter is None:
            similar = self.shared.identity.plus(self.similar_step.scaled(-scale)).norm_bound(decide_at=1.0).upper
            radius, method = (norm, BY_NORM) if norm <= similar else (similar, BY_SIMILAR)
        if not radius < 1.0:
            method = f"inconclusive at bound {radius:.6g} ({method})"
        norm_method = (
            f"upper bound ({STRUCTURED_METHOD}: {bound.lower:.9g} <= ||T|| <= {bound.upper:.9g}; {bound.tests} tests)"
        )
        verdict = _verdict(bound.upper, bound.lower)
        proof = Proof(BoundClaim.UPPER, BoundClaim.UPPER, verdict, CertificateMethod.STRUCTURED)
        return PlantCertificate("", kind, radius, norm, norm_method, method, proof=proof)

    def estimate(self, scale: float) -> PlantCertificate:
        """:meth:`certificate`'s numbers, cheaply, for the search of a scale (:func:`~foilc_hil.design.admission.
        admit`): a long trial's 2-norm from below by :data:`ESTIMATE_STEPS` Lanczos steps (within about 1 % on these
        maps: enough to place the minimum of a convex function of the scale); a short trial's certificate."""
        trial = None if self.dense else self.trial(scale)
        if trial is None:
            return self.certificate(scale)
        norm = trial.lanczos_lower(ESTIMATE_STEPS)
        return PlantCertificate("", "estimate", norm, norm, "lower bound (Lanczos)")


def _verdict(upper: float, lower: float) -> MonotoneVerdict:
    """Monotone when the upper bound is at most the contraction limit, not monotone when the lower bound is above
    it, else inconclusive."""
    if upper <= CONTRACTION_LIMIT:
        return MonotoneVerdict.MONOTONE
    return MonotoneVerdict.NOT_MONOTONE if lower > CONTRACTION_LIMIT else MonotoneVerdict.INCONCLUSIVE


class _Shared:
    """What the plants' maps of one law share: ``L`` as one operator, the identity or the Q-filter the maps start
    from, and ``L`` dense for short trials (each made on first use)."""

    def __init__(self, update: LiftedUpdate, law: LawStructure, channels: int) -> None:
        self.update, self.law, self.channels = update, law, channels

    @functools.cached_property
    def operator(self) -> TrialOperator:
        """``L``."""
        return self.update.operator()

    @functools.cached_property
    def identity(self) -> TrialOperator:
        """``I`` on the learnable samples."""
        return TrialOperator.identity(self.update.length, self.channels)

    @functools.cached_property
    def first(self) -> TrialOperator | None:
        """What the map is before the learning term: ``I``, or the Q-filter on the whole trial (``None``: it has
        no state-space form)."""
        if self.law.q_filter is None:
            return self.identity
        return _q_filter_operator(self.law.q_filter, self.law.n_samples, self.channels)

    @functools.cached_property
    def dense_gain(self) -> np.ndarray:
        """``L`` dense."""
        return self.update.dense()


def _certificates(
    verdict: ScaledVerdict, law: LawStructure, require_monotonic: bool, designed: Bounds, addition: Mapping[str, Any]
) -> Certificates:
    """The typed certificates of ``verdict`` (``designed``: the bounds at scale 1)."""
    return Certificates(
        spectral_radius=verdict.spectral_radius,
        norm_2=verdict.norm_2,
        monotonic_required=require_monotonic,
        n_samples=law.n_samples,
        lead=law.lead,
        fractional_memory=FractionalMemory(law.fractional_memory),
        filter_first_weight=1.0,
        naive_without_filter=designed,
        designed=designed,
        vertices=len(verdict.plants) - 1,
        q_filter=law.q_filter is not None,
        action=CertificateAction.NONE,
        gain_scale=verdict.scale,
        asymptotic=verdict.asymptotic,
        monotonic=verdict.monotonic,
        plants=verdict.plants,
        **addition,
    )


@dataclass(frozen=True)
class LiftedDesign:
    """What :func:`certify_lifted` needs of a lifted law: its update ``L`` (the law runs ``s L``), what its
    certificates add at scale ``s`` (``{"noilc": weights}``, ``{"gradient": step}``), its kind, and the rule's
    settings."""

    kind: LawKind
    update: LiftedUpdate
    addition: Callable[[float], Mapping[str, Any]]
    policy: DivergentFilterPolicy = DivergentFilterPolicy.RESCALE
    require_monotonic: bool = True
    growth_horizon: int = 10


def certify_lifted(model: DiscreteModel, uncertainty: Uncertainty, lifted: LiftedDesign, law: LawStructure) -> Design:
    """The design of a lifted feedforward law ``u_k = u_{k-1} + s L e_{k-1}`` (NOILC, gradient): certificates of
    its trial map at the nominal plant and every vertex (module notes), under the rule of
    :mod:`foilc_hil.design.admission` (``s = 1`` unless it had to rescale).

    Raises
    ------
    foilc_hil.errors.ConvergenceCertificateError
        When the rule refuses the design (exit 3).
    """
    if law.lead != model.input_delay:
        raise InputError(f"law: its lead {law.lead} must be the model's input delay {model.input_delay}")
    plants = [("nominal", model.A, model.B)]
    plants += [
        (f"vertex {i}", model.A + dA, model.B + dB) for i, (dA, dB) in enumerate(uncertainty_vertices(uncertainty), 1)
    ]

    shared = _Shared(lifted.update, law, model.n_outputs)
    maps = [(name, _PlantMaps(lifted.update, model, A_v, B_v, law, shared)) for name, A_v, B_v in plants]

    @functools.cache
    def evaluate(scale: float) -> ScaledVerdict:
        return ScaledVerdict(scale, tuple(each.certificate(scale).named(name) for name, each in maps))

    @functools.cache
    def estimate(scale: float) -> ScaledVerdict:
        return ScaledVerdict(scale, tuple(each.estimate(scale).named(name) for name, each in maps))

    admission = admit(
        evaluate,
        law=str(lifted.kind),
        policy=lifted.policy,
        require_monotonic=lifted.require_monotonic,
        growth_horizon=lifted.growth_horizon,
        estimate=estimate,
    )
    designed = evaluate(1.0)
    chosen = admission.verdict
    certificates = replace(
        _certificates(chosen, law, lifted.require_monotonic, Bounds(designed.spectral_radius, designed.norm_2),
                      lifted.addition(chosen.scale)),
        action=admission.action,
        rescale_criterion=admission.criterion,
        growth_bound=admission.growth_bound,
    )
    P = np.zeros((model.n_inputs, model.n_states + model.n_outputs))
    return Design(
        law=lifted.kind,
        model=model,
        uncertainty=uncertainty,
        P=P,
        kp=0.0,
        r=UNUSED_ORDER,
        gain_scale=chosen.scale,
        certificates=certificates,
    )


@as_step("NOILC gain and certificates")
def certify_noilc(
    model: DiscreteModel,
    uncertainty: Uncertainty,
    config: NoilcConfig,
    law: LawStructure,
    *,
    require_monotonic: bool,
    policy: DivergentFilterPolicy = DivergentFilterPolicy.RESCALE,
    growth_horizon: int = 10,
) -> Design:
    """The NOILC design for ``model``: its weights, and certificates of the law as it runs (nominal, vertices),
    rescaled or refused by the rule of :mod:`foilc_hil.design.admission`."""
    weights = noilc_weights(model, config, law.n_samples)
    base = noilc_update(model, weights, law.n_samples)
    lifted = LiftedDesign(
        LawKind.NOILC,
        base,
        lambda scale: {"noilc": replace(weights, scale=scale)},
        policy,
        require_monotonic,
        growth_horizon,
    )
    return certify_lifted(model, uncertainty, lifted, law)
