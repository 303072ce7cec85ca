"""One trial loop: ``simulate`` is the bench's ``TrialLoop`` on a ``SimulatedDrive``, with the bench's divergence rule.

Checked against things ``simulate`` does not compute itself: the bench over the embedded emulator (the real CiA 402
master and virtual drive on a virtual CAN bus), the plant's own step response, and the MCAP log of a ``TrialLoop``
built here by hand.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from drivers.cia402 import State402
from drivers.config import BusConfig
from foilc_hil.config import Config, load_config
from foilc_hil.design.models import DiscreteModel, augment_input_delay
from foilc_hil.design.record import Design
from foilc_hil.errors import ConfigError
from foilc_hil.io.mcap_log import McapLogWriter, read_log
from foilc_hil.loop.bench import TrialLoop
from foilc_hil.loop.log_sink import McapSink
from foilc_hil.loop.rig import RunRequest, plan_axis, run_rig
from foilc_hil.loop.settings import loop_settings
from foilc_hil.loop.simulated_drive import SimulatedDrive
from foilc_hil.loop.simulation import simulate
from foilc_hil.references import reference_profile
from plant_emulator.device import TimingMode
from plant_emulator.physics import build_plant
from tests.support.designs import plain_design

A_C, B_C = -1.23, 1.68
TS = 0.05
N = 20  # 1 s trials
VELOCITY_SCALE = 1e6  # counts per plant unit: the CAN path quantises commands and feedback to 1e-6


def _config(tmp_path: Path, *, plant: dict[str, Any] | None = None, bench: dict[str, Any] | None = None) -> Config:
    document = {
        "plant": {"a": A_C, "b": B_C, "c": 1.0, **(plant or {})},
        "reference": {"profile": "piecewise", "segments": [{"duration": N * TS, "start": 1.0}]},
        "sample_time": TS,
        "trials": 5,
        "drive": {
            "node_id": 1,
            "mode": "csv",
            "velocity_scale": VELOCITY_SCALE,
            "velocity_limit": 1000.0,  # never reached: the law's and the limiter's clamps stay inactive
            "heartbeat_timeout_factor": 10.0,
            "heartbeat_consumer_ms": 2000,
        },
        "bench": {"settle_time": 0.05, "settle_tolerance": 0.5, **(bench or {})},
    }
    path = tmp_path / "one_loop.yaml"
    path.write_text(yaml.safe_dump(document), encoding="utf-8")
    return load_config(path)


def _design() -> Design:
    """A FOILC design for the CAN loop's one-cycle delay with a chosen gain (no LMI run)."""
    kp, r = 0.2, 0.5
    ad = math.exp(A_C * TS)
    bd = B_C * (ad - 1.0) / A_C
    aug, _ = augment_input_delay(DiscreteModel(np.array([[ad]]), np.array([[bd]]), np.array([[1.0]]), TS), 1)
    gain = [[-0.5 * ad / bd, 0.0, 0.7 / (bd * (1.0 + kp * TS**-r))]]
    return plain_design(
        aug.A, aug.B, aug.C, gain, kp=kp, r=r, sample_time=TS, input_delay=1, C_measured=aug.measured_output
    )


def _bench(config: Config, design: Design, channel: str, out: Path | None = None) -> Any:
    request = RunRequest(
        config=config, out=out, law="foilc", design=design, bus=BusConfig(interface="embedded", channel=channel)
    )
    return run_rig(request)


# --- the simulated drive ----------------------------------------------------------------------------------------


@pytest.mark.parametrize("delay", [0, 1, 2])
def test_simulated_drive_applies_a_command_after_its_transport_delay(tmp_path: Path, delay: int) -> None:
    """A unit pulse set after SYNC 0 moves the output first in the answer to SYNC ``1 + delay``; that answer is
    one ZOH step of the plant from rest, computed here from the continuous model."""
    drive = SimulatedDrive(build_plant(_config(tmp_path).plant), sample_time=TS, input_delay=delay)
    drive.enable()
    drive.begin_trial(1)
    outputs = []
    for cycle in range(delay + 3):
        drive.sync()
        outputs.append(drive.wait_feedback(1.0).velocity)
        drive.set_target(1.0 if cycle == 0 else 0.0)
    first_move = 1 + delay
    assert outputs[:first_move] == [0.0] * first_move
    assert outputs[first_move] == pytest.approx(B_C * (math.exp(A_C * TS) - 1.0) / A_C, rel=1e-12)
    assert outputs[first_move + 1] == pytest.approx(outputs[first_move] * math.exp(A_C * TS), rel=1e-12)


def test_a_trial_starts_at_the_sync_that_reset_the_plant(tmp_path: Path) -> None:
    drive = SimulatedDrive(build_plant(_config(tmp_path, plant={"x0": [0.5]}).plant), sample_time=TS)
    drive.enable()
    drive.sync()
    drive.sync()  # the plant decays from x0
    assert drive.wait_feedback(1.0).velocity == pytest.approx(0.5 * math.exp(A_C * TS), rel=1e-12)
    drive.begin_trial(2)
    drive.sync()
    feedback = drive.wait_feedback(1.0)
    assert feedback.velocity == 0.5  # the initial condition itself: no step on the trial's first SYNC
    assert feedback.state is State402.OPERATION_ENABLED


def test_simulated_drive_is_one_axis(tmp_path: Path) -> None:
    identity = [[1.0, 0.0], [0.0, 1.0]]
    config = _config(tmp_path, plant={"a": [[-1.0, 0.0], [0.0, -2.0]], "b": identity, "c": identity})
    with pytest.raises(ConfigError, match="one axis"):
        SimulatedDrive(build_plant(config.plant), sample_time=TS)


