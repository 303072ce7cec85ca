"""Co-design of FOILC: ``kp``, ``r`` and the learning gain chosen together, for the law as it runs.

Why
---
Theorem 1's LMI has no ``kp`` or ``r``, and the loop-shaping tuner shapes ``K (1 + kp s^r) G(s)``, a loop the
learning law never closes. Neither looks at what decides how fast the law converges from trial to trial: the
lifted map ``T = I - H F'`` of :mod:`foilc_hil.design.certificates`, in which the fractional filter ``F'`` and the
gain ``p2`` act together. This module chooses them together by minimising the worst-case certified convergence
factor of that map. The LMI keeps its role (robust 2D stability of the state term ``p1`` within the trial, and the
reference ``p2``); the tuner's ``kp``, ``r`` are an initial guess.

Search space and objective
--------------------------
``P = (beta p1, s p2)`` with ``(p1, p2)`` the LMI's, the filter ``F = 1 + kappa (1 - z^-1)^r`` (Grünwald–Letnikov,
zero history: ``law.fractional_memory: controllable``) with ``kappa = kp h^-r``, so ``kp = kappa h^r``. The search
runs on ``(kappa, r, g, beta)``, ``g = s (1 + kappa)`` the effective gain on the newest error sample (the filter's
first weight is ``1 + kappa``), ``beta`` in ``[0, 1]`` (the LMI certified robust 2D stability of ``beta = 1``; the
lifted-map certificate, not the LMI, certifies the chosen point). ``kappa = 0`` -- IOILC -- is in the space, and so
is IOILC's own design (``beta = s = 1``).

    objective = max(worst-case induced 2-norm, sampled time-varying 2-norm) + noise_weight * noise gain

1. **Search (surrogate)**: the worst over the frozen plants (nominal, uncertainty vertices) of
   ``sup_w |1 - s H_L(w) F_L(w)|``, the symbol of the length-``L`` Toeplitz map (``H_L`` in closed form for the
   closed loop ``A + B beta p1``): ``T`` is a finite section of the Toeplitz operator with that symbol, so the sup
   bounds its norm (up to the frequency grid). A grid over ``(kappa, r, g, beta)``, then Nelder–Mead from the best
   point, the best ``kappa = 0`` point and the tuner's point.
2. **Finalists**: the best two polished points, the initial guess and IOILC's design are certified EXACTLY at the full
   trial (:func:`~foilc_hil.design.certificates.certify_as_given`: the same certificate as every design), and
   checked on ``time_varying_samples`` seeded draws of a time-varying ``Delta(t)`` (piecewise-constant extreme
   points) on a trial shortened to ``time_varying_horizon`` samples: a dense map, a sampled check, not a proof.
   The finalist with the lowest objective wins; IOILC's design is a finalist, so with ``noise_weight = 0`` and no
   time-varying draw above the frozen certificates the co-designed law is never certified worse than IOILC.
   Speed without changing the choice (``docs/codesign.md``): the grid screens its shapes with a lower bound (a
   maximum over fewer frequencies), and a finalist whose time-varying norm is already above the best objective
   (first bounded from below by power iteration) is ruled out before its exact certificate.
3. The winner goes through :func:`~foilc_hil.design.certificates.certify` like every design (policy and
   monotonicity from ``synthesis``).

Noise gain (single input and output)
------------------------------------
White measurement noise ``n`` (unit variance) enters the law twice: the state term ``p1`` sees ``pinv(C) n`` in
the reconstructed state, the learning term sees ``-n`` in the measured error. In the long-trial limit every
frequency ``w`` is a scalar recursion over trials, ``du_k = T du_{k-1} + a n_k + b n_{k-1}`` with
``R = 1/(1 - p1 Gz)``, ``a = R p1 c``, ``b = -R (p1 c + s p2 z^(d+1) F)`` (the error sample ``e[i]`` is measured
at ``(i+1) Ts``, one sample after the state the law reconstructs at ``i``), ``T = 1 - R s p2 z^d F Gy``; its stationary
variance is ``|a|^2 + |T a + b|^2 / (1 - |T|^2)`` and the error's is ``|Gy|^2`` times that. The noise gain is its
average over frequency: the stationary per-sample error variance per unit noise variance. A fast law (``T``
near 0) passes the noise of the last trial through (gain about 1); a slow one averages it over trials.

Module order: after :mod:`foilc_hil.design.lmi` (its gain is the starting point), before
:mod:`foilc_hil.design.tuning` and :mod:`foilc_hil.design.pipeline`.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, replace

import numpy as np

from foilc_hil.config import CodesignConfig, DivergentFilterPolicy, FractionalMemory, LawKind
from foilc_hil.design.certificate_record import CertificateAction, CodesignRecord, Timing
from foilc_hil.design.certificates import certify, map_certificate
from foilc_hil.design.fractional import gl_weights
from foilc_hil.design.lifted import LawStructure, LoopPlant
from foilc_hil.design.lmi import LmiSolution
from foilc_hil.design.map_norms import power_norm
from foilc_hil.design.models import DiscreteModel, Uncertainty, uncertainty_vertices
from foilc_hil.design.record import Design
from foilc_hil.errors import ConfigError
from foilc_hil.progress import as_step

__all__ = ["Candidate", "CodesignSearch", "codesign", "time_varying_map"]

#: ``r`` recorded when the co-design picks ``kp = 0`` (the law has no fractional term then).
UNUSED_ORDER = 1.0
#: The search grid: ``kappa = kp h^-r`` (0 and a log range), ``r``, and ``g`` (the gain on the newest sample,
#: relative to the LMI's ``p2``, which is close to deadbeat).
KAPPA_GRID = (0.0, 0.03, 0.1, 0.3, 1.0, 3.0, 10.0)
ORDER_GRID = tuple(float(r) for r in np.linspace(0.1, 1.9, 7))
GAIN_GRID = tuple(float(g) for g in np.geomspace(0.05, 2.0, 13))
#: ... and ``beta``, the factor on the LMI's state term ``p1`` (1: the LMI's; 0: no state term).
BETA_GRID = (0.0, 0.5, 1.0)
#: The grid's screening bound evaluates every this many-th frequency of the symbols.
SCREEN_STRIDE = 8
#: Power iterations of the finalists' cheap lower bound on a time-varying map's norm.
POWER_STEPS = 20
#: Bounds of the continuous search.
KAPPA_MIN, KAPPA_MAX, ORDER_MIN, ORDER_MAX, GAIN_MIN, GAIN_MAX = 1e-6, 1e3, 0.02, 1.98, 1e-3, 4.0
#: Finalists certified exactly (besides the initial guess and IOILC's design), and Nelder–Mead starts.
FINALISTS = 2
POLISH_EVALUATIONS = 120
#: Dwell of the piecewise-constant time-varying draws: switch with this probability per sample.
SWITCH_PROBABILITY = 0.05


@dataclass(frozen=True)
class Candidate:
    """A point of the search: ``kappa = kp h^-r``, ``r``, ``g = s (1 + kappa)``, ``beta`` (the factor on the LMI's
    ``p1``); ``value`` its surrogate objective."""

    kappa: float
    r: float
    g: float
    beta: float = 1.0
    value: float = math.inf

    @property
    def scale(self) -> float:
        """``s``, the factor on the LMI's ``p2``."""
        return self.g / (1.0 + self.kappa)

    def kp(self, sample_time: float) -> float:
        """``kp = kappa h^r``."""
        return self.kappa * sample_time**self.r

    def vector(self) -> list[float]:
        """``(log kappa, r, log g, beta)``: the coordinates Nelder–Mead moves in."""
        return [math.log(self.kappa), self.r, math.log(self.g), self.beta]


