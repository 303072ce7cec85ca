"""Reference profiles: eq. (49), eq. (52), piecewise; sample alignment t = (i + 1) Ts."""

from __future__ import annotations

import numpy as np
import pytest

from foilc_hil.config import ReferenceConfig, Segment
from foilc_hil.errors import ConfigError
from foilc_hil.references import reference_profile, sample_times, trial_samples


def test_eq49_half_open_intervals() -> None:
    cfg = ReferenceConfig(profile="eq49")
    r = reference_profile(cfg, 0.01)
    assert trial_samples(cfg, 0.01) == 2000 and r.shape == (2000,)
    t = sample_times(cfg, 0.01)
    assert t[0] == pytest.approx(0.01) and t[-1] == pytest.approx(20.0)
    # 1 on (0, 10], 0 on (10, 20]: t = 10 s is sample 999
    assert r[999] == 1.0 and r[1000] == 0.0
    assert np.all(r[:1000] == 1.0) and np.all(r[1000:] == 0.0)


def test_eq52_ramp_and_time_scale() -> None:
    cfg = ReferenceConfig(profile="eq52")
    r = reference_profile(cfg, 0.01)
    t = sample_times(cfg, 0.01)
    assert r.shape == (600,)
    expected = np.piecewise(
        t * 1000.0,
        [t * 1000.0 <= 3000.0 + 1e-6, (t * 1000.0 > 3000.0 + 1e-6) & (t * 1000.0 <= 4000.0 + 1e-6)],
        [400.0, lambda tm: 400.0 + 0.2 * (tm - 3000.0), 600.0],
    )
    np.testing.assert_allclose(r, expected, atol=1e-9)
    assert r[299] == 400.0  # t = 3 s
    assert r[349] == pytest.approx(500.0)  # t = 3.5 s, mid-ramp
    assert r[-1] == 600.0
    slow = ReferenceConfig(profile="eq52", time_scale=2.0, scale=0.5)
    r2 = reference_profile(slow, 0.01)
    assert r2.shape == (1200,)
    np.testing.assert_allclose(r2[1::2], 0.5 * r, atol=1e-9)  # same profile at twice the duration, halved


def test_piecewise_segments() -> None:
    cfg = ReferenceConfig(
        profile="piecewise",
        segments=[Segment(duration=1.0, start=0.0, end=2.0), Segment(duration=0.5, start=2.0)],
    )
    r = reference_profile(cfg, 0.1)
    assert r.shape == (15,)
    np.testing.assert_allclose(r[:10], 2.0 * np.arange(1, 11) * 0.1, atol=1e-12)
    np.testing.assert_allclose(r[10:], 2.0)


def test_sample_time_must_divide_the_trial() -> None:
    with pytest.raises(ConfigError, match="sample_time"):
        trial_samples(ReferenceConfig(profile="eq49"), 0.03)
    with pytest.raises(ConfigError, match="sample_time"):
        trial_samples(ReferenceConfig(profile="eq49"), -1.0)
