"""The loop tuner against independent truths.

Truths used:
* K = 1 has a closed form: the spec fixes ``P = 1 + kp (j wc)^r = exp(j(-pi + phi_m)) / G(j wc)``, so
  ``kp (j wc)^r = P - 1`` gives ``r = 2 arg(P - 1) / pi`` and ``kp = |P - 1| / wc^r`` (the solver brackets a
  residual on an r grid instead);
* loops with textbook margins (``w0/s``, ``w0/s * exp(-T s)``) for the sweep;
* finite differences of ``arg L`` for the flat-phase condition; ``atan2`` for the plant phase in messages.
"""

from __future__ import annotations

import cmath
import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
from hypothesis import assume, example, given, settings
from hypothesis import strategies as st

from foilc_hil.config import load_config
from foilc_hil.design.open_loop import (
    CONTROL_CROSSOVER_RTOL,
    CONTROL_PHASE_TOL_DEG,
    ControlCheck,
    OpenLoop,
    PlantTf,
    frequency_sweep,
    oustaloup,
)
from foilc_hil.design.tuning import evaluate_pair, tune, tune_loop
from foilc_hil.errors import ConfigError, TuningInfeasibleError


def _closed_form(num: list[float], den: list[float], delay: float, wc: float, pm_deg: float) -> tuple[float, float]:
    g = np.polyval(num, 1j * wc) / np.polyval(den, 1j * wc) * cmath.exp(-1j * delay * wc)
    needed = cmath.exp(1j * (math.radians(pm_deg) - math.pi)) / g - 1.0
    r = 2.0 * cmath.phase(needed) / math.pi
    return abs(needed) / wc**r, r


def _only_touches_one(num: list[float], den: list[float], wc: float, kp: float, r: float) -> bool:
    """``|L|`` (K = 1) is on the same side of 1 one sweep step either side of ``wc``: a tangent, not a crossing."""
    step = 10.0 ** (1.0 / 2000)  # the dense sweep's grid ratio (2000 points per decade)
    sides = [
        abs((1.0 + kp * (1j * w) ** r) * np.polyval(num, 1j * w) / np.polyval(den, 1j * w)) > 1.0
        for w in (wc / step, wc * step)
    ]
    return sides[0] == sides[1]


def _phase_at(num: list[float], den: list[float], delay: float, K: float, kp: float, r: float, w: float) -> float:
    return float(np.angle(OpenLoop(PlantTf(num, den, delay), K, kp, r).response(np.array([w]))[0]))


PAPER_NUM = [1.68]
PAPER_DEN = [1.0, 1.23]


def test_paper_literal_spec_is_infeasible_with_computed_numbers() -> None:
    plant_deg = -math.degrees(math.atan2(70.0, 1.23))  # -88.99: first-order lag, independent of the solver
    for flat in (False, True):
        with pytest.raises(TuningInfeasibleError) as info:
            tune_loop(PlantTf(PAPER_NUM, PAPER_DEN, 0.0), 70.0, 70.0, flat_phase=flat)
        message = str(info.value)
        assert f"{plant_deg:.2f} deg" in message
        assert "-110.00 deg" in message
        assert f"{-110.0 - plant_deg:+.2f} deg" in message  # the lag it would need
        assert f"({180.0 + plant_deg:.2f}, 180.00)" in message  # what is reachable instead
    # just inside the reachable window it becomes feasible, just outside it does not
    edge = 180.0 + plant_deg
    assert tune_loop(PlantTf(PAPER_NUM, PAPER_DEN, 0.0), 70.0, edge + 0.5).kp > 0
    with pytest.raises(TuningInfeasibleError):
        tune_loop(PlantTf(PAPER_NUM, PAPER_DEN, 0.0), 70.0, edge - 0.5)


def test_feasible_with_one_cycle_delay_matches_closed_form() -> None:
    result = tune_loop(PlantTf(PAPER_NUM, PAPER_DEN, 0.01), 70.0, 70.0)
    kp, r = _closed_form(PAPER_NUM, PAPER_DEN, 0.01, 70.0, 70.0)
    assert result.K == 1.0
    assert result.r == pytest.approx(r, rel=1e-9)
    assert result.kp == pytest.approx(kp, rel=1e-9)
    assert len(result.solutions) == 1
    assert result.achieved_crossover == pytest.approx(70.0, rel=1e-6)
    assert result.achieved_phase_margin_deg == pytest.approx(70.0, abs=1e-4)
    check = result.checks.python_control
    assert check is not None
    assert check.agrees_with_sweep is True
    assert check.closed_loop_stable is True
    document = result.to_json()
    assert {"K", "kp", "r", "crossover", "phase_margin_deg", "plant", "achieved"} <= set(document)
    assert document["plant"] == {"num": [1.68], "den": [1.0, 1.23], "delay": 0.01}