class CodesignSearch:
    """The surrogate objective of the module notes for one model, uncertainty, LMI gain and law."""

    def __init__(
        self, model: DiscreteModel, uncertainty: Uncertainty, P: np.ndarray, law: LawStructure, noise_weight: float
    ) -> None:
        from scipy.fft import next_fast_len

        n = model.n_states
        self.model, self.law, self.noise_weight = model, law, noise_weight
        self.p1, self.p2 = P[:, :n], P[:, n:]
        self.length = law.n_samples - law.lead
        self.n_fft = next_fast_len(max(1024, 2 * self.length))
        self.z = np.exp(2j * np.pi * np.arange(self.n_fft) / self.n_fft)
        self.plants = [(model.A, model.B)]
        self.plants += [(model.A + dA, model.B + dB) for dA, dB in uncertainty_vertices(uncertainty)]
        self._symbols: dict[float, np.ndarray] = {}
        self._resolvent: np.ndarray | None = None
        self.scalar = model.n_inputs == 1 and model.n_outputs == 1
        if noise_weight > 0 and not self.scalar:
            raise ConfigError(
                "needs a single-input single-output plant (the noise gain is scalar)",
                key="synthesis.codesign.noise_weight",
            )
        n_plant = n - model.input_delay * model.n_inputs
        self._noise_input = np.zeros((n, model.n_outputs))  # measurement noise -> reconstructed state
        self._noise_input[:n_plant] = np.linalg.pinv(model.measured_output[:, :n_plant])
        self.evaluations = 0

    def markov_symbols(self, beta: float) -> np.ndarray:
        """Per frozen plant, the symbol of ``h_j = C A_cl^(j + d) B p2``, ``j < L`` (``A_cl = A + B beta p1``), on
        the half grid ``z_k``, ``k <= n_fft / 2``: shape ``(plants, n_fft // 2 + 1, p, p)``.

        The Markov parameters are built for all plants at once by doubling (``h_(j + 2^i) = A_cl^(2^i) h_j``: one
        batched product per power of two) and transformed by a real FFT. The ``h_j`` are real, so the symbol at
        ``conj(z)`` is the conjugate of that at ``z`` and has the same norm: the half grid loses nothing.
        """
        if beta not in self._symbols:
            from scipy.fft import rfft

            A_cl = np.stack([A + beta * (B @ self.p1) for A, B in self.plants])
            drive = np.stack([B @ self.p2 for _, B in self.plants])
            blocks = np.empty((len(self.plants), self.length, *drive.shape[1:]))
            with np.errstate(all="ignore"):  # an unstable closed loop overflows: its symbol norm is then inf
                blocks[:, 0] = np.linalg.matrix_power(A_cl, self.law.lead) @ drive
                power, filled = A_cl, 1
                while filled < self.length:
                    step = min(filled, self.length - filled)
                    blocks[:, filled : filled + step] = power[:, None] @ blocks[:, :step]
                    power, filled = power @ power, filled + step
                symbols = rfft(self.model.measured_output @ blocks, n=self.n_fft, axis=1)
            # a continuous search visits new betas all the time: keep the cache small (the grid's three stay hot)
            self._symbols = {beta: symbols} if len(self._symbols) > 64 else {**self._symbols, beta: symbols}
        return self._symbols[beta]

    def filter_symbol(self, kappa: float, r: float) -> np.ndarray:
        """The symbol of the length-``L`` zero-history filter ``1 + kappa GL_r`` on the whole grid ``z``."""
        from scipy.fft import fft

        return np.asarray(fft(self._filter_weights(kappa, r), n=self.n_fft))

    def _half_filter_symbol(self, kappa: float, r: float) -> np.ndarray:
        """:meth:`filter_symbol` on the half grid of :meth:`markov_symbols` (real weights: nothing is lost)."""
        from scipy.fft import rfft

        return np.asarray(rfft(self._filter_weights(kappa, r), n=self.n_fft))

    def _filter_weights(self, kappa: float, r: float) -> np.ndarray:
        weights = kappa * gl_weights(r, self.length)
        weights[0] += 1.0
        return weights

    def _peaks(self, beta: float, filt: np.ndarray, scales: np.ndarray, stride: int = 1) -> np.ndarray:
        """``symbol_norm`` at one ``beta`` and filter symbol for every scale ``s`` in ``scales`` at once, on every
        ``stride``-th frequency of the half grid (``stride > 1``: a lower bound)."""
        symbols = self.markov_symbols(beta)[:, ::stride]
        filt = filt[::stride]
        with np.errstate(all="ignore"):
            if self.scalar:
                product = symbols[:, :, 0, 0] * filt[None, :]
                peaks = np.max(np.abs(1.0 - scales[:, None, None] * product[None]), axis=(1, 2))
            else:
                product = symbols * filt[None, :, None, None]
                eye = np.eye(symbols.shape[-1])
                T = eye - scales[:, None, None, None, None] * product[None]
                peaks = np.max(np.linalg.norm(T, 2, axis=(-2, -1)), axis=(1, 2))
        return np.where(np.isfinite(peaks), peaks, math.inf)

    def symbol_norm(self, point: Candidate) -> float:
        """Worst over the frozen plants of ``sup_w ||I - s H_L(w) F_L(w)||``."""
        filt = self._half_filter_symbol(point.kappa, point.r)
        return float(self._peaks(point.beta, filt, np.array([point.scale]))[0])

    def noise_gain(self, point: Candidate) -> float | None:
        """The stationary error variance per unit white measurement-noise variance (module notes); ``None``
        for several inputs or outputs, ``inf`` when some frequency does not contract."""
        if not self.scalar:
            return None
        A, B, C = self.model.A, self.model.B, self.model.measured_output
        p1 = point.beta * self.p1
        with np.errstate(all="ignore"):
            if self._resolvent is None:  # u -> z: the same for every point
                self._resolvent = np.linalg.solve(self.z[:, None, None] * np.eye(A.shape[0]) - A, B)
            resolvent = self._resolvent
            R = 1.0 / (1.0 - (p1 @ resolvent)[:, 0, 0])
            Gy = self.z * (C @ resolvent)[:, 0, 0]
            noise_state = float((p1 @ self._noise_input)[0, 0])
            learning = point.scale * float(self.p2[0, 0]) * self.z**self.law.lead
            learning = learning * self.filter_symbol(point.kappa, point.r)
            T = 1.0 - R * learning * Gy
            if not float(np.max(np.abs(T))) < 1.0:
                return math.inf
            # e[i] is measured at (i+1) Ts, one sample after the state reconstructed at i: its noise is advanced
            a, b = R * noise_state, -R * (noise_state + learning * self.z)
            variance = np.abs(a) ** 2 + np.abs(T * a + b) ** 2 / (1.0 - np.abs(T) ** 2)
            return float(np.mean(np.abs(Gy) ** 2 * variance))

    def objective(self, point: Candidate) -> float:
        """The surrogate objective: symbol norm plus the weighted noise gain."""
        self.evaluations += 1
        value = self.symbol_norm(point)
        if self.noise_weight > 0:
            noise = self.noise_gain(point)
            value += self.noise_weight * (math.inf if noise is None else noise)
        return value if math.isfinite(value) else 1e300

    def grid(self) -> tuple[Candidate, Candidate]:
        """The best grid point and the best ``kappa = 0`` grid point, with their values (ties: the earlier point
        of the grid's order, integer points first).

        Every grid point is covered, cheaply. The points sharing ``(beta, kappa, r)`` share the product
        ``H_L F_L``: it is formed once and all gains of :data:`GAIN_GRID` are evaluated on it in one array
        operation. Without a noise weight the fractional shapes are first screened on every
        :data:`SCREEN_STRIDE`-th frequency: a maximum over fewer frequencies is a lower bound of the full one (the
        same floating-point values, a subset of them), so a shape whose bound is above the best value found is
        ruled out exactly, and only the others are evaluated on the whole grid, lowest bound first.
        """
        gains = np.array(GAIN_GRID)
        integer = min(self._best_of_shape(i, (beta, 0.0, UNUSED_ORDER), gains) for i, beta in enumerate(BETA_GRID))
        best = integer
        shapes = [(b, k, r) for b in BETA_GRID for k in KAPPA_GRID if k > 0 for r in ORDER_GRID]
        first = len(BETA_GRID)  # the fractional shapes come after the integer ones in the grid's order
        if self.noise_weight > 0:
            for index, shape in enumerate(shapes, start=first):
                best = min(best, self._best_of_shape(index, shape, gains))
            return best[2], integer[2]
        bounds = [
            (
                float(
                    np.min(self._peaks(beta, self._half_filter_symbol(kappa, r), gains / (1.0 + kappa), SCREEN_STRIDE))
                ),
                index,
                (beta, kappa, r),
            )
            for index, (beta, kappa, r) in enumerate(shapes, start=first)
        ]
        self.evaluations += len(gains) * len(shapes)  # each point is evaluated below or ruled out by its bound
        for bound, index, shape in sorted(bounds):
            if bound > best[0]:
                break
            best = min(best, self._best_of_shape(index, shape, gains, counted=False))
        return best[2], integer[2]

    def _best_of_shape(
        self, index: int, shape: tuple[float, float, float], gains: np.ndarray, *, counted: bool = True
    ) -> tuple[float, int, Candidate]:
        """``(value, grid position, point)`` of the best gain at ``shape = (beta, kappa, r)`` (values as
        :meth:`objective`); the position orders ties as the grid does."""
        beta, kappa, r = shape
        if self.noise_weight > 0:
            values = np.array([self.objective(Candidate(kappa, r, float(g), beta)) for g in gains])
        else:
            values = self._peaks(beta, self._half_filter_symbol(kappa, r), gains / (1.0 + kappa))
            values = np.where(np.isfinite(values), values, 1e300)
            self.evaluations += len(gains) if counted else 0
        best = int(np.argmin(values))
        return (
            float(values[best]),
            index * len(gains) + best,
            Candidate(kappa, r, float(gains[best]), beta, float(values[best])),
        )

    def polish(self, start: Candidate) -> Candidate:
        """Nelder–Mead from ``start`` on ``(log kappa, r, log g, beta)`` (``kappa = 0`` stays 0: ``log g, beta``)."""
        from scipy.optimize import minimize

        options = {"maxfev": POLISH_EVALUATIONS, "xatol": 1e-3, "fatol": 1e-6}
        if start.kappa == 0.0:

            def integer(x: np.ndarray) -> float:
                return self.objective(_point([-math.inf, start.r, x[0], x[1]]))

            found = minimize(integer, [math.log(start.g), start.beta], method="Nelder-Mead", options=options)
            return replace(_point([-math.inf, start.r, found.x[0], found.x[1]]), value=float(found.fun))

        def fractional(x: np.ndarray) -> float:
            return self.objective(_point(list(x)))

        found = minimize(fractional, start.vector(), method="Nelder-Mead", options=options)
        return replace(_point(list(found.x)), value=float(found.fun))


