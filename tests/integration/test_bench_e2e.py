"""``foilc-hil run`` end to end over the embedded emulator (real CiA 402 master + virtual drive on a virtual bus).

Checks, each against something the bench did not compute itself:
- the MCAP file opens with the standard ``mcap`` reader and holds the interface's topics and metadata;
- the ``/can`` frames account exactly for the cycles: every SYNC is answered by both TPDOs, and the SYNCs are the
  commissioning steps + the loop's cycles (``timing.cycles``) + the shutdown steps, told apart by the controlword
  of the RPDO before each SYNC;
- each trial's SSE recomputed from its ``/ilc/sample`` rows equals ``/ilc/trial``, and every row describes one
  instant: its error is its own ``reference - output`` (``output[i] = y((i+1) Ts)`` at ``t = (i+1) Ts``);
- the learning reduces the error (the trial-1 SSE is the reference's energy, as the axis starts at rest);
- ``foilc-hil replay --verify`` re-runs the law on the logged outputs and finds every command bit-identical.
"""

from __future__ import annotations

import base64
import json
from typing import Any

import pytest
import yaml

from drivers.cia301 import SYNC_COB_ID, FunctionCode, cob_id
from drivers.cia402 import Command402, State402, decode_state
from foilc_hil.cli import main
from tests.support.bench import NODE, SAMPLE_TIME, SAMPLES, bench_config, read_mcap

pytestmark = pytest.mark.slow


def frame_ledger(frames: list[dict[str, Any]]) -> dict[str, int]:
    """Count SYNCs by phase from the frame sequence: a SYNC belongs to the phase of the RPDO1 sent before it.

    Commissioning walks the state machine with one RPDO + SYNC per controlword up to ENABLE OPERATION; the loop
    then sends SYNC, waits for the TPDOs, sends its RPDO (still ENABLE OPERATION); shutdown commands QUICK STOP and
    DISABLE VOLTAGE, each with a SYNC.
    """
    sync_id = SYNC_COB_ID
    rpdo1 = cob_id(FunctionCode.RPDO1, NODE)
    counts = {"startup_syncs": 0, "loop_syncs": 0, "shutdown_syncs": 0, "loop_rpdos": 0, "other_rpdos": 0}
    enabled_seen = False
    stopping = False
    first_enable_sync_done = False
    for frame in frames:
        if frame["dir"] != "tx":
            continue
        if frame["id"] == rpdo1:
            controlword = int.from_bytes(base64.b64decode(frame["data"])[:2], "little")
            if controlword in (Command402.QUICK_STOP, Command402.DISABLE_VOLTAGE) and enabled_seen:
                stopping = True
            if controlword == Command402.ENABLE_OPERATION and not stopping:
                if first_enable_sync_done:
                    counts["loop_rpdos"] += 1
                else:
                    counts["other_rpdos"] += 1
                enabled_seen = True
            else:
                counts["other_rpdos"] += 1
        elif frame["id"] == sync_id:
            if stopping:
                counts["shutdown_syncs"] += 1
            elif enabled_seen and first_enable_sync_done:
                counts["loop_syncs"] += 1
            else:
                counts["startup_syncs"] += 1
                if enabled_seen:
                    first_enable_sync_done = True
    return counts


@pytest.fixture(scope="module")
def bench_run(tmp_path_factory: pytest.TempPathFactory) -> dict[str, Any]:
    tmp_path = tmp_path_factory.mktemp("e2e")
    config = bench_config(tmp_path)
    out = tmp_path / "run.mcap"
    import contextlib
    import io

    stdout = io.StringIO()
    with contextlib.redirect_stdout(stdout):
        code = main(
            ["run", "--config", str(config), "--emulator", "embedded", "--trials", "4", "--out", str(out), "--json"]
        )
    document = json.loads(stdout.getvalue())
    topics, metadata = read_mcap(out)
    return {"code": code, "document": document, "topics": topics, "metadata": metadata, "out": out, "tmp": tmp_path}


def test_run_succeeds_and_reports_every_trial(bench_run: dict[str, Any]) -> None:
    assert bench_run["code"] == 0
    document = bench_run["document"]
    assert document["law"] == "foilc"
    assert [t["trial"] for t in document["trials"]] == [1, 2, 3, 4]
    assert document["stopped"] is None
    assert document["log"] == str(bench_run["out"])
    assert document["timing"]["period"] == SAMPLE_TIME
    assert document["timing"]["missed_deadlines"] == 0
    assert "certificates" in document["design"]
    assert document["bus_load"]["period"] == SAMPLE_TIME and 0 < document["bus_load"]["load"] <= 0.7


def test_log_layout_and_metadata(bench_run: dict[str, Any]) -> None:
    topics, metadata = bench_run["topics"], bench_run["metadata"]
    assert {"/can", "/ilc/sample", "/ilc/trial"} <= set(topics)
    assert "foilc_hil.config" in metadata and "foilc_hil.design" in metadata
    logged_config = yaml.safe_load(metadata["foilc_hil.config"]["yaml"])
    assert logged_config["sample_time"] == SAMPLE_TIME
    assert len(topics["/ilc/sample"]) == 4 * SAMPLES
    assert [t["trial"] for t in topics["/ilc/trial"]] == [1, 2, 3, 4]


