"""The open loop ``L(s) = K (1 + kp s^r) G(s)`` of the loop-shaping tuner (:mod:`foilc_hil.design.tuning`) and the
two checks of a tuned loop that are independent of its solver.

:class:`PlantTf` is the plant's transfer function ``G(s) = num(s) / den(s) * exp(-delay s)``, :class:`OpenLoop`
the loop with the fractional PD term, evaluated exactly (``(j w)^r`` and the delay, no approximation).

Checking
--------
Every answer of the tuner is checked twice, independently of the solver:

1. :func:`frequency_sweep`: a dense log-frequency sweep of ``L(j w)`` (numpy, exact ``(j w)^r`` and delay) finds
   every gain crossover by interpolation and its phase margin; the tuner's ``achieved`` numbers come from here
   and must meet the spec (``tuning.DENSE_CROSSOVER_RTOL``, ``tuning.DENSE_PHASE_TOL_DEG``);
2. :func:`control_check`: python-control's ``stability_margins`` on a rational model: ``s^r = s^n s^alpha``
   (``n = round(r)``, ``|alpha| <= 1/2``) with ``s^alpha`` replaced by an Oustaloup approximation
   (:func:`oustaloup`) of order 7 on ``[wc/1000, 1000 wc]`` centred on the crossover, where its phase error is
   smallest (0.07 deg within a factor 2 of the centre, 0.3 deg a decade away, for ``alpha = 1/2``), and the delay
   by a Padé approximation. Measured over 32 random feasible designs: crossover within 0.01 % (``K = 1``) and
   0.9 % (flat phase, where ``|L|`` is flat near ``wc``), phase margin within 0.06 deg. It must agree within
   :data:`CONTROL_CROSSOVER_RTOL` / :data:`CONTROL_PHASE_TOL_DEG`. The same model gives the closed-loop poles
   (stability of the unity-feedback loop, as far as the approximation goes).

Module order: after :mod:`foilc_hil.design.codesign`, before :mod:`foilc_hil.design.tuning`.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from foilc_hil.errors import ConfigError

__all__ = [
    "CONTROL_CROSSOVER_RTOL",
    "CONTROL_PHASE_TOL_DEG",
    "SWEEP_POINTS_PER_DECADE",
    "Coefficients",
    "ControlCheck",
    "Crossing",
    "OpenLoop",
    "PlantTf",
    "SweepResult",
    "control_check",
    "frequency_sweep",
    "oustaloup",
    "wrap_deg",
]

Coefficients = Sequence[float] | np.ndarray
"""Polynomial coefficients, highest power first."""

#: python-control on the Oustaloup/Padé model must agree with the dense sweep within 1 % ...
CONTROL_CROSSOVER_RTOL = 0.01
#: ... and 1 degree.
CONTROL_PHASE_TOL_DEG = 1.0

SWEEP_POINTS_PER_DECADE = 2000
_OUSTALOUP_ORDER = 7
_OUSTALOUP_SPAN = 1000.0  # the approximation band is [wc / span, wc * span]


# --- data -----------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Crossing:
    """One gain crossover of ``L(j w)``: frequency (rad/s) and phase margin there (deg, in ``(-180, 180]``)."""

    frequency: float
    phase_margin_deg: float


@dataclass(frozen=True)
class SweepResult:
    """What the dense frequency sweep found in ``[w_min, w_max]``."""

    w_min: float
    w_max: float
    crossings: tuple[Crossing, ...]
    gain_margin_db: float | None  # smallest over the phase crossovers in the window; None: no phase crossover
    phase_crossover: float | None
    points_per_decade: int  # the grid the sweep ran on: the record says what was swept, not the default

    def nearest(self, w: float) -> Crossing | None:
        """The crossing closest to ``w`` on a log scale."""
        if not self.crossings:
            return None
        return min(self.crossings, key=lambda c: abs(math.log(c.frequency / w)))

    def worst(self) -> Crossing | None:
        """The crossing with the smallest phase margin."""
        if not self.crossings:
            return None
        return min(self.crossings, key=lambda c: c.phase_margin_deg)


@dataclass(frozen=True)
class ControlCheck:
    """What :func:`control_check` found: python-control's margins of ``L`` on a rational model.

    Attributes
    ----------
    method
        How the model was made and checked (python-control's version, Oustaloup's order and band, Padé's order).
    crossover, phase_margin_deg
        The gain crossover nearest the one asked about (rad/s) and its phase margin (deg); ``None``: none found.
    closed_loop_max_real_pole, closed_loop_stable
        The closed loop's largest real part of a pole (rad/s) and whether it is negative; ``None``: not computed.
    closed_loop_note
        Why the closed loop was not computed (an improper loop has no state-space feedback), or ``None``.
    agrees_with_sweep
        Whether crossover and phase margin agree with the dense sweep's crossing within ``CONTROL_CROSSOVER_RTOL`` /
        ``CONTROL_PHASE_TOL_DEG``; ``None``: no crossing was given to compare with.
    error
        Why the check could not run (it then never counts as agreement), or ``None``.
    """

    method: str
    crossover: float | None = None
    phase_margin_deg: float | None = None
    closed_loop_max_real_pole: float | None = None
    closed_loop_stable: bool | None = None
    closed_loop_note: str | None = None
    agrees_with_sweep: bool | None = None
    error: str | None = None

    def to_json(self) -> dict[str, Any]:
        """The ``tune`` document's ``checks.python_control``: the keys that apply, in this order."""
        if self.error is not None:
            return {"method": self.method, "error": self.error, "agrees_with_sweep": False}
        document: dict[str, Any] = {
            "method": self.method,
            "crossover": self.crossover,
            "phase_margin_deg": self.phase_margin_deg,
        }
        if self.closed_loop_note is None:
            document["closed_loop_max_real_pole"] = self.closed_loop_max_real_pole
            document["closed_loop_stable"] = self.closed_loop_stable
        else:
            document["closed_loop_stable"] = None
            document["closed_loop_note"] = self.closed_loop_note
        if self.agrees_with_sweep is not None:
            document["agrees_with_sweep"] = self.agrees_with_sweep
            document["tolerance"] = {"crossover_rel": CONTROL_CROSSOVER_RTOL, "phase_margin_deg": CONTROL_PHASE_TOL_DEG}
        return document


# --- the plant and the open loop -------------------------------------------------------------------------------


def _frozen_array(values: Coefficients) -> np.ndarray:
    """Leading zeros trimmed, as a read-only float array (a frozen value object must not change under us)."""
    array = np.trim_zeros(np.asarray(values, dtype=float), "f")
    array.flags.writeable = False
    return array


@dataclass(frozen=True, eq=False, init=False)
class PlantTf:
    """The plant ``G(s) = num(s) / den(s) * exp(-delay s)``, validated once at construction.

    Parameters
    ----------
    num, den
        Numerator and denominator, highest power first; leading zeros are trimmed and the arrays made read-only.
    delay
        Transport delay, seconds, finite and ``>= 0``.

    Raises
    ------
    foilc_hil.errors.ConfigError
        ``plant.num`` / ``plant.den`` empty (all zeros) or not finite, ``plant.delay`` negative or not finite.
    """

    num: np.ndarray
    den: np.ndarray
    delay: float

    def __init__(self, num: Coefficients, den: Coefficients, delay: float = 0.0) -> None:
        # a hand-written __init__: it takes any coefficient sequence, the fields hold only validated arrays
        num_a = _frozen_array(num)
        den_a = _frozen_array(den)
        if num_a.size == 0 or not np.all(np.isfinite(num_a)):
            raise ConfigError("must be finite and non-zero", key="plant.num")
        if den_a.size == 0 or not np.all(np.isfinite(den_a)):
            raise ConfigError("must be finite and non-zero", key="plant.den")
        if not (math.isfinite(delay) and delay >= 0.0):
            raise ConfigError(f"must be finite and >= 0, got {delay!r}", key="plant.delay")
        object.__setattr__(self, "num", num_a)
        object.__setattr__(self, "den", den_a)
        object.__setattr__(self, "delay", float(delay))

    def __eq__(self, other: object) -> bool:
        # by value: the generated __eq__ would compare arrays elementwise and fail on their truth value
        if not isinstance(other, PlantTf):
            return NotImplemented
        return self._key() == other._key()

    def __hash__(self) -> int:
        return hash(self._key())

    def _key(self) -> tuple[tuple[float, ...], tuple[float, ...], float]:
        return tuple(float(x) for x in self.num), tuple(float(x) for x in self.den), self.delay

    def rational(self, w: np.ndarray | float) -> np.ndarray:
        """``num(j w) / den(j w)``: the response without the delay."""
        s = 1j * np.asarray(w, dtype=float)
        return np.asarray(np.polyval(self.num, s) / np.polyval(self.den, s))

    def response(self, w: np.ndarray | float) -> np.ndarray:
        """``G(j w)``, delay included."""
        return np.asarray(self.rational(w) * np.exp(-1j * self.delay * np.asarray(w, dtype=float)))

    def rational_phase(self, w: float) -> float:
        """Continuous phase of ``num(j w) / den(j w)`` in radians: the sum of the factors' angles.

        Each factor ``(j w - z)`` has an angle continuous in ``w > 0`` (no root on the imaginary axis at ``w``),
        so this is the phase unwrapped from ``w -> 0+``.
        """
        s = 1j * w
        phase = float(np.angle(self.num[0] / self.den[0]))
        phase += float(np.sum(np.angle(s - np.roots(self.num)))) if self.num.size > 1 else 0.0
        phase -= float(np.sum(np.angle(s - np.roots(self.den)))) if self.den.size > 1 else 0.0
        return phase

    def phase(self, w: float) -> float:
        """Continuous phase of ``G(j w)`` in radians: :meth:`rational_phase` minus ``delay * w``.

        E.g. ``-pi/2 - 0.7`` for ``1.68/(s + 1.23) e^{-0.01 s}`` at ``w = 70`` rather than a value folded into
        ``(-pi, pi]``.
        """
        return self.rational_phase(w) - self.delay * w

    def phase_slope(self, w: float) -> float:
        """``d arg G(j w) / d w`` in rad per rad/s: ``Re(num'/num - den'/den)(j w) - delay``."""
        s = 1j * w
        log_derivative = np.polyval(np.polyder(self.num), s) / np.polyval(self.num, s) - np.polyval(
            np.polyder(self.den), s
        ) / np.polyval(self.den, s)
        return float(np.real(log_derivative)) - self.delay

    def corners(self) -> list[float]:
        """The non-zero poles' and zeros' magnitudes and ``1 / delay``: where ``|G|`` and ``arg G`` bend."""
        roots = np.concatenate([np.roots(self.num), np.roots(self.den)])
        corners = [float(abs(z)) for z in roots if abs(z) > 0]
        if self.delay > 0:
            corners.append(1.0 / self.delay)
        return corners

    def scaled(self, wc: float) -> tuple[np.ndarray, np.ndarray]:
        """``num(wc sigma)``, ``den(wc sigma)``: the polynomials in ``sigma = s / wc`` (well conditioned near wc)."""
        return (
            self.num * wc ** np.arange(self.num.size - 1, -1, -1),
            self.den * wc ** np.arange(self.den.size - 1, -1, -1),
        )


@dataclass(frozen=True)
class OpenLoop:
    """The open loop ``L(s) = K (1 + kp s^r) G(s)``, validated once at construction.

    Raises
    ------
    foilc_hil.errors.ConfigError
        ``tuning.kp`` negative, ``tuning.r`` outside ``(0, 2)``, ``K`` not positive (or any not finite).
    """

    plant: PlantTf
    K: float = 1.0
    kp: float = 0.0
    r: float = 1.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.kp) and self.kp >= 0):
            raise ConfigError(f"must be >= 0, got {self.kp!r}", key="tuning.kp")
        if not (math.isfinite(self.r) and 0 < self.r < 2):
            raise ConfigError(f"must satisfy 0 < r < 2, got {self.r!r}", key="tuning.r")
        if not (math.isfinite(self.K) and self.K > 0):
            raise ConfigError(f"must be > 0, got {self.K!r}", key="K")

    def pd_term(self, w: np.ndarray | float) -> np.ndarray:
        """``1 + kp (j w)^r`` (principal branch of ``(j w)^r``)."""
        w = np.asarray(w, dtype=float)
        return np.asarray(1.0 + self.kp * w**self.r * np.exp(1j * self.r * math.pi / 2.0))

    def rational(self, w: np.ndarray | float) -> np.ndarray:
        """``L(j w)`` without the plant's delay."""
        return np.asarray(self.K * self.pd_term(w) * self.plant.rational(w))

    def response(self, w: np.ndarray | float) -> np.ndarray:
        """``L(j w) = K (1 + kp (j w)^r) G(j w)`` evaluated exactly."""
        return np.asarray(self.rational(w) * np.exp(-1j * self.plant.delay * np.asarray(w, dtype=float)))

    def gain_at(self, w: float) -> float:
        """``|L(j w)|`` at one frequency."""
        return float(np.abs(self.response(np.array([w]))[0]))


