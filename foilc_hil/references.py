"""Repeated set-point profiles ``y_r(t)`` of one trial: paper eq. (49), eq. (52) and user piecewise profiles.

Sample alignment (shared with :mod:`foilc_hil.laws.learning` and :mod:`foilc_hil.loop.simulation`)
-------------------------------------------------------------------------------------
A trial of ``N`` samples issues the inputs ``u(0) .. u(N-1)``; ``u(i)`` is held over ``[i Ts, (i+1) Ts)``.
Trial arrays (reference, output, error, ``E``) are indexed ``i = 0 .. N-1`` and hold the value at the END of
sample ``i``, i.e. at ``t = (i + 1) Ts``::

    reference[i] = y_r((i + 1) Ts)        output[i] = y((i + 1) Ts)        error[i] = reference[i] - output[i]

So ``error[i]`` is the paper's ``e(t_d + 1)`` for ``t_d = i``: the first sample the input ``u(i)`` can move
(relative degree one). The printed profiles are defined on half-open intervals ``0 < t <= T``, which is exactly
the grid ``(i + 1) Ts``, ``i = 0 .. N-1``: the uncontrollable initial output ``y(0)`` is not part of a trial.
"""

from __future__ import annotations

import math

import numpy as np

from foilc_hil.config import ReferenceConfig
from foilc_hil.errors import ConfigError

__all__ = ["MAX_TRIAL_SAMPLES", "reference_profile", "sample_times", "trial_duration", "trial_samples"]

#: the most samples a trial may have: 200 s at 1 kHz, ten times the longest trial the design is measured at (a
#: trial's arrays, its design and its certificates grow with N; a segment of 1e12 s asked for 7 PiB)
MAX_TRIAL_SAMPLES = 200_000
#: eq. (49): 1 on (0, 10] s, 0 on (10, 20] s.
_EQ49_DURATION = 20.0
#: eq. (52) is printed in milliseconds over (0, 6000]; with ``time_scale = 1`` a trial lasts 6 s.
_EQ52_DURATION = 6.0


def trial_duration(cfg: ReferenceConfig) -> float:
    """Length of one trial in seconds (``time_scale`` stretches every profile in time), the ``lead_in`` and
    ``lead_out`` ramps included."""
    return _profile_duration(cfg) + cfg.lead_in + cfg.lead_out


def _profile_duration(cfg: ReferenceConfig) -> float:
    """Length of the profile itself, between the lead-in and the lead-out."""
    if cfg.profile == "eq49":
        base = _EQ49_DURATION
    elif cfg.profile == "eq52":
        base = _EQ52_DURATION
    else:
        assert cfg.segments is not None  # the config validator requires segments for 'piecewise'
        base = math.fsum(segment.duration for segment in cfg.segments)
    return base * cfg.time_scale


def trial_samples(cfg: ReferenceConfig, sample_time: float) -> int:
    """Samples per trial, ``N = T / Ts``.

    Raises
    ------
    foilc_hil.errors.ConfigError
        Naming ``sample_time`` when the trial is not a whole number of samples, or is shorter than one; naming the
        longest segment (or ``sample_time``) when it has more than :data:`MAX_TRIAL_SAMPLES`.
    """
    if not (sample_time > 0 and math.isfinite(sample_time)):
        raise ConfigError("must be positive and finite", key="sample_time")
    duration = trial_duration(cfg)
    ratio = duration / sample_time
    if not ratio <= MAX_TRIAL_SAMPLES:  # NaN and inf too
        raise ConfigError(
            f"a trial of {duration:g} s at sample_time {sample_time:g} s is {ratio:.3g} samples; at most "
            f"{MAX_TRIAL_SAMPLES} (shorten the trial or lengthen sample_time)",
            key=_longest_segment(cfg),
        )
    n = round(ratio)
    if n < 1 or abs(ratio - n) > 1e-6 * max(1.0, ratio):
        raise ConfigError(
            f"the trial ({duration:g} s, reference.profile {cfg.profile}) is not a whole number of samples of "
            f"{sample_time:g} s",
            key="sample_time",
        )
    return int(n)


