"""Loop-shaping tuner for the fractional PD function ``1 + kp s^r`` (paper Section 4.1, done soundly).

What it is: an INITIAL GUESS for ``kp``, ``r``, not a convergence proof. The learning law never closes the loop
``L`` shaped here, so nothing links this specification to trial-to-trial convergence; that is certified by
:mod:`foilc_hil.design.certificates`, and ``synthesis.design: codesign`` (:mod:`foilc_hil.design.codesign`) uses
the answer only as the starting point of its search.

The paper puts its specification on ``P(s) = 1 + kp s^r`` alone (eqs. (26)-(30)); that is not a loop
specification and is unreachable (errata item 2). Here the specification is on the open loop

    ``L(s) = K (1 + kp s^r) G(s)``,  ``G(s) = num(s) / den(s) * exp(-delay s)``,

* ``|L(j wc)| = 1`` (gain crossover at ``wc``),
* ``arg L(j wc) = -180 deg + phase_margin`` (taken modulo 360 deg, as margin tools do),
* with ``flat_phase`` also ``d arg L / dw = 0`` at ``wc`` (iso-damping); then ``K > 0`` is solved too,
  otherwise ``K = 1``.

Solving
-------
Write ``P = 1 + x e^{j a}`` with ``x = kp wc^r > 0`` and ``a = r pi / 2`` in ``(0, pi)``. ``K > 0`` does not
change the phase, so the phase spec fixes the phase ``theta = arg P`` that the PD term must supply:
``theta = (-pi + phi_m - arg G(j wc)) mod 2 pi``. The triangle ``0, 1, P`` gives, by the law of sines,

    ``x = sin(theta) / sin(a - theta)``,  ``|P| = sin(a) / sin(a - theta)``,

which is positive exactly when ``0 < theta < a``: the PD term adds between 0 and ``r * 90`` deg of lead, so
``theta`` must lie in ``(0, 180)`` deg (and ``r > 2 theta / pi``) or the spec is unreachable.

* Without flat phase (``K = 1``): the magnitude residual ``log(sin a / sin(a - theta)) + log|G(j wc)|`` is
  strictly decreasing in ``a`` (its derivative is ``-sin(theta) / (sin a sin(a - theta))``) from ``+inf`` to
  ``-inf``, so there is exactly one solution; it is bracketed on a fine ``r`` grid and refined with ``brentq``.
* With flat phase: ``d arg P / dw = (r / w) x sin(a) / |P|^2 = (r / wc) sin(theta) sin(a - theta) / sin(a)`` is
  positive, rising from 0 (``a -> theta``) to ``+inf`` (``a -> pi``); the flatness residual
  ``(r / wc) sin(theta) sin(a - theta) / sin(a) + d arg G / dw`` is bracketed on the grid (sign changes, plus
  tangential roots found by bounded minimisation) and refined with ``brentq``. A root exists whenever the plant's
  phase slope at ``wc`` is negative, and it is unique: in ``u = a - theta`` the residual's first term is
  ``(r / wc) sin(theta) sin(u) / sin(u + theta)``, whose ``u``-derivative ``sin(theta)^2 / sin(u + theta)^2``
  (times ``r / wc``) is positive, and ``r = 2 (u + theta) / pi`` also grows with ``u``, so the term is strictly
  increasing from 0 and crosses the constant ``-d arg G / dw`` once (checked on 120 random specs). The
  bracketing still searches for several roots, as a guard. ``K = 1 / (|P| |G(j wc)|)``. An answer with
  ``r`` near 2 sits where the phase of ``(j w)^r`` is near 180 deg and the PD term is nearly a pure double
  differentiator: :func:`tune` warns (``checks.warnings``) when ``r > FLAT_PHASE_ORDER_WARNING``.

Choosing among solutions: the largest worst-case phase margin over all gain crossovers found in the sweep
window, then the largest gain margin, then the smallest ``kp`` (the smallest instantaneous gain
``kp h^-r`` of the discretised filter, errata item 4).

Checking
--------
Every answer is checked twice, independently of the solver, by the two checks of
:mod:`foilc_hil.design.open_loop` (its notes): a dense frequency sweep of ``L(j w)`` (the ``achieved`` numbers, which
must meet the spec within :data:`DENSE_CROSSOVER_RTOL` and :data:`DENSE_PHASE_TOL_DEG`), and python-control's
margins on an Oustaloup/Padé model of the loop, which must agree with the sweep.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, replace
from typing import TYPE_CHECKING, Any

import numpy as np

from foilc_hil.design.open_loop import (
    ControlCheck,
    Crossing,
    OpenLoop,
    PlantTf,
    SweepResult,
    control_check,
    frequency_sweep,
    wrap_deg,
)
from foilc_hil.errors import ConfigError, TuningInfeasibleError
from foilc_hil.progress import as_step

if TYPE_CHECKING:
    from foilc_hil.config import Config

__all__ = [
    "DENSE_CROSSOVER_RTOL",
    "DENSE_PHASE_TOL_DEG",
    "SELECTION",
    "ConfiguredPair",
    "LoopShape",
    "LoopSolution",
    "TuningChecks",
    "TuningResult",
    "evaluate_pair",
    "tune",
    "tune_loop",
]


#: The dense sweep must put the gain crossover within this relative distance of ``wc`` ...
DENSE_CROSSOVER_RTOL = 1e-4
#: ... and the phase margin within this many degrees of the spec.
DENSE_PHASE_TOL_DEG = 0.01
_EDGE = np.concatenate([np.logspace(-12, -2.5, 120), np.linspace(10**-2.5, 1 - 10**-2.5, 4000)])
#: fractions u in (0, 1) of the r interval, dense near both ends where the residuals blow up
#: Above this order the tuner warns: ``(j w)^r`` then has a phase near 180 deg (a near double differentiator).
FLAT_PHASE_ORDER_WARNING = 1.8
#: how :func:`tune_loop` chooses among several solutions (the order of :func:`_ranked_solutions`)
SELECTION = (
    "solutions with a positive (or no) gain margin first, then the largest worst-case phase margin over all "
    "crossovers, then the largest gain margin, then the smallest kp"
)
#: the sweep's note when ``|L|`` never crosses 1 in its window
_NO_CROSSOVER = "|L| does not cross 1 in the window: no gain crossover (infinite phase margin)"
_GRID_FRACTIONS = np.unique(np.concatenate([_EDGE, 1.0 - _EDGE]))


# --- data -----------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class LoopSolution:
    """One ``(K, kp, r)`` meeting the spec, with what the dense sweep says about it."""

    K: float
    kp: float
    r: float
    worst_phase_margin_deg: float
    gain_margin_db: float | None
    n_crossings: int


@dataclass(frozen=True)
class LoopShape:
    """What a solved specification was solved with at ``wc``: the plant's phase (deg) and gain, the phase the PD term
    supplies (deg) and, with flat phase, the plant's phase slope (deg per rad/s; ``None`` without)."""

    plant_phase_deg: float
    plant_gain: float
    pd_phase_deg: float
    plant_phase_slope_deg_per_rad_s: float | None = None


