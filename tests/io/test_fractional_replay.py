"""The fractional PD's compiled near field rounds as scipy's 2-D direct sum did: old FOILC logs still verify.

``tests/data/foilc_fft_near_field.mcap`` is a ``foilc-hil simulate --out`` log written at commit 81e8c27, when the
near field of the fractional convolution was scipy's 2-D ``signal.convolve(..., method="direct")``: FOILC
(``kp = 0.05``, ``r = 0.7``) on the first-order plant ``a = -1.23, b = 1.68`` (seed 3), 3 trials of 520 samples at
10 ms -- past ``FFT_THRESHOLD``, so every update between trials ran the near field and the FFT far field. Config::

    plant: {a: -1.23, b: 1.68, c: 1.0, seed: 3}
    reference: {profile: piecewise, segments: [{duration: 2.6, start: 0.0, end: 1.0}, {duration: 2.6, start: 1.0}]}
    sample_time: 0.01
    trials: 3
    law: {kind: foilc}
    tuning: {kp: 0.05, r: 0.7}

A near field summed in another order (``np.convolve`` per column) fails this log's verification at trial 2.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from foilc_hil.config import Config
from foilc_hil.design.fractional import FFT_THRESHOLD
from foilc_hil.design.record import Design
from foilc_hil.io.mcap_log import read_log
from foilc_hil.logtools.replay import verify_log
from foilc_hil.loop.simulation import simulate
from foilc_hil.references import trial_samples
from foilc_hil.schema import load_yaml_text, validate

pytestmark = pytest.mark.slow

OLD_LOG = Path(__file__).resolve().parents[1] / "data" / "foilc_fft_near_field.mcap"


def _controls(samples: list[dict[str, object]]) -> bytes:
    return np.array([float(s["control"]) for s in samples]).tobytes()  # type: ignore[arg-type]


def test_an_old_foilc_log_verifies_a_new_run_repeats_it_and_a_tampered_one_fails(tmp_path: Path) -> None:
    old = read_log(OLD_LOG)
    assert old.config_yaml is not None and old.design is not None
    config = validate(Config, load_yaml_text(old.config_yaml), source="fixture")
    n = trial_samples(config.reference, config.sample_time)
    assert n >= FFT_THRESHOLD  # the long path: near field direct, far field by FFT
    assert verify_log(old).verified

    # a new run with the logged design writes a log that verifies and repeats the old commands bit for bit
    out = tmp_path / "new.mcap"
    simulate(config, law="foilc", trials=3, design=Design.from_json(old.design), out=out)
    new = read_log(out)
    assert verify_log(new).verified
    assert _controls(new.samples) == _controls(old.samples)

    # one command one ulp off, in the third trial (after two updates through the fractional PD), is caught there
    index = 2 * n + 17
    new.samples[index]["control"] = math.nextafter(float(new.samples[index]["control"]), math.inf)
    tampered = verify_log(new)
    assert not tampered.verified
    assert tampered.first_divergence is not None
    assert (tampered.first_divergence.trial, tampered.first_divergence.sample) == (3, 17)
