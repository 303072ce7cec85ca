"""Offline simulation against independent discrete-time closed forms on a linear plant."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from foilc_hil.config import Config, load_config
from foilc_hil.design.fractional import FractionalPD
from foilc_hil.design.record import Design
from foilc_hil.loop.simulation import plot_simulation, simulate
from tests.support.designs import plain_design

A_C, B_C = -1.23, 1.68
TS = 0.05
N = 30  # 1.5 s trials


def _config(tmp_path: Path, extra: str = "", x0: float = 0.0) -> Config:
    text = f"""
plant:
  a: {A_C}
  b: {B_C}
  c: 1.0
  x0: [{x0}]
{extra}
reference:
  profile: piecewise
  segments:
    - {{duration: 0.5, start: 0.0, end: 1.0}}
    - {{duration: 1.0, start: 1.0}}
sample_time: {TS}
trials: 3
"""
    path = tmp_path / "sim.yaml"
    path.write_text(text, encoding="utf-8")
    return load_config(path)


def _zoh() -> tuple[float, float]:
    ad = math.exp(A_C * TS)
    return ad, B_C * (ad - 1.0) / A_C


def _design(p1: float, p2: float, kp: float, r: float) -> Design:
    ad, bd = _zoh()
    return plain_design([[ad]], [[bd]], [[1.0]], [[p1, p2]], kp=kp, r=r, sample_time=TS)


def _reference() -> np.ndarray:
    t = np.arange(1, N + 1) * TS
    return np.where(t <= 0.5 + 1e-12, 2.0 * t, 1.0)


def test_foilc_trials_1_and_2_match_closed_form(tmp_path: Path) -> None:
    x0, p1, p2, kp, r = 0.5, -0.3, 8.0, 0.2, 0.6
    config = _config(tmp_path, x0=x0)
    result = simulate(config, law="foilc", trials=2, design=_design(p1, p2, kp, r))
    t = np.arange(1, N + 1) * TS
    # trial 1 runs the zero feedforward: the free response of x' = a x from x0, in continuous time
    y1 = x0 * np.exp(A_C * t)
    np.testing.assert_allclose(result.outputs[0, :, 0], y1, rtol=1e-12, atol=1e-13)
    np.testing.assert_allclose(result.reference[:, 0], _reference(), atol=1e-12)
    e1 = _reference() - y1
    # d = 0: the whole trial is controllable; the law's memory starts at e1[0] with zero history before it.
    E1 = FractionalPD(kp, r, TS, history="zero").matrix(N) @ e1
    # trial 2: dx(t+1) = (Ad + Bd p1) dx(t) + Bd p2 E1[t], dx(0) = 0 (same x0), y2 = y1 + dx
    ad, bd = _zoh()
    dx = np.zeros(N + 1)
    u2 = np.zeros(N)
    for i in range(N):
        u2[i] = p1 * dx[i] + p2 * E1[i]
        dx[i + 1] = ad * dx[i] + bd * u2[i]
    np.testing.assert_allclose(result.controls[1, :, 0], u2, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(result.outputs[1, :, 0], y1 + dx[1:], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(result.learned[0, :, 0], E1, rtol=1e-9, atol=1e-12)
    assert [m.trial for m in result.metrics] == [1, 2]
    assert result.metrics[1].sse == pytest.approx(float(np.sum((_reference() - y1 - dx[1:]) ** 2)))


def test_p_type_with_input_delay_matches_closed_form(tmp_path: Path) -> None:
    gain = 0.8
    config = _config(tmp_path, extra="")
    config = config.model_copy(update={"law": config.law.model_copy(update={"p_type_gain": gain})})
    result = simulate(config, law="p-type", trials=2, input_delay=1)
    ref = _reference()
    np.testing.assert_array_equal(result.outputs[0], 0.0)  # zero input from rest
    # u2(t) = gain * e1[t + 1] (zero at the last sample); the plant applies u2(t - 1) during sample t
    u2 = np.append(gain * ref[1:], 0.0)
    ad, bd = _zoh()
    x, y2 = 0.0, np.zeros(N)
    for i in range(N):
        applied = u2[i - 1] if i >= 1 else 0.0
        x = ad * x + bd * applied
        y2[i] = x
    np.testing.assert_allclose(result.controls[1, :, 0], u2, rtol=1e-12)
    np.testing.assert_allclose(result.outputs[1, :, 0], y2, rtol=1e-9, atol=1e-12)


def test_disturbance_starts_at_its_trial(tmp_path: Path) -> None:
    d = 0.3
    config = _config(tmp_path, extra=f"  disturbance: {{kind: constant, amplitude: {d}, start_trial: 2}}")
    ad, bd = _zoh()
    # a P-type law that learns nothing (Gamma = 0), given as a design: the pipeline refuses it (||T|| = 1 is not a
    # certified contraction), and here it only has to leave the plant's response to the disturbance alone
    silent = plain_design([[ad]], [[bd]], [[1.0]], [[0.0, 0.0]], kp=0.0, r=1.0, sample_time=TS, law="p-type")
    result = simulate(config, law="p-type", trials=2, design=silent)
    t = np.arange(1, N + 1) * TS
    np.testing.assert_array_equal(result.outputs[0], 0.0)
    np.testing.assert_allclose(result.outputs[1, :, 0], d / A_C * (np.exp(A_C * t) - 1.0), rtol=1e-10)


#: The plant's real input gain ten times the model's (b + 15 sin(pi / 2 + 1e-3 t), nearly constant over a trial): the
#: design, certified (and rescaled) on the model, learns ten times too fast on this plant.
MISMODELLED = "  variation: {b: {kind: sine, amplitude: 15.0, frequency: 0.001, phase: 1.5707963}}"


def test_divergence_stops_the_run(tmp_path: Path) -> None:
    config = _config(tmp_path, extra=MISMODELLED)
    config = config.model_copy(update={"law": config.law.model_copy(update={"p_type_gain": 500.0})})
    result = simulate(config, law="p-type", trials=20)
    assert result.stopped
    assert 2 <= len(result.metrics) < 20
    assert result.outputs.shape[0] == len(result.metrics)


@pytest.mark.slow
def test_mcap_log_and_plots(tmp_path: Path) -> None:
    from foilc_hil.io.mcap_log import read_log

    config = _config(tmp_path, x0=0.2)
    out = tmp_path / "sim.mcap"
    result = simulate(config, law="foilc", trials=2, design=_design(-0.1, 5.0, 0.0, 1.0), out=out)
    log = read_log(out)
    assert not log.truncated
    assert log.completed_trials == [1, 2]
    assert len(log.samples) == 2 * N
    second = [s for s in log.samples if s["trial"] == 2]
    assert [s["control"] for s in second] == result.controls[1, :, 0].tolist()  # bit-exact floats
    # layout 2: a row's output is y((i + 1) Ts); the law's input at sample 0, y(0), is the trial's initial_output
    assert [s["output"] for s in second] == result.outputs[1, :, 0].tolist()
    assert log.trials[1]["initial_output"] == result.feedback[1, 0, 0] == 0.2
    assert log.trials[1]["final_output"] == result.outputs[1, -1, 0]
    assert log.trials[1]["sse"] == result.metrics[1].sse
    assert log.design is not None and log.design["P"] == [[-0.1, 5.0]]
    paths = plot_simulation(result, tmp_path / "plots")
    assert sorted(p.name for p in paths) == ["control.png", "error.png", "outputs.png", "sse.png"]
    assert all(p.stat().st_size > 1000 for p in paths)


# --- fractional memory: the converged error with an uncontrollable first sample ------------------------------------


def _delayed_design(kp: float, r: float) -> Design:
    from foilc_hil.design.models import DiscreteModel, augment_input_delay

    ad, bd = _zoh()
    aug, _ = augment_input_delay(DiscreteModel(np.array([[ad]]), np.array([[bd]]), np.array([[1.0]]), TS), 1)
    first_weight = 1.0 + kp * TS**-r
    return plain_design(
        aug.A, aug.B, aug.C, [[-0.5 * ad / bd, 0.0, 0.7 / (bd * first_weight)]], kp=kp, r=r, sample_time=TS,
        input_delay=1, C_measured=aug.measured_output,
    )


def _step_config(tmp_path: Path, memory: str) -> Config:
    path = tmp_path / f"step_{memory}.yaml"
    path.write_text(
        f"""