@dataclass(frozen=True)
class ConfiguredPair:
    """The configured ``kp``, ``r`` evaluated beside a solved specification: its achieved crossover and phase margin
    (``None``: no gain crossover)."""

    kp: float
    r: float
    crossover: float | None
    phase_margin_deg: float | None


@dataclass(frozen=True)
class TuningChecks:
    """How a tuning answer was checked (the ``tune`` document's ``checks``).

    Attributes
    ----------
    warnings
        Plain-language warnings: what the answer does not guarantee about the whole loop.
    sweep
        The dense sweep of the chosen loop (no crossings: ``|L|`` never crosses 1 in its window).
    python_control
        python-control's cross-check (:func:`~foilc_hil.design.open_loop.control_check`), or ``None`` (not asked
        for, or no crossing to check).
    shape
        A solved specification's plant and PD phases at ``wc`` (``None`` for a given pair).
    configured_pair
        The configured pair, evaluated beside a solved specification, or ``None``.
    """

    warnings: tuple[str, ...]
    sweep: SweepResult
    python_control: ControlCheck | None = None
    shape: LoopShape | None = None
    configured_pair: ConfiguredPair | None = None

    @property
    def selection(self) -> str:
        """How the answer was chosen among several solutions (:data:`SELECTION`; ``""`` for a given pair)."""
        return "" if self.shape is None else SELECTION

    def to_json(self) -> dict[str, Any]:
        """The ``checks`` document: the keys that apply, in this order."""
        document: dict[str, Any] = {"warnings": list(self.warnings), "sweep": _sweep_json(self.sweep)}
        if self.python_control is not None:
            document["python_control"] = self.python_control.to_json()
        if self.shape is not None:
            document["plant_phase_deg"] = self.shape.plant_phase_deg
            document["plant_gain"] = self.shape.plant_gain
            document["pd_phase_deg"] = self.shape.pd_phase_deg
            if self.shape.plant_phase_slope_deg_per_rad_s is not None:
                document["plant_phase_slope_deg_per_rad_s"] = self.shape.plant_phase_slope_deg_per_rad_s
            document["selection"] = SELECTION
        if self.configured_pair is not None:
            document["configured_pair"] = asdict(self.configured_pair)
        return document


