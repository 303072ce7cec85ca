"""The log writer process can never hold the axis, and a failed write stops the run at the next trial boundary.

Each case runs ``foilc-hil run`` as a process on the embedded emulator (lockstep) and does to its log writer what an
unlucky bench does: stops it (``SIGSTOP``: a hung NFS or USB disk), kills it, interrupts the run while it is stopped,
fills the disk under it. Each must end with the drive confirmed disabled, exit 1 (130 for the signal), one stderr
line naming the log, a ``--json`` document listing exactly the trials the file holds, and a file that still reads.
Before the fix a stopped writer held a moving axis as long as the stall lasted (the loop blocked in a pipe write,
signals ignored), and a full disk was found 13 trials late.
"""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from foilc_hil.io.mcap_log import McapLogReader
from tests.support.bench import NODE, bench_config, completed_trials_on_disk

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[2]
#: a generous bound for anything a test waits for: a loaded 2-core machine is slow, never wrong
PATIENCE = 120.0


@dataclass
class Finished:
    returncode: int
    stderr: list[str]
    document: dict[str, object]


def _command(config: Path, out: Path, trials: int) -> list[str]:
    return [sys.executable, "-m", "foilc_hil.cli", "run", "--config", str(config), "--trials", str(trials),
            "--out", str(out), "--json"]


def _start(command: list[str]) -> subprocess.Popen[str]:
    env = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.Popen(command, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env, cwd=ROOT)


def _finish(process: subprocess.Popen[str]) -> Finished:
    stdout, stderr = process.communicate(timeout=PATIENCE)
    return Finished(process.returncode, [line for line in stderr.splitlines() if line.strip()], json.loads(stdout))


def _writer_of(process: subprocess.Popen[str]) -> int:
    """The pid of the run's log writer process (a child of the run), once it exists."""
    deadline = time.monotonic() + PATIENCE
    while time.monotonic() < deadline and process.poll() is None:
        for task in Path(f"/proc/{process.pid}/task").iterdir():
            for child in (task / "children").read_text().split():
                if b"foilc_hil.io.log_child" in Path(f"/proc/{child}/cmdline").read_bytes():
                    return int(child)
        time.sleep(0.02)
    raise AssertionError(f"no log writer process appeared (run exited {process.poll()})")


def _when_trials_on_disk(process: subprocess.Popen[str], out: Path, trials: int) -> None:
    deadline = time.monotonic() + PATIENCE
    while time.monotonic() < deadline and process.poll() is None:
        if completed_trials_on_disk(out) >= trials:
            return
        time.sleep(0.02)
    raise AssertionError(f"the run exited ({process.poll()}) or never logged {trials} trials")


@pytest.fixture
def running(tmp_path: Path) -> Iterator[tuple[subprocess.Popen[str], Path]]:
    """A long run on the embedded emulator, two trials on disk; killed with its writer if a test fails."""
    with long_run(tmp_path) as run:
        yield run


@contextlib.contextmanager
def long_run(tmp_path: Path) -> Iterator[tuple[subprocess.Popen[str], Path]]:
    """A long run on the embedded emulator, two trials on disk; killed with its writer on the way out."""
    out = tmp_path / "run.mcap"
    process = _start(_command(bench_config(tmp_path), out, trials=100_000))
    writers: list[int] = []
    try:
        writers.append(_writer_of(process))
        _when_trials_on_disk(process, out, 2)
        yield process, out
    finally:
        for pid in (process.pid, *writers):
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        process.communicate()


def _logged_trials(out: Path) -> list[int]:
    with McapLogReader(out) as reader:
        return [int(trial) for trial in reader.read().completed_trials]


def _assert_confirmed_stop(result: Finished) -> None:
    assert f"drive {NODE} confirmed disabled" in result.stderr[-1], result.stderr
    stop = result.document["drive_stop"]
    assert isinstance(stop, dict) and stop["confirmed"] is True and stop["state"] == "SWITCH_ON_DISABLED"


