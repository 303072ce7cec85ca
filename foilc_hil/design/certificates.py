"""Convergence certificates of the learning law AS IT RUNS: the lifted trial-to-trial map (errata item 4).

Theorem 1 certifies the Roesser model (18), in which the learning gain multiplies ``E`` as if ``E`` were the
error. The law that runs multiplies the Grünwald–Letnikov-discretised ``E = (I + kp D^r) e``, whose newest
sample carries the weight ``1 + kp h^-r`` (hundreds to thousands at millisecond steps), so a gain certified on
(18) can diverge once the filter is switched on. This module certifies the law with the filter (and the
input delay, and an optional Q-filter) on whole trials.

The maps certified are those of :mod:`foilc_hil.design.error_map` (its notes): the error map ``T = I - H F'``
without a Q-filter, the input map ``M`` with one; the norms come from :mod:`foilc_hil.design.map_norms`.

What is exact and what is estimated
-----------------------------------
* Spectral radius of ``T`` (asymptotic convergence): EXACT. In "controllable" mode ``F'`` is lower-triangular
  Toeplitz, so ``T`` is block lower-triangular Toeplitz and its eigenvalues are those of ``I - h_0 w_0``. In
  "trial" mode ``F`` is lower-triangular Toeplitz except its first few columns (the Caputo correction for
  ``e(0)`` and, for ``r > 1``, ``e'(0)``), which makes ``T`` block lower triangular with one small leading block;
  the eigenvalues are those of that block and of the diagonal block
  ``I - h_0 w_0`` (``w_0 = 1 + kp h^-r``). The Toeplitz-plus-columns decomposition of ``F`` is verified on a
  random probe against ``FractionalPD.apply``; if it does not hold, ``T`` is built densely instead.
* Induced 2-norm of ``T`` (monotonic convergence in l2), first: a RIGOROUS UPPER BOUND from the truncated
  Toeplitz symbol (:meth:`~foilc_hil.design.error_map.LiftedErrorMap.symbol_upper_bound`: the sup of the symbol on
  a fine grid, widened by its Lipschitz constant, plus the correction columns' Frobenius norm). When that bound is
  below 1 it is the certificate (``norm_2_method = "upper bound (truncated Toeplitz symbol)"``; ``norm_2`` is then
  the bound, at most a few 1e-5 above the exact finite-trial norm on the shipped configs) and nothing iterative
  runs. Otherwise a
  power iteration's ``||T v||`` (a unit ``v``: a rigorous LOWER bound) at or above 1 settles the verdict, not
  monotonic (``"lower bound (power iteration; the symbol bound is not below 1)"``). Only between the two, for
  the exact value: ARPACK (``scipy.sparse.linalg.svds``) with
  FFT matrix-vector products, to a relative tolerance of 1e-8 -- an iterative estimate of the exact finite-trial
  norm, not a bound. For trials short enough (``L p <= DENSE_LIMIT``) it is a dense SVD instead; if ARPACK does
  not converge, a dense SVD up to ``DENSE_FALLBACK_LIMIT`` rows, else no certificate. When the spectral radius
  is already ``>= 1`` the norm is not needed for the verdict: ``norm_2`` is then a lower bound (the larger of
  the radius and a short power iteration).
* The rescale search of :func:`certify` evaluates tens of scales of ``p2`` at every plant; for single-output
  Toeplitz maps the blocks are affine in the scale, so :class:`_ScaledErrorMap` computes each plant's symbol once
  and a scale costs one pass over the grid -- the same bounds, not an approximation of them.
* ``norm_2_symbol``: the sup over a frequency grid of the Toeplitz symbol of ``T`` (the long-trial limit of the
  2-norm of the Toeplitz part), for information.
* With a Q-filter: up to :data:`DENSE_LIMIT` rows the dense map (exact); beyond, the structured certificate of
  :mod:`foilc_hil.design.qmap` in bounded time (a symbol bound plus an exact test of the finite-length
  correction; the exact radius of a causal filter's map; each plant's ``proof`` says what is proved and how;
  ``docs/certificates.md``). The rescale search runs on that module's cheap estimates and certifies the scale it
  picks on the whole trial.
* Uncertainty vertices are FROZEN (constant ``Delta``) plants; a time-varying ``Delta(t)`` makes the map
  non-Toeplitz and is covered only by the LMI of Theorem 1 and by simulation.

Module order: after :mod:`foilc_hil.design.certificate_record` (whose typed
:class:`~foilc_hil.design.certificate_record.Certificates` this module fills in), :mod:`foilc_hil.design.lifted`,
:mod:`foilc_hil.design.map_norms`, :mod:`foilc_hil.design.error_map` and :mod:`foilc_hil.design.qmap`, before
:mod:`foilc_hil.design.lmi` (which certifies the gain it solves for).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from foilc_hil.config import DivergentFilterPolicy, LawKind
from foilc_hil.design.certificate_record import (
    BoundClaim,
    Bounds,
    CertificateAction,
    CertificateMethod,
    Certificates,
    GrowthBound,
    MonotoneVerdict,
    PlantCertificate,
    Proof,
    PTypeGain,
)
from foilc_hil.design.error_map import dense_input_map, lifted_error_map
from foilc_hil.design.lifted import (
    SYMBOL_GRID_CAP,
    LawStructure,
    LoopPlant,
    grid_bound,
    moments,
    symbol_grid,
)
from foilc_hil.design.map_norms import (
    CONTRACTION_LIMIT,
    DENSE_LIMIT,
    operator_norm,
    power_norm,
    radius_of,
)
from foilc_hil.design.models import DiscreteModel, Uncertainty, uncertainty_vertices
from foilc_hil.design.ptype import frequency_bound
from foilc_hil.design.qmap import (
    INPUT_MAP,
    EdgeProxy,
    StructuredInputMap,
    input_map_certificate,
    structured_input_map,
    triangular_radius,
    unstructured_certificate,
)
from foilc_hil.design.record import Design
from foilc_hil.errors import ConvergenceCertificateError
from foilc_hil.progress import as_step

__all__ = [
    "Certification",
    "PTypeScales",
    "ScaledVerdict",
    "certify",
    "certify_as_given",
    "certify_p_type",
    "map_certificate",
]


def _error_map_certificate(loop: LoopPlant, law: LawStructure) -> PlantCertificate:
    """:func:`map_certificate` without a Q-filter: the exact error map ``T``."""
    T = lifted_error_map(loop, law)
    if not np.all(np.isfinite(T.H.blocks)):
        return PlantCertificate("", "error", math.inf, math.inf, "overflow")
    radius = T.spectral_radius()
    bound = T.symbol_upper_bound() if radius < 1.0 and T.size > DENSE_LIMIT and T.F is not None else math.inf
    if radius >= 1.0:
        norm = max(radius, power_norm(T.size, T.matvec, T.rmatvec))
        method = "lower bound (spectral radius >= 1; power iteration)"
    elif bound < 1.0:  # conclusive: monotonic, and no iterative or dense SVD is needed
        norm, method = bound, "upper bound (truncated Toeplitz symbol)"
    else:
        # a cheap lower bound first: above one it settles the verdict (not monotonic) without ARPACK, which the
        # rescale search would otherwise run at every scale past the admissible interval (seconds each at N = 6000)
        lower = power_norm(T.size, T.matvec, T.rmatvec, enough=1.0) if T.size > DENSE_LIMIT else 0.0
        if lower >= 1.0:
            norm, method = lower, "lower bound (power iteration; the symbol bound is not below 1)"
        else:
            norm, method = operator_norm(T.size, T.matvec, T.rmatvec, T.to_dense, T.norm_upper_bound)
    symbol = T.symbol_norm() if T.F is not None else None
    return PlantCertificate("", "error", radius, norm, method, norm_2_symbol=symbol)


def _dense_input_certificate(loop: LoopPlant, law: LawStructure) -> PlantCertificate:
    """The Q-filtered input map of a short trial, densely: exact 2-norm and spectral radius."""
    assert law.q_filter is not None
    F = law.filter().dense()
    M = dense_input_map(loop.A, loop.B, loop.C_measured, loop.p1, loop.p2, F, law.q_filter.matrix(), law.lead)
    if not np.all(np.isfinite(M)):
        return PlantCertificate("", INPUT_MAP, math.inf, math.inf, "overflow", "overflow")
    norm, radius = float(np.linalg.norm(M, 2)), radius_of(M)
    verdict = MonotoneVerdict.MONOTONE if norm <= CONTRACTION_LIMIT else MonotoneVerdict.NOT_MONOTONE
    proof = Proof(BoundClaim.EXACT, BoundClaim.EXACT, verdict, CertificateMethod.DENSE)
    return PlantCertificate("", INPUT_MAP, radius, norm, "dense", "dense", proof=proof)


def _input_map_certificate(
    loop: LoopPlant, law: LawStructure, scaled: StructuredInputMap | None = None, scale: float = 1.0
) -> PlantCertificate:
    """:func:`map_certificate` with a Q-filter: the input map ``M``, densely for short trials, else in the
    structured form of :mod:`foilc_hil.design.qmap` (``scaled``: that form of the unscaled loop, ``scale`` the
    scale of ``p2`` to certify), else -- a map without that structure -- inconclusive."""
    assert law.q_filter is not None
    if law.n_samples * loop.B.shape[1] <= DENSE_LIMIT:
        return _dense_input_certificate(loop.scaled(scale), law)
    structured = scaled if scaled is not None else structured_input_map(loop, law)
    if structured is None:
        return unstructured_certificate(loop.scaled(scale), law)
    return input_map_certificate(structured, scale, exact=law.exact)


def map_certificate(loop: LoopPlant, law: LawStructure) -> PlantCertificate:
    """Spectral radius and induced 2-norm of the lifted trial-to-trial map for one plant (module notes).

    Without ``law.q_filter`` the error map ``T``, with it the input map ``M``. When the spectral radius is not
    below one the 2-norm is not computed: ``norm_2`` then holds a lower bound (``||T|| >= rho(T)``) and
    ``norm_2_method`` says so. The result's ``plant`` name is empty (the caller names it).
    """
    if law.q_filter is None:
        return _error_map_certificate(loop, law)
    return _input_map_certificate(loop, law)


@dataclass(frozen=True)
class _ScaledErrorMap:
    """The error map ``T(s) = I - s H F'`` of one single-output plant for every scale ``s`` of ``p2`` at once.

    The rescale search of :func:`certify` evaluates tens of scales at every plant. ``H`` is linear in ``p2``, so
    the Toeplitz blocks are ``tau_j(s) = delta_j - s c_j`` with ``c = h * w`` (``h`` the unscaled Markov
    parameters, ``w`` the filter's weights) computed once, and so is their spectrum on the symbol grid: a scale
    then costs one pass over that grid. The numbers are those of
    :meth:`~foilc_hil.design.error_map.LiftedErrorMap.spectral_radius` and
    :meth:`~foilc_hil.design.error_map.LiftedErrorMap.symbol_upper_bound` (the same rigorous :func:`grid_bound`,
    with ``S_1``, ``S_2`` of ``T(s)`` equal to ``s`` times those of ``c``), for pure Toeplitz maps (no correction
    columns) longer than :data:`DENSE_LIMIT`; anything else, and any scale whose bound is not below one, takes
    :func:`map_certificate`.
    """

    c: np.ndarray  # (L,)
    # the rfft of c on the symbol grid (|symbol| is even in theta: half the grid suffices) as its real part and
    # squared modulus: |1 - s C|^2 = 1 - 2 s Re C + s^2 |C|^2, one fused pass per scale
    real: np.ndarray
    modulus2: np.ndarray
    grid: int
    c_moments: tuple[float, float]  # sum_j j |c_j|, sum_j j^2 |c_j|: S_1 and S_2 of T(s) are s times these
    info_spectrum: np.ndarray  # fft of c on LiftedErrorMap.symbol_norm's grid

    @staticmethod
    def of(loop: LoopPlant, law: LawStructure) -> _ScaledErrorMap | None:
        """The precomputed map, or ``None`` where :func:`map_certificate` must run (see the class notes)."""
        from scipy.fft import fft, rfft

        if law.q_filter is not None or loop.C_measured.shape[0] != 1 or loop.p2.shape != (1, 1):
            return None
        T = lifted_error_map(loop, law)
        if T.F is None or T.F.corrections.shape[1] or T.size <= DENSE_LIMIT or not np.all(np.isfinite(T.H.blocks)):
            return None
        taus = T.taus()[:, 0, 0]
        c = -taus  # tau_j = delta_j - c_j
        c[0] += 1.0
        _, s1, s2 = moments(np.abs(c))
        grid = symbol_grid(T.length, moments(np.abs(taus)), SYMBOL_GRID_CAP)  # s = 1: the largest moments
        info = fft(c, n=max(4096, 2 * T.length))
        spectrum = rfft(c, n=grid)
        return _ScaledErrorMap(
            c, np.ascontiguousarray(spectrum.real), np.abs(spectrum) ** 2, grid, (s1, s2), np.asarray(info)
        )

    def certificate(self, scale: float, loop: LoopPlant, law: LawStructure) -> PlantCertificate | None:
        """The certificate at ``scale`` when it is conclusive -- the symbol bound below one, or else a power
        iteration's lower bound at or above one -- else ``None`` (``loop``, ``law``: the unscaled map's)."""
        radius = abs(1.0 - scale * float(self.c[0]))
        if radius >= 1.0:
            return None
        peak = math.sqrt(max(0.0, float(np.max(scale * scale * self.modulus2 - 2.0 * scale * self.real)) + 1.0))
        taus = -scale * self.c
        taus[0] += 1.0
        sums = (float(np.sum(np.abs(taus))), scale * self.c_moments[0], scale * self.c_moments[1])
        bound = grid_bound(peak, self.grid, sums)
        symbol = float(np.max(np.abs(1.0 - scale * self.info_spectrum)))
        if bound < 1.0:
            return PlantCertificate(
                "", "error", radius, bound, "upper bound (truncated Toeplitz symbol)", norm_2_symbol=symbol
            )
        T = lifted_error_map(loop.scaled(scale), law)
        lower = power_norm(T.size, T.matvec, T.rmatvec, enough=1.0)
        if lower < 1.0:  # inconclusive: the exact norm decides (map_certificate)
            return None
        method = "lower bound (power iteration; the symbol bound is not below 1)"
        return PlantCertificate("", "error", radius, lower, method, norm_2_symbol=symbol)


@dataclass(frozen=True)
class Certification:
    """What :func:`certify` hands back: the gain that runs, its scale and the certificates."""

    P: np.ndarray
    gain_scale: float
    certificates: Certificates


def _plants(model: DiscreteModel, uncertainty: Uncertainty) -> list[tuple[str, np.ndarray, np.ndarray]]:
    plants = [("nominal", model.A, model.B)]
    for index, (dA, dB) in enumerate(uncertainty_vertices(uncertainty), start=1):
        plants.append((f"vertex {index}", model.A + dA, model.B + dB))
    return plants


@dataclass(frozen=True)
class ScaledVerdict:
    """The certificates of one gain scale ``s`` at every plant (nominal first, then the vertices): what the rescale
    rule of every law reads (here for the 2D laws; :mod:`foilc_hil.design.admission` for p-type, noilc, gradient)."""

    scale: float
    plants: tuple[PlantCertificate, ...]

    def _worst(self, key: str) -> float:
        values = [float(getattr(entry, key)) for entry in self.plants]
        return max(values) if values and all(math.isfinite(v) for v in values) else math.inf

    @property
    def spectral_radius(self) -> float:
        """The worst-case spectral radius (``inf`` when one is not finite)."""
        return self._worst("spectral_radius")

    @property
    def norm_2(self) -> float:
        """The worst-case induced 2-norm."""
        return self._worst("norm_2")

    @property
    def asymptotic(self) -> bool:
        """Certified to converge."""
        return self.spectral_radius < 1.0

    @property
    def monotonic(self) -> bool:
        """Certified to converge monotonically in l2."""
        return self.asymptotic and self.norm_2 <= CONTRACTION_LIMIT

    def admissible(self, require_monotonic: bool) -> bool:
        """What the rule asks of it."""
        return self.monotonic if require_monotonic else self.asymptotic

    def bounds(self) -> Bounds:
        return Bounds(self.spectral_radius, self.norm_2)


class _Evaluator:
    """The lifted maps of one gain, nominal and at the uncertainty vertices, per scale of ``p2`` (cached)."""

    def __init__(self, model: DiscreteModel, uncertainty: Uncertainty, P: np.ndarray, law: LawStructure) -> None:
        n = model.n_states
        self.law = law
        self.loops = [
            (name, LoopPlant(A_v, B_v, model.measured_output, P[:, :n], P[:, n:]))
            for name, A_v, B_v in _plants(model, uncertainty)
        ]
        self._cache: dict[float, ScaledVerdict] = {}
        self._scaled: dict[tuple[int, float, float, str], _ScaledErrorMap | None] = {}
        self._structured: dict[tuple[int, float, float, str], StructuredInputMap | None] = {}
        self._proxies: dict[tuple[int, float, float, str], EdgeProxy | None] = {}

    def at(self, scale: float, law: LawStructure | None = None) -> ScaledVerdict:
        """The verdict with ``p2`` scaled by ``scale`` (for ``law``, default the law as it runs)."""
        if law is not None:
            return self._evaluate(scale, law)
        if scale not in self._cache:
            self._cache[scale] = self._evaluate(scale, self.law)
        return self._cache[scale]

    def _evaluate(self, scale: float, law: LawStructure) -> ScaledVerdict:
        return ScaledVerdict(scale, tuple(self._certificate(index, scale, law) for index in range(len(self.loops))))

    def _certificate(self, index: int, scale: float, law: LawStructure) -> PlantCertificate:
        """One plant's certificate: the precomputed scaled map where it is conclusive, else :func:`map_certificate`."""
        name, loop = self.loops[index]
        key = (index, law.kp, law.r, str(law.fractional_memory))
        if law.q_filter is not None:
            if law.n_samples * loop.B.shape[1] <= DENSE_LIMIT:
                return _input_map_certificate(loop, law, scale=scale).named(name)
            if key not in self._structured:
                self._structured[key] = structured_input_map(loop, law)
            return _input_map_certificate(loop, law, self._structured[key], scale).named(name)
        if key not in self._scaled:
            self._scaled[key] = _ScaledErrorMap.of(loop, law)
        scaled = self._scaled[key]
        fast = None if scaled is None else scaled.certificate(scale, loop, law)
        return (fast or map_certificate(loop.scaled(scale), law)).named(name)

    def _proxy(self, index: int) -> EdgeProxy | None:
        """The rescale search's estimate of plant ``index``'s Q-filtered map (``None``: no structured form, or a
        trial short enough to certify densely at every scale)."""
        loop = self.loops[index][1]
        law = self.law
        if law.q_filter is None or law.n_samples * loop.B.shape[1] <= DENSE_LIMIT:
            return None
        key = (index, law.kp, law.r, str(law.fractional_memory))
        if key not in self._structured:
            self._structured[key] = structured_input_map(loop, law)
        if key not in self._proxies:
            structured = self._structured[key]
            self._proxies[key] = None if structured is None else EdgeProxy(structured)
        return self._proxies[key]

    def estimate(self, scale: float, key: str) -> float:
        """The worst-case ``key`` at ``scale`` for the search: the certificates themselves where they are cheap
        (no Q-filter, short trials), else the Q-filtered maps' :class:`~foilc_hil.design.qmap.EdgeProxy` (the
        spectral radius of a causal filter's map exactly, from its diagonal)."""
        proxies = [self._proxy(index) for index in range(len(self.loops))]
        if any(proxy is None for proxy in proxies):
            return float(getattr(self.at(scale), key))
        values = []
        for index, proxy in enumerate(proxies):
            assert proxy is not None
            structured = self._structured[(index, self.law.kp, self.law.r, str(self.law.fractional_memory))]
            if key == "spectral_radius" and structured is not None and structured.triangular:
                values.append(triangular_radius(structured, scale))
            else:
                values.append(proxy.estimate(scale))
        return max(values) if all(math.isfinite(v) for v in values) else math.inf

    def admissible(self, scale: float, require_monotonic: bool) -> bool:
        """Whether ``scale`` looks admissible to the search's estimates (:meth:`estimate`)."""
        if self.estimate(scale, "spectral_radius") >= 1.0:
            return False
        return not require_monotonic or self.estimate(scale, "norm_2") <= CONTRACTION_LIMIT

    def objective(self, key: str) -> Callable[[float], float]:
        """The worst-case ``key`` estimate as a function of ``log(scale)`` (``1e300`` where it is not finite)."""

        def worst(log_scale: float) -> float:
            value = self.estimate(math.exp(log_scale), key)
            return value if math.isfinite(value) else 1e300

        return worst


