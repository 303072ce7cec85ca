"""``foilc-hil run`` over four axes against four separate emulator processes, over ``udp_multicast`` inside ONE
private network namespace the test creates (``unshare --net``; nothing is sent in the host namespace).

Each emulator process gets its axis's own config (:func:`foilc_hil.config.axis_configs` of
configs/scara_4axis.yaml, written out with :func:`foilc_hil.config.dump_config`: its plant, node id and scales);
the bench runs the shipped four-axis config in lockstep, one SYNC per cycle for all four over the wall-clock bus.
"""

from __future__ import annotations

import json
import shlex
import subprocess
import sys
from pathlib import Path

import pytest
import yaml

from foilc_hil.config import axis_configs, dump_config, load_config
from tests.support.netns import NETNS_SETUP, namespaces_allowed

pytestmark = [pytest.mark.netns, pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[2]
SCARA = ROOT / "configs" / "scara_4axis.yaml"
GROUP = "239.74.163.6"
TRIALS = 2


@pytest.mark.timeout(420)
def test_four_axes_against_four_emulator_processes_in_a_private_netns(tmp_path: Path) -> None:
    reason = namespaces_allowed()
    if reason is not None:
        pytest.skip(reason)
    # The shipped config with the heartbeats loosened for a loaded test machine (at load 8 node 4's heartbeat came
    # 0.398 s apart against the shipped 0.3 s): what is tested here is four axes learning across processes
    document = yaml.safe_load(SCARA.read_text(encoding="utf-8"))
    document["drive"].update(heartbeat_timeout_factor=20.0, heartbeat_consumer_ms=3000)
    scara = tmp_path / "scara_4axis.yaml"
    scara.write_text(yaml.safe_dump(document), encoding="utf-8")
    axes = axis_configs(load_config(scara))
    python = shlex.quote(sys.executable)
    bus = f"udp_multicast:{GROUP}"
    starts, logs = [], []
    for axis in axes:
        node = axis.drive.node_id
        config = tmp_path / f"axis{node}.yaml"
        config.write_text(dump_config(axis), encoding="utf-8")
        log = tmp_path / f"emulator{node}.log"
        logs.append(log)
        starts.append(f"{python} -m plant_emulator --config {shlex.quote(str(config))} --bus {bus} --mode lockstep "
                      f"2> {shlex.quote(str(log))} & E{node}=$!")
    out = tmp_path / "xproc.mcap"
    ready = " && ".join(f"grep -q ready {shlex.quote(str(log))}" for log in logs)
    pids = " ".join(f"$E{axis.drive.node_id}" for axis in axes)
    script = "; ".join([
        NETNS_SETUP,
        *starts,
        f"for i in $(seq 600); do {ready} && break; sleep 0.1; done",
        f"{python} -m foilc_hil.cli run --config {shlex.quote(str(scara))} --bus {bus} --mode lockstep "
        f"--trials {TRIALS} --out {shlex.quote(str(out))} --json --quiet; RC=$?",
        f"kill -INT {pids}; wait {pids}",
        "exit $RC",
    ])
    done = subprocess.run(["unshare", "--net", "--", "sh", "-c", script], cwd=ROOT, capture_output=True, text=True,
                          timeout=400, env={"PYTHONPATH": str(ROOT), "PATH": "/usr/sbin:/usr/bin:/sbin:/bin"})
    emulators = "\n".join(log.read_text(encoding="utf-8") for log in logs if log.exists())
    assert done.returncode == 0, f"bench: {done.stderr[-3000:]}\nemulators: {emulators[-3000:]}"
    document = json.loads(done.stdout)
    assert document["bus"] == bus
    assert [axis["node_id"] for axis in document["axes"]] == [1, 2, 3, 4]
    for axis in document["axes"]:
        sse = [trial["sse"] for trial in axis["trials"]]
        assert len(sse) == TRIALS and sse[1] < sse[0], (axis["node_id"], sse)
        assert axis["drive_stop"]["confirmed"] is True and axis["drive_stop"]["state"] == "SWITCH_ON_DISABLED"
    # every emulator process served the same SYNCs (one SYNC for all axes) and ended disabled
    finals = [line for line in emulators.splitlines() if "stopped after" in line]
    assert len(finals) == 4 and all("drive SWITCH_ON_DISABLED" in line for line in finals)
    assert len({line.split("stopped after ")[1].split(" SYNC")[0] for line in finals}) == 1