def _longest_segment(cfg: ReferenceConfig) -> str:
    """The key a too-long trial is named by: its longest piecewise segment, else ``sample_time``."""
    if cfg.profile != "piecewise" or not cfg.segments:
        return "sample_time"
    longest = max(range(len(cfg.segments)), key=lambda k: cfg.segments[k].duration)  # type: ignore[index]
    return f"reference.segments[{longest}].duration"


def sample_times(cfg: ReferenceConfig, sample_time: float) -> np.ndarray:
    """The instants ``(i + 1) Ts``, ``i = 0 .. N-1``, at which the trial arrays are defined (module docstring)."""
    n = trial_samples(cfg, sample_time)
    return np.arange(1, n + 1, dtype=float) * sample_time


def reference_profile(cfg: ReferenceConfig, sample_time: float) -> np.ndarray:
    """The reference of one trial sampled at ``t = (i + 1) Ts``, shape ``(N,)``, multiplied by ``cfg.scale``.

    For a plant with several outputs the same profile applies to every output (the laws broadcast ``(N,)``
    to ``(N, p)``).

    Parameters
    ----------
    cfg
        The ``reference:`` section.
    sample_time
        ``Ts`` in seconds.
    """
    t = sample_times(cfg, sample_time)
    # Breakpoints are compared with a tolerance far below one sample so that e.g. 1000 * 0.01 lands on 10 s.
    tol = 1e-9 * sample_time
    if cfg.lead_in or cfg.lead_out:
        return _with_leads(cfg, t, tol)
    return _profile_values(cfg, t, tol) * cfg.scale


def _with_leads(cfg: ReferenceConfig, t: np.ndarray, tol: float) -> np.ndarray:
    """The profile shifted by ``lead_in``, with a ramp from rest up to its first value before it and from its last
    value down to rest after it (the profile's own ends, sampled just inside them)."""
    begin, end = cfg.lead_in, cfg.lead_in + _profile_duration(cfg)
    inner = np.clip(t - begin, tol, end - begin)
    values = _profile_values(cfg, inner, tol)
    edges = _profile_values(cfg, np.array([tol, end - begin]), tol)
    first, last = float(edges[0]), float(edges[1])
    if cfg.lead_in:
        before = t <= begin + tol
        values = np.where(before, first * np.clip(t / cfg.lead_in, 0.0, 1.0), values)
    if cfg.lead_out:
        after = t > end + tol
        values = np.where(after, last * np.clip((t[-1] - t) / cfg.lead_out, 0.0, 1.0), values)
    return np.asarray(values * cfg.scale, dtype=float)


def _profile_values(cfg: ReferenceConfig, t: np.ndarray, tol: float) -> np.ndarray:
    """The profile (unscaled) at the instants ``t`` of its own time axis."""
    if cfg.profile == "eq49":
        edge = 10.0 * cfg.time_scale
        values = np.where(t <= edge + tol, 1.0, 0.0)
    elif cfg.profile == "eq52":
        t_ms = t * (1000.0 / cfg.time_scale)
        tol_ms = tol * (1000.0 / cfg.time_scale)
        ramp = 0.2 * (t_ms - 3000.0) + 400.0
        values = np.where(t_ms <= 3000.0 + tol_ms, 400.0, np.where(t_ms <= 4000.0 + tol_ms, ramp, 600.0))
    else:
        values = _piecewise(cfg, t, tol)
    return np.asarray(values, dtype=float)


def _piecewise(cfg: ReferenceConfig, t: np.ndarray, tol: float) -> np.ndarray:
    """Segments in order; segment ``j`` covers ``(t_j, t_j + duration_j]`` (holds ``start`` or ramps to ``end``)."""
    assert cfg.segments is not None
    values = np.zeros_like(t)
    assigned = np.zeros(t.shape, dtype=bool)
    begin = 0.0
    for segment in cfg.segments:
        length = segment.duration * cfg.time_scale
        finish = begin + length
        inside = ~assigned & (t <= finish + tol)
        if segment.end is None:
            values[inside] = segment.start
        else:
            fraction = np.clip((t[inside] - begin) / length, 0.0, 1.0)
            values[inside] = segment.start + (segment.end - segment.start) * fraction
        assigned |= inside
        begin = finish
    # Rounding can leave the very last sample a hair past the sum of durations: it belongs to the last segment.
    if not np.all(assigned):
        last = cfg.segments[-1]
        values[~assigned] = last.start if last.end is None else last.end
    return values
