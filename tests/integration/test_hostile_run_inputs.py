"""Hostile input to the commands that run trials, bounded: exit 2 and one line naming the field, found before the
design; and physics that diverge at run time end in the drive's fault and a confirmed stop, never a traceback.

Before: a piecewise segment of 1e12 s tried to allocate 7 PiB (exit 1, 26 lines); a PMSM inertia of 1e-30 or 1e-9
gave NaN physics raised again inside the stop (three tracebacks); ``sample_time: 1e-300`` with ``simulate`` was
``math domain error``; an ``--out`` that is a directory, or on a read-only file system, was refused only after the
design.
"""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import yaml

from foilc_hil.cli import main
from tests.support.bench import NODE, bench_config

ROOT = Path(__file__).resolve().parents[2]


def _write(tmp_path: Path, document: dict[str, Any]) -> Path:
    path = tmp_path / "hostile.yaml"
    path.write_text(yaml.safe_dump(document), encoding="utf-8")
    return path


def _one_line(capsys: pytest.CaptureFixture[str], command: str) -> str:
    err = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
    assert len(err) == 1 and err[0].startswith(f"foilc-hil {command}: "), err
    return err[0]


@pytest.fixture
def no_design(monkeypatch: pytest.MonkeyPatch) -> None:
    """The design pipeline must not be reached: these are refused before it."""
    from foilc_hil.design import pipeline

    def designed(*args: Any, **kwargs: Any) -> Any:
        raise AssertionError("the design ran before the input was refused")

    monkeypatch.setattr(pipeline, "build_design", designed)


LONG_SEGMENT = {"reference": {"profile": "piecewise", "segments": [
    {"duration": 1.0, "start": 0.0, "end": 1.0}, {"duration": 1.0e12, "start": 1.0}]}}


@pytest.mark.parametrize("command", [["simulate", "--trials", "1"], ["run", "--trials", "1", "--out", "OUT"],
                                     ["synthesize"]])
@pytest.mark.parametrize(("document", "key"), [
    (LONG_SEGMENT, "reference.segments[1].duration"),
    ({"sample_time": 1.0e-300}, "sample_time"),
    ({"plant": {"model": "pmsm", "a": -5.0, "b": 5.0, "pmsm": {"inertia": 1.0e-30}}}, "plant.pmsm"),
    ({"plant": {"model": "pmsm", "a": -5.0, "b": 5.0, "pmsm": {"inertia": 1.0e-9}}}, "plant.pmsm"),
])
def test_a_hostile_config_is_refused_naming_the_field(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], no_design: None, command: list[str],
    document: dict[str, Any], key: str,
) -> None:
    config = _write(tmp_path, document)
    argv = [arg.replace("OUT", str(tmp_path / "x.mcap")) for arg in command]
    assert main([*argv, "--config", str(config)]) == 2
    line = _one_line(capsys, command[0])
    assert f"{config}: {key}: " in line, line
    if key == "plant.pmsm":
        assert "inertia" in line and "diverge" in line


@pytest.mark.parametrize("where", ["a directory", "a missing directory"])
def test_a_bad_out_is_refused_before_the_design(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], no_design: None, where: str
) -> None:
    out = tmp_path if where == "a directory" else tmp_path / "missing" / "x.mcap"
    for command in (["run", "--out", str(out)], ["simulate", "--out", str(out)]):
        assert main([*command, "--config", str(bench_config(tmp_path)), "--trials", "1"]) == 2
        line = _one_line(capsys, command[0])
        assert f"{out}: cannot create: " in line and ("is a directory" in line or "no such directory" in line)
    assert not list(tmp_path.glob(".*.probe"))  # the probe leaves nothing behind