def _record(
    evaluator: _Evaluator, chosen: ScaledVerdict, require_monotonic: bool, action: CertificateAction
) -> Certificates:
    """The typed certificates of the ``chosen`` verdict (the designed and naive ones for comparison)."""
    law = evaluator.law
    return Certificates(
        spectral_radius=chosen.spectral_radius,
        norm_2=chosen.norm_2,
        monotonic_required=require_monotonic,
        n_samples=law.n_samples,
        lead=law.lead,
        fractional_memory=law.fractional_memory,
        filter_first_weight=law.filter_first_weight,
        naive_without_filter=evaluator.at(1.0, law.without_filters()).bounds(),
        designed=evaluator.at(1.0).bounds(),
        vertices=len(evaluator.loops) - 1,
        q_filter=law.q_filter is not None,
        action=action,
        gain_scale=chosen.scale,
        asymptotic=chosen.asymptotic,
        monotonic=chosen.monotonic,
        plants=chosen.plants,
    )


def certify_as_given(
    model: DiscreteModel, uncertainty: Uncertainty, P: np.ndarray, law: LawStructure, *, require_monotonic: bool
) -> Certificates:
    """The certificates of gain ``P`` exactly as given, nominal and at the uncertainty vertices (no fix)."""
    evaluator = _Evaluator(model, uncertainty, np.asarray(P, dtype=float), law)
    return _record(evaluator, evaluator.at(1.0), require_monotonic, CertificateAction.NONE)