def _sweep_json(sweep: SweepResult) -> dict[str, Any]:
    """``checks.sweep``: the window, its crossings and gain margin, and the tolerances (the note without a
    crossing)."""
    if not sweep.crossings:
        return {
            "w_min": sweep.w_min,
            "w_max": sweep.w_max,
            "crossings": [],
            "gain_margin_db": sweep.gain_margin_db,
            "note": _NO_CROSSOVER,
        }
    return {
        "w_min": sweep.w_min,
        "w_max": sweep.w_max,
        "points_per_decade": sweep.points_per_decade,
        "crossings": [asdict(c) for c in sweep.crossings],
        "gain_margin_db": sweep.gain_margin_db,
        "phase_crossover": sweep.phase_crossover,
        "tolerance": {"crossover_rel": DENSE_CROSSOVER_RTOL, "phase_margin_deg": DENSE_PHASE_TOL_DEG},
    }


@dataclass(frozen=True)
class TuningResult:
    """Result of :func:`tune_loop` / :func:`evaluate_pair`.

    ``crossover`` / ``phase_margin_deg`` are the specification when one was solved, and the achieved values
    when a given ``kp``/``r`` pair was evaluated (``mode == "direct"``); ``None`` there means ``|L|`` never
    crosses 1 in the sweep window (infinite phase margin).
    """

    K: float
    kp: float
    r: float
    crossover: float | None
    phase_margin_deg: float | None
    flat_phase: bool
    plant_num: tuple[float, ...]
    plant_den: tuple[float, ...]
    plant_delay: float
    achieved_crossover: float | None
    achieved_phase_margin_deg: float | None
    checks: TuningChecks
    mode: str = "spec"  # "spec": solved; "direct": kp and r given
    solutions: tuple[LoopSolution, ...] = ()

    @property
    def plant(self) -> dict[str, Any]:
        """``{"num", "den", "delay"}`` of the plant the loop was shaped on."""
        return {"num": list(self.plant_num), "den": list(self.plant_den), "delay": self.plant_delay}

    @property
    def achieved(self) -> dict[str, float | None]:
        """``{"crossover", "phase_margin_deg"}`` measured by the dense sweep."""
        return {"crossover": self.achieved_crossover, "phase_margin_deg": self.achieved_phase_margin_deg}

    def to_json(self) -> dict[str, Any]:
        """The interface's ``tune`` document, plus ``mode``, ``flat_phase``, ``solutions`` and ``checks``.

        Non-finite numbers become ``null`` (the CLI prints strict JSON).
        """
        return _finite_or_none(
            {
                "K": self.K,
                "kp": self.kp,
                "r": self.r,
                "crossover": self.crossover,
                "phase_margin_deg": self.phase_margin_deg,
                "plant": {"num": list(self.plant_num), "den": list(self.plant_den), "delay": self.plant_delay},
                "achieved": {"crossover": self.achieved_crossover, "phase_margin_deg": self.achieved_phase_margin_deg},
                "mode": self.mode,
                "flat_phase": self.flat_phase,
                "solutions": [asdict(s) for s in self.solutions],
                "checks": self.checks.to_json(),
            }
        )