def _clip(value: float, low: float, high: float) -> float:
    return min(max(value, low), high)


def _point(x: list[float]) -> Candidate:
    """The candidate at the unconstrained ``(log kappa, r, log g, beta)``, clipped to the bounds
    (``log kappa = -inf``: ``kappa = 0``)."""
    kappa = 0.0 if x[0] == -math.inf else _clip(math.exp(x[0]), KAPPA_MIN, KAPPA_MAX)
    return Candidate(
        kappa,
        _clip(float(x[1]), ORDER_MIN, ORDER_MAX),
        _clip(math.exp(x[2]), GAIN_MIN, GAIN_MAX),
        _clip(float(x[3]), 0.0, 1.0),
    )


def _draw_deltas(uncertainty: Uncertainty, steps: int, rng: np.random.Generator) -> list[tuple[np.ndarray, np.ndarray]]:
    """``(dA(t), dB(t))`` for ``t < steps``: piecewise-constant extreme points of each channel's unit ball."""
    n, m = uncertainty.G1.shape[0], uncertainty.H2.shape[1]
    terms = [np.zeros((steps, n, n)), np.zeros((steps, n, m))]
    for kind, G, H in uncertainty.channels():
        delta = np.zeros((G.shape[1], H.shape[0]))
        for t in range(steps):
            if t == 0 or rng.random() < SWITCH_PROBABILITY:
                raw = rng.standard_normal(delta.shape)
                delta = raw / np.linalg.norm(raw, 2)  # on the boundary of the unit ball (+-1 for scalars)
            terms[0 if kind == "state" else 1][t] += G @ delta @ H
    return list(zip(terms[0], terms[1], strict=True))


