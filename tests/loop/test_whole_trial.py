"""The compiled whole trial (``SimulatedDrive.run_whole_trial``) against the per-cycle path of the same loop.

The truth here is the per-cycle path: ``TrialLoop`` calling ``LearningLaw.command`` and the plant's ``step`` once
per SYNC, which the rest of the suite checks against closed forms and the CAN bench. The compiled trial must give
the same trajectories for every law and both plants, with everything random or time-varying switched on (noise,
``Delta a(t)``, ``Delta b(t)``, a disturbance from a later trial), and stop where the per-cycle path stops.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from foilc_hil.config import Config, load_config
from foilc_hil.design.models import DiscreteModel, augment_input_delay
from foilc_hil.design.pipeline import build_design
from foilc_hil.design.record import Design
from foilc_hil.errors import LearningDivergedError
from foilc_hil.laws.learning import make_law
from foilc_hil.loop.bench import TrialLoop
from foilc_hil.loop.interfaces import TrialRecord, WholeTrial
from foilc_hil.loop.scheduler import CycleBlock
from foilc_hil.loop.settings import loop_settings
from foilc_hil.loop.simulated_drive import SimulatedDrive
from foilc_hil.references import reference_profile
from plant_emulator.device import TimingMode
from plant_emulator.physics import build_plant

TS = 0.02
N = 30
TRIALS = 4
FIRST_ORDER: dict[str, Any] = {
    "a": -1.23,
    "b": 1.68,
    "c": 1.0,
    "x0": [0.1],
    "output_noise": 0.01,
    "variation": {"a": {"kind": "sine", "amplitude": 0.3, "frequency": 7.0},
                  "b": {"kind": "random_walk", "amplitude": 0.2, "frequency": 3.0}},
    "disturbance": {"kind": "square", "amplitude": 0.2, "frequency": 9.0, "start_time": 0.1, "start_trial": 3},
    "saturation": {"u_min": -1.5, "u_max": 1.5},
}
PMSM: dict[str, Any] = {
    "model": "pmsm",
    "a": -1.23,
    "b": 1.68,
    "c": 1.0,
    "output_noise": 0.5,
    "disturbance": {"kind": "step", "amplitude": 0.05, "start_time": 0.2, "start_trial": 2},
    "pmsm": {"internal_step": 0.0005, "velocity_filter": 0.002, "drift": {"amplitude": 0.05, "frequency": 2.0}},
}


def _config(tmp_path: Path, plant: dict[str, Any], top: float = 1.0) -> Config:
    document = {
        "plant": plant,
        "reference": {"profile": "piecewise", "segments": [{"duration": N * TS, "start": 0.0, "end": top}]},
        "sample_time": TS,
        "bench": {"divergence_factor": 1e9},
    }
    path = tmp_path / "whole_trial.yaml"
    path.write_text(yaml.safe_dump(document), encoding="utf-8")
    return load_config(path)


def _design(config: Config, law: str, delay: int) -> Design:
    """FOILC/IOILC with a chosen gain on the ZOH model (no LMI run); P-type and NOILC from the pipeline."""
    if law in ("p-type", "noilc"):
        return build_design(config, law, N, input_delay=delay)
    from tests.support.designs import plain_design

    kp = 0.2 if law == "foilc" else 0.0
    ad = math.exp(-1.23 * TS)
    bd = 1.68 * (ad - 1.0) / -1.23
    aug, _ = augment_input_delay(DiscreteModel(np.array([[ad]]), np.array([[bd]]), np.array([[1.0]]), TS), delay)
    gain = [[-0.4 * ad / bd, *([0.1] * delay), 0.6 / (bd * (1.0 + kp * TS**-0.5))]]
    return plain_design(aug.A, aug.B, aug.C, gain, kp=kp, r=0.5, sample_time=TS, law=law, input_delay=delay,
                        C_measured=aug.measured_output)


class _Records:
    def __init__(self) -> None:
        self.records: list[TrialRecord] = []

    def trial_finished(self, record: TrialRecord) -> None:
        self.records.append(record)

    def timing(self, block: CycleBlock) -> None:
        """Lockstep logs no timing."""


def _run(config: Config, design: Design, *, whole: bool, limits: tuple[float, float] | None = None) -> tuple[
    list[TrialRecord], str, int
]:
    """The trials through ``TrialLoop`` on a simulated drive; returns the records, why it stopped, and how many
    trials the drive ran whole."""
    law = make_law(design, config.law, N, limits=limits)
    drive = SimulatedDrive(build_plant(config.plant), sample_time=TS, input_delay=design.error_lead,
                           whole_trials=whole)
    ran: list[WholeTrial] = []
    run_whole_trial = drive.run_whole_trial

    def counted(law_: object, seen: np.ndarray, control: np.ndarray) -> WholeTrial | None:
        result = run_whole_trial(law_, seen, control)
        if result is not None:
            ran.append(result)
        return result

    drive.run_whole_trial = counted  # type: ignore[method-assign,assignment]
    sink = _Records()
    settings = loop_settings(config, TimingMode.LOCKSTEP, settle_between_trials=False)
    loop = TrialLoop(drive, law, reference_profile(config.reference, TS), None, settings, log=sink,
                     before_trial=drive.begin_trial)
    drive.enable()
    try:
        stopped = loop.run(TRIALS).stopped or ""
    except LearningDivergedError as exc:
        stopped = str(exc)
    return sink.records, stopped, len(ran)


def _assert_same(whole: list[TrialRecord], per_cycle: list[TrialRecord]) -> None:
    assert len(whole) == len(per_cycle) == TRIALS
    for ours, theirs in zip(whole, per_cycle, strict=True):
        for field in ("seen", "control", "applied", "output", "E"):
            np.testing.assert_allclose(getattr(ours, field), getattr(theirs, field), rtol=1e-12, atol=1e-12,
                                       err_msg=f"trial {ours.trial}: {field}")
        assert ours.metrics.sse == pytest.approx(theirs.metrics.sse, rel=1e-12)


@pytest.mark.parametrize("law", ["foilc", "ioilc", "p-type", "noilc"])
@pytest.mark.parametrize("plant", ["first_order", "pmsm"])
def test_whole_trials_give_the_per_cycle_trajectories(tmp_path: Path, law: str, plant: str) -> None:
    config = _config(tmp_path, FIRST_ORDER if plant == "first_order" else PMSM, 1.0 if plant == "first_order" else 50)
    delay = 2 if law == "foilc" else 1  # FOILC also with two commands in flight (the augmented state's FIFO)
    design = _design(config, law, delay)
    limits = (-40.0, 40.0) if law == "foilc" else None  # the law's clamp inside the compiled step too
    whole, stopped_whole, ran = _run(config, design, whole=True, limits=limits)
    per_cycle, stopped, ran_per_cycle = _run(config, design, whole=False, limits=limits)
    assert (ran, ran_per_cycle) == (TRIALS, 0)  # each path ran as named
    assert stopped_whole == stopped == ""
    _assert_same(whole, per_cycle)
    assert not np.array_equal(whole[-1].control, whole[0].control)  # it learned: the comparison is not of zeros


@pytest.mark.parametrize("law", ["foilc", "p-type"])
def test_a_plant_delay_of_whole_samples_runs_whole_trials_too(tmp_path: Path, law: str) -> None:
    """``plant.delay`` = 2 samples: the plant applies each command two steps late (step() keeps a command queue and
    integrates over (t + dt) - t); the compiled trial hands it the command from two steps before."""
    config = _config(tmp_path, {**FIRST_ORDER, "delay": 2 * TS})
    design = _design(config, law, 3)  # the design looks ahead over the drive's and the plant's delays
    whole, stopped_whole, ran = _run(config, design, whole=True)
    per_cycle, stopped, _ = _run(config, design, whole=False)
    assert ran == TRIALS and stopped_whole == stopped == ""
    _assert_same(whole, per_cycle)


def test_a_whole_trial_stops_where_the_per_cycle_path_stops(tmp_path: Path) -> None:
    """An unstable plant overflows to inf within the first trial: both paths stop at the same cycle, same words."""
    config = _config(tmp_path, {"a": 2000.0, "b": 1.0, "c": 1.0, "x0": [1.0]})
    design = _design(config, "ioilc", 1)
    whole, stopped_whole, ran = _run(config, design, whole=True)
    per_cycle, stopped, _ = _run(config, design, whole=False)
    assert ran == 1 and whole == per_cycle == []
    # x(k TS) = e^(40 k) overflows past 1.8e308 = e^709.8 at step k = 18: the feedback of the trial's cycle 18
    assert stopped_whole == stopped == "non-finite drive feedback (inf) at cycle 18"


def test_the_drive_ends_a_whole_trial_where_its_cycles_would(tmp_path: Path) -> None:
    """After a whole trial the drive's next SYNC is the trial's last cycle: the plant, the command FIFO and the
    feedback are those of the per-cycle path, so the loop's closing measurement y(N Ts) is the same."""
    config = _config(tmp_path, FIRST_ORDER)
    design = _design(config, "foilc", 2)
    whole, _, _ = _run(config, design, whole=True)
    per_cycle, _, _ = _run(config, design, whole=False)
    assert [record.seen[-1] for record in whole] == pytest.approx([record.seen[-1] for record in per_cycle],
                                                                 rel=1e-12, abs=1e-12)
    assert all(np.isnan(record.sync_times[:-1]).all() for record in whole)  # not measured per cycle: said so
    assert not np.isnan(whole[0].sync_times[-1])
