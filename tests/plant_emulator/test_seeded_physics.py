"""The phases and the noise seed a reproduction seed moves (issue 26, target 9): ``plant.variation.*.phase``,
``plant.disturbance.phase``, ``plant.pmsm.drift.phase`` and ``plant.noise_seed``, each against an independent truth
(the closed-form signal, or the same drift reached through ``phase_per_trial``), and phase 0 as before."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from foilc_hil.config import load_config
from foilc_hil.errors import ConfigError
from plant_emulator.config import DisturbanceConfig, PlantConfig, VariationConfig
from plant_emulator.physics import build_plant
from plant_emulator.physics.disturbance import Disturbance
from plant_emulator.physics.pmsm import PmsmPlant
from plant_emulator.physics.variation import VariationSignal

DT, STEPS, T0 = 1e-2, 500, 0.37


def _midpoints() -> np.ndarray:
    return T0 + (np.arange(STEPS) + 0.5) * DT


@pytest.mark.parametrize("phase", [0.0, 0.8, -2.5])
def test_the_variation_sine_takes_its_phase(phase: float) -> None:
    signal = VariationSignal(VariationConfig(kind="sine", amplitude=0.1, frequency=2.3, phase=phase), 0, 1)
    got = signal.values(T0, DT, STEPS)
    np.testing.assert_allclose(got, 0.1 * np.sin(2.3 * _midpoints() + phase), rtol=0, atol=1e-12)
    step = VariationSignal(VariationConfig(kind="sine", amplitude=0.1, frequency=2.3, phase=phase), 0, 1)
    assert step.over_step(T0, DT) == got[0]  # one step at a time: the same number


@pytest.mark.parametrize(("kind", "phase"), [("sine", 1.1), ("square", 2.0), ("square", 0.0)])
def test_the_disturbance_wave_takes_its_phase(kind: str, phase: float) -> None:
    config = DisturbanceConfig.model_validate(
        {"kind": kind, "amplitude": 0.2, "frequency": 3.0, "start_time": 1.0, "phase": phase}
    )
    disturbance = Disturbance(config)
    disturbance.reset(1)
    got = disturbance.values(T0, DT, STEPS)
    t = _midpoints()
    wave = np.sin(3.0 * (t - 1.0) + phase)
    expected = 0.2 * (wave if kind == "sine" else np.where(wave >= 0, 1.0, -1.0))
    expected[t < 1.0] = 0.0
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-12)
    assert disturbance.over_step(T0, DT) == got[0]  # one step at a time: the same number


def test_a_phase_on_a_shape_without_one_is_refused_naming_the_key() -> None:
    with pytest.raises(ConfigError, match=r"plant\.variation\.a: phase applies to kind 'sine'") as caught:
        load_config(None, {"plant.variation.a.kind": "random_walk", "plant.variation.a.phase": 1.0})
    assert caught.value.exit_code == 2
    with pytest.raises(ConfigError, match=r"plant\.disturbance: phase applies to kinds 'sine' and 'square'"):
        load_config(None, {"plant.disturbance.kind": "step", "plant.disturbance.phase": 1.0})


def _pmsm_trial(plant: PmsmPlant, trial: int, steps: int = 300) -> np.ndarray:
    plant.reset(trial)
    return np.array([plant.step(np.array([300.0]), 1e-3)[0] for _ in range(steps)])


def _pmsm(drift: dict[str, float], **plant: Any) -> PmsmPlant:
    pmsm = {"drift": {"amplitude": 0.3, "frequency": 20.0, **drift}}
    built = build_plant(PlantConfig.model_validate({"model": "pmsm", "seed": 3, "pmsm": pmsm, **plant}))
    assert isinstance(built, PmsmPlant)
    return built


def test_the_drift_phase_is_the_phase_a_trial_reaches_by_phase_per_trial() -> None:
    """``J(t) = J (1 + A sin(f t + phase + phase_per_trial (k - 1)))``: phase 1.3 in trial 2 with no step per trial
    is the same drift as phase 0 with 1.3 per trial, bit for bit; and it is not the drift of phase 0."""
    by_phase = _pmsm_trial(_pmsm({"phase": 1.3}), 2)
    by_trial = _pmsm_trial(_pmsm({"phase_per_trial": 1.3}), 2)
    assert by_phase.tobytes() == by_trial.tobytes()
    assert not np.array_equal(by_phase, _pmsm_trial(_pmsm({}), 2))


def test_the_load_torque_phase_moves_the_square_wave() -> None:
    """A square load torque with phase pi is the one of the opposite amplitude (sign of sin(x + pi) = -sign sin x)."""
    shifted = {"kind": "square", "amplitude": 0.3, "frequency": 7.0, "phase": math.pi}
    opposite = {"kind": "square", "amplitude": -0.3, "frequency": 7.0}
    first = _pmsm_trial(_pmsm({}, disturbance=shifted), 1)
    second = _pmsm_trial(_pmsm({}, disturbance=opposite), 1)
    np.testing.assert_allclose(first, second, rtol=0, atol=1e-9)
    assert not np.allclose(first, _pmsm_trial(_pmsm({}, disturbance={**opposite, "amplitude": 0.3}), 1))


def test_the_noise_seed_moves_the_noise_alone() -> None:
    """``plant.noise_seed`` reseeds the sensor noise and keeps the pmsm's parameter draw (``plant.seed``); unset, the
    noise follows the physics seed as before."""
    spread = {"inertia": 0.2, "viscous": 0.3}
    base = {"model": "pmsm", "seed": 3, "output_noise": 0.5, "pmsm": {"spread": spread}}

    def plant(**extra: Any) -> PmsmPlant:
        built = build_plant(PlantConfig.model_validate({**base, **extra}))
        assert isinstance(built, PmsmPlant)
        return built

    default, reseeded, again = plant(), plant(noise_seed=11), plant(noise_seed=11)
    assert reseeded._drawn == default._drawn  # the same axis
    assert not np.array_equal(reseeded.noise.trial_vector(1, 50), default.noise.trial_vector(1, 50))
    assert np.array_equal(reseeded.noise.trial_vector(1, 50), again.noise.trial_vector(1, 50))
    other_axis = plant(seed=4, noise_seed=11)
    assert other_axis._drawn != default._drawn
    assert np.array_equal(other_axis.noise.trial_vector(2, 50), reseeded.noise.trial_vector(2, 50))
    assert np.array_equal(default.noise.trial_vector(1, 50), plant(noise_seed=3).noise.trial_vector(1, 50))