def time_varying_map(
    model: DiscreteModel, P: np.ndarray, law: LawStructure, deltas: list[tuple[np.ndarray, np.ndarray]]
) -> np.ndarray:
    """The dense error map ``T = I - H_tv F'`` of the law on the plant ``(A + dA(t), B + dB(t))``.

    ``deltas`` has one ``(dA, dB)`` per sample of the trial (``law.n_samples``, at least ``L + lead``), the same in
    every trial (a time-varying, trial-invariant plant, as eq. (48)'s ``Delta a(t)``). Column ``i`` of ``H_tv``
    is the response of ``e~ = e[lead:]`` to a unit learning term at ``u[i]``; it is built by propagating all
    columns at once.
    """
    n, lead = model.n_states, law.lead
    length = law.n_samples - lead
    p = model.n_outputs
    p1, p2 = P[:, :n], P[:, n:]
    Z = np.zeros((n, length * p))
    H = np.zeros((length * p, length * p))
    for t in range(length + lead):
        dA, dB = deltas[t]
        A_t, B_t = model.A + dA, model.B + dB
        Z = (A_t + B_t @ p1) @ Z  # z[t+1] = A_cl(t) z[t] + B(t) u[t]
        if t < length:
            Z[:, t * p : (t + 1) * p] += B_t @ p2
        if t >= lead:  # e[t] = C z[t+1] is e~[t - lead]
            H[(t - lead) * p : (t - lead + 1) * p] = model.measured_output @ Z
    F = law.filter().dense()[lead:, lead:]
    return np.eye(length * p) - H @ np.kron(F, np.eye(p))