def test_a_stopped_writer_stops_the_run_and_the_drive(running: tuple[subprocess.Popen[str], Path]) -> None:
    process, out = running
    writer = _writer_of(process)
    os.kill(writer, signal.SIGSTOP)
    try:
        result = _finish(process)  # before the fix: blocked in a pipe write for as long as the writer was stopped
    finally:
        os.kill(writer, signal.SIGCONT)
    assert result.returncode == 1, result.stderr
    assert len(result.stderr) == 1 and result.stderr[0].startswith("foilc-hil run: "), result.stderr
    assert f"{out}: the log writer process (pid {writer}) stalled" in result.stderr[0]
    _assert_confirmed_stop(result)
    listed = [trial["trial"] for trial in result.document["trials"]]  # type: ignore[attr-defined]
    # resumed, the writer finishes the file (summary and footer) with what it had: every trial the report listed
    _wait_gone(writer)
    assert listed and set(listed) <= set(_logged_trials(out))
    assert listed == list(range(1, len(listed) + 1))


def _wait_gone(pid: int) -> None:
    deadline = time.monotonic() + PATIENCE
    while time.monotonic() < deadline:
        try:
            os.kill(pid, 0)
        except ProcessLookupError:
            return
        if Path(f"/proc/{pid}/stat").read_text().split(")")[-1].split()[0] == "Z":
            return  # a zombie: it has exited, its parent (the ended run) no longer reaps it
        time.sleep(0.02)
    raise AssertionError(f"process {pid} did not end")


def test_a_killed_writer_stops_the_run_and_the_drive(running: tuple[subprocess.Popen[str], Path]) -> None:
    process, out = running
    os.kill(_writer_of(process), signal.SIGKILL)
    result = _finish(process)
    assert result.returncode == 1, result.stderr
    assert len(result.stderr) == 1 and f"{out}: the log writer process" in result.stderr[0], result.stderr
    _assert_confirmed_stop(result)
    listed = [trial["trial"] for trial in result.document["trials"]]  # type: ignore[attr-defined]
    assert listed == _logged_trials(out)  # no footer: the damage-tolerant reader reads the chunks on disk


def test_sigint_while_the_writer_is_stopped_is_honoured(running: tuple[subprocess.Popen[str], Path]) -> None:
    process, _out = running
    writer = _writer_of(process)
    os.kill(writer, signal.SIGSTOP)
    try:
        process.send_signal(signal.SIGINT)
        result = _finish(process)  # before the fix: SIGINT ignored until the writer was continued
    finally:
        os.kill(writer, signal.SIGCONT)
    assert result.returncode in (130, 1), result.stderr  # the signal, or the stall found first
    _assert_confirmed_stop(result)


def _can_mount_tmpfs() -> str | None:
    if shutil.which("unshare") is None or os.geteuid() != 0:
        return "needs root and unshare(1) for a private tmpfs (a real full disk)"
    probe = subprocess.run(["unshare", "--mount", "--", "sh", "-c", "mount -t tmpfs -o size=64k tmpfs /mnt"],
                           capture_output=True, check=False)
    return None if probe.returncode == 0 else f"cannot mount a tmpfs here: {probe.stderr.decode().strip()}"


def test_a_full_disk_stops_the_run_at_the_next_trial_boundary(tmp_path: Path) -> None:
    reason = _can_mount_tmpfs()
    if reason is not None:
        pytest.skip(reason)
    disk = tmp_path / "disk"
    disk.mkdir()
    out = disk / "run.mcap"
    config = bench_config(tmp_path)
    run = " ".join(_command(config, out, trials=400))
    # a 384 KiB disk: full after a few of this config's trials; the file is copied out before the mount goes
    script = f"mount -t tmpfs -o size=384k tmpfs {disk} && {run}; status=$?; cp {out} {tmp_path}; exit $status"
    process = _start(["unshare", "--mount", "--", "sh", "-c", script])
    result = _finish(process)
    assert result.returncode == 1, result.stderr
    assert len(result.stderr) == 1, result.stderr
    assert f"{out}: No space left on device" in result.stderr[0]
    _assert_confirmed_stop(result)
    listed = [trial["trial"] for trial in result.document["trials"]]  # type: ignore[attr-defined]
    on_disk = _logged_trials(tmp_path / "run.mcap")
    assert listed == on_disk and len(listed) >= 1
    # found at the next trial boundary at the latest: the run went on for at most two trials past the last one
    # written (the trial whose write failed, and the one at whose end the failure was read)
    assert isinstance(result.document["trials_run"], int)
    assert len(listed) <= result.document["trials_run"] <= len(listed) + 2