@pytest.mark.slow
def test_an_out_on_a_read_only_file_system_is_refused_before_the_design(tmp_path: Path) -> None:
    probe = subprocess.run(["unshare", "--mount", "--", "true"], capture_output=True, check=False)
    if os.geteuid() != 0 or probe.returncode != 0:
        pytest.skip("needs root and unshare(1) for a private read-only mount")
    mount = tmp_path / "ro"
    mount.mkdir()
    config = bench_config(tmp_path)
    # the design would take the run past the marker; refused first, the run never prints it
    run = (f"{sys.executable} -c \"import sys; from foilc_hil.design import pipeline; "
           f"pipeline.build_design = lambda *a, **k: sys.exit(99); from foilc_hil.cli import main; "
           f"sys.exit(main(['run', '--config', '{config}', '--out', '{mount}/x.mcap']))\"")
    script = f"mount -t tmpfs -o ro tmpfs {mount} && {run}"
    result = subprocess.run(["unshare", "--mount", "--", "sh", "-c", script], capture_output=True, text=True,
                            env={**os.environ, "PYTHONPATH": str(ROOT)}, cwd=ROOT, check=False, timeout=120)
    assert result.returncode == 2, result.stderr
    assert result.stderr.strip() == f"foilc-hil run: {mount}/x.mcap: cannot create: read-only file system"


@pytest.mark.slow
def test_physics_that_diverge_mid_run_fault_the_drive_and_the_stop_is_reported(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    """A plant whose output turns NaN in trial 2 (physics the checks let through): the emulated drive faults with
    EMCY 0x6100 and restarts its plant; the run exits 1 with one line and the confirmed stop."""
    from plant_emulator.physics.first_order import FirstOrderPlant

    original = FirstOrderPlant.step_scalar
    calls = [0]

    def diverging(self: FirstOrderPlant, u: float, dt: float) -> float:
        calls[0] += 1
        return math.nan if calls[0] == 350 else original(self, u, dt)

    monkeypatch.setattr(FirstOrderPlant, "step_scalar", diverging)
    out = tmp_path / "run.mcap"
    assert main(["run", "--config", str(bench_config(tmp_path)), "--trials", "4", "--out", str(out)]) == 1
    line = _one_line(capsys, "run")
    assert "EMCY 0x6100" in line and f"drive {NODE} confirmed disabled" in line, line
    assert calls[0] >= 350


@pytest.mark.slow
def test_a_drive_fault_is_one_stderr_line_at_the_default_log_level(tmp_path: Path) -> None:
    """In a process (a logging handler made before pytest's capture would hide a second line in process): the
    EMCY was printed twice, once as the master's log warning and once as the result."""
    command = [sys.executable, "-m", "foilc_hil.cli", "run", "--config", str(bench_config(tmp_path)), "--trials",
               "3", "--out", str(tmp_path / "f.mcap"), "--quiet", "--inject", "emcy-over-current@2+20"]
    result = subprocess.run(command, capture_output=True, text=True, env={**os.environ, "PYTHONPATH": str(ROOT)},
                            cwd=ROOT, check=False, timeout=120)
    lines = [line for line in result.stderr.splitlines() if line.strip()]
    assert result.returncode == 1 and len(lines) == 1, lines
    assert "EMCY 0x2310" in lines[0] and f"drive {NODE} confirmed disabled" in lines[0]


@pytest.mark.parametrize("kind", ["/dev/zero", "a FIFO", "a 2 MiB file"])
def test_a_special_or_huge_eds_is_refused_through_the_cli(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], kind: str
) -> None:
    """``drive.eds`` naming /dev/zero, a FIFO or a file past the cap: exit 2, one line with the file and what it is
    (a FIFO was "EDS file not found" after a blocking read; a 50 MB EDS took 30 s and 1.7 GB)."""
    if kind == "/dev/zero":
        eds = Path("/dev/zero")
    elif kind == "a FIFO":
        eds = tmp_path / "drive.eds"
        os.mkfifo(eds)
    else:
        eds = tmp_path / "big.eds"
        with eds.open("wb") as stream:
            stream.truncate(2 << 20)
    config = bench_config(tmp_path)
    document = yaml.safe_load(config.read_text(encoding="utf-8"))
    document["drive"]["eds"] = str(eds)
    config.write_text(yaml.safe_dump(document), encoding="utf-8")
    assert main(["run", "--config", str(config), "--trials", "1", "--out", str(tmp_path / "x.mcap")]) == 2
    line = _one_line(capsys, "run")
    assert f"{eds}: is " in line and ("not a regular file" in line or "an EDS is at most" in line), line