def wrap_deg(angle: np.ndarray | float) -> np.ndarray:
    """Wrap degrees into ``(-180, 180]``."""
    return np.asarray(180.0 - np.mod(180.0 - np.asarray(angle, dtype=float), 360.0))


# --- independent check 1: dense sweep -------------------------------------------------------------------------


def frequency_sweep(
    loop: OpenLoop, w_min: float, w_max: float, points_per_decade: int = SWEEP_POINTS_PER_DECADE
) -> SweepResult:
    """Every gain crossover of ``L(j w)`` on a dense log grid, by linear interpolation in ``log w``.

    Independent of the solver: it only evaluates ``L`` and interpolates. Phase is unwrapped along the grid
    (rational part) with the delay's ``-delay * w`` added exactly, so wrapping is never guessed.
    """
    decades = math.log10(w_max / w_min)
    w = np.logspace(math.log10(w_min), math.log10(w_max), max(64, int(decades * points_per_decade)) + 1)
    rational = loop.rational(w)
    log_mag = np.log(np.abs(rational))
    phase = np.unwrap(np.angle(rational))
    # anchor the unwrapped branch on the plant's continuous phase at the first grid point
    anchor = loop.plant.rational_phase(float(w[0])) + float(np.angle(loop.pd_term(w[0])))
    phase += 2 * math.pi * round((anchor - phase[0]) / (2 * math.pi))
    phase_deg = np.degrees(phase - loop.plant.delay * w)
    log_w = np.log(w)

    crossings: list[Crossing] = []
    # a grid point may land exactly on |L| = 1 (the grid is anchored on wc): compare "above 1" flags, not signs
    above = log_mag > 0.0
    for i in np.nonzero(above[:-1] != above[1:])[0]:
        frac = log_mag[i] / (log_mag[i] - log_mag[i + 1])
        wc = float(np.exp(log_w[i] + frac * (log_w[i + 1] - log_w[i])))
        ph = phase_deg[i] + frac * (phase_deg[i + 1] - phase_deg[i])
        crossings.append(Crossing(wc, float(wrap_deg(180.0 + ph))))

    # phase crossovers: the phase passes an odd multiple of -180 deg
    shifted = (phase_deg + 180.0) / 360.0
    cells = np.floor(shifted)
    gain_margin_db: float | None = None
    phase_crossover: float | None = None
    for i in np.nonzero(cells[:-1] != cells[1:])[0]:
        level = max(cells[i], cells[i + 1])
        frac = (level - shifted[i]) / (shifted[i + 1] - shifted[i])
        gm = -float(log_mag[i] + frac * (log_mag[i + 1] - log_mag[i])) * 20.0 / math.log(10.0)
        if gain_margin_db is None or gm < gain_margin_db:
            gain_margin_db = gm
            phase_crossover = float(np.exp(log_w[i] + frac * (log_w[i + 1] - log_w[i])))
    return SweepResult(float(w[0]), float(w[-1]), tuple(crossings), gain_margin_db, phase_crossover, points_per_decade)