def test_can_frames_account_exactly_for_the_cycles(bench_run: dict[str, Any]) -> None:
    frames = bench_run["topics"]["/can"]
    by_id: dict[tuple[int, str], int] = {}
    for frame in frames:
        by_id[(frame["id"], frame["dir"])] = by_id.get((frame["id"], frame["dir"]), 0) + 1
    syncs = by_id[(SYNC_COB_ID, "tx")]
    # every SYNC is answered by both TPDOs of the shipped mapping (statusword+velocity, torque+position)
    assert by_id[(cob_id(FunctionCode.TPDO1, NODE), "rx")] == syncs
    assert by_id[(cob_id(FunctionCode.TPDO2, NODE), "rx")] == syncs
    ledger = frame_ledger(frames)
    cycles = bench_run["document"]["timing"]["cycles"]
    assert ledger["loop_syncs"] == cycles
    assert ledger["loop_rpdos"] == cycles  # one command per cycle (zero while settling)
    assert ledger["startup_syncs"] + ledger["loop_syncs"] + ledger["shutdown_syncs"] == syncs
    # commissioning: at least SHUTDOWN, SWITCH ON, ENABLE OPERATION; shutdown: QUICK STOP and DISABLE VOLTAGE
    assert ledger["startup_syncs"] >= 3
    assert ledger["shutdown_syncs"] >= 2
    # trial cycles: N + 1 per trial; the rest settled the axis
    assert cycles >= 4 * (SAMPLES + 1)
    # SDO traffic is all commissioning: request and response counts match
    assert by_id[(cob_id(FunctionCode.SDO_RX, NODE), "tx")] == by_id[(cob_id(FunctionCode.SDO_TX, NODE), "rx")]


def test_drive_ends_disabled(bench_run: dict[str, Any]) -> None:
    frames = bench_run["topics"]["/can"]
    rpdo1 = cob_id(FunctionCode.RPDO1, NODE)
    tpdo1 = cob_id(FunctionCode.TPDO1, NODE)
    controlwords = [int.from_bytes(base64.b64decode(f["data"])[:2], "little") for f in frames if f["id"] == rpdo1]
    assert controlwords[-1] == Command402.DISABLE_VOLTAGE
    statuswords = [int.from_bytes(base64.b64decode(f["data"])[:2], "little") for f in frames if f["id"] == tpdo1]
    assert decode_state(statuswords[-1]) != State402.OPERATION_ENABLED


def test_trial_sse_recomputed_from_samples(bench_run: dict[str, Any]) -> None:
    samples = bench_run["topics"]["/ilc/sample"]
    trials = {t["trial"]: t for t in bench_run["topics"]["/ilc/trial"]}
    for k, record in trials.items():
        rows = sorted((s for s in samples if s["trial"] == k), key=lambda s: s["sample"])
        assert [r["sample"] for r in rows] == list(range(SAMPLES))
        sse = 0.0
        assert rows[-1]["output"] == record["final_output"]
        for i, row in enumerate(rows):
            # one instant per row (layout 2): t = (i + 1) Ts, and the error is the row's own reference - output
            assert row["t"] == pytest.approx((i + 1) * SAMPLE_TIME, rel=1e-12)
            assert row["error"] == row["reference"] - row["output"]
            sse += row["error"] ** 2
        assert sse == pytest.approx(record["sse"], rel=1e-12, abs=0.0)
        assert record["rmse"] == pytest.approx((record["sse"] / SAMPLES) ** 0.5, rel=1e-12)
        assert record["max_abs_error"] == max(abs(r["error"]) for r in rows)


def test_learning_reduces_the_error(bench_run: dict[str, Any]) -> None:
    trials = bench_run["topics"]["/ilc/trial"]
    samples = [s for s in bench_run["topics"]["/ilc/sample"] if s["trial"] == 1]
    # trial 1 runs a zero feedforward: the axis stays (nearly) at rest, so the SSE is about the reference energy
    energy = sum(s["reference"] ** 2 for s in samples)
    assert trials[0]["sse"] == pytest.approx(energy, rel=0.05)
    assert trials[-1]["sse"] < 0.5 * trials[0]["sse"]


def test_replay_verify_passes(bench_run: dict[str, Any], capsys: pytest.CaptureFixture[str]) -> None:
    capsys.readouterr()
    code = main(["replay", str(bench_run["out"]), "--verify", "--json"])
    document = json.loads(capsys.readouterr().out)
    assert code == 0, document
    assert document["verified"] is True
    assert document["samples_checked"] == 4 * SAMPLES


def test_trials_log_the_command_limits_the_law_clamps_to(bench_run: dict[str, Any]) -> None:
    """The law is built with the limiter's limits (drive.velocity_limit 500); replay --verify rebuilds it with them."""
    trials = bench_run["topics"]["/ilc/trial"]
    assert trials and all(record["command_limits"] == [-500.0, 500.0] for record in trials)
    controls = [s["control"] for s in bench_run["topics"]["/ilc/sample"]]
    assert max(abs(c) for c in controls) <= 500.0