def _finite_or_none(value: Any) -> Any:
    if isinstance(value, dict):
        return {key: _finite_or_none(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [_finite_or_none(item) for item in value]
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, np.bool_):
        return bool(value)
    return value


# --- the solver -----------------------------------------------------------------------------------------------


def _brackets_and_roots(residual: Any, r_grid: np.ndarray) -> list[float]:
    """All roots of ``residual`` on ``r_grid``: sign changes refined by brentq, plus tangential roots."""
    from scipy.optimize import brentq, minimize_scalar

    values = np.array([residual(r) for r in r_grid])
    roots: list[float] = []
    for i in np.nonzero(np.sign(values[:-1]) * np.sign(values[1:]) <= 0)[0]:
        if values[i] == 0.0:
            roots.append(float(r_grid[i]))
            continue
        if values[i + 1] == 0.0:
            continue  # counted at i + 1
        roots.append(float(brentq(residual, r_grid[i], r_grid[i + 1], xtol=1e-14, rtol=1e-13, maxiter=200)))
    # a double root touches zero without a sign change: look at local minima of |residual|
    magnitude = np.abs(values)
    scale = max(1.0, float(np.median(magnitude)))
    for j in range(1, len(r_grid) - 1):
        if magnitude[j] <= magnitude[j - 1] and magnitude[j] <= magnitude[j + 1] and magnitude[j] < 1e-3 * scale:
            if np.sign(values[j - 1]) != np.sign(values[j + 1]):
                continue  # already a sign change
            found = minimize_scalar(
                lambda x: abs(residual(x)),
                bounds=(r_grid[j - 1], r_grid[j + 1]),
                method="bounded",
                options={"xatol": 1e-13},
            )
            if abs(residual(found.x)) < 1e-10 * scale:
                roots.append(float(found.x))
    roots.sort()
    unique: list[float] = []
    for root in roots:
        if not unique or abs(root - unique[-1]) > 1e-9:
            unique.append(root)
    return unique


def _deg(x: float) -> str:
    return f"{math.degrees(x):.2f}"


@dataclass(frozen=True)
class _Spec:
    """The loop specification at the crossover and what the plant contributes there."""

    plant: PlantTf
    wc: float
    phase_margin_deg: float
    gain: float  # |G(j wc)|
    phase_g: float  # arg G(j wc), rad
    theta: float  # the phase the PD term must add, rad, in (0, pi)
    where: str  # the plain-language context of an infeasibility message

    @property
    def r_min(self) -> float:
        """The smallest ``r`` whose lead ``r 90`` deg can reach ``theta``."""
        return 2.0 * self.theta / math.pi

    @property
    def r_grid(self) -> np.ndarray:
        """The ``r`` interval ``(r_min, 2)`` sampled densely near both ends."""
        return self.r_min + (2.0 - self.r_min) * _GRID_FRACTIONS

    def x_of(self, r: float) -> float:
        """``kp wc^r`` meeting the phase condition for this ``r``."""
        a = r * math.pi / 2.0
        return math.sin(self.theta) / math.sin(a - self.theta)

    def magnitude_of(self, r: float) -> float:
        """``|1 + kp (j wc)^r|`` for this ``r`` (on the phase condition)."""
        a = r * math.pi / 2.0
        return math.sin(a) / math.sin(a - self.theta)


def _spec(plant: PlantTf, crossover: float, phase_margin_deg: float) -> _Spec:
    """Validate the spec and read the plant at ``wc``; infeasible when the PD lead cannot reach the phase."""
    if not (math.isfinite(crossover) and crossover > 0):
        raise ConfigError(f"must be > 0 rad/s, got {crossover!r}", key="tuning.crossover")
    if not (math.isfinite(phase_margin_deg) and 0 < phase_margin_deg < 180):
        raise ConfigError(f"must be in (0, 180) degrees, got {phase_margin_deg!r}", key="tuning.phase_margin_deg")
    wc = float(crossover)
    g = complex(plant.response(wc))
    gain = abs(g)
    if gain == 0.0 or not math.isfinite(gain):
        raise TuningInfeasibleError(f"the plant's gain at wc={wc:g} rad/s is {gain:g}; no finite K, kp can fix it")
    phase_g = plant.phase(wc)
    target = -math.pi + math.radians(phase_margin_deg)
    theta = float(np.mod(target - phase_g, 2 * math.pi))
    where = (
        f"the plant's phase at wc={wc:g} rad/s is {_deg(phase_g)} deg; the spec needs arg L = "
        f"{_deg(target)} deg (mod 360)"
    )
    return _Spec(plant, wc, float(phase_margin_deg), gain, phase_g, theta, where)


def _unreachable(spec: _Spec, flat_phase: bool) -> TuningInfeasibleError:
    """Why the PD lead (``0 .. r 90`` deg for ``kp > 0``, ``0 < r < 2``) cannot give the phase the spec needs."""
    target = -math.pi + math.radians(spec.phase_margin_deg)
    lag = float(np.mod(target - spec.phase_g + math.pi, 2 * math.pi) - math.pi)
    reachable = _reachable_margins(180.0 + math.degrees(spec.phase_g))
    return TuningInfeasibleError(
        f"{spec.where}, so 1 + kp*s^r would have to add {math.degrees(lag):+.2f} deg, but it adds only "
        f"0..+r*90 deg of lead (< +180) for kp > 0, 0 < r < 2, and K > 0 leaves the phase unchanged"
        f"{' (flat phase included)' if flat_phase else ''}; {reachable}"
    )


def _candidates(spec: _Spec, slope_g: float, flat_phase: bool) -> list[OpenLoop]:
    """Every ``(K, kp, r)`` meeting the spec: ``K = 1`` and ``|L(j wc)| = 1``, or flat phase solving for ``K``."""
    wc, r_grid = spec.wc, spec.r_grid
    if not flat_phase:
        roots = _brackets_and_roots(lambda r: math.log(spec.magnitude_of(r)) + math.log(spec.gain), r_grid)
        if not roots:
            raise TuningInfeasibleError(
                f"{spec.where}; with K = 1 the needed |1 + kp*(j wc)^r| = {1 / spec.gain:.4g} is not met for any r "
                f"in ({spec.r_min:.4g}, 2) (it needs r closer to an end than {_GRID_FRACTIONS[0]:.0e})"
            )
        return [OpenLoop(spec.plant, 1.0, spec.x_of(r) / wc**r, r) for r in roots]

    def flatness(r: float) -> float:
        a = r * math.pi / 2.0
        return (r / wc) * math.sin(spec.theta) * math.sin(a - spec.theta) / math.sin(a) + slope_g

    roots = _brackets_and_roots(flatness, r_grid)
    if not roots:
        raise TuningInfeasibleError(
            f"{spec.where}; flat phase needs the PD term's phase slope (always > 0) to cancel the plant's "
            f"phase slope d arg G/dw = {math.degrees(slope_g):+.4g} deg/(rad/s) at wc, which is not negative"
            if slope_g >= 0
            else f"{spec.where}; no r in ({spec.r_min:.4g}, 2) makes d arg L/dw = 0 at wc"
        )
    return [OpenLoop(spec.plant, 1.0 / (spec.magnitude_of(r) * spec.gain), spec.x_of(r) / wc**r, r) for r in roots]


def _ranked_solutions(wc: float, candidates: list[OpenLoop]) -> list[tuple[LoopSolution, SweepResult, OpenLoop]]:
    """Each candidate with its dense sweep, best first (the selection rule :data:`SELECTION`)."""
    ranked: list[tuple[LoopSolution, SweepResult, OpenLoop]] = []
    for loop in candidates:
        sweep = frequency_sweep(loop, wc * 1e-3, wc * 1e3)
        worst = sweep.worst()
        solution = LoopSolution(
            K=loop.K,
            kp=loop.kp,
            r=loop.r,
            worst_phase_margin_deg=worst.phase_margin_deg if worst else 180.0,
            gain_margin_db=sweep.gain_margin_db,
            n_crossings=len(sweep.crossings),
        )
        ranked.append((solution, sweep, loop))

    def preference(item: tuple[LoopSolution, SweepResult, OpenLoop]) -> tuple[bool, float, float, float]:
        solution = item[0]
        gain_margin = solution.gain_margin_db if solution.gain_margin_db is not None else math.inf
        return (gain_margin <= 0.0, -solution.worst_phase_margin_deg, -gain_margin, solution.kp)

    return sorted(ranked, key=preference)


def _achieved(spec: _Spec, chosen: LoopSolution, sweep: SweepResult) -> Crossing:
    """The sweep's crossing nearest ``wc``; refuse the answer when it misses the spec (independent check)."""
    achieved = sweep.nearest(spec.wc)
    if (
        achieved is None
        or abs(achieved.frequency - spec.wc) > DENSE_CROSSOVER_RTOL * spec.wc
        or abs(wrap_deg(achieved.phase_margin_deg - spec.phase_margin_deg)) > DENSE_PHASE_TOL_DEG
    ):
        raise TuningInfeasibleError(
            f"the solver's answer K={chosen.K:.6g}, kp={chosen.kp:.6g}, r={chosen.r:.6g} fails the independent "
            f"frequency sweep (crossover {achieved.frequency if achieved else None}, "
            f"phase margin {achieved.phase_margin_deg if achieved else None}); refusing to report it"
        )
    return achieved


def tune_loop(
    plant: PlantTf,
    crossover: float,
    phase_margin_deg: float,
    flat_phase: bool = False,
    *,
    python_control: bool = True,
) -> TuningResult:
    """Solve ``|L(j wc)| = 1``, ``arg L(j wc) = -180 + phase_margin_deg`` (and flatness) for ``kp, r`` (``K``).

    Parameters
    ----------
    plant
        The plant ``G`` (validated at construction).
    crossover
        Gain crossover ``wc``, rad/s.
    phase_margin_deg
        Phase margin, degrees, in ``(0, 180)``.
    flat_phase
        Also require ``d arg L / dw = 0`` at ``wc`` and solve ``K``; otherwise ``K = 1``.
    python_control
        Also cross-check the answer with python-control's margins (``checks.python_control``); the design
        pipeline, which keeps only ``kp`` and ``r``, passes ``False``: importing python-control costs a process
        about 1.5 s (it imports matplotlib), more than the whole design on paper_sim.

    Returns
    -------
    TuningResult
        The chosen solution (criterion in the module docstring), all solutions, and the checks.

    Raises
    ------
    foilc_hil.errors.TuningInfeasibleError
        No ``kp > 0``, ``0 < r < 2`` (``K > 0``) meets the spec; the message says which part and why.
    foilc_hil.errors.ConfigError
        A parameter is out of range (named).
    """
    spec = _spec(plant, crossover, phase_margin_deg)
    if not 0.0 < spec.theta < math.pi:
        raise _unreachable(spec, flat_phase)
    slope_g = plant.phase_slope(spec.wc)
    ranked = _ranked_solutions(spec.wc, _candidates(spec, slope_g, flat_phase))
    chosen, sweep, loop = ranked[0]
    achieved = _achieved(spec, chosen, sweep)
    shape = LoopShape(
        plant_phase_deg=math.degrees(spec.phase_g),
        plant_gain=spec.gain,
        pd_phase_deg=math.degrees(spec.theta),
        plant_phase_slope_deg_per_rad_s=math.degrees(slope_g) if flat_phase else None,
    )
    checks = replace(_checks(loop, sweep, achieved, python_control=python_control), shape=shape)
    return TuningResult(
        K=chosen.K,
        kp=chosen.kp,
        r=chosen.r,
        crossover=spec.wc,
        phase_margin_deg=spec.phase_margin_deg,
        flat_phase=flat_phase,
        plant_num=tuple(float(x) for x in loop.plant.num),
        plant_den=tuple(float(x) for x in loop.plant.den),
        plant_delay=loop.plant.delay,
        achieved_crossover=achieved.frequency,
        achieved_phase_margin_deg=achieved.phase_margin_deg,
        mode="spec",
        solutions=tuple(solution for solution, _, _ in ranked),
        checks=checks,
    )


def _reachable_margins(pm_low: float) -> str:
    """Which phase margins the PD lead can reach at this crossover: ``(pm_low, pm_low + 180)`` within (0, 180)."""
    low = float(np.mod(pm_low, 360.0))
    # the reachable set of arg L + 180 is the open arc (low, low + 180) mod 360; intersect with (0, 180)
    arcs = [(low, low + 180.0), (low - 360.0, low - 180.0)]
    pieces = [(max(0.0, a), min(180.0, b)) for a, b in arcs if min(180.0, b) > max(0.0, a)]
    if not pieces:
        return "no phase margin in (0, 180) deg is reachable at this crossover"
    text = " or ".join(f"({a:.2f}, {b:.2f})" for a, b in pieces)
    return f"phase margins reachable at this crossover: {text} deg"


def _checks(loop: OpenLoop, sweep: SweepResult, achieved: Crossing, *, python_control: bool) -> TuningChecks:
    """The warnings and checks of ``loop``, whose sweep crosses at ``achieved`` (python-control's if asked)."""
    return TuningChecks(
        warnings=tuple(_warnings(sweep, achieved, loop.gain_at(sweep.w_max)) + _order_warning(loop.r)),
        sweep=sweep,
        python_control=control_check(loop, achieved.frequency, achieved) if python_control else None,
    )


def _warnings(sweep: SweepResult, achieved: Crossing, loop_at_w_max: float) -> list[str]:
    """Plain-language warnings: what the spec at ``wc`` does not guarantee about the whole loop."""
    warnings: list[str] = []
    others = [c for c in sweep.crossings if c is not achieved]
    if others:
        listed = ", ".join(f"{c.frequency:.4g} rad/s (PM {c.phase_margin_deg:.2f} deg)" for c in others)
        warnings.append(f"|L| also crosses 1 at {listed}")
    if sweep.gain_margin_db is not None and sweep.gain_margin_db <= 0.0:
        warnings.append(
            f"|L| >= 1 where the phase passes -180 deg (gain margin {sweep.gain_margin_db:.2f} dB at "
            f"{sweep.phase_crossover:.4g} rad/s): as a feedback loop this would be unstable"
        )
    if loop_at_w_max >= 1.0:
        warnings.append(
            f"|L| = {loop_at_w_max:.3g} >= 1 at {sweep.w_max:.4g} rad/s: the loop does not roll off "
            "(r above the plant's relative degree)"
        )
    return warnings


def _order_warning(r: float) -> list[str]:
    """The flat-phase warning: an order near 2 makes ``1 + kp s^r`` a near double differentiator."""
    if r <= FLAT_PHASE_ORDER_WARNING:
        return []
    return [
        f"r = {r:.4g} is close to 2: the PD term is nearly a double differentiator (phase of (jw)^r near 180 deg), "
        "so the answer is fragile and its discretised filter's first weight 1 + kp h^-r large; this is an initial "
        "guess, not a convergence proof (synthesis.design: codesign chooses kp, r for the law as it runs)"
    ]


def evaluate_pair(loop: OpenLoop, *, python_control: bool = True) -> TuningResult:
    """The achieved crossover and phase margin of ``loop`` as given (its ``K``, ``kp``, ``r``; no solving).

    The sweep window spans three decades beyond the plant's poles, zeros, ``1/delay`` and the PD corner
    ``kp^(-1/r)``. With several gain crossovers, the one with the smallest phase margin is reported.
    ``python_control`` as in :func:`tune_loop`.
    """
    corners = loop.plant.corners()
    if loop.kp > 0:
        corners.append(loop.kp ** (-1.0 / loop.r))
    corners = corners or [1.0]
    w_min = max(min(corners) * 1e-3, 1e-6)
    w_max = min(max(corners) * 1e3, 1e7)
    sweep = frequency_sweep(loop, w_min, w_max, points_per_decade=1000)
    worst = sweep.worst()
    if worst is not None:
        checks = _checks(loop, sweep, worst, python_control=python_control)
    else:
        loop_at_w_max = loop.gain_at(w_max)
        checks = TuningChecks(
            warnings=(
                f"|L| stays {'above' if loop_at_w_max > 1 else 'below'} 1 over [{sweep.w_min:.4g}, "
                f"{sweep.w_max:.4g}] rad/s: no gain crossover",
            ),
            sweep=sweep,
        )
    return TuningResult(
        K=float(loop.K),
        kp=float(loop.kp),
        r=float(loop.r),
        crossover=worst.frequency if worst else None,
        phase_margin_deg=worst.phase_margin_deg if worst else None,
        flat_phase=False,
        plant_num=tuple(float(x) for x in loop.plant.num),
        plant_den=tuple(float(x) for x in loop.plant.den),
        plant_delay=loop.plant.delay,
        achieved_crossover=worst.frequency if worst else None,
        achieved_phase_margin_deg=worst.phase_margin_deg if worst else None,
        mode="direct",
        checks=checks,
    )


@as_step("tuning kp, r (loop shaping)")
def tune(config: Config, *, python_control: bool = True) -> TuningResult:
    """Tune (or evaluate) the fractional PD function for ``config`` (CLI overrides already applied).

    A complete spec (``tuning.crossover`` and ``tuning.phase_margin_deg``) is solved; otherwise a given
    ``tuning.kp``/``tuning.r`` pair is evaluated. When both are present the spec is solved and the given pair is
    evaluated too (``checks.configured_pair``). ``python_control=False`` leaves out python-control's
    cross-check (:func:`tune_loop`); the dense sweep's check of the answer always runs.

    Raises
    ------
    foilc_hil.errors.ConfigError
        Neither a complete spec nor ``kp``/``r``; the message names the missing key.
    foilc_hil.errors.TuningInfeasibleError
        The spec cannot be met.
    """
    from plant_emulator.linear import continuous_model

    tuning = config.tuning
    has_spec = tuning.crossover is not None and tuning.phase_margin_deg is not None
    has_pair = tuning.kp is not None and tuning.r is not None
    if tuning.crossover is not None and tuning.phase_margin_deg is None:
        raise ConfigError("is required with 'crossover' (--phase-margin)", key="tuning.phase_margin_deg")
    if tuning.phase_margin_deg is not None and tuning.crossover is None:
        raise ConfigError("is required with 'phase_margin_deg' (--crossover)", key="tuning.crossover")
    if not has_spec and not has_pair:
        raise ConfigError(
            "is required: give 'crossover' and 'phase_margin_deg' (or 'kp' and 'r') in the tuning section, "
            "or --crossover and --phase-margin",
            key="tuning.crossover",
        )
    model = continuous_model(config.plant)
    plant = PlantTf(*model.transfer_function(), delay=model.delay)
    if has_spec:
        assert tuning.crossover is not None and tuning.phase_margin_deg is not None
        result = tune_loop(
            plant, tuning.crossover, tuning.phase_margin_deg, tuning.flat_phase, python_control=python_control
        )
        if has_pair:
            assert tuning.kp is not None and tuning.r is not None
            pair = evaluate_pair(OpenLoop(plant, 1.0, tuning.kp, tuning.r), python_control=python_control)
            configured = ConfiguredPair(pair.kp, pair.r, pair.achieved_crossover, pair.achieved_phase_margin_deg)
            result = replace(result, checks=replace(result.checks, configured_pair=configured))
        return result
    assert tuning.kp is not None and tuning.r is not None
    return evaluate_pair(OpenLoop(plant, 1.0, tuning.kp, tuning.r), python_control=python_control)
