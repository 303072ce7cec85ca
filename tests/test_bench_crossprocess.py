"""The bench and the emulator in two processes, over ``udp_multicast``, with real-time SYNC.

Both processes run inside ONE private network namespace the test creates (``unshare --net``), with multicast
routed over its own loopback, so no frame ever leaves it; the host namespace never opens ``udp_multicast``.
The test checks what a real-time run reports (structure and consistency, never wall-clock performance): the
timing statistics in the ``--json`` document, and one ``/timing`` record per cycle in the log.
"""

from __future__ import annotations

import json
import math
import shlex
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from mcap.reader import make_reader

ROOT = Path(__file__).resolve().parents[1]
GROUP = "239.74.163.2"
SAMPLE_TIME = 0.005
SAMPLES = 100  # 0.5 s trials
TRIALS = 2
NETNS_SETUP = "ip link set lo up; ip link set lo multicast on; ip route add 224.0.0.0/4 dev lo"


def _unshare_available() -> str | None:
    """None when ``unshare --net`` works here, else why not."""
    if shutil.which("unshare") is None or shutil.which("ip") is None:
        return "unshare or ip is not installed"
    probe = subprocess.run(
        ["unshare", "--net", "--", "sh", "-c", NETNS_SETUP], capture_output=True, text=True, timeout=30
    )
    if probe.returncode != 0:
        return f"unshare --net is not permitted here: {probe.stderr.strip() or probe.returncode}"
    return None


def _config(tmp_path: Path) -> Path:
    document = {
        "plant": {"model": "first_order", "a": -1.23, "b": 1.68, "c": 1.0},
        "reference": {
            "profile": "piecewise",
            "segments": [{"duration": 0.2, "start": 0.0, "end": 20.0}, {"duration": 0.3, "start": 20.0}],
        },
        "sample_time": SAMPLE_TIME,
        "trials": TRIALS,
        "tuning": {"kp": 0.2, "r": 0.5},
        "drive": {
            "node_id": 1,
            "mode": "csv",
            "velocity_scale": 1000.0,
            "velocity_limit": 500.0,
            "heartbeat_timeout_factor": 10.0,  # the shared test machine can stall a process for a while
            "heartbeat_consumer_ms": 2000,
        },
        "bench": {"settle_time": 0.02, "settle_tolerance": 0.05, "watchdog_cycles": 20},
        # SYNC loss only after 40 periods: this shared test machine can stall a process for tens of milliseconds;
        # the test is about the plumbing, not the machine.
        "emulator": {"timing": "realtime", "sync_loss_cycles": 40},
    }
    path = tmp_path / "xproc.yaml"
    path.write_text(yaml.safe_dump(document), encoding="utf-8")
    return path


def test_realtime_run_across_processes_over_udp_multicast(tmp_path: Path) -> None:
    reason = _unshare_available()
    if reason is not None:
        pytest.skip(reason)
    config = _config(tmp_path)
    out = tmp_path / "xproc.mcap"
    emulator_log = tmp_path / "emulator.stderr"
    bus = f"udp_multicast:{GROUP}"
    python = shlex.quote(sys.executable)
    emulator_config = config
    emulator = f"{python} -m plant_emulator --config {shlex.quote(str(emulator_config))} --bus {bus} --mode realtime"
    bench = (
        f"{python} -m foilc_hil.cli run --config {shlex.quote(str(config))} --bus {bus} --mode realtime "
        f"--trials {TRIALS} --out {shlex.quote(str(out))} --json --quiet"
    )
    script = "; ".join(
        [
            NETNS_SETUP,
            f"{emulator} 2> {shlex.quote(str(emulator_log))} & EMU=$!",
            # wait for the emulator's ready line (at most 30 s) before the bench resets and commissions it
            f"for i in $(seq 300); do grep -q ready {shlex.quote(str(emulator_log))} && break; sleep 0.1; done",
            f"{bench}; RC=$?",
            "kill -INT $EMU; wait $EMU",
            "exit $RC",
        ]
    )
    result = subprocess.run(
        ["unshare", "--net", "--", "sh", "-c", script],
        capture_output=True,
        text=True,
        timeout=600,
        cwd=ROOT,
        env={"PYTHONPATH": str(ROOT), "PATH": "/usr/sbin:/usr/bin:/sbin:/bin"},
    )
    emulator_text = emulator_log.read_text(encoding="utf-8") if emulator_log.exists() else ""
    assert result.returncode == 0, f"bench: {result.stderr}\nemulator: {emulator_text}"
    assert "ready" in emulator_text
    document = json.loads(result.stdout)
    timing = document["timing"]
    assert timing["mode"] == "realtime"
    assert timing["period"] == SAMPLE_TIME
    assert timing["cycles"] >= TRIALS * (SAMPLES + 1)
    assert isinstance(timing["missed_deadlines"], int) and timing["missed_deadlines"] >= 0
    for key in ("jitter_p50_us", "jitter_p99_us", "jitter_max_us"):
        assert isinstance(timing[key], float) and math.isfinite(timing[key]) and timing[key] >= 0.0, key
    assert timing["jitter_p50_us"] <= timing["jitter_p99_us"] <= timing["jitter_max_us"]
    assert [t["trial"] for t in document["trials"]] == list(range(1, TRIALS + 1))
    # one /timing record per cycle, and the log agrees with the JSON on the missed deadlines
    records = []
    with out.open("rb") as stream:
        for _schema, _channel, message in make_reader(stream).iter_messages(topics=["/timing"]):
            records.append(json.loads(message.data))
    assert len(records) == timing["cycles"]
    assert [r["cycle"] for r in records] == list(range(timing["cycles"]))
    assert sum(1 for r in records if r["missed"]) <= timing["missed_deadlines"]
    assert max(r["lateness_us"] for r in records) == pytest.approx(timing["jitter_max_us"])