def _time_varying_draws(
    uncertainty: Uncertainty, law: LawStructure, settings: CodesignConfig
) -> list[list[tuple[np.ndarray, np.ndarray]]]:
    """The seeded time-varying draws on the shortened trial, drawn once: every finalist is checked on the same
    ones (none without draws or without uncertainty)."""
    if settings.time_varying_samples == 0 or uncertainty.is_zero:
        return []
    steps = min(law.n_samples, settings.time_varying_horizon + law.lead)
    rng = np.random.default_rng(settings.seed)
    return [_draw_deltas(uncertainty, steps, rng) for _ in range(settings.time_varying_samples)]


def _lower_norm(T: np.ndarray) -> float:
    """A lower bound on ``||T||_2``: :func:`~foilc_hil.design.map_norms.power_norm` with :data:`POWER_STEPS`
    power iterations on ``T^T T`` from its fixed start (any ``v`` gives a lower bound; the iterations make it
    tight)."""
    return power_norm(T.shape[1], T.__matmul__, T.T.__matmul__, iterations=POWER_STEPS + 1)


def _time_varying_norm(
    model: DiscreteModel,
    P: np.ndarray,
    law: LawStructure,
    draws: list[list[tuple[np.ndarray, np.ndarray]]],
    floor: float = math.inf,
) -> float:
    """Worst induced 2-norm over the time-varying ``draws`` on the shortened trial (``nan`` without draws).

    With a ``floor``: if a cheap lower bound (:func:`_lower_norm`) of some draw's norm is above it, that bound is
    returned at once, before any SVD -- enough for the caller, which only needs to know the worst exceeds it.
    """
    if not draws:
        return math.nan
    short = replace(law, n_samples=len(draws[0]), q_filter=None)
    maps = [time_varying_map(model, P, short, deltas) for deltas in draws]
    if not all(np.all(np.isfinite(T)) for T in maps):
        return math.inf
    if math.isfinite(floor):
        bound = max(_lower_norm(T) for T in maps)
        if bound > floor:
            return bound
    return max(float(np.linalg.norm(T, 2)) for T in maps)


