"""``EmbeddedEmulator`` (``--emulator embedded``) and the ``plant-emulator`` command line."""

from __future__ import annotations

import math
import signal
import struct
import subprocess
import sys
import time
from pathlib import Path

import pytest

from foilc_hil.config import Config, load_config
from foilc_hil.errors import ExitCode
from plant_emulator.cli import _build_drives, load_settings, main
from plant_emulator.config import DisturbanceConfig, PlantConfig
from plant_emulator.embedded import EmbeddedEmulator
from plant_emulator.settings import EmulatorConfig
from tests.support.emulator_harness import Harness

pytestmark = pytest.mark.timeout(60)
ROOT = Path(__file__).resolve().parents[2]


def test_each_embedded_emulator_has_its_own_channel() -> None:
    config = Config.model_validate({"plant": {"model": "pmsm"}, "drive": {"node_id": 7, "velocity_scale": 1000.0}})
    first = EmbeddedEmulator.from_config(config)
    second = EmbeddedEmulator.from_config(config)
    assert first.bus_config.interface == "inprocess"  # lockstep: the synchronous in-process transport
    assert first.bus_config.channel != second.bus_config.channel
    assert first.device is first.drive and first.drive.node_id == 7


def test_begin_trial_switches_the_disturbance_on() -> None:
    """From ``start_trial`` on, a constant disturbance moves a plant at rest: x(t) = d / -a (1 - e^{a t})."""
    a, d, period = -2.0, 0.5, 0.01
    plant = PlantConfig(
        model="first_order", a=a, b=1.0, c=1.0,
        disturbance=DisturbanceConfig(kind="constant", amplitude=d, start_trial=2),
    )
    with Harness(plant, cycle_period=period, velocity_scale=1000.0) as h:
        h.start()
        for _ in range(10):
            h.sync(wait_for=h.tpdo1)
        assert struct.unpack_from("<Hi", h.recorder.frames[h.tpdo1][-1])[1] == 0  # trial 1: no disturbance
        h.drive.begin_trial(2)
        cycles = 10
        for _ in range(cycles):
            h.sync(wait_for=h.tpdo1)
        velocity = struct.unpack_from("<Hi", h.recorder.frames[h.tpdo1][-1])[1]
    expected = d / -a * (1.0 - math.exp(a * cycles * period))
    assert velocity == round(expected * 1000.0)


def test_cli_loads_only_its_sections(tmp_path: Path) -> None:
    config = tmp_path / "bench.yaml"
    config.write_text(
        "plant: {model: pmsm}\nsample_time: 0.005\ndrive: {node_id: 9}\nemulator: {timing: realtime}\n"
        "law: {kind: foilc}\nbench: {mode: lockstep}\n",
        encoding="utf-8",
    )
    settings = load_settings(str(config), {"drive.node_id": 4, "emulator.timing": None})
    assert settings.drive.node_id == 4  # --node-id wins over the file
    assert settings.emulator == EmulatorConfig(timing="realtime")
    assert settings.sample_time == 0.005
    assert load_config(config).emulator.timing == "realtime"  # the bench reads the same section alike


def test_one_process_serves_each_axis_with_its_own_plant_as_its_own_process_would(
        monkeypatch: pytest.MonkeyPatch) -> None:
    import plant_emulator.physics as physics

    built: list[tuple[PlantConfig, int | None]] = []
    original = physics.build_plant

    def recording(plant: PlantConfig, seed: int | None = None) -> physics.Plant:
        built.append((plant, seed))
        return original(plant, seed=seed)

    monkeypatch.setattr(physics, "build_plant", recording)
    scara = Path(__file__).resolve().parents[2] / "configs" / "scara_4axis.yaml"
    settings = load_settings(str(scara), {"drive.node_id": None, "emulator.timing": None})
    _build_drives(settings, (1, 2, 3, 4, 9))
    shared = built[:]
    for axis in settings.axes:  # each axis alone, as four processes build it (the axis's sections in place)
        _build_drives(settings.model_copy(update={"plant": axis.plant, "axes": ()}), (axis.node_id,))
    assert shared[:4] == built[5:]
    assert len({plant.pmsm.inertia for plant, _seed in shared[:4]}) == 4
    assert shared[4] == (settings.plant, settings.plant.seed + settings.emulator.seed + 4)  # not an axis


@pytest.mark.parametrize(
    ("argv", "text"),
    [
        (["--bus", "nope"], "INTERFACE:CHANNEL"),
        (["--bus", "virtual:x", "--node-id", "0"], "--node-id"),
        (["--bus", "virtual:x", "--mode", "fast"], "invalid choice"),
        (["--bus", "virtual:x", "--config", "/nonexistent.yaml"], "no such file"),
    ],
)
def test_cli_bad_input_exits_2_with_one_line(
    argv: list[str], text: str, capsys: pytest.CaptureFixture[str]
) -> None:
    try:
        code = main(argv)
    except SystemExit as exc:  # argparse's own usage errors
        code = int(exc.code or 0)
    err = capsys.readouterr().err
    assert code == ExitCode.USAGE
    assert text in err and len(err.strip().splitlines()) == 1


def test_cli_bad_config_key(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    config = tmp_path / "bad.yaml"
    config.write_text("emulator: {sync_loss_cycle: 3}\n", encoding="utf-8")
    assert main(["--bus", "virtual:x", "--config", str(config)]) == ExitCode.USAGE
    err = capsys.readouterr().err.strip()
    assert "emulator.sync_loss_cycle" in err and "sync_loss_cycles" in err and len(err.splitlines()) == 1


@pytest.mark.slow
def test_console_script_runs_until_sigterm() -> None:
    """A virtual bus in a child process reaches nothing outside it; the process boots, says ready, stops on TERM."""
    process = subprocess.Popen(
        [sys.executable, "-m", "plant_emulator", "--bus", "virtual:cli-test", "--node-id", "6"],
        cwd=ROOT,
        stderr=subprocess.PIPE,
        text=True,
    )
    assert process.stderr is not None
    try:
        ready = process.stderr.readline()
        assert "ready" in ready and "node 6" in ready
        time.sleep(0.1)
        process.send_signal(signal.SIGTERM)
        assert process.wait(timeout=10) == 0
        assert "stopped" in process.stderr.read()
    finally:
        if process.poll() is None:
            process.kill()