plant: {{a: {A_C}, b: {B_C}, c: 1.0}}
reference: {{profile: piecewise, segments: [{{duration: {N * TS}, start: 1.0}}]}}
sample_time: {TS}
law: {{fractional_memory: {memory}}}
""",
        encoding="utf-8",
    )
    return load_config(path)


def test_controllable_memory_removes_the_mittag_leffler_tail(tmp_path: Path) -> None:
    """d = 1, a unit step from rest: e(Ts) = 1 can never be moved. With the memory on the controllable samples the
    learned error goes to zero; with the paper-literal Caputo memory over the whole trial (which subtracts e(Ts))
    it converges to the fixed point e + kp D^r e = 0, a Mittag-Leffler decay ~ E_r(-t^r / kp), not to zero."""
    from scipy.special import rgamma

    kp, r, trials = 0.3, 0.6, 80
    finals = {}
    for memory in ("controllable", "trial"):
        result = simulate(
            _step_config(tmp_path, memory), law="foilc", trials=trials, design=_delayed_design(kp, r), input_delay=1
        )
        assert not result.stopped
        error = result.errors[-1][:, 0]
        assert error[0] == pytest.approx(1.0)  # the uncontrollable sample: the plant rests until u(0) arrives
        finals[memory] = error
    controllable_rmse = float(np.sqrt(np.mean(finals["controllable"][1:] ** 2)))
    assert controllable_rmse < 1e-6  # relative to the unit step
    tail = finals["trial"][1:]
    assert float(np.sqrt(np.mean(tail**2))) > 0.1  # the defect: a persistent offset
    # Its shape: the continuous fixed point e(tau) = e(Ts) E_r(-tau^r / kp), tau = time since the first sample
    # (Mittag-Leffler by its power series), matched up to the O(h) Grunwald-Letnikov error of the discrete law.
    tau = np.arange(N) * TS
    z = -(tau**r) / kp
    mittag_leffler = sum(z**k * rgamma(r * k + 1) for k in range(200))
    np.testing.assert_allclose(finals["trial"], mittag_leffler, atol=0.08)
    # ... and exactly the discrete fixed point F[1:, 1:] e[1:] = -F[1:, 0] e[0] of the Caputo operator.
    F = FractionalPD(kp, r, TS).matrix(N)
    fixed = -np.linalg.solve(F[1:, 1:], F[1:, :1] @ finals["trial"][:1])
    np.testing.assert_allclose(tail, fixed, atol=1e-6)


def test_a_design_that_looks_ahead_less_than_the_plants_delay_names_plant_delay(tmp_path: Path) -> None:
    """A ready design with ``input_delay`` 0 cannot run a plant whose own delay is 2 samples (the simulated drive
    would need a negative transport delay): a ConfigError naming ``plant.delay``, not the drive's internal
    ``input_delay: must be >= 0, got -2``. Below half a sample the delay rounds to none and the design runs."""
    from foilc_hil.errors import ConfigError

    design = _design(-0.4, 3.0, kp=0.05, r=0.6)
    with pytest.raises(ConfigError) as caught:
        simulate(_config(tmp_path, extra=f"  delay: {2 * TS}"), law="foilc", trials=1, design=design)
    assert caught.value.key == "plant.delay"
    assert "input_delay 0" in str(caught.value)
    result = simulate(_config(tmp_path, extra=f"  delay: {0.4 * TS}"), law="foilc", trials=1, design=design)
    assert len(result.metrics) == 1
