"""A fault of the SYNC producer process is a fault of the run: the drive ends stopped, confirmed by reading it back.

Inside a private network namespace this test creates (``unshare --net``, multicast on its own loopback), a realtime
bench on ``configs/realtime_1khz.yaml`` runs against a ``plant-emulator`` process over ``udp_multicast``, with SYNC
from its producer process (:mod:`drivers.sync_process`). Once the loop runs on it, the producer is SIGKILLed (found
as the bench's child by its command line, killed by its pid). The bench must stop with exit 1 naming the producer's
death, and report the drive confirmed disabled; the emulator's own last line says the same from the drive's side.
No timing is asserted: the run stops at the bench's next SYNC wait whenever that is.
"""

from __future__ import annotations

import json
import os
import shlex
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from tests.crossprocess.test_bench_crossprocess import SHIPPED
from tests.support.netns import NETNS_SETUP, unshare_available

pytestmark = [pytest.mark.netns, pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[2]
GROUP = "239.74.163.14"

_SCRIPT = """
import json, os, signal, subprocess, sys, time
from pathlib import Path
config, out, bus = sys.argv[1], Path(sys.argv[2]), "udp_multicast:" + sys.argv[3]
python = sys.executable
emulator = subprocess.Popen([python, "-m", "plant_emulator", "--config", config, "--bus", bus, "--mode", "realtime"],
                            stderr=subprocess.PIPE, text=True)
try:
    while "ready" not in emulator.stderr.readline():
        pass
    bench = subprocess.Popen([python, "-m", "foilc_hil.cli", "run", "--config", config, "--bus", bus, "--mode",
                              "realtime", "--out", str(out), "--json", "--quiet"], stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True)
    def producer():
        for task in Path(f"/proc/{bench.pid}/task").iterdir():
            for child in (task / "children").read_text().split():
                if b"drivers.sync_process" in Path(f"/proc/{child}/cmdline").read_bytes():
                    return int(child)
        return None
    killed = None
    while bench.poll() is None and killed is None:
        time.sleep(0.2)
        pid = producer()
        started = pid is not None and out.exists() and out.stat().st_size > 0
        if started:
            time.sleep(1.0)  # the loop runs on its SYNCs by now
            os.kill(pid, signal.SIGKILL)
            killed = pid
    stdout, stderr = bench.communicate(timeout=300)
finally:
    emulator.send_signal(signal.SIGINT)
    _, emulator_tail = emulator.communicate(timeout=60)
print(json.dumps({"code": bench.returncode, "killed": killed, "document": stdout, "stderr": stderr,
                  "emulator": emulator_tail}))
"""


def test_a_killed_sync_producer_stops_the_run_with_the_drive_confirmed_disabled(tmp_path: Path) -> None:
    reason = unshare_available()
    if reason is not None:
        pytest.skip(reason)
    document = yaml.safe_load(SHIPPED.read_text(encoding="utf-8"))
    document["trials"] = 50  # longer than the test: the kill ends it
    config = tmp_path / "rt.yaml"
    config.write_text(yaml.safe_dump(document), encoding="utf-8")
    command = shlex.join([sys.executable, "-c", _SCRIPT, str(config), str(tmp_path / "run.mcap"), GROUP])
    result = subprocess.run(["unshare", "--net", "--", "sh", "-c", f"{NETNS_SETUP}; {command}"], capture_output=True,
                            text=True, timeout=900, cwd=ROOT, env={**os.environ, "PYTHONPATH": str(ROOT)})
    assert result.returncode == 0, result.stderr
    report = json.loads(result.stdout.strip().splitlines()[-1])
    assert report["killed"] is not None, report["stderr"]
    assert report["code"] == 1, report["stderr"]
    error = json.loads(report["document"])["error"]
    assert "SYNC producer process" in error["message"] and "killed by signal 9" in error["message"]
    assert error["drive_stop"]["confirmed"] is True and error["drive_stop"]["state"] in ("SWITCH_ON_DISABLED", "FAULT")
    assert "drive SWITCH_ON_DISABLED" in report["emulator"] or "drive FAULT" in report["emulator"]