@dataclass(frozen=True)
class _Finalist:
    candidate: Candidate
    P: np.ndarray
    law: LawStructure
    norm_2: float
    time_varying: float
    noise: float | None
    objective: float


def _finalist(
    search: CodesignSearch,
    candidate: Candidate,
    settings: CodesignConfig,
    draws: list[list[tuple[np.ndarray, np.ndarray]]],
    beat: float = math.inf,
) -> _Finalist | None:
    """Certify ``candidate`` exactly at the full trial and check it on the time-varying draws; ``None`` when it
    cannot reach an objective of ``beat`` or lower.

    The screening bound comes first because it is cheap: the objective is at least the time-varying norm plus the
    weighted noise gain (``max(norm, varying) >= varying``), both computed on the short trial or the symbol grid,
    and the time-varying norm is itself first bounded from below by power iteration. Above ``beat`` neither its
    SVDs nor the exact certificate at the full trial (the expensive part) are needed to rule it out.
    """
    law = search.law
    h = law.sample_time
    structure = replace(law, kp=candidate.kp(h), r=candidate.r if candidate.kappa > 0 else UNUSED_ORDER)
    P = np.hstack([candidate.beta * search.p1, candidate.scale * search.p2])
    noise = search.noise_gain(candidate)
    penalty = settings.noise_weight * (math.inf if noise is None else noise) if settings.noise_weight > 0 else 0.0
    varying = _time_varying_norm(search.model, P, structure, draws, floor=beat - penalty)
    if (varying if math.isfinite(varying) else 0.0) + penalty > beat:
        return None
    C, p1, p2 = search.model.measured_output, P[:, : search.p1.shape[1]], P[:, search.p1.shape[1] :]
    # the certificate of every design (map_certificate), at each frozen plant; the worst one counts
    norm = max(map_certificate(LoopPlant(A, B, C, p1, p2), structure).norm_2 for A, B in search.plants)
    value = (max(norm, varying) if math.isfinite(varying) else norm) + penalty
    return _Finalist(candidate, P, structure, norm, varying, noise, value)