@settings(max_examples=15, deadline=None)
@given(
    pole=st.floats(0.2, 20.0),
    second_pole=st.one_of(st.none(), st.floats(0.5, 50.0)),
    gain=st.floats(0.2, 50.0),
    delay=st.floats(0.0, 0.05),
    wc=st.floats(0.5, 100.0),
    pm=st.floats(5.0, 175.0),
)
# found by hypothesis: r -> 2 puts a notch of |L| at wc, which then only touches 1 there
@example(pole=0.5, second_pole=0.5, gain=40.0, delay=0.0, wc=0.5, pm=175.0)
def test_k1_solver_matches_closed_form(
    pole: float, second_pole: float | None, gain: float, delay: float, wc: float, pm: float
) -> None:
    den = [1.0, pole] if second_pole is None else list(np.polymul([1.0, pole], [1.0, second_pole]))
    num = [gain]
    kp, r = _closed_form(num, den, delay, wc, pm)
    if not 0.0 < r < 2.0 - 1e-9 or r < 1e-9:
        with pytest.raises(TuningInfeasibleError):
            tune_loop(PlantTf(num, den, delay), wc, pm)
        return
    assume(r > 1e-6)  # a PD order this close to 0 is at the grid's resolution
    if _only_touches_one(num, den, wc, kp, r):
        # no gain crossover for the independent sweep to confirm: the tuner must refuse, not report
        with pytest.raises(TuningInfeasibleError, match="fails the independent frequency sweep"):
            tune_loop(PlantTf(num, den, delay), wc, pm)
        return
    result = tune_loop(PlantTf(num, den, delay), wc, pm)
    assert result.r == pytest.approx(r, rel=1e-7, abs=1e-10)
    assert result.kp == pytest.approx(kp, rel=1e-6)
    # the spec itself, evaluated directly
    value = OpenLoop(PlantTf(num, den, delay), 1.0, result.kp, result.r).response(np.array([wc]))[0]
    assert abs(value) == pytest.approx(1.0, rel=1e-7)  # brentq's r tolerance times d log|P| / dr
    assert math.degrees(cmath.phase(value)) % 360 == pytest.approx((pm - 180.0) % 360, abs=1e-6)


@pytest.mark.parametrize(
    ("num", "den", "delay", "wc", "pm"),
    [
        (PAPER_NUM, PAPER_DEN, 0.01, 70.0, 70.0),
        ([10.0], [1.0, 3.0, 2.0], 0.0, 5.0, 45.0),
        ([4.0], [1.0, 2.0, 0.0], 0.05, 3.0, 50.0),
    ],
)
def test_flat_phase_solutions_meet_all_three_specs(
    num: list[float], den: list[float], delay: float, wc: float, pm: float
) -> None:
    result = tune_loop(PlantTf(num, den, delay), wc, pm, flat_phase=True)
    assert result.solutions
    step = wc * 1e-5
    for solution in result.solutions:
        K, kp, r = solution.K, solution.kp, solution.r
        assert K > 0 and kp > 0 and 0 < r < 2
        value = OpenLoop(PlantTf(num, den, delay), K, kp, r).response(np.array([wc]))[0]
        assert abs(value) == pytest.approx(1.0, rel=1e-8)
        assert math.degrees(cmath.phase(value)) % 360 == pytest.approx((pm - 180.0) % 360, abs=1e-6)
        slope = np.unwrap(
            [_phase_at(num, den, delay, K, kp, r, wc - step), _phase_at(num, den, delay, K, kp, r, wc + step)]
        )
        assert abs(slope[1] - slope[0]) / (2 * step) < 1e-6 * (1 + abs(PlantTf(num, den, delay).phase_slope(wc)))


