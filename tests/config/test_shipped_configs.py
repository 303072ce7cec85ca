"""Every shipped config loads; paper_sim's uncertainty bound covers its parameter variation."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from foilc_hil.config import load_config
from foilc_hil.references import reference_profile, trial_samples

ALL_YAML = sorted((Path(__file__).resolve().parents[2] / "configs").glob("*.yaml"))
# `commission params` parameter sets (top-level key `parameters` only) are another document type, checked by the
# commissioning tests; every other shipped YAML is a bench config.
CONFIGS = [path for path in ALL_YAML if set(yaml.safe_load(path.read_text(encoding="utf-8")) or {}) != {"parameters"}]


def test_there_are_shipped_configs() -> None:
    names = {path.name for path in CONFIGS}
    assert {"paper_sim.yaml", "paper_experiment.yaml"} <= names


@pytest.mark.parametrize("path", CONFIGS, ids=lambda p: p.name)
def test_config_loads(path: Path) -> None:
    config = load_config(path)
    n = trial_samples(config.reference, config.sample_time)
    assert reference_profile(config.reference, config.sample_time).shape == (n,)


def test_paper_sim_uncertainty_covers_the_variation() -> None:
    config = load_config(CONFIGS[0].parent / "paper_sim.yaml")
    plant = config.plant
    assert plant.a is not None and plant.b is not None
    a, b, ts = plant.a[0][0], plant.b[0][0], config.sample_time
    da, db = plant.variation.a.amplitude, plant.variation.b.amplitude
    assert da > 0 and db > 0

    def zoh(alpha: float, beta: float) -> tuple[float, float]:
        ad = math.exp(alpha * ts)
        return ad, beta * (ad - 1.0) / alpha

    a0, b0 = zoh(a, b)
    grid_a = np.linspace(-da, da, 101)
    grid_b = np.linspace(-db, db, 101)
    worst_a = max(abs(zoh(a + x, b)[0] - a0) for x in grid_a)
    worst_b = max(abs(zoh(a + x, b + y)[1] - b0) for x in grid_a for y in grid_b)
    u = plant.uncertainty
    assert u.G1 is not None and u.H1 is not None and u.G2 is not None and u.H2 is not None
    bound_a = float(np.linalg.norm(np.asarray(u.G1), 2) * np.linalg.norm(np.asarray(u.H1), 2))
    bound_b = float(np.linalg.norm(np.asarray(u.G2), 2) * np.linalg.norm(np.asarray(u.H2), 2))
    assert worst_a <= bound_a
    assert worst_b <= bound_b
    assert plant.disturbance.start_trial == 5
