"""Per-trial tracking metrics, shared by simulation, the bench, the log and the report."""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np


@dataclass(frozen=True)
class TrialMetrics:
    """``/ilc/trial`` message: sum of squared errors, root mean square error and peak error of one trial.

    ``trial`` counts from 1. For multi-output plants the sums run over all outputs and samples.
    """

    trial: int
    sse: float
    rmse: float
    max_abs_error: float

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


def trial_metrics(trial: int, error: np.ndarray) -> TrialMetrics:
    """Metrics of one trial's tracking error ``e = y_r - y`` (shape ``(N,)`` or ``(N, p)``)."""
    e = np.asarray(error, dtype=float)
    if e.size == 0:
        raise ValueError("empty error signal")
    sse = float(np.sum(e * e))
    return TrialMetrics(
        trial=trial,
        sse=sse,
        rmse=float(np.sqrt(sse / e.size)),
        max_abs_error=float(np.max(np.abs(e))),
    )
