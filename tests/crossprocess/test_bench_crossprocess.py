"""The bench and the emulator in two processes, over ``udp_multicast``, in real time at 1 kHz with the shipped settings.

Both processes run inside ONE private network namespace the test creates (``unshare --net``), with multicast
routed over its own loopback, so no frame ever leaves it; the host namespace never opens ``udp_multicast``.
The run uses ``configs/realtime_1khz.yaml`` as shipped (timing, host setup), with shorter trials and watchdogs
that ride out a second's stall of a loaded host. The test checks that the run completes and that what it reports
is consistent (never wall-clock performance, which ``benchmarks/realtime.py`` measures): the timing statistics in
the ``--json`` document, one ``/timing`` record per cycle in the log, and the counts of both agreeing.
"""

from __future__ import annotations

import json
import math
import shlex
import subprocess
import sys
from pathlib import Path

import pytest
import yaml
from mcap.reader import make_reader

from tests.support.netns import NETNS_SETUP, unshare_available

pytestmark = [pytest.mark.netns, pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[2]
SHIPPED = ROOT / "configs" / "realtime_1khz.yaml"
GROUP = "239.74.163.2"
SAMPLE_TIME = 0.001
TIME_SCALE = 0.05  # eq. (52) in 0.3 s: 300 samples at 1 kHz
SAMPLES = 300
TRIALS = 2


def _config(tmp_path: Path) -> Path:
    document = yaml.safe_load(SHIPPED.read_text(encoding="utf-8"))
    assert document["sample_time"] == SAMPLE_TIME and document["bench"]["mode"] == "realtime"
    document["reference"]["time_scale"] = TIME_SCALE  # shorter trials; every realtime setting stays as shipped
    document["trials"] = TRIALS
    # A loaded 2-core host (a test suite beside it) stalled a process for 21 ms: the shipped policy's 20 SYNCs
    # without any answer aborted the run. The policy is under test elsewhere (test_fault_policy,
    # test_realtime_loop); here a run across processes must complete and report consistently, so the watchdogs
    # get a second of stall.
    document["bench"]["faults"]["lost_feedback"] = 1000
    document["emulator"]["sync_loss_cycles"] = 1000.0
    path = tmp_path / "xproc.yaml"
    path.write_text(yaml.safe_dump(document), encoding="utf-8")
    return path


def test_realtime_run_across_processes_over_udp_multicast(tmp_path: Path) -> None:
    reason = unshare_available()
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
        # P-type: its design is the cheapest (no LMI); the law does not matter to the timing under test
        f"--trials {TRIALS} --law p-type --out {shlex.quote(str(out))} --json --quiet"
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
    assert [t["trial"] for t in document["trials"]] == list(range(1, TRIALS + 1))
    assert document["drive_stop"]["confirmed"] is True
    for key in ("missed_deadlines", "skipped_deadlines", "missing_feedback", "late_feedback"):
        assert isinstance(timing[key], int) and timing[key] >= 0, key
    assert timing["missed_deadlines"] <= timing["cycles"]  # a cycle misses its deadline at most once
    for key in ("jitter_p50_us", "jitter_p99_us", "jitter_max_us"):
        assert isinstance(timing[key], float) and math.isfinite(timing[key]) and timing[key] >= 0.0, key
    assert timing["jitter_p50_us"] <= timing["jitter_p99_us"] <= timing["jitter_max_us"]
    host = timing["realtime"]  # what the host setup applied, or why not
    assert host["gc"] == "frozen" and host["memory_locked"] in (True, False)
    assert host["scheduler"] == "SCHED_FIFO 50" or any("sched_fifo_priority" in line for line in host["not_applied"])
    # one /timing record per cycle, and the log's counts agree with the JSON document's
    records = []
    with out.open("rb") as stream:
        for _schema, _channel, message in make_reader(stream).iter_messages(topics=["/timing"]):
            records.append(json.loads(message.data))
    assert len(records) == timing["cycles"]
    assert [r["cycle"] for r in records] == list(range(timing["cycles"]))
    assert sum(1 for r in records if r["missed"]) == timing["missed_deadlines"]
    lost = sum(1 for r in records if r["lost_feedback"])
    assert lost == timing["missing_feedback"] == document["faults"]["lost_feedback"]
    assert max(r["lateness_us"] for r in records) == pytest.approx(timing["jitter_max_us"])