def _summary(designed: ScaledVerdict, law: LawStructure) -> str:
    return (
        f"spectral radius {designed.spectral_radius:.4g}, induced 2-norm {designed.norm_2:.4g} "
        f"(filter first weight 1 + kp h^-r = {law.filter_first_weight:.4g})"
    )


def _refuse(policy: DivergentFilterPolicy, summary: str) -> None:
    """Raise for the policies that do not rescale (``refuse``, and ``augment``, which is not implemented)."""
    if policy is DivergentFilterPolicy.REFUSE:
        raise ConvergenceCertificateError(
            f"the law as it runs is not certified to converge: {summary}; synthesis.on_divergent_filter=refuse"
        )
    if policy is DivergentFilterPolicy.AUGMENT:
        raise ConvergenceCertificateError(
            f"the law as it runs is not certified to converge: {summary}; 'augment' is not implemented, "
            "use synthesis.on_divergent_filter=rescale"
        )


def _best_scale(evaluator: _Evaluator, summary: str, require_monotonic: bool) -> tuple[ScaledVerdict, str]:
    """The scale of ``p2`` minimising the worst-case 2-norm (monotonic), else the worst spectral radius."""
    from scipy.optimize import minimize_scalar

    # The optimum sits near 1 / (filter gain * loop gain); search a window wide enough around it.
    low = math.log(min(1.0, 1e-3 / max(1.0, evaluator.law.filter_first_weight)))
    # 1. Monotonic: the worst-case 2-norm is convex in s and 1 at s = 0; take its minimiser.
    search = minimize_scalar(
        evaluator.objective("norm_2"), bounds=(low, 0.0), method="bounded", options={"xatol": 1e-2}
    )
    best = evaluator.at(math.exp(float(search.x)))
    if best.monotonic:
        return best, "monotonic"
    if require_monotonic:
        raise ConvergenceCertificateError(
            f"the law as it runs is not certified to converge monotonically: {summary}; no rescaling of p2 "
            f"in (0, 1] gives an induced 2-norm below 1 (best {best.norm_2:.6g} at scale {best.scale:.4g})"
        )
    # 2. Asymptotic only (monotonic not required, and not reachable): minimise the worst spectral radius.
    search = minimize_scalar(
        evaluator.objective("spectral_radius"), bounds=(low, 0.0), method="bounded", options={"xatol": 1e-2}
    )
    best = evaluator.at(math.exp(float(search.x)))
    if not best.asymptotic:
        raise ConvergenceCertificateError(
            f"the law as it runs is not certified to converge: {summary}; no rescaling of p2 in (0, 1] helps "
            f"(best worst-case spectral radius {best.spectral_radius:.6g} at scale {best.scale:.4g})"
        )
    return best, "asymptotic"