def _choose(
    search: CodesignSearch,
    uncertainty: Uncertainty,
    settings: CodesignConfig,
    initial_guess: tuple[float, float] | None,
) -> tuple[_Finalist, _Finalist, int]:
    """Grid, Nelder–Mead, then the exact certificates of the finalists: the best one, IOILC's design (always a
    finalist) and how many finalists were considered.

    IOILC's design is certified first; a later finalist is certified only if its screening bound does not
    exceed the best objective so far (:func:`_finalist`), so the winner -- the lowest objective, ties to the
    earlier finalist, IOILC's design last -- is the one certifying every finalist would pick.
    """
    law = search.law
    starts = list(search.grid())
    if initial_guess is not None and initial_guess[0] > 0:
        kappa = initial_guess[0] * law.sample_time ** -initial_guess[1]
        starts.append(Candidate(kappa, initial_guess[1], 1.0 + kappa))  # the paper's point: s = 1, beta = 1
    polished = sorted((search.polish(start) for start in starts), key=lambda c: c.value)
    ioilc = Candidate(0.0, UNUSED_ORDER, 1.0)  # IOILC's own design: kp = 0, the LMI gain as is
    # distinct points only (polishing from different starts may end at the same one); IOILC's design last
    unique = {(c.kappa, c.r, c.g, c.beta): c for c in [*polished[:FINALISTS], *starts[2:]]}
    pool = [c for key, c in unique.items() if key != (ioilc.kappa, ioilc.r, ioilc.g, ioilc.beta)]
    draws = _time_varying_draws(uncertainty, law, settings)
    baseline = _finalist(search, ioilc, settings, draws)
    assert baseline is not None  # nothing to beat: always certified
    ranked = [(baseline.objective, len(pool), baseline)]
    for position, candidate in enumerate(pool):
        finalist = _finalist(search, candidate, settings, draws, beat=min(ranked)[0])
        if finalist is not None:
            ranked.append((finalist.objective, position, finalist))
    return min(ranked, key=lambda entry: entry[:2])[2], baseline, len(pool) + 1


