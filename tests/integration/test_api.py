"""The public Python API (``docs/api.md``) on the embedded emulator, through its documented names only.

Checks, each against something the API did not compute itself: a trial read back from the log equals the one the
bench yielded, every array bit for bit (the log is written by another process, through JSON); the drive is left
disabled, as the emulated drive itself reports, when the ``with`` block raises; the SSE is the sum of the squared
error samples; ``fh.design`` stays the function when the subpackage of the same name is imported; ``import
foilc_hil`` loads nothing else.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import foilc_hil as fh
from drivers.cia402 import State402
from tests.support.bench import bench_config

ROOT = Path(__file__).resolve().parents[2]
ARRAYS = ("reference", "output", "control", "error", "E")


class ScriptError(Exception):
    """The script's own error, raised inside the ``with`` block."""


@pytest.fixture(scope="module")
def config(tmp_path_factory: pytest.TempPathFactory) -> Any:
    return fh.load_config(bench_config(tmp_path_factory.mktemp("api")), overrides={"trials": 3, "law.kind": "p-type"})


@pytest.fixture(scope="module")
def design(config: Any) -> Any:
    return fh.design(config)


@pytest.mark.slow
def test_a_trial_read_back_from_the_log_equals_the_live_one(config: Any, design: Any, tmp_path: Path) -> None:
    out = tmp_path / "run.mcap"
    with fh.Bench(config, design=design, out=out) as bench:
        live = list(bench.trials(3))
    assert [trial.index for trial in live] == [1, 2, 3]
    log = fh.open_log(out)
    back = log.trials()
    assert len(back) == 3
    for ran, read in zip(live, back, strict=True):
        for name in ARRAYS:
            assert np.array_equal(getattr(ran, name), getattr(read, name)), (ran.index, name)
        assert ran.metrics == read.metrics
        assert ran.same_as(read)
    for trial in live:
        assert trial.output.shape == trial.reference.shape == (200,)
        assert trial.sse == pytest.approx(float(np.sum(trial.error**2)), rel=1e-12)
        assert np.array_equal(trial.error, trial.reference - trial.output)
    assert live[-1].sse < live[0].sse  # it learned
    assert log.config.sample_time == config.sample_time
    assert log.design is not None and np.array_equal(log.design.P, design.P)


def test_a_different_trial_is_not_the_same(config: Any, design: Any, tmp_path: Path) -> None:
    """``same_as`` can fail: trials 1 and 2 differ, and one changed bit is seen."""
    out = tmp_path / "run.mcap"
    with fh.Bench(config, design=design, out=out) as bench:
        first, second = bench.trials(2)
    assert not first.same_as(second)
    read = fh.open_log(out).trials()[0]
    read.output[7] = np.nextafter(read.output[7], np.inf)
    assert not first.same_as(read)


def test_the_bench_is_left_stopped_when_the_block_raises(config: Any, design: Any) -> None:
    states = []
    with pytest.raises(ScriptError), fh.Bench(config, design=design) as bench:
        for trial in bench.trials(3):
            assert bench.emulator is not None
            states.append(bench.emulator.drive.state)
            raise ScriptError(f"the script failed after trial {trial.index}")
    assert states == [State402.OPERATION_ENABLED]  # moving while the block ran
    assert bench.emulator is not None
    assert bench.emulator.drive.state is State402.SWITCH_ON_DISABLED  # the drive's own state machine
    report = bench.stop_report
    assert report is not None and report.confirmed and report.state is State402.SWITCH_ON_DISABLED


@pytest.mark.slow
def test_breaking_out_stops_the_drive_and_the_log_holds_what_ran(config: Any, design: Any, tmp_path: Path) -> None:
    out = tmp_path / "run.mcap"
    with fh.Bench(config, design=design, out=out) as bench:
        for trial in bench.trials(3):
            if trial.index == 2:
                break
        more = list(bench.trials(1))  # another call continues the numbering
    assert [trial.index for trial in more] == [3]
    assert bench.emulator is not None and bench.emulator.drive.state is State402.SWITCH_ON_DISABLED
    assert [trial.index for trial in fh.open_log(out).trials()] == [1, 2, 3]
    assert [metrics.trial for metrics in bench.report().outcome.trials] == [1, 2, 3]


def test_simulate_returns_the_trials_its_log_holds(config: Any, design: Any, tmp_path: Path) -> None:
    out = tmp_path / "sim.mcap"
    results = fh.simulate(config, design=design, trials=3, out=out)
    assert [trial.index for trial in results] == [1, 2, 3]
    for ran, read in zip(results, fh.open_log(out).trials(), strict=True):
        assert ran.same_as(read)
        assert ran.sse == pytest.approx(float(np.sum(ran.error**2)), rel=1e-12)
    assert results[-1].sse < results[0].sse


