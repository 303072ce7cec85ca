"""Per-trial tracking metrics, shared by simulation, the bench, the log and the report."""

from __future__ import annotations

from dataclasses import asdict, dataclass
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
    """

    trial: int
    sse: float
    rmse: float
    max_abs_error: float
    rmse_learnable: float
    max_abs_error_learnable: float

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