# --- independent check 2: python-control on a rational model ---------------------------------------------------


def oustaloup(
    alpha: float, w_low: float, w_high: float, order: int = _OUSTALOUP_ORDER
) -> tuple[np.ndarray, np.ndarray, float]:
    """Oustaloup's rational approximation of ``s^alpha`` (``-1 < alpha < 1``) on ``[w_low, w_high]``.

    Returns ``zeros, poles, gain`` with ``s^alpha ~ gain * prod (s - z_k) / (s - p_k)``, ``2 order + 1`` pairs.
    """
    k = np.arange(-order, order + 1, dtype=float)
    span = w_high / w_low
    n_pairs = 2 * order + 1
    zero_freqs = w_low * span ** ((k + order + 0.5 * (1 - alpha)) / n_pairs)
    pole_freqs = w_low * span ** ((k + order + 0.5 * (1 + alpha)) / n_pairs)
    return -zero_freqs, -pole_freqs, w_high**alpha


def control_check(loop: OpenLoop, crossover: float, reference: Crossing | None = None) -> ControlCheck:
    """python-control's margins of ``L`` with ``s^r`` -> ``s^n`` times Oustaloup, and delay -> Padé.

    Frequencies are scaled by ``crossover`` (``s = wc * sigma``) so the polynomials stay well conditioned.
    Returns (:class:`ControlCheck`) the crossover nearest ``crossover``, its phase margin, the closed-loop poles'
    largest real part, and, when ``reference`` (the dense sweep's crossing) is given, whether both agree within
    ``CONTROL_CROSSOVER_RTOL`` / ``CONTROL_PHASE_TOL_DEG``.
    """
    import control

    wc = crossover
    K, kp, r, delay = loop.K, loop.kp, loop.r, loop.plant.delay
    plant = control.tf(*loop.plant.scaled(wc))
    # s^r = s^n * s^alpha with |alpha| <= 1/2: Oustaloup's band-edge phase error grows with |alpha|
    integer_part = round(r)
    alpha = r - integer_part
    zeros, poles, gain = oustaloup(alpha, 1.0 / _OUSTALOUP_SPAN, _OUSTALOUP_SPAN)
    frac = control.zpk(zeros, poles, gain) if alpha != 0 else control.tf([1.0], [1.0])
    s = control.tf("s")
    s_power = frac * s**integer_part
    pd_term = 1 + kp * wc**r * s_power  # kp (wc sigma)^r
    pade_order = 0
    delay_model = control.tf([1.0], [1.0])
    if delay * wc > 1e-6:  # below: under 1e-4 deg of phase at wc, and Pade's coefficients would overflow
        pade_order = int(min(12, max(3, math.ceil(2 * delay * wc * 3))))
        pnum, pden = control.pade(delay * wc, pade_order)
        delay_model = control.tf(pnum, pden)
    try:
        model = control.minreal(K * pd_term * plant * delay_model, verbose=False)
        # stability_margins also computes the Nyquist distance (unused here) from a high-degree polynomial that
        # can overflow; the phase margin and crossover it returns are checked against the sweep below.
        with np.errstate(over="ignore", invalid="ignore"), warnings.catch_warnings():
            warnings.simplefilter("ignore", RuntimeWarning)
            _, pm, _, _, wgc, _ = control.stability_margins(model, returnall=True)
    except (ValueError, ArithmeticError, np.linalg.LinAlgError) as exc:
        # the check could not run: say so; it never counts as agreement
        return ControlCheck("python-control stability_margins", agrees_with_sweep=False, error=str(exc))
    wgc = np.atleast_1d(np.asarray(wgc, dtype=float))
    pm = np.atleast_1d(np.asarray(pm, dtype=float))
    method = (
        f"python-control {control.__version__} stability_margins; s^r = s^{integer_part} * Oustaloup(s^"
        f"{alpha:.4g}, order {_OUSTALOUP_ORDER}) on [wc/{_OUSTALOUP_SPAN:g}, {_OUSTALOUP_SPAN:g} wc]; delay: "
        f"Pade order {pade_order}"
    )
    found: Crossing | None = None
    if wgc.size:
        i = int(np.argmin(np.abs(np.log(wgc))))
        found = Crossing(float(wgc[i] * wc), float(wrap_deg(pm[i])))
    max_real: float | None = None
    stable: bool | None = None
    note: str | None = None
    try:
        closed = control.feedback(model, 1)
        max_real = float(np.max(np.real(closed.poles()))) * wc
        stable = bool(max_real < 0)
    except (ValueError, np.linalg.LinAlgError) as exc:  # an improper loop has no state-space feedback
        note = f"not computed: {exc}"
    return ControlCheck(
        method,
        crossover=None if found is None else found.frequency,
        phase_margin_deg=None if found is None else found.phase_margin_deg,
        closed_loop_max_real_pole=max_real,
        closed_loop_stable=stable,
        closed_loop_note=note,
        agrees_with_sweep=None if reference is None else _agrees(found, reference),
    )


def _agrees(found: Crossing | None, reference: Crossing) -> bool:
    """Whether python-control's crossover and phase margin agree with the dense sweep's crossing ``reference``."""
    return bool(
        found is not None
        and abs(found.frequency - reference.frequency) <= CONTROL_CROSSOVER_RTOL * reference.frequency
        and abs(wrap_deg(found.phase_margin_deg - reference.phase_margin_deg)) <= CONTROL_PHASE_TOL_DEG
    )