def test_errors_are_the_products(config: Any, design: Any, tmp_path: Path) -> None:
    with fh.Bench(config, design=design) as bench, pytest.raises(fh.errors.ConfigError, match="trials"):
        next(bench.trials(0))
    with pytest.raises(fh.errors.InputError, match="not open"):
        next(fh.Bench(config, design=design).trials(1))
    with pytest.raises(fh.errors.LogFormatError, match="no such file"):
        fh.open_log(tmp_path / "absent.mcap")
    with pytest.raises(fh.errors.ConfigError, match="law"):
        fh.design(config, law="no-such-law")
    several = fh.load_config(ROOT / "configs" / "scara_4axis.yaml")
    with pytest.raises(fh.errors.ConfigError, match="axes"):
        fh.Bench(several)


@pytest.mark.slow
def test_to_pandas_holds_every_sample(config: Any, design: Any, tmp_path: Path) -> None:
    pandas = pytest.importorskip("pandas")  # the [pandas] extra; the dev extra installs it
    out = tmp_path / "sim.mcap"
    results = fh.simulate(config, design=design, trials=2, out=out)
    frame = fh.open_log(out).to_pandas()
    assert isinstance(frame, pandas.DataFrame)
    assert len(frame) == 2 * 200
    for trial in results:
        rows = frame[frame["trial"] == trial.index].sort_values("sample")
        for name in ARRAYS:
            assert np.array_equal(rows[name].to_numpy(), getattr(trial, name))


def test_to_pandas_without_pandas_names_the_extra(config: Any, design: Any, tmp_path: Path,
                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    out = tmp_path / "sim.mcap"
    fh.simulate(config, design=design, trials=1, out=out)
    monkeypatch.setitem(sys.modules, "pandas", None)  # what an interpreter without pandas finds
    with pytest.raises(ImportError, match=r"foilc-hil\[pandas\]"):
        fh.open_log(out).to_pandas()


def test_frames_are_python_can_messages(config: Any, design: Any, tmp_path: Path) -> None:
    import can

    out = tmp_path / "run.mcap"
    with fh.Bench(config, design=design, out=out) as bench:
        list(bench.trials(1))
    frames = list(fh.open_log(out).frames())
    assert frames and all(isinstance(frame, can.Message) for frame in frames)
    syncs = sum(1 for frame in frames if frame.arbitration_id == 0x080 and not frame.is_rx)
    assert syncs >= bench.report().cycles  # the loop's cycles, and the commissioning's and the stop's


def _fresh(probe: str) -> Any:
    child = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, cwd=ROOT, timeout=120,
                           check=False)
    assert child.returncode == 0, child.stderr
    return json.loads(child.stdout.splitlines()[-1])


def test_import_foilc_hil_loads_nothing_else() -> None:
    loaded = _fresh("import json, sys, foilc_hil\n"
                    "print(json.dumps(sorted(m for m in sys.modules if m.split('.')[0] in "
                    "('foilc_hil', 'drivers', 'plant_emulator', 'numpy', 'can', 'canopen'))))")
    assert loaded == ["foilc_hil"]
    # and not blind: a public name imports its module on first use
    assert "foilc_hil.api.log" in _fresh("import json, sys, foilc_hil\nfoilc_hil.open_log\n"
                                         "print(json.dumps(sorted(sys.modules)))")


@pytest.mark.slow
def test_design_stays_the_function_when_the_subpackage_is_imported() -> None:
    # the import system binds a subpackage to its parent's attribute of the same name
    assert _fresh("import json, foilc_hil, foilc_hil.design.pipeline\n"
                  "from foilc_hil.design import record\n"
                  "print(json.dumps([callable(foilc_hil.design), foilc_hil.design.__module__, record.__name__]))"
                  ) == [True, "foilc_hil.api.bench", "foilc_hil.design.record"]


@pytest.mark.slow
def test_a_new_iteration_ends_a_suspended_one(config: Any, design: Any, tmp_path: Path) -> None:
    out = tmp_path / "run.mcap"
    with fh.Bench(config, design=design, out=out) as bench:
        suspended = bench.trials(3)  # kept in a variable: not closed when the script moves on
        assert next(suspended).index == 1
        assert [trial.index for trial in bench.trials(1)] == [2]
    assert [trial.index for trial in fh.open_log(out).trials()] == [1, 2]
    assert bench.emulator is not None and bench.emulator.drive.state is State402.SWITCH_ON_DISABLED