def _largest_admissible(evaluator: _Evaluator, best: ScaledVerdict, require_monotonic: bool) -> float:
    """Largest admissible scale (same criterion), by bisection on the search's estimates between the chosen scale
    and 1 (not admissible), the result certified as every chosen scale is (else the chosen scale itself)."""
    lo, hi = best.scale, 1.0
    for _ in range(40):
        if hi - lo <= 1e-2 * hi:
            break
        mid = math.sqrt(lo * hi)
        if evaluator.admissible(mid, require_monotonic):
            lo = mid
        else:
            hi = mid
    return lo if lo == best.scale or evaluator.at(lo).admissible(require_monotonic) else best.scale


@as_step("certificates of the law as it runs")
def certify(
    model: DiscreteModel,
    uncertainty: Uncertainty,
    P: np.ndarray,
    law: LawStructure,
    *,
    policy: DivergentFilterPolicy = DivergentFilterPolicy.RESCALE,
    require_monotonic: bool = True,
    growth_horizon: int = 10,
) -> Certification:
    """Certify the law with gain ``P`` as it runs (``law``), nominal and at the uncertainty vertices; fix or refuse.

    The law is admissible when the spectral radius is below one at every plant (asymptotic convergence) and, if
    ``require_monotonic``, the induced 2-norm too (monotonic convergence of the error in l2). Otherwise, by
    ``policy`` (``synthesis.on_divergent_filter``):

    ``rescale``
        scale ``p2`` by ``s`` in ``(0, 1]``. The worst-case 2-norm of ``I - s K`` is convex in ``s`` and equals
        one at ``s = 0``, so the scales with a monotonic certificate form an interval ``(0, s_max)``; we take the
        ``s`` that minimises the worst-case 2-norm (the fastest certified monotone contraction, bounded Brent
        search on ``log s``; the largest admissible ``s`` is reported too, by bisection). When no ``s`` gives a
        2-norm below one -- typical for ``r > 1``, where the fractional term's phase exceeds 90 degrees over a
        band of low frequencies, and whenever the Caputo corrections for ``e(0)``, ``e'(0)`` dominate -- and
        monotonicity is not required, we take the ``s`` minimising the worst-case spectral radius instead and
        report ``monotonic: false`` with the growth bound ``||T||_2^k`` over ``growth_horizon`` trials.
        ``P`` is returned with ``p2`` scaled.
    ``refuse``
        raise :class:`ConvergenceCertificateError`.
    ``augment``
        not available: designing on a model augmented with the filter's dynamics is not implemented; raises
        :class:`ConvergenceCertificateError` saying so (use ``rescale``).

    The certificate is of ``law.fractional_memory``'s operator and records it (the law refuses a design
    certified with another one).

    Raises
    ------
    foilc_hil.errors.ConvergenceCertificateError
        When the law is not certified and cannot be fixed (exit 3).
    """
    policy = DivergentFilterPolicy.parse(policy)
    P = np.asarray(P, dtype=float)
    evaluator = _Evaluator(model, uncertainty, P, law)
    designed = evaluator.at(1.0)
    if designed.admissible(require_monotonic):
        return Certification(P, 1.0, _record(evaluator, designed, require_monotonic, CertificateAction.NONE))
    summary = _summary(designed, law)
    _refuse(policy, summary)
    best, criterion = _best_scale(evaluator, summary, require_monotonic)
    scaled = P.copy()
    scaled[:, model.n_states :] = best.scale * P[:, model.n_states :]
    # ||T^k|| <= ||T||^k: a rigorous bound on how much the error's l2 norm can grow over the run.
    growth = GrowthBound(growth_horizon, best.norm_2**growth_horizon) if criterion == "asymptotic" else None
    record = _record(evaluator, best, require_monotonic, CertificateAction.RESCALE)
    certificates = replace(
        record,
        growth_bound=growth,
        rescale_criterion=criterion,
        largest_admissible_scale=_largest_admissible(evaluator, best, require_monotonic),
    )
    return Certification(scaled, best.scale, certificates)


