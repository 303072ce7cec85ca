"""``foilc-hil run`` over four axes on one bus (configs/scara_4axis.yaml, the embedded emulator, one trial loop).

What is checked comes from outside the run's own summary: each axis's SSE recomputed from its logged samples, the
one-SYNC-per-cycle schedule read from the logged CAN frames (every axis's RPDO and TPDO between two SYNCs), each
axis's law re-run bit for bit by ``replay --verify``, and each drive's final state as read back from it.
"""

from __future__ import annotations

import base64
import contextlib
import io
import itertools
import json
from collections import Counter
from pathlib import Path
from typing import Any, cast

import numpy as np
import pytest
import yaml

from drivers.cia301 import SYNC_COB_ID, FunctionCode, cob_id
from foilc_hil.cli import main
from foilc_hil.io.mcap_log import read_log

pytestmark = pytest.mark.slow

ROOT = Path(__file__).resolve().parents[2]
SCARA = ROOT / "configs" / "scara_4axis.yaml"
NODES = (1, 2, 3, 4)
SAMPLES = 200  # 0.5 s at 2.5 ms
TRIALS = 3


@pytest.fixture(scope="module")
def scara_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[int, dict, Path]:
    out = tmp_path_factory.mktemp("scara") / "scara.mcap"
    stdout = io.StringIO()
    with contextlib.redirect_stdout(stdout):
        code = main(["run", "--config", str(SCARA), "--trials", str(TRIALS), "--json", "--out", str(out)])
    return code, json.loads(stdout.getvalue()), out


def test_four_axes_run_in_one_loop_and_every_axis_learns(scara_run: tuple[int, dict, Path]) -> None:
    code, document, out = scara_run
    assert code == 0
    assert [axis["node_id"] for axis in document["axes"]] == list(NODES)
    contents = read_log(out)
    for axis in document["axes"]:
        node = axis["node_id"]
        sse = [trial["sse"] for trial in axis["trials"]]
        assert len(sse) == TRIALS and sse[0] > sse[1] > sse[2], (node, sse)  # every axis learns
        assert axis["drive_stop"]["confirmed"] is True and axis["drive_stop"]["state"] == "SWITCH_ON_DISABLED"
        # the reported SSE is the sum of the squared logged errors of this axis's samples (an independent sum)
        for trial in range(1, TRIALS + 1):
            errors = np.array([s["error"] for s in contents.samples if s["axis"] == node and s["trial"] == trial])
            assert errors.shape == (SAMPLES,)
            assert float(np.sum(errors**2)) == pytest.approx(sse[trial - 1], rel=1e-12)
    # the run's figure is over all axes together: the divergence guard's SSE
    totals = [sum(axis["trials"][k]["sse"] for axis in document["axes"]) for k in range(TRIALS)]
    assert [trial["sse"] for trial in document["trials"]] == pytest.approx(totals, rel=1e-12)
    assert {trial["axis"] for trial in contents.trials} == set(NODES) and len(contents.trials) == TRIALS * len(NODES)
    assert document["bus_load"]["load"] < document["bus_load"]["limit"]


def test_every_axis_is_commanded_and_answers_within_each_sync_period(scara_run: tuple[int, dict, Path]) -> None:
    code, document, out = scara_run
    assert code == 0
    frames = read_log(out).frames
    periods: list[Counter[int]] = []
    for frame in frames:
        if frame["id"] == SYNC_COB_ID and frame["dir"] == "tx":
            periods.append(Counter())
        elif periods:
            periods[-1][frame["id"]] += 1
    pdo_ids = [cob_id(code, node) for node in NODES for code in (FunctionCode.RPDO1, FunctionCode.TPDO1)]
    # the loop's cycles: consecutive SYNC periods, each carrying every axis's RPDO and TPDO1 exactly once (one SYNC
    # serves every axis); the enable before and the safe stop after have periods of their own
    served = [k for k, period in enumerate(periods) if [period[frame_id] for frame_id in pdo_ids] == [1] * 8]
    assert max(_runs(served)) >= document["timing"]["cycles"] - 1  # one period may be shared with the enable's last


