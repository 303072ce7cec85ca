"""Run inside a private network namespace by ``tests/crossprocess/test_crossprocess_stops.py``: a lockstep bench and a
``plant-emulator`` process over ``udp_multicast``; once two trials are on disk, do ``ACTION`` to the bench
(``stall``: SIGSTOP its log writer process; ``signals``: SIGINT, then SIGINT again 20 ms later), then print one JSON
line: the bench's exit code, its stderr lines and ``--json`` document, and the emulated drive's state as the
emulator reports it on stdin's end (its ``state`` line)."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
BUS = "udp_multicast:239.74.163.2"


def _children(pid: int) -> list[int]:
    found = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        found += [int(child) for child in (task / "children").read_text().split()]
    return found


def _trials_on_disk(out: Path) -> int:
    from foilc_hil.io.mcap_log import McapLogReader

    try:
        with McapLogReader(out) as reader:
            return len(reader.read().completed_trials)
    except Exception:
        return 0


def main(config: str, out_path: str, action: str) -> int:
    out = Path(out_path)
    python = sys.executable
    emulator = subprocess.Popen([python, "-m", "plant_emulator", "--config", config, "--bus", BUS, "--mode",
                                 "lockstep"], stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        return _run(emulator, out, action)
    finally:  # whatever went wrong, no emulator outlives the test
        if emulator.poll() is None:
            emulator.kill()
            emulator.communicate()


def _run(emulator: subprocess.Popen[str], out: Path, action: str) -> int:
    """The bench against the started ``emulator``: two trials on disk, ``action``, the report (see the module)."""
    python, config = sys.executable, sys.argv[1]
    deadline = time.monotonic() + 60
    while emulator.stderr is not None and "ready" not in emulator.stderr.readline():
        if time.monotonic() > deadline:
            raise SystemExit("the emulator did not start")
    bench = subprocess.Popen([python, "-m", "foilc_hil.cli", "run", "--config", config, "--bus", BUS, "--mode",
                              "lockstep", "--trials", "100000", "--law", "p-type", "--out", str(out), "--json"],
                             stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    writers: list[int] = []
    try:
        return _act(bench, emulator, out, action, writers)
    finally:  # a failure on the way leaves neither the bench nor a stopped writer behind
        for pid in writers:
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)
        if bench.poll() is None:
            bench.kill()
            bench.communicate()


def _act(bench: subprocess.Popen[str], emulator: subprocess.Popen[str], out: Path, action: str,
         writers: list[int]) -> int:
    while _trials_on_disk(out) < 2 and bench.poll() is None:
        time.sleep(0.05)
    writer = next(pid for pid in _children(bench.pid)
                  if b"foilc_hil.io.log_child" in Path(f"/proc/{pid}/cmdline").read_bytes())
    if action == "stall":
        writers.append(writer)
        os.kill(writer, signal.SIGSTOP)
    else:
        bench.send_signal(signal.SIGINT)
        time.sleep(0.02)
        bench.send_signal(signal.SIGINT)
    stdout, stderr = bench.communicate(timeout=120)
    if action == "stall":
        os.kill(writer, signal.SIGCONT)
        writers.clear()
    emulator.send_signal(signal.SIGINT)
    emulator.communicate(timeout=60)
    print(json.dumps({"code": bench.returncode, "stderr": [line for line in stderr.splitlines() if line.strip()],
                      "document": json.loads(stdout) if stdout.strip() else None}))
    return 0

if __name__ == "__main__":
    raise SystemExit(main(*sys.argv[1:4]))
