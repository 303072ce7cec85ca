"""Per-trial tracking metrics, shared by simulation, the bench, the log and the report."""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from typing import Any

import numpy as np


@dataclass(frozen=True)
class TrialMetrics:
    """``/ilc/trial`` message: sum of squared errors, root mean square error and peak error of one trial.

    ``trial`` counts from 1. For multi-output plants the sums run over all outputs and samples.
    ``rmse_learnable`` is the RMSE over the samples an input of the trial can move: with ``d`` cycles of input
    delay the first ``d`` error samples are fixed by the initial condition (e.g. a step reference from rest over a
    SYNC-driven CAN loop) and no law can reduce them, so this is the figure learning is judged by.
    ``max_abs_error_learnable`` is the peak error over the same samples: ``max_abs_error`` of a trial that starts
    from rest under a stepped reference is that first, unlearnable sample in every trial (e.g. the demo's 400 rpm).
    ``noise_floor`` (from trial 2 on; ``None`` in trial 1) is :func:`noise_floor` of this trial's error against the
    previous trial's: the RMS of the error's trial-to-trial variation, the part no learning law can learn
    (``docs/robustness.md``, *Noise floor*).
    """

    trial: int
    sse: float
    rmse: float
    max_abs_error: float
    rmse_learnable: float
    max_abs_error_learnable: float
    noise_floor: float | None = None

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


def trial_metrics(trial: int, error: np.ndarray, *, first_learnable: int = 0) -> TrialMetrics:
    """Metrics of one trial's tracking error ``e = y_r - y`` (shape ``(N,)`` or ``(N, p)``).

    ``first_learnable`` is the first error sample an input of the trial can move (the input delay in samples).
    """
    e = np.asarray(error, dtype=float)
    if e.size == 0:
        raise ValueError("empty error signal")
    if not 0 <= first_learnable < e.shape[0]:
        raise ValueError(f"first_learnable must be in 0..{e.shape[0] - 1}, got {first_learnable}")
    sse = float(np.sum(e * e))
    learnable = e[first_learnable:]
    return TrialMetrics(
        trial=trial,
        sse=sse,
        rmse=float(np.sqrt(sse / e.size)),
        max_abs_error=float(np.max(np.abs(e))),
        rmse_learnable=float(np.sqrt(np.sum(learnable * learnable) / learnable.size)),
        max_abs_error_learnable=float(np.max(np.abs(learnable))),
    )


def noise_floor(error: np.ndarray, previous: np.ndarray) -> float:
    """The noise floor of a trial: ``sqrt(mean((e_k - e_{k-1})^2) / 2)`` over all samples and outputs.

    A law can learn only what repeats from trial to trial; the error's trial-varying part (measurement noise, a
    time-varying plant, and the noise the law feeds back into the next input) it cannot. With white noise of
    standard deviation ``sigma`` on the measurement and an input that no longer changes, ``e_k - e_{k-1}`` is the
    difference of two independent noise samples, so the expected square of the figure is exactly ``sigma^2``; once a
    law has converged it is the level its tracking error fluctuates at (``docs/robustness.md`` works out the
    deadbeat case, ``sqrt(3) sigma``). Before convergence it also holds the learning's own progress. Samples no
    input can move (the input delay) need no special case: what repeats in them cancels, their noise does not.

    Parameters
    ----------
    error, previous
        The errors ``e = y_r - y`` of this trial and the one before, the same shape (``(N,)`` or ``(N, p)``).
    """
    e = np.asarray(error, dtype=float)
    before = np.asarray(previous, dtype=float)
    if e.size == 0 or e.shape != before.shape:
        raise ValueError(f"the previous trial's error has shape {before.shape}, this one {e.shape} (non-empty)")
    change = e - before
    return float(np.sqrt(np.mean(change * change) / 2.0))


class NoiseFloorTracker:
    """Adds :func:`noise_floor` to each trial's metrics in turn (it keeps the previous trial's error)."""

    def __init__(self) -> None:
        self._previous: np.ndarray | None = None

    def measured(self, metrics: TrialMetrics, error: np.ndarray) -> TrialMetrics:
        """``metrics`` with ``noise_floor`` set against the previous call's ``error`` (unset on the first call)."""
        current = np.array(error, dtype=float)
        previous, self._previous = self._previous, current
        if previous is None or previous.shape != current.shape:
            return metrics
        return replace(metrics, noise_floor=noise_floor(current, previous))