def test_flat_phase_infeasible_when_plant_phase_rises() -> None:
    num, den = [100.0, 100.0], list(np.polymul([1.0, 100.0], [1.0, 200.0]))  # lead: zero at 1, poles at 100, 200
    assert PlantTf(num, den, 0.0).phase_slope(5.0) > 0
    assert tune_loop(PlantTf(num, den, 0.0), 5.0, 40.0).kp > 0  # the K = 1 spec is reachable
    with pytest.raises(TuningInfeasibleError, match="not negative"):
        tune_loop(PlantTf(num, den, 0.0), 5.0, 40.0, flat_phase=True)


def test_wrapped_plant_phase_with_long_delay() -> None:
    num, den, delay, wc = [1.0], [1.0, 1.0], 0.1, 30.0
    expected = -math.atan2(wc, 1.0) - delay * wc  # below -180 deg: the modulo-360 spec must still work
    assert PlantTf(num, den, delay).phase(wc) == pytest.approx(expected)
    result = tune_loop(PlantTf(num, den, delay), wc, 45.0)
    assert result.achieved_phase_margin_deg == pytest.approx(45.0, abs=1e-3)
    kp, r = _closed_form(num, den, delay, wc, 45.0)
    assert result.r == pytest.approx(r, rel=1e-8)
    assert result.kp == pytest.approx(kp, rel=1e-7)


def test_sweep_matches_textbook_margins() -> None:
    w0, delay = 10.0, 0.05
    # L = w0/s: crossover w0, phase margin 90 deg, no phase crossover
    sweep = frequency_sweep(OpenLoop(PlantTf([w0], [1.0, 0.0], 0.0), 1.0, 0.0, 1.0), 0.01, 1e4)
    assert len(sweep.crossings) == 1
    assert sweep.crossings[0].frequency == pytest.approx(w0, rel=1e-6)
    assert sweep.crossings[0].phase_margin_deg == pytest.approx(90.0, abs=1e-6)
    assert sweep.gain_margin_db is None
    # L = w0/s e^{-Ts}: PM = 90 - w0 T (deg); phase crossover at w = pi/(2T), GM = -20 log10(w0 / w)
    sweep = frequency_sweep(OpenLoop(PlantTf([w0], [1.0, 0.0], delay), 1.0, 0.0, 1.0), 0.01, 1e3)
    assert sweep.crossings[0].phase_margin_deg == pytest.approx(90.0 - math.degrees(w0 * delay), abs=1e-5)
    w180 = math.pi / (2 * delay)
    assert sweep.phase_crossover == pytest.approx(w180, rel=1e-5)
    assert sweep.gain_margin_db == pytest.approx(-20 * math.log10(w0 / w180), abs=1e-4)


def test_evaluate_pair_round_trip_and_direct_evaluation() -> None:
    solved = tune_loop(PlantTf([10.0], [1.0, 3.0, 2.0], 0.02), 5.0, 55.0)
    direct = evaluate_pair(OpenLoop(PlantTf([10.0], [1.0, 3.0, 2.0], 0.02), 1.0, solved.kp, solved.r))
    assert direct.mode == "direct"
    assert direct.achieved_crossover == pytest.approx(5.0, rel=1e-5)
    assert direct.achieved_phase_margin_deg == pytest.approx(55.0, abs=1e-3)
    assert direct.checks.python_control is not None
    assert direct.checks.python_control.agrees_with_sweep is True


def test_the_sweep_record_names_the_grid_the_sweep_ran_on() -> None:
    """``checks.sweep.points_per_decade`` is the sweep's own grid: a given pair is swept at 1000 a decade and a
    solved one at the default 2000 (the record said 2000 for both)."""
    plant = PlantTf([10.0], [1.0, 3.0, 2.0], 0.02)
    solved = tune_loop(plant, 5.0, 60.0, python_control=False)
    direct = evaluate_pair(OpenLoop(plant, 1.0, solved.kp, solved.r), python_control=False)
    assert solved.to_json()["checks"]["sweep"]["points_per_decade"] == 2000
    assert direct.to_json()["checks"]["sweep"]["points_per_decade"] == 1000