class PTypeScales:
    """The P-type design ``P = (0 s Gamma)`` at every scale ``s`` of its gain, from one set of lifted maps: what the
    rule of :mod:`foilc_hil.design.admission` searches over (the pipeline's P-type design).

    ``design(s)`` is certified as it runs (``law``: ``kp = 0``), its certificates adding the gain and its
    frequency-domain bound (:class:`PTypeGain`); ``estimate(s)`` gives the rescale search's worst-case spectral
    radius and 2-norm (cheap; the certificates themselves where they are cheap anyway).
    """

    def __init__(
        self,
        model: DiscreteModel,
        uncertainty: Uncertainty,
        gain: np.ndarray,
        law: LawStructure,
        *,
        require_monotonic: bool,
    ) -> None:
        self.model, self.uncertainty, self.law = model, uncertainty, law
        self.gain = np.asarray(gain, dtype=float)
        self.require_monotonic = require_monotonic
        P = np.hstack([np.zeros((model.n_inputs, model.n_states)), self.gain])
        self._evaluator = _Evaluator(model, uncertainty, P, law)

    def design(self, scale: float) -> Design:
        """The design with ``Gamma`` scaled by ``scale`` and its certificates (``designed``: at scale 1; the naive
        comparison: the scaled gain with the filters off)."""
        gamma = scale * self.gain
        evaluator = self._evaluator
        record = _record(evaluator, evaluator.at(scale), self.require_monotonic, CertificateAction.NONE)
        certificates = replace(
            record,
            naive_without_filter=evaluator.at(scale, self.law.without_filters()).bounds(),
            gain_scale=1.0,
            p_type=PTypeGain(gamma, frequency_bound(self.model, gamma)),
        )
        P = np.hstack([np.zeros((self.model.n_inputs, self.model.n_states)), gamma])
        return Design(
            law=LawKind.P_TYPE,
            model=self.model,
            uncertainty=self.uncertainty,
            P=P,
            kp=self.law.kp,
            r=self.law.r,
            certificates=certificates,
        )

    def estimate(self, scale: float) -> Bounds:
        """The worst-case spectral radius and 2-norm at ``scale`` as the rescale search sees them."""
        return Bounds(self._evaluator.estimate(scale, "spectral_radius"), self._evaluator.estimate(scale, "norm_2"))


@as_step("certificates of the P-type law")
def certify_p_type(
    model: DiscreteModel, uncertainty: Uncertainty, gain: np.ndarray, law: LawStructure, *, require_monotonic: bool
) -> Design:
    """The P-type design ``P = (0 Gamma)`` on ``model``, with its certificates as it runs (``law``: ``kp = 0``).

    The gain is the law's (``law.p_type_gain`` or its default, :mod:`foilc_hil.design.ptype`), run as given:
    the certificates report it, nothing rescales it (``synthesis.on_divergent_filter`` is about the fractional
    filter, which P-type does not have). They add the gain and its frequency-domain bound (:class:`PTypeGain`).
    """
    return PTypeScales(model, uncertainty, gain, law, require_monotonic=require_monotonic).design(1.0)
