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


@pytest.mark.parametrize("profile", ["eq52", "piecewise"])
def test_lead_in_and_lead_out_ramp_from_and_to_rest_around_the_same_profile(profile: str) -> None:
    segments = [Segment(duration=0.5, start=2.0, end=3.0), Segment(duration=0.5, start=3.0)]
    base = ReferenceConfig(profile=profile, segments=segments if profile == "piecewise" else None, scale=1.5)
    led = base.model_copy(update={"lead_in": 0.2, "lead_out": 0.3})
    ts = 0.001
    plain, with_leads = reference_profile(base, ts), reference_profile(led, ts)
    assert trial_samples(led, ts) == trial_samples(base, ts) + 500 == with_leads.shape[0]
    # the profile itself, shifted by the lead-in (to rounding of its instants)
    np.testing.assert_allclose(with_leads[200:200 + plain.shape[0]], plain, rtol=0, atol=1e-9 * np.abs(plain).max())
    # the ramps meet the profile at its own start and end (t = 0 and T of the profile, not its first sample)
    first = (2.0 if profile == "piecewise" else 400.0) * 1.5
    last = plain[-1]
    lead_in, lead_out = with_leads[:200], with_leads[200 + plain.shape[0]:]
    # a straight ramp up from rest to the first value, and down from the last one to rest at the trial's end
    np.testing.assert_allclose(lead_in, first * np.arange(1, 201) / 200, atol=1e-9)
    np.testing.assert_allclose(lead_out, last * (1 - np.arange(1, 301) / 300), atol=1e-9)
    assert with_leads[-1] == 0.0 and np.all(np.diff(lead_in) > 0)


def test_a_negative_lead_is_refused() -> None:
    from pydantic import ValidationError

    with pytest.raises(ValidationError):
        ReferenceConfig(profile="eq52", lead_in=-0.1)
