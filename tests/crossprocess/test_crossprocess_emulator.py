"""``plant-emulator`` in its own process on ``udp_multicast``, driven by the product's master in another process.

Both processes run inside ONE private network namespace the test creates (``unshare --net``), with multicast
routed on its loopback: nothing is ever sent in the host namespace.
"""

from __future__ import annotations

import json
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

from tests.support.netns import namespaces_allowed

pytestmark = [pytest.mark.netns, pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[2]
GROUP = "239.74.163.2"
NODE_ID = 4
TARGET_RPM = 300.0


@pytest.mark.timeout(180)
def test_master_drives_emulator_process_over_udp_multicast(tmp_path: Path) -> None:
    reason = namespaces_allowed()
    if reason is not None:
        pytest.skip(reason)
    config = tmp_path / "bench.yaml"
    config.write_text(
        "plant: {model: pmsm}\nsample_time: 0.01\ndrive: {node_id: 4, velocity_scale: 1000.0}\n"
        "emulator: {timing: lockstep}\nlaw: {kind: foilc}\n",  # 'law' belongs to the bench: ignored here
        encoding="utf-8",
    )
    log = tmp_path / "emulator.log"
    python = shlex.quote(sys.executable)
    script = " ".join(
        [
            "ip link set lo up && ip link set lo multicast on && ip route add 224.0.0.0/4 dev lo || exit 97;",
            f"{python} -m plant_emulator --config {shlex.quote(str(config))} --bus udp_multicast:{GROUP}",
            f"--node-id {NODE_ID} --mode lockstep 2> {shlex.quote(str(log))} & EMU=$!;",
            f"for i in $(seq 100); do grep -q ready {shlex.quote(str(log))} && break; sleep 0.1; done;",
            f"{python} tests/support/crossprocess_driver_script.py {GROUP} {NODE_ID}; RC=$?;",
            "kill -TERM $EMU; wait $EMU; echo emulator-exit=$? >&2; exit $RC",
        ]
    )
    done = subprocess.run(
        ["unshare", "--net", "--", "sh", "-c", script],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=150,
    )
    emulator_log = log.read_text(encoding="utf-8") if log.exists() else ""
    assert done.returncode == 0, f"driver failed: {done.stderr[-2000:]}\nemulator: {emulator_log[-2000:]}"
    assert "ready" in emulator_log and "emulator-exit=0" in done.stderr
    result = json.loads(done.stdout.strip().splitlines()[-1])
    assert result["vendor_id"] == 0x464F494C  # identity read over SDO across processes
    assert result["enabled_state"] == "OPERATION_ENABLED"
    velocities = result["velocities"]
    assert velocities[0] == pytest.approx(0.0, abs=1.0)  # one-cycle delay: the first answer is still at rest
    assert velocities[-1] == pytest.approx(TARGET_RPM, rel=0.03)  # the axis followed the CSV target
    assert result["after_quick_stop"] in ("QUICK_STOP_ACTIVE", "SWITCH_ON_DISABLED")
    assert result["after_disable"] == "SWITCH_ON_DISABLED"