# --- simulate is the trial loop -----------------------------------------------------------------------------------


def test_simulate_logs_what_the_trial_loop_on_a_simulated_drive_logs(tmp_path: Path) -> None:
    config = _config(tmp_path)
    design = _design()
    simulated = tmp_path / "simulate.mcap"
    result = simulate(config, law="foilc", trials=3, design=design, input_delay=1, out=simulated)
    by_hand = tmp_path / "trial_loop.mcap"
    law = plan_axis(config, "foilc", N, design=design, input_delay=1).law
    drive = SimulatedDrive(build_plant(config.plant), sample_time=TS, input_delay=1)
    drive.enable()
    with McapLogWriter(by_hand, config_yaml=None, fsync=False) as writer:
        settings = loop_settings(config, TimingMode.LOCKSTEP, settle_between_trials=False)
        reference = reference_profile(config.reference, TS)
        loop = TrialLoop(
            drive, law, reference, None, settings, log=McapSink(writer, law.limits), before_trial=drive.begin_trial
        )
        outcome = loop.run(3)
    ours, theirs = read_log(simulated), read_log(by_hand)
    assert len(ours.samples) == 3 * N
    assert ours.samples == theirs.samples  # every field of every row, bit for bit
    assert ours.trials == theirs.trials
    assert [m.sse for m in result.metrics] == [m.sse for m in outcome.trials]


def test_bench_over_the_emulator_and_simulate_agree(tmp_path: Path) -> None:
    """The same design and plant, once over CAN (master + virtual drive, lockstep) and once offline with the CAN
    loop's one-cycle delay: the per-trial metrics and samples agree to the CAN path's quantisation."""
    config = _config(tmp_path)
    design = _design()
    result = simulate(config, law="foilc", trials=config.trials, design=design, input_delay=1)
    out = tmp_path / "bench.mcap"
    report = _bench(config, design, "foilc-hil-test-one-loop", out)
    assert not result.stopped and report.outcome.stopped is None
    bench_sse = [m.sse for m in report.outcome.trials]
    assert bench_sse[0] == result.metrics[0].sse == pytest.approx(N)  # trial 1: u = 0 from rest, e = 1 throughout
    np.testing.assert_allclose(bench_sse, [m.sse for m in result.metrics], rtol=1e-5)
    assert bench_sse[-1] < bench_sse[1] < 0.1 * bench_sse[0]  # learning (e(Ts) = 1 stays: it cannot be moved)
    # sample by sample: the output at t = (i + 1) Ts and the command (one sample off would be ~0.1 apart)
    samples = read_log(out).samples
    for field, simulated in (("output", result.outputs), ("control", result.controls)):
        logged = np.array([row[field] for row in samples]).reshape(simulated.shape)
        np.testing.assert_allclose(logged, simulated, rtol=0, atol=1e-4)  # the law amplifies 1e-6


# --- one divergence rule ---------------------------------------------------------------------------------------


def test_one_divergence_rule_offline_and_on_the_bench(tmp_path: Path) -> None:
    """A disturbance from trial 4 raises the SSE above 2 x the best trial's but far below 2 x trial 1's: both paths
    stop after trial 4 with the bench's rule (x best SSE), restoring the best feedforward."""
    config = _config(
        tmp_path,
        plant={"disturbance": {"kind": "constant", "amplitude": 4.0, "start_trial": 4}},
        bench={"divergence_factor": 2.0, "settle_tolerance": 5.0},
    )
    design = _design()
    result = simulate(config, law="foilc", trials=config.trials, design=design, input_delay=1)
    report = _bench(config, design, "foilc-hil-test-one-rule")
    for stopped, metrics in ((result.stopped, result.metrics), (report.outcome.stopped, report.outcome.trials)):
        sse = [m.sse for m in metrics]
        assert len(sse) == 4
        best = min(sse[:3])
        assert 2.0 * best < sse[3] < 2.0 * sse[0]  # the rule measured against trial 1 would not have tripped
        assert stopped is not None
        assert f"trial 4 SSE {sse[3]:.6g} > 2 x best SSE {best:.6g} (trial 3)" in stopped
    assert report.outcome.diverged


def test_simulate_clamps_to_the_bench_command_limits(tmp_path: Path) -> None:
    """A step reference from rest asks the first samples for an output no command reaches by then: unclamped, the
    law integrates that error trial after trial (the demo's first command grew ~3,000 rpm a trial). Offline, as on
    the bench, the law clamps to ``drive.velocity_limit`` and the log records the limits."""
    limit = 2.0  # the step's steady state needs u = 1.23 / 1.68 = 0.73; the first samples ask for far more
    path = tmp_path / "one_loop.yaml"
    _config(tmp_path)  # writes one_loop.yaml, edited below
    document = yaml.safe_load(path.read_text(encoding="utf-8"))
    document["drive"]["velocity_limit"] = limit
    path.write_text(yaml.safe_dump(document), encoding="utf-8")
    config = load_config(path)
    out = tmp_path / "clamped.mcap"
    result = simulate(config, law="foilc", trials=8, design=_design(), input_delay=1, out=out)
    controls = np.asarray(result.controls)
    assert np.max(np.abs(controls)) == pytest.approx(limit)  # reached, never passed
    again = simulate(config, law="foilc", trials=8, design=_design(), input_delay=1).controls
    assert np.array_equal(np.asarray(again), controls)  # deterministic: the clamp is the law's, not chance
    assert all(trial["command_limits"] == [-limit, limit] for trial in read_log(out).trials)