def test_evaluate_pair_without_crossover_reports_none() -> None:
    # |L| = |1 + kp (jw)^r| * 1.68 / |jw + 1.23| stays above 1 when kp is large and r is close to 1
    result = evaluate_pair(OpenLoop(PlantTf(PAPER_NUM, PAPER_DEN, 0.0), 1.0, 3.0, 1.05))
    assert result.achieved_crossover is None and result.crossover is None
    assert result.checks.warnings
    w = np.logspace(-3, 4, 500)
    assert np.all(np.abs(OpenLoop(PlantTf(PAPER_NUM, PAPER_DEN, 0.0), 1.0, 3.0, 1.05).response(w)) > 1)


def test_a_pair_without_crossover_but_with_a_gain_margin_is_documented_and_rendered() -> None:
    """No gain crossover, but a phase crossover (the delay): the sweep's note and gain margin in the document, and
    the text summary (it read the untyped checks' ``phase_crossover``, absent there, and raised KeyError)."""
    from foilc_hil.commands.tune import render

    result = evaluate_pair(OpenLoop(PlantTf([0.001], PAPER_DEN, 0.01), 1.0, 0.01, 0.5))
    assert result.achieved_crossover is None and result.checks.python_control is None
    sweep = result.to_json()["checks"]["sweep"]
    assert list(sweep) == ["w_min", "w_max", "crossings", "gain_margin_db", "note"]
    assert sweep["crossings"] == [] and sweep["gain_margin_db"] > 0 and "no gain crossover" in sweep["note"]
    text = render(result)
    assert f"gain margin {sweep['gain_margin_db']:.3g} dB at" in text and "warning: |L| stays below 1" in text


def test_checks_documents_keep_their_keys_in_order() -> None:
    """The ``tune`` document's ``checks`` (docs/interface.md) from the typed checks: each variant's keys, in order."""
    plain = ControlCheck("m", 1.0, 2.0, closed_loop_max_real_pole=-1.0, closed_loop_stable=True)
    assert list(plain.to_json()) == ["method", "crossover", "phase_margin_deg", "closed_loop_max_real_pole",
                                     "closed_loop_stable"]
    compared = dataclasses.replace(plain, agrees_with_sweep=True).to_json()
    assert list(compared)[-2:] == ["agrees_with_sweep", "tolerance"] and compared["agrees_with_sweep"] is True
    improper = ControlCheck("m", 1.0, 2.0, closed_loop_note="not computed: improper", agrees_with_sweep=False)
    assert improper.to_json() == {
        "method": "m", "crossover": 1.0, "phase_margin_deg": 2.0, "closed_loop_stable": None,
        "closed_loop_note": "not computed: improper", "agrees_with_sweep": False,
        "tolerance": {"crossover_rel": CONTROL_CROSSOVER_RTOL, "phase_margin_deg": CONTROL_PHASE_TOL_DEG},
    }  # fmt: skip
    failed = ControlCheck("python-control stability_margins", agrees_with_sweep=False, error="overflow")
    assert failed.to_json() == {"method": "python-control stability_margins", "error": "overflow",
                                "agrees_with_sweep": False}
    solved = tune_loop(PlantTf(PAPER_NUM, PAPER_DEN, 0.01), 70.0, 70.0, flat_phase=True, python_control=False)
    assert list(solved.to_json()["checks"]) == ["warnings", "sweep", "plant_phase_deg", "plant_gain", "pd_phase_deg",
                                                "plant_phase_slope_deg_per_rad_s", "selection"]
    assert list(solved.to_json()["checks"]["sweep"]) == ["w_min", "w_max", "points_per_decade", "crossings",
                                                         "gain_margin_db", "phase_crossover", "tolerance"]


@pytest.mark.parametrize("alpha", [-0.5, -0.2, 0.3, 0.5])
def test_oustaloup_is_close_to_s_alpha_mid_band(alpha: float) -> None:
    """Small phase error near the band's centre, larger towards its edges: why the check centres on wc."""
    zeros, poles, gain = oustaloup(alpha, 1e-3, 1e3, order=7)
    for w, phase_tol in ((1.0, 0.1), (0.5, 0.15), (2.0, 0.15), (0.1, 0.4)):
        value = gain * np.prod(1j * w - zeros) / np.prod(1j * w - poles)
        exact = (1j * w) ** alpha
        assert abs(value / exact) == pytest.approx(1.0, rel=1e-3)
        assert abs(math.degrees(cmath.phase(value / exact))) < phase_tol


