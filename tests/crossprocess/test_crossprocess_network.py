"""``plant-emulator --node-id 1,2,3,4`` in one process, four masters on one :class:`~drivers.network.DriveNetwork` in
another, over ``udp_multicast`` inside ONE private network namespace the test creates (``unshare --net``): nothing
is ever sent in the host namespace.
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
GROUP = "239.74.163.5"
NODES = (1, 2, 3, 4)


@pytest.mark.timeout(240)
def test_four_emulated_nodes_in_one_process_across_processes(tmp_path: Path) -> None:
    reason = namespaces_allowed()
    if reason is not None:
        pytest.skip(reason)
    config = tmp_path / "bench.yaml"
    config.write_text("plant: {model: pmsm}\nsample_time: 0.01\ndrive: {velocity_scale: 1000.0}\n"
                      "emulator: {timing: lockstep}\n", encoding="utf-8")
    log = tmp_path / "emulator.log"
    python = shlex.quote(sys.executable)
    nodes = ",".join(str(n) for n in NODES)
    script = " ".join(
        [
            "ip link set lo up && ip link set lo multicast on && ip route add 224.0.0.0/4 dev lo || exit 97;",
            f"{python} -m plant_emulator --config {shlex.quote(str(config))} --bus udp_multicast:{GROUP}",
            f"--node-id {nodes} --mode lockstep 2> {shlex.quote(str(log))} & EMU=$!;",
            f"for i in $(seq 150); do [ $(grep -c ready {shlex.quote(str(log))}) -ge {len(NODES)} ] && break;",
            "sleep 0.1; done;",
            f"{python} tests/support/crossprocess_network_script.py {GROUP} {nodes}; RC=$?;",
            "kill -TERM $EMU; wait $EMU; echo emulator-exit=$? >&2; exit $RC",
        ]
    )
    done = subprocess.run(["unshare", "--net", "--", "sh", "-c", script], cwd=ROOT, capture_output=True, text=True,
                          timeout=220)
    emulator_log = log.read_text(encoding="utf-8") if log.exists() else ""
    assert done.returncode == 0, f"driver failed: {done.stderr[-2000:]}\nemulator: {emulator_log[-2000:]}"
    assert "emulator-exit=0" in done.stderr
    assert [f"ready: node {n} " in emulator_log for n in NODES] == [True] * len(NODES)
    result = json.loads(done.stdout.strip().splitlines()[-1])
    # each node followed its own CSV target (100 rpm x node id): the frames reached the right node both ways
    for node in NODES:
        assert result["final_velocity"][str(node)] == pytest.approx(100.0 * node, rel=0.05)
    assert result["cycles"] == {str(n): 100 for n in NODES}  # 100 SYNCs in the loop, each counted by every member
    assert result["stopped"] == {str(n): [True, "SWITCH_ON_DISABLED"] for n in NODES}
    # the emulator's last lines: every node ends disabled, and all served the same SYNCs
    finals = [line for line in emulator_log.splitlines() if "stopped after" in line]
    assert len(finals) == len(NODES) and all("drive SWITCH_ON_DISABLED" in line for line in finals)
    assert len({line.split("stopped after ")[1].split(" SYNC")[0] for line in finals}) == 1
