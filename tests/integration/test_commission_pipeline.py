"""The commissioning pipeline end to end on the emulator (docs/commissioning.md):
``commission identify --out axis.yaml`` -> ``tune`` -> ``synthesize`` -> ``run``, short runs.

The base config emulates the PMSM axis; identify writes the identified ``a, b, c, num, den, delay, uncertainty``
into its ``plant:`` section and keeps ``model: pmsm``, so ``run`` drives the same emulated axis with a design made
on the identified model.
"""

from __future__ import annotations

import importlib.util
import json
import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from foilc_hil.cli import main
from foilc_hil.config import load_config
from foilc_hil.design.pipeline import build_design
from foilc_hil.references import trial_samples
from plant_emulator.linear import continuous_model

pytestmark = pytest.mark.timeout(600)

BASE = {
    "plant": {"model": "pmsm", "output_noise": 1.0, "seed": 2},
    "reference": {
        "profile": "piecewise",
        "segments": [{"duration": 0.25, "start": 0.0, "end": 300.0}, {"duration": 0.25, "start": 300.0}],
    },
    "sample_time": 0.01,
    "trials": 3,
    "tuning": {"crossover": 5.0, "phase_margin_deg": 150.0},
    "drive": {"mode": "csv", "velocity_limit": 3000.0},
    "bench": {"settle_time": 0.05, "settle_tolerance": 3.0},
}


@pytest.fixture(scope="module")
def identified(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict[str, object]]:
    folder = tmp_path_factory.mktemp("pipeline")
    base = folder / "base.yaml"
    base.write_text(yaml.safe_dump(BASE), encoding="utf-8")
    out = folder / "my_axis.yaml"
    argv = ["commission", "identify", "--config", str(base), "--amplitudes", "300,600", "--hold", "1.0",
            "--rest", "1.0", "--repetitions", "1", "--out", str(out), "--json"]
    code, document = _json(argv)
    assert code == 0
    return out, document


def _json(argv: list[str]) -> tuple[int, dict[str, object]]:
    import contextlib
    import io

    buffer = io.StringIO()
    with contextlib.redirect_stdout(buffer):
        code = main(argv)
    return code, json.loads(buffer.getvalue()) if buffer.getvalue().strip() else {}


def test_the_fragment_is_a_config_with_the_identified_plant(identified: tuple[Path, dict[str, object]]) -> None:
    out, document = identified
    config = load_config(out)
    plant = document["plant"]
    assert isinstance(plant, dict)
    assert config.plant.model == "pmsm"  # the emulated axis is kept
    model = continuous_model(config.plant)  # a/b/c and num/den agree (checked by continuous_model)
    assert float(model.a[0, 0]) == plant["a"] and float(model.b[0, 0]) == plant["b"]
    assert config.plant.uncertainty.G1 is not None and config.plant.uncertainty.G2 is not None
    assert config.tuning.crossover == 5.0  # the base config's other sections are kept


def test_tune_accepts_the_fragment(identified: tuple[Path, dict[str, object]]) -> None:
    out, document = identified
    code, tuned = _json(["tune", "--config", str(out), "--json"])
    assert code == 0
    plant = document["plant"]
    assert isinstance(plant, dict)
    # tune rebuilds num/den from a/b/c (ss2tf): equal to the last bits
    np.testing.assert_allclose(tuned["plant"]["num"], plant["num"], rtol=1e-12)  # type: ignore[index]
    np.testing.assert_allclose(tuned["plant"]["den"], plant["den"], rtol=1e-12)  # type: ignore[index]
    assert tuned["plant"]["delay"] == plant["delay"]  # type: ignore[index]
    assert tuned["achieved"]["crossover"] == pytest.approx(5.0, rel=1e-3)  # type: ignore[index]


def test_synthesis_accepts_the_fragment(identified: tuple[Path, dict[str, object]]) -> None:
    out, document = identified
    config = load_config(out, {"tuning.kp": 0.2, "tuning.r": 0.6})
    design = build_design(config, "foilc", trial_samples(config.reference, config.sample_time), input_delay=1)
    uncertainty = document["uncertainty"]
    assert isinstance(uncertainty, dict)
    # the design saw the identified uncertainty: delay augmentation keeps dA's block in G1's first row
    assert np.asarray(design.G1)[0, 0] == pytest.approx(uncertainty["G1"][0][0])
    assert design.to_json()["certificates"]["spectral_radius"] < 1


@pytest.mark.skipif(importlib.util.find_spec("foilc_hil.commands.synthesize") is None,
                    reason="the synthesize command module is not in this checkout yet")
def test_synthesize_command_accepts_the_fragment(identified: tuple[Path, dict[str, object]]) -> None:
    out, _ = identified
    code, document = _json(["synthesize", "--config", str(out), "--json"])
    assert code == 0 and "P" in document


@pytest.mark.slow
def test_run_on_the_emulator_learns_with_the_identified_design(identified: tuple[Path, dict[str, object]],
                                                                tmp_path: Path) -> None:
    out, _ = identified
    log = tmp_path / "run.mcap"
    code, document = _json(["run", "--config", str(out), "--trials", "3", "--out", str(log), "--json"])
    assert code == 0
    trials = document["trials"]
    assert isinstance(trials, list) and len(trials) == 3
    rmse = [t["rmse"] for t in trials]
    assert all(math.isfinite(r) for r in rmse)
    assert rmse[-1] < rmse[0]  # learning on the real (emulated PMSM) axis with the identified design
    assert log.stat().st_size > 0
