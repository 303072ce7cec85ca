"""The bench under faults, each mid-trial: the emulator stops answering, the drive faults, the user presses Ctrl-C.

Each must end with a safe drive (the last controlword the bench sent is QUICK STOP or DISABLE VOLTAGE, and the
drive is not OPERATION ENABLED), a log the standard ``mcap`` reader opens holding every trial completed before the
fault, and one clear line on stderr with the right exit code (1 for faults, 130 for SIGINT).

A drive that stopped responding cannot change state any more; there the evidence of a safe stop is what the bench
sent (a real drive's heartbeat consumer, 0x1016, would also trip its 0x6007 abort-connection reaction).

The emulator here is the real one (``plant_emulator``), either started by the test on its own ``virtual`` channel
(so the test can hurt it) with the CLI pointed at ``--bus virtual:<channel>``, or embedded in a CLI subprocess.
"""

from __future__ import annotations

import base64
import json
import os
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import can
import pytest
import yaml

from drivers.bus import open_bus
from drivers.cia301 import FunctionCode, NmtCommand, cob_id
from drivers.cia402 import Command402, State402, decode_state
from drivers.drive import DISABLED_STATES
from foilc_hil.cli import main
from foilc_hil.config import load_config
from tests.support.bench import (
    NODE,
    assert_completed_trials_intact,
    bench_config,
    completed_trials_on_disk,
    read_log,
    when_mid_trial,
)

ROOT = Path(__file__).resolve().parents[2]
SAFE_CONTROLWORDS = {int(Command402.QUICK_STOP), int(Command402.DISABLE_VOLTAGE)}


def last_word(frames: list[dict[str, Any]], cob: int) -> int:
    words = [int.from_bytes(base64.b64decode(f["data"])[:2], "little") for f in frames if f["id"] == cob]
    assert words, f"no frames with COB-ID 0x{cob:X} in the log"
    return words[-1]


@pytest.fixture
def emulator_on_channel(tmp_path: Path) -> Iterator[tuple[Any, str, Path]]:
    """The real emulator on a fresh virtual channel, outside the bench (so the test can stop or fault it)."""
    from plant_emulator.embedded import EmbeddedEmulator

    config_path = bench_config(tmp_path, watchdog_cycles=3)
    config = load_config(config_path)
    emulator = EmbeddedEmulator.from_config(config)
    with emulator:
        yield emulator, emulator.channel, config_path


def run_cli(config_path: Path, channel: str, out: Path, trials: int, *extra: str) -> int:
    return main(
        [
            "run",
            "--config",
            str(config_path),
            "--bus",
            f"inprocess:{channel}",
            "--trials",
            str(trials),
            "--out",
            str(out),
            "--quiet",
            *extra,
        ]
    )


