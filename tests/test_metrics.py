"""Trial metrics against hand computations."""

from __future__ import annotations

import math

import numpy as np
import pytest

from foilc_hil.metrics import trial_metrics


def test_metrics_of_a_known_error() -> None:
    error = np.array([3.0, -4.0, 0.0, 0.0])
    metrics = trial_metrics(2, error)
    assert metrics.trial == 2
    assert metrics.sse == 25.0
    assert metrics.rmse == pytest.approx(2.5)
    assert metrics.max_abs_error == 4.0
    assert metrics.rmse_learnable == metrics.rmse  # no input delay: every sample is learnable
    assert metrics.max_abs_error_learnable == metrics.max_abs_error


def test_learnable_rmse_leaves_out_the_delayed_samples() -> None:
    """With one cycle of input delay the first sample (fixed by the initial condition) is left out."""
    error = np.array([400.0, 1.0, -1.0, 1.0])
    metrics = trial_metrics(1, error, first_learnable=1)
    assert metrics.rmse == pytest.approx(math.sqrt((400.0**2 + 3) / 4))
    assert metrics.rmse_learnable == pytest.approx(1.0)
    assert metrics.max_abs_error == 400.0 and metrics.max_abs_error_learnable == 1.0


@pytest.mark.parametrize("first", [-1, 4])
def test_first_learnable_must_lie_inside_the_trial(first: int) -> None:
    with pytest.raises(ValueError, match="first_learnable"):
        trial_metrics(1, np.ones(4), first_learnable=first)