@pytest.mark.parametrize(
    ("num", "den", "delay", "wc", "pm", "flat"),
    [
        ([2.0], [1.0, 1.0], 0.0, 10.0, 100.0, False),
        ([10.0], [1.0, 3.0, 2.0], 0.03, 4.0, 40.0, False),
        ([4.0], [1.0, 2.0, 0.0], 0.05, 3.0, 50.0, True),
    ],
)
def test_python_control_check_agrees(
    num: list[float], den: list[float], delay: float, wc: float, pm: float, flat: bool
) -> None:
    result = tune_loop(PlantTf(num, den, delay), wc, pm, flat_phase=flat)
    check = result.checks.python_control
    assert check is not None and check.crossover is not None and check.phase_margin_deg is not None
    assert result.achieved_crossover is not None and result.achieved_phase_margin_deg is not None
    assert check.agrees_with_sweep is True
    assert abs(check.crossover / result.achieved_crossover - 1) <= CONTROL_CROSSOVER_RTOL
    assert abs(check.phase_margin_deg - result.achieved_phase_margin_deg) <= CONTROL_PHASE_TOL_DEG


def test_flat_phase_with_delay_is_flagged() -> None:
    """Flat phase with the one-cycle delay meets the three specs at wc, but r > 1 on a first-order plant never
    rolls off: the tuner must say so rather than hide it."""
    result = tune_loop(PlantTf(PAPER_NUM, PAPER_DEN, 0.01), 70.0, 70.0, flat_phase=True)
    assert result.r > 1
    warnings = " ".join(result.checks.warnings)
    assert "does not roll off" in warnings
    assert result.checks.sweep.gain_margin_db is not None and result.checks.sweep.gain_margin_db < 0
    assert result.checks.python_control is not None and result.checks.python_control.closed_loop_stable is False


def test_bad_parameters_are_named() -> None:
    with pytest.raises(ConfigError, match=r"tuning\.crossover"):
        tune_loop(PlantTf(PAPER_NUM, PAPER_DEN, 0.0), -1.0, 45.0)
    with pytest.raises(ConfigError, match=r"tuning\.phase_margin_deg"):
        tune_loop(PlantTf(PAPER_NUM, PAPER_DEN, 0.0), 10.0, 190.0)
    with pytest.raises(ConfigError, match=r"plant\.delay"):
        PlantTf(PAPER_NUM, PAPER_DEN, -0.1)  # validated once, at construction
    with pytest.raises(ConfigError, match=r"tuning\.r"):
        OpenLoop(PlantTf(PAPER_NUM, PAPER_DEN, 0.0), 1.0, 1.0, 2.0)


def _config(tmp_path: Path, tuning: str) -> Path:
    path = tmp_path / "c.yaml"
    path.write_text(f"plant: {{a: -1.23, b: 1.68, c: 1, delay: 0.01}}\ntuning: {tuning}\n", encoding="utf-8")
    return path


def test_tune_from_config(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match=r"tuning\.crossover"):
        tune(load_config(_config(tmp_path, "{}")))
    with pytest.raises(ConfigError, match=r"tuning\.phase_margin_deg"):
        tune(load_config(_config(tmp_path, "{crossover: 70}")))
    with pytest.raises(ConfigError, match=r"tuning\.phase_margin_deg"):  # a half spec is never ignored
        tune(load_config(_config(tmp_path, "{crossover: 70, kp: 1.0, r: 0.5}")))
    with pytest.raises(ConfigError, match=r"tuning\.crossover"):
        tune(load_config(_config(tmp_path, "{phase_margin_deg: 45}")))
    both = tune(load_config(_config(tmp_path, "{crossover: 70, phase_margin_deg: 70, kp: 1.0, r: 0.5}")))
    assert both.mode == "spec"
    assert both.checks.configured_pair is not None and both.checks.configured_pair.kp == 1.0
    pair = tune(load_config(_config(tmp_path, "{kp: 1.0, r: 0.5}")))
    assert pair.mode == "direct" and pair.kp == 1.0 and pair.r == 0.5


# --- the value objects ----------------------------------------------------------------------------------------