@pytest.mark.slow
def test_emulator_stops_responding_mid_trial(
    emulator_on_channel: tuple[Any, str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    emulator, channel, config_path = emulator_on_channel
    out = tmp_path / "dead.mcap"
    watcher = when_mid_trial(emulator, 2, emulator.drive.stop_responding)
    code = run_cli(config_path, channel, out, trials=20)
    assert watcher.fired
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 1
    assert len(err) == 1 and err[0].startswith("foilc-hil run: ")
    assert "feedback" in err[0] or "heartbeat" in err[0]
    assert f"drive {NODE} NOT confirmed disabled" in err[0]  # a silent drive cannot be read back: say so
    topics = read_log(out)
    trials = assert_completed_trials_intact(topics, 2)
    assert len(trials) == 2  # the fault hit trial 3, which is not in the log
    assert last_word(topics["/can"], cob_id(FunctionCode.RPDO1, NODE)) in SAFE_CONTROLWORDS


@pytest.mark.slow
def test_drive_fault_mid_trial(
    emulator_on_channel: tuple[Any, str, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    emulator, channel, config_path = emulator_on_channel
    out = tmp_path / "fault.mcap"
    watcher = when_mid_trial(emulator, 2, lambda: emulator.drive.inject_fault("over-current"))
    code = run_cli(config_path, channel, out, 20, "--json")
    assert watcher.fired
    captured = capsys.readouterr()
    err = captured.err.strip().splitlines()
    assert code == 1
    # --json: one document on stdout, the error and what the run had done (the partial result)
    document = json.loads(captured.out)
    assert document["error"]["exit_code"] == 1 and document["error"]["kind"] == "runtime_failure"
    assert [trial["trial"] for trial in document["trials"]] == [1, 2]
    assert document["log"] == str(out) and document["drive_stop"]["confirmed"] is True
    assert document["stopped"] == document["error"]["message"].split("; ")[0]
    assert len(err) == 1 and err[0].startswith("foilc-hil run: ")
    assert "EMCY" in err[0] or "fault" in err[0]
    assert f"drive {NODE} confirmed disabled" in err[0]
    topics = read_log(out)
    trials = assert_completed_trials_intact(topics, 2)
    assert len(trials) == 2  # the fault hit trial 3, which is not in the log
    assert last_word(topics["/can"], cob_id(FunctionCode.RPDO1, NODE)) in SAFE_CONTROLWORDS
    assert emulator.drive.state != State402.OPERATION_ENABLED
    assert decode_state(last_word(topics["/can"], cob_id(FunctionCode.TPDO1, NODE))) != State402.OPERATION_ENABLED


@pytest.mark.slow
def test_sigint_mid_trial_in_a_subprocess(tmp_path: Path) -> None:
    config_path = bench_config(tmp_path)
    out = tmp_path / "interrupted.mcap"
    command = [
        sys.executable,
        "-m",
        "foilc_hil.cli",
        "run",
        "--config",
        str(config_path),
        "--emulator",
        "embedded",
        "--trials",
        "200",
        "--out",
        str(out),
        "--quiet",
    ]
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    process = subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=ROOT)
    try:
        # wait until at least two trials are on disk (the writer flushes a chunk at every trial end)
        deadline = time.monotonic() + 120.0
        completed = 0
        while time.monotonic() < deadline and process.poll() is None:
            completed = completed_trials_on_disk(out)
            if completed >= 2:
                break
            time.sleep(0.05)
        assert process.poll() is None, process.communicate()
        assert completed >= 2
        process.send_signal(signal.SIGINT)
        _stdout, stderr = process.communicate(timeout=60)
    finally:
        if process.poll() is None:
            process.kill()
            process.communicate()
    assert process.returncode == 130, stderr
    lines = [line for line in stderr.strip().splitlines() if line]
    assert len(lines) == 1 and lines[0].startswith("foilc-hil run: ") and "SIGINT" in lines[0]
    topics = read_log(out)
    trials = assert_completed_trials_intact(topics, 2)
    assert len(trials) < 200
    rpdo1 = cob_id(FunctionCode.RPDO1, NODE)
    assert last_word(topics["/can"], rpdo1) in SAFE_CONTROLWORDS
    assert decode_state(last_word(topics["/can"], cob_id(FunctionCode.TPDO1, NODE))) != State402.OPERATION_ENABLED


@pytest.mark.slow
@pytest.mark.parametrize("command", [NmtCommand.STOP, NmtCommand.ENTER_PRE_OPERATIONAL])
@pytest.mark.parametrize("abort_option", [0, 3])
def test_third_party_nmt_mid_trial_ends_confirmed_disabled(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], command: NmtCommand, abort_option: int
) -> None:
    """Another node takes the drive out of OPERATIONAL mid-trial. Whether or not the drive reacts itself (0x6007),
    the run exits 1 naming the node and the NMT state its heartbeat reported (DriveNmtStateError), and the drive
    ends disabled, read back from the drive, not assumed."""
    from plant_emulator.embedded import EmbeddedEmulator

    config_path = bench_config(tmp_path, watchdog_cycles=3)
    document = yaml.safe_load(config_path.read_text(encoding="utf-8"))
    document["drive"]["abort_connection_option"] = abort_option
    # lockstep time is the SYNC count, as on a real bus: the heartbeat must report the NMT change before the feedback
    # watchdog trips (lost_feedback 3 + 1 SYNCs = 20 ms), so it beats every 10 ms here (the default is 100 ms)
    document["drive"]["heartbeat_producer_ms"] = 10
    config_path.write_text(yaml.safe_dump(document), encoding="utf-8")
    config = load_config(config_path)
    emulator = EmbeddedEmulator.from_config(config)
    out = tmp_path / "nmt.mcap"
    with emulator:
        def third_party_nmt() -> None:
            with open_bus(emulator.bus_config) as bus:  # a third node on the emulator's channel
                bus.send(can.Message(arbitration_id=0, data=[int(command), NODE], is_extended_id=False))

        watcher = when_mid_trial(emulator, 1, third_party_nmt)
        code = run_cli(config_path, emulator.channel, out, trials=20)
        assert watcher.fired
        state_after = emulator.drive.state
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 1
    assert len(err) == 1 and err[0].startswith("foilc-hil run: "), err
    # noticed from the drive's heartbeat, not when the feedback watchdog trips: the error of the run (NMT STOP),
    # or, when the drive's own EMCY (0x8100, sent in PRE-OPERATIONAL) ended the run first, a note on it
    reported = "STOPPED" if command is NmtCommand.STOP else "PRE_OPERATIONAL"
    assert f"node {NODE} left NMT OPERATIONAL: its heartbeat reports {reported}" in err[0], err[0]
    if command is NmtCommand.STOP:  # a stopped node sends no EMCY: the heartbeat is the only news
        assert err[0].startswith(f"foilc-hil run: node {NODE} left NMT OPERATIONAL"), err[0]
    assert "watchdog" not in err[0], err[0]
    assert f"drive {NODE} confirmed disabled" in err[0], err[0]
    assert state_after in DISABLED_STATES
    assert_completed_trials_intact(read_log(out), 1)