def test_export_dbc_holds_every_axis_and_decodes_each_axis_logged_output(scara_run: tuple[int, dict, Path],
                                                                          tmp_path: Path) -> None:
    cantools = pytest.importorskip("cantools")  # the oracle: an independent DBC reader
    _, _, out = scara_run
    dbc = tmp_path / "axes.dbc"
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(["export", str(out), "--format", "dbc", "--out", str(dbc), "--json"]) == 0
    db = cantools.database.load_file(str(dbc), strict=True)
    assert {node.name for node in db.nodes} == {"foilc_hil_master", *(f"drive_{node}" for node in NODES)}
    contents = read_log(out)
    for node in NODES:
        tpdo1 = cob_id(FunctionCode.TPDO1, node)
        assert db.get_message_by_frame_id(cob_id(FunctionCode.RPDO1, node)).senders == ["foilc_hil_master"]
        velocities = np.array([db.decode_message(tpdo1, base64.b64decode(frame["data"]))["velocity_actual_value"]
                               for frame in contents.frames if frame["id"] == tpdo1])
        outputs = np.array([row["output"] for row in contents.samples if row.get("axis") == node])
        assert outputs.size == TRIALS * SAMPLES and np.abs(outputs).max() > 1.0  # this axis moved
        # every logged output of this axis is one of ITS drive's decoded TPDO velocities, in plant units
        gaps = np.abs(velocities[None, :] - outputs[:, None]).min(axis=1)
        assert gaps.max() <= 1e-9 * max(1.0, float(np.abs(outputs).max()))


