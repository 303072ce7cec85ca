"""Run by ``tests/crossprocess/test_latched_crossprocess.py`` INSIDE a private network namespace: a realtime bench run
across processes with missed deadlines induced two ways, watched by an independent receiver process.

Processes, all over ``udp_multicast`` on the namespace's own loopback:

- the **receiver** (the instrument, :mod:`benchmarks.frame_recorder`, nothing of the product imported): every frame
  with its kernel timestamp, on a socket with a 16 MiB receive buffer, and how many datagrams its socket dropped;
- ``plant-emulator`` and ``foilc-hil run`` (the config handed in: realtime, with ``stall@...`` injected);
- the **stopper**: counts the SYNCs on the bus and, right after the SYNCs numbered in ``STOPS``, stops the whole
  bench process with SIGSTOP for :data:`STOP_SECONDS`, then SIGCONT.

Usage: ``python tests/support/latched_crossprocess_script.py GROUP CONFIG OUT_DIR``; writes ``frames.json`` (the
recorder's document: its frames and its socket's drops), ``bench.json`` (``run --json``) and ``stops.json`` (each
stop's SYNC count and the wall-clock times of its SIGSTOP and SIGCONT, the clock of the receiver's timestamps), and
exits with the bench's code. Never run it in the host namespace.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from benchmarks import frame_recorder

ROOT = Path(__file__).resolve().parents[2]
#: SYNC counts (from the bench's first) after which the stopper stops the bench: with 200-cycle settles and
#: 300-sample trials, some fall in trials, some between them
STOPS = (350, 450, 1300, 1400, 1500)
STOP_SECONDS = 0.03

_STOPPER = """
import json, os, signal, sys, time, can
bench, stops, seconds = int(sys.argv[2]), [int(s) for s in sys.argv[3].split(",")], float(sys.argv[4])
bus = can.Bus(interface="udp_multicast", channel=sys.argv[1])
syncs, done = 0, []
print("listening", flush=True)
while stops:
    m = bus.recv(1.0)
    if m is None:
        try:
            os.kill(bench, 0)
        except OSError:
            break
        continue
    if m.arbitration_id != 0x80:
        continue
    syncs += 1
    if syncs == stops[0]:
        stopped = time.time()
        os.kill(bench, signal.SIGSTOP)
        time.sleep(seconds)
        resumed = time.time()
        os.kill(bench, signal.SIGCONT)
        done.append((syncs, stopped, resumed))
        stops.pop(0)
bus.shutdown()
with open(sys.argv[5], "w") as out:
    json.dump(done, out)
"""


def _started(process: subprocess.Popen[str], what: str) -> None:
    """Wait for the process's ``listening`` line."""
    assert process.stdout is not None
    line = process.stdout.readline()
    if "listening" not in line:
        raise RuntimeError(f"{what} did not start: {line!r}")


def main(group: str, config: str, out_dir: Path) -> int:
    python = sys.executable
    bus = f"udp_multicast:{group}"
    receiver = frame_recorder.start(group, out_dir / "frames.json")
    emulator_log = (out_dir / "emulator.stderr").open("w")
    emulator = subprocess.Popen([python, "-m", "plant_emulator", "--config", config, "--bus", bus, "--mode",
                                 "realtime"], stderr=emulator_log, cwd=ROOT)
    for _ in range(300):
        if "ready" in (out_dir / "emulator.stderr").read_text():
            break
        time.sleep(0.1)
    with (out_dir / "bench.json").open("w") as bench_out, (out_dir / "bench.stderr").open("w") as bench_err:
        bench = subprocess.Popen([python, "-m", "foilc_hil.cli", "run", "--config", config, "--bus", bus, "--mode",
                                  "realtime", "--law", "p-type", "--out", str(out_dir / "run.mcap"), "--json",
                                  "--quiet"], stdout=bench_out, stderr=bench_err, cwd=ROOT)
        stopper = subprocess.Popen([python, "-c", _STOPPER, group, str(bench.pid), ",".join(map(str, STOPS)),
                                    str(STOP_SECONDS), str(out_dir / "stops.json")], stdout=subprocess.PIPE,
                                   text=True)
        _started(stopper, "the stopper")
        code = bench.wait(timeout=600)
    stopper.wait(timeout=30)
    emulator.send_signal(signal.SIGINT)
    emulator.wait(timeout=30)
    emulator_log.close()
    frame_recorder.stop(receiver, out_dir / "frames.json")
    return code


if __name__ == "__main__":
    if os.environ.get("FOILC_NETNS") != "1":  # a guard: multicast only inside the namespace the test made
        raise SystemExit("run by tests/crossprocess/test_latched_crossprocess.py inside a private network namespace "
                         "only")
    raise SystemExit(main(sys.argv[1], sys.argv[2], Path(sys.argv[3])))