def test_plant_tf_validates_once_with_the_named_errors() -> None:
    with pytest.raises(ConfigError, match=r"plant\.num: must be finite and non-zero"):
        PlantTf([0.0, 0.0], [1.0, 1.0])
    with pytest.raises(ConfigError, match=r"plant\.den: must be finite and non-zero"):
        PlantTf([1.0], [1.0, math.nan])
    with pytest.raises(ConfigError, match=r"plant\.delay: must be finite and >= 0, got inf"):
        PlantTf([1.0], [1.0, 1.0], math.inf)
    plant = PlantTf([0.0, 2.0], [0.0, 0.0, 1.0, 3.0], 0.1)  # leading zeros are not a higher order
    assert plant.num.tolist() == [2.0] and plant.den.tolist() == [1.0, 3.0]
    with pytest.raises(ValueError, match="read-only"):
        plant.num[0] = 5.0
    with pytest.raises(dataclasses.FrozenInstanceError):
        plant.delay = 0.2  # type: ignore[misc]


def test_plant_tf_equality_is_by_value() -> None:
    plant = PlantTf([2.0], [1.0, 3.0], 0.1)
    same = PlantTf(np.array([0.0, 2.0]), (1, 3), 0.1)
    assert plant == same and hash(plant) == hash(same)
    assert plant != PlantTf([2.0], [1.0, 3.0], 0.2)
    assert plant != PlantTf([2.0], [1.0, 4.0], 0.1)


def test_plant_tf_response_phase_and_slope_match_first_order_closed_forms() -> None:
    b, a, delay = 1.68, 1.23, 0.01
    plant = PlantTf([b], [1.0, a], delay)
    for w in (0.1, 1.23, 70.0, 500.0):  # 500 rad/s: arg G below -180 deg, unwrapped
        expected = b / complex(a, w) * cmath.exp(-1j * delay * w)
        assert complex(plant.response(w)) == pytest.approx(expected, rel=1e-12)
        assert plant.phase(w) == pytest.approx(-math.atan2(w, a) - delay * w, rel=1e-12)
        assert plant.phase_slope(w) == pytest.approx(-a / (a * a + w * w) - delay, rel=1e-12)


def test_plant_tf_corners_are_pole_zero_magnitudes_and_inverse_delay() -> None:
    # zero at -10, poles at 0 (no corner), -2, -5; delay 0.25 s: corner 4 rad/s
    plant = PlantTf([1.0, 10.0], np.polymul([1.0, 0.0], np.polymul([1.0, 2.0], [1.0, 5.0])), 0.25)
    assert sorted(plant.corners()) == pytest.approx([2.0, 4.0, 5.0, 10.0])
    assert PlantTf([1.0], [1.0, 0.0]).corners() == []


@pytest.mark.parametrize(("K", "kp", "r"), [(1.0, 0.0, 1.0), (0.7, 0.05, 0.4), (2.5, 0.3, 1.6)])
def test_open_loop_response_matches_the_complex_power(K: float, kp: float, r: float) -> None:
    plant = PlantTf([10.0], [1.0, 3.0, 2.0], 0.02)
    loop = OpenLoop(plant, K, kp, r)
    for w in (0.05, 1.0, 7.0, 300.0):
        s = 1j * w
        # Python's complex power is the principal branch: an independent (j w)^r
        expected = K * (1.0 + kp * s**r) * 10.0 / (s * s + 3.0 * s + 2.0) * cmath.exp(-plant.delay * s)
        assert complex(loop.response(w)) == pytest.approx(expected, rel=1e-12)
        assert loop.gain_at(w) == pytest.approx(abs(expected), rel=1e-12)


def test_open_loop_validates_once_with_the_named_errors() -> None:
    plant = PlantTf(PAPER_NUM, PAPER_DEN)
    with pytest.raises(ConfigError, match=r"tuning\.kp: must be >= 0, got -0\.1"):
        OpenLoop(plant, 1.0, -0.1, 0.5)
    with pytest.raises(ConfigError, match=r"tuning\.kp"):
        OpenLoop(plant, 1.0, math.nan, 0.5)
    with pytest.raises(ConfigError, match=r"tuning\.r: must satisfy 0 < r < 2, got 0\.0"):
        OpenLoop(plant, 1.0, 1.0, 0.0)
    with pytest.raises(ConfigError, match=r"K: must be > 0, got 0\.0"):
        OpenLoop(plant, 0.0, 1.0, 0.5)
    with pytest.raises(dataclasses.FrozenInstanceError):
        OpenLoop(plant).kp = 1.0  # type: ignore[misc]