def test_replay_verify_and_report_handle_every_axis(scara_run: tuple[int, dict, Path], tmp_path: Path,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    code, _document, out = scara_run
    assert code == 0
    capsys.readouterr()
    assert main(["replay", str(out), "--verify", "--json"]) == 0
    replayed = json.loads(capsys.readouterr().out)
    assert replayed["verified"] is True and replayed["samples_checked"] == len(NODES) * TRIALS * SAMPLES
    assert [(axis["node_id"], axis["verified"], axis["trials_checked"]) for axis in replayed["axes"]] == [
        (node, True, TRIALS) for node in NODES]
    assert main(["report", str(out), "--out", str(tmp_path / "report"), "--json"]) == 0
    reported = json.loads(capsys.readouterr().out)
    assert [axis["node_id"] for axis in reported["axes"]] == list(NODES)
    for axis in reported["axes"]:
        assert len(axis["trials"]) == TRIALS and (tmp_path / "report" / f"axis-{axis['node_id']}" / "sse.png").is_file()


def test_replay_verify_holds_each_axis_latched_to_its_own_frames(scara_run: tuple[int, dict, Path]) -> None:
    """The wire check runs per axis: one axis's ``latched`` moved at one sample fails ``replay --verify`` on ``/can``,
    for that axis alone (each axis's view holds its own RPDO among the four nodes' frames)."""
    from foilc_hil.logtools.axes import verify_axes

    _code, _document, out = scara_run
    contents = read_log(out)
    row = [s for s in contents.samples if s["axis"] == NODES[2] and s["trial"] == 2][SAMPLES // 2]
    row["latched"] += 0.5
    total, axes = verify_axes(contents)
    assert not total.verified
    divergence = total.first_divergence
    assert divergence is not None and divergence.topic == "/can" and "latched" in divergence.reason
    assert (divergence.trial, divergence.sample) == (2, SAMPLES // 2)
    assert [(axis.node_id, axis.verification.verified) for axis in axes] == [(n, n != NODES[2]) for n in NODES]


def test_one_axis_lost_feedback_holds_that_axis_alone(scara_run: tuple[int, dict, Path], tmp_path: Path,
                                                      capsys: pytest.CaptureFixture[str]) -> None:
    """Axis 1's TPDO sets dropped for three cycles of trial 2: axis 1 is held and counts them; the other axes are
    given their own answers, so they learn exactly as in the clean run (bit for bit), and replay --verify agrees."""
    _code, clean, _out = scara_run
    out = tmp_path / "lost.mcap"
    capsys.readouterr()
    code = main(["run", "--config", str(SCARA), "--trials", "2", "--inject", "drop-tpdo@2+50:count=3", "--json",
                 "--out", str(out)])
    document = json.loads(capsys.readouterr().out)
    assert code == 0 and document["faults"]["lost_feedback"] == 3
    sse = {axis["node_id"]: [trial["sse"] for trial in axis["trials"]] for axis in document["axes"]}
    clean_sse = {axis["node_id"]: [trial["sse"] for trial in axis["trials"]] for axis in clean["axes"]}
    assert sse[1][0] == clean_sse[1][0] and sse[1][1] != clean_sse[1][1]  # axis 1's trial 2 held three values
    assert {node: sse[node] for node in NODES[1:]} == {node: clean_sse[node][:2] for node in NODES[1:]}
    lost = {(record["axis"], record["trial"]): record["lost_feedback"] for record in read_log(out).trials}
    assert lost == {(node, trial): 3 if (node, trial) == (1, 2) else 0 for node in NODES for trial in (1, 2)}
    assert main(["replay", str(out), "--verify", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["verified"] is True


@pytest.mark.parametrize(("spec", "faulted"), [("emcy-over-current@1+20", 1),  # no axis: the first axis
                                              ("emcy-over-current@1+20:axis=3", 3)])
def test_a_fault_on_one_axis_stops_all_four_confirmed_per_drive(spec: str, faulted: int, tmp_path: Path,
                                                                capsys: pytest.CaptureFixture[str]) -> None:
    out, config = tmp_path / "fault.mcap", tmp_path / "scara.yaml"
    document = yaml.safe_load(SCARA.read_text(encoding="utf-8"))
    # the injected fault is under test, not the heartbeats: the threaded emulator's 100 ms beats came 0.32 s apart
    # on a loaded host, past the default 3 x 0x1017, and that loss was reported first
    document["drive"]["heartbeat_timeout_factor"] = 30.0
    config.write_text(yaml.safe_dump(document), encoding="utf-8")
    code = main(["run", "--config", str(config), "--trials", "2", "--inject", spec, "--json", "--out", str(out)])
    document = json.loads(capsys.readouterr().out)
    assert code == 1 and "EMCY 0x2310" in document["error"]["message"]
    stops = {axis["node_id"]: axis["drive_stop"] for axis in document["axes"]}
    assert sorted(stops) == list(NODES)
    assert all(stop["confirmed"] is True and stop["commanded"] is True for stop in stops.values())
    assert stops[faulted]["state"] == "FAULT"  # the faulted axis, read back in FAULT (a disabled power stage)
    assert {stops[node]["state"] for node in NODES if node != faulted} == {"SWITCH_ON_DISABLED"}
    assert document["trials"] == []  # the fault came in the first trial


@pytest.mark.parametrize("config", [SCARA, ROOT / "configs" / "demo.yaml"])
def test_a_fault_on_a_node_that_is_not_an_axis_is_refused(config: Path, tmp_path: Path,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["run", "--config", str(config), "--trials", "1", "--inject", "drop-tpdo@1+5:axis=9", "--json",
                 "--out", str(tmp_path / "refused.mcap")])
    document = json.loads(capsys.readouterr().out)
    assert code == 2 and document["error"]["message"].startswith("inject[0].axis: node 9 is not an axis")


def test_a_precomputed_design_is_refused_for_axes(capsys: pytest.CaptureFixture[str]) -> None:
    from foilc_hil.config import load_config
    from foilc_hil.errors import InputError
    from foilc_hil.loop.rig import RunRequest, run_rig

    with pytest.raises(InputError, match=r"^design: "):
        run_rig(RunRequest(config=load_config(SCARA), out=None, trials=1, design=cast(Any, object())))


def _runs(indices: list[int]) -> list[int]:
    """Lengths of the runs of consecutive integers in ``indices`` (sorted)."""
    runs = [1]
    for before, after in itertools.pairwise(indices):
        if after == before + 1:
            runs[-1] += 1
        else:
            runs.append(1)
    return runs