@as_step("co-design of kp, r and P")
def codesign(
    model: DiscreteModel,
    uncertainty: Uncertainty,
    solution: LmiSolution,
    law: LawStructure,
    settings: CodesignConfig,
    *,
    rates: tuple[float, float],
    initial_guess: tuple[float, float] | None = None,
    policy: DivergentFilterPolicy = DivergentFilterPolicy.RESCALE,
    require_monotonic: bool = True,
    growth_horizon: int = 10,
) -> Design:
    """The co-designed FOILC (module notes), starting from the LMI ``solution`` (solved with ``rates`` =
    ``(tau, theta)``) and the ``initial_guess`` ``(kp, r)`` of the tuner.

    Raises
    ------
    foilc_hil.errors.ConfigError
        A Q-filter or the paper-literal fractional memory (the search's symbols assume neither), or a noise
        weight on a plant with several inputs or outputs.
    foilc_hil.errors.ConvergenceCertificateError
        When even the best point is not certified and the policy cannot fix it (exit 3).
    """
    if law.q_filter is not None:
        raise ConfigError("codesign does not support law.q_filter; use synthesis.design: paper", key="synthesis.design")
    if law.fractional_memory is not FractionalMemory.CONTROLLABLE:
        raise ConfigError("codesign needs law.fractional_memory: controllable", key="synthesis.design")
    started = time.perf_counter()
    search = CodesignSearch(model, uncertainty, solution.P, law, settings.noise_weight)
    best, baseline, finalists = _choose(search, uncertainty, settings, initial_guess)
    outcome = certify(
        model,
        uncertainty,
        best.P,
        best.law,
        policy=policy,
        require_monotonic=require_monotonic,
        growth_horizon=growth_horizon,
    )
    chosen = best.candidate
    record = CodesignRecord(
        objective=best.objective,
        noise_weight=settings.noise_weight,
        noise_gain=best.noise,
        gain=chosen.scale,
        symbol_norm=search.symbol_norm(chosen),
        state_gain=chosen.beta,
        time_varying_norm_2=best.time_varying,
        time_varying_samples=settings.time_varying_samples,
        time_varying_horizon=settings.time_varying_horizon,
        ioilc_objective=baseline.objective,
        ioilc_norm_2=baseline.norm_2,
        candidates=search.evaluations + finalists,
        initial_guess=initial_guess,
    )
    scale = chosen.scale * outcome.gain_scale
    certificates = replace(
        outcome.certificates,
        action=CertificateAction.CODESIGN,
        gain_scale=scale,
        codesign=record,
        lmi=solution.checks,
        seconds=Timing(solution.seconds, solution.seconds + time.perf_counter() - started),
    )
    return Design(
        law=LawKind.FOILC,
        model=model,
        uncertainty=uncertainty,
        P=outcome.P,
        kp=best.law.kp,
        r=best.law.r,
        Qb=solution.Qb,
        Qt=solution.Qt,
        gamma=solution.gamma,
        tau=rates[0],
        theta=rates[1],
        gain_scale=scale,
        certificates=certificates,
    )
