"""Trial metrics against hand computations."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from scipy.signal import lfilter

from foilc_hil.metrics import NoiseFloorTracker, noise_floor, trial_metrics


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


def test_noise_floor_of_a_known_change() -> None:
    """``sqrt(mean((e_k - e_{k-1})^2) / 2)``: a change of +-2 on every sample gives sqrt(4 / 2)."""
    before = np.array([5.0, 1.0, -3.0, 0.5])
    assert noise_floor(before + np.array([2.0, -2.0, 2.0, -2.0]), before) == pytest.approx(math.sqrt(2.0))
    assert noise_floor(before, before) == 0.0  # what repeats (learnable or not) is no noise
    with pytest.raises(ValueError, match="shape"):
        noise_floor(before, before[:3])


def test_noise_floor_is_sigma_when_the_input_no_longer_changes() -> None:
    """Analytic case 1: a fixed input, white measurement noise sigma: ``E[(v_k - v_{k-1})^2] / 2 = sigma^2``."""
    sigma, n = 0.3, 20_000
    rng = np.random.default_rng(1)
    clean = np.sin(np.linspace(0.0, 20.0, n))  # any repeating error: it cancels
    errors = [clean - sigma * rng.standard_normal(n) for _ in range(2)]
    # the squared figure is sigma^2 chi^2_1 averaged over n samples: relative sd sqrt(2 / n) = 1 %
    assert noise_floor(errors[1], errors[0]) == pytest.approx(sigma, rel=0.03)


def test_noise_floor_of_a_deadbeat_law_is_sqrt_3_sigma() -> None:
    """Analytic case 2: the lifted inverse law ``u_{k+1} = u_k + G^-1 e_k`` on ``e_k = r - G u_k - v_k`` gives
    ``e_k = v_{k-1} - v_k`` from trial 2 on, so ``e_k - e_{k-1} = 2 v_{k-1} - v_k - v_{k-2}``: variance
    ``6 sigma^2``, noise floor ``sqrt(3) sigma``. The trials run through :class:`NoiseFloorTracker`."""
    sigma, n, trials = 0.05, 20_000, 8
    rng = np.random.default_rng(2)
    # G: the lower-triangular Toeplitz map of y[i] = 0.9 y[i-1] + 0.2 u[i]; G^-1 is its inverse filter
    plant, inverse = ([0.2], [1.0, -0.9]), ([1.0, -0.9], [0.2])
    reference = np.ones(n)
    u = np.zeros(n)
    tracker = NoiseFloorTracker()
    floors = []
    for k in range(1, trials + 1):
        error = reference - lfilter(*plant, u) - sigma * rng.standard_normal(n)
        metrics = tracker.measured(trial_metrics(k, error), error)
        floors.append(metrics.noise_floor)
        u = u + lfilter(*inverse, error)
    assert floors[0] is None  # trial 1 has nothing to compare with
    settled = np.array(floors[3:], dtype=float)  # from trial 4 on: three noise samples apart from the start
    assert float(np.sqrt(np.mean(settled**2))) == pytest.approx(math.sqrt(3.0) * sigma, rel=0.03)


def test_simulated_noise_floor_is_at_least_the_sensor_noise(tmp_path: Path) -> None:
    """Through ``simulate`` (plant noise, the bench's loop): ``e_k - e_{k-1} = -(v_k - v_{k-1}) + (y_{k-1} - y_k)``
    with the true outputs' change independent of the fresh noise ``v_k``, so ``E[floor^2] >= sigma^2``; without noise
    a converged law's floor vanishes."""
    from foilc_hil.config import load_config
    from foilc_hil.loop.simulation import simulate

    def floors(noise: float) -> np.ndarray:
        path = tmp_path / f"noise{noise}.yaml"
        path.write_text(
            f"plant: {{a: -1.23, b: 1.68, c: 1.0, output_noise: {noise}, seed: 4}}\n"
            "reference: {profile: piecewise, segments: [{duration: 3.0, start: 0.0, end: 1.0}]}\n"
            "sample_time: 0.01\nlaw: {kind: ioilc}\n",
            encoding="utf-8",
        )
        result = simulate(load_config(path), law="ioilc", trials=6, input_delay=1)
        assert result.metrics[0].noise_floor is None
        return np.array([m.noise_floor for m in result.metrics[3:]], dtype=float)

    sigma = 0.02
    assert float(np.sqrt(np.mean(floors(sigma) ** 2))) > 0.9 * sigma  # 300 samples x 3 trials: sd ~3 %
    clean = floors(0.0)  # the learning transient's own change, shrinking every trial
    assert bool(np.all(np.diff(clean) < 0)) and float(clean[-1]) < 1e-6
