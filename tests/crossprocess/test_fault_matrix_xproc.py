"""The fault matrix's process faults: ``foilc-hil run`` and ``plant-emulator`` in two processes over ``udp_multicast``.

The rows run in turn inside one private network namespace (``unshare --net``, multicast routed over its own
loopback, as in ``tests/crossprocess/test_bench_crossprocess.py``), so no frame leaves it. Inside, :func:`orchestrate`
(this module, run as a script) starts a fresh ``plant-emulator`` process per row, waits for its ready line, runs the
bench (``foilc_hil.cli.main`` in the orchestrating process, in lockstep for many trials) and, for the signal rows, hurts
the emulator's process once the log holds a completed trial. It prints one JSON document: per row, the bench's exit
code, its ``--json`` document and stderr, and the emulator's stderr, whose last line names the drive's final CiA 402
state (read from the drive itself).

The rows are part of the matrix whose table is in ``docs/reliability.md`` (see
``tests/integration/test_fault_matrix.py``).
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import shlex
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
import yaml

from drivers.cia402 import State402
from drivers.faults import InjectKind, parse_injection
from tests.integration.test_fault_matrix import STOPPED_STATES, Outcome, Stop, bench_document, check_log
from tests.support.bench import completed_trials_on_disk
from tests.support.netns import NETNS_SETUP, unshare_available

pytestmark = [pytest.mark.netns, pytest.mark.slow]

ROOT = Path(__file__).resolve().parents[2]
GROUP = "239.74.163.9"
XPROC_TRIALS = 2000  # the run is ended by the fault long before; lockstep trials over UDP take ~0.1 s
NMT_AT_SYNC = 300  # a few trials in: commissioning, settles and 60-sample trials


@dataclass(frozen=True)
class XRow:
    """One process fault: how it is made, what must happen, the docs' words."""

    fault: str
    how: str  # the docs' words for the injection
    outcome: Outcome
    names: str
    stop: Stop
    after: str
    signal_name: str = ""  # SIGKILL / SIGSTOP sent to the emulator's process
    emulator_inject: str = ""  # plant-emulator --inject spec
    where: str = "across processes, private netns"

    @property
    def inject(self) -> str:
        return self.emulator_inject

    @property
    def kind(self) -> InjectKind | None:
        return parse_injection(self.emulator_inject).kind if self.emulator_inject else None

    def outcome_text(self) -> str:
        return f"exit 1, one line naming it (`{self.names}`)"

    def kept_text(self) -> str:
        return "every trial before the fault intact; the one it hit not logged"


XPROC_MATRIX: tuple[XRow, ...] = (
    XRow("NMT stop from a third party, across processes", f"`plant-emulator --inject nmt-stop@c{NMT_AT_SYNC}`",
         Outcome.ABORTS, "left NMT OPERATIONAL", Stop.CONFIRMED, "disabled, read back by the run and by the drive",
         emulator_inject=f"nmt-stop@c{NMT_AT_SYNC}"),
    XRow("the emulator's process killed (SIGKILL)", "`kill -KILL` the `plant-emulator` process mid-run",
         Outcome.ABORTS, "consecutive SYNCs without feedback", Stop.NOT_CONFIRMED,
         "gone: nothing to read, and the run says so", signal_name="SIGKILL"),
    XRow("the emulator's process stopped (SIGSTOP), continued after the run",
         "`kill -STOP` the `plant-emulator` process mid-run, `kill -CONT` after the bench exited",
         Outcome.ABORTS, "consecutive SYNCs without feedback", Stop.NOT_CONFIRMED,
         "the run cannot read it (said so); once continued the drive disables itself (its heartbeat consumer, "
         "the bench's queued NMT), read from its last line", signal_name="SIGSTOP"),
)


def _wait(predicate: Any, limit: float) -> bool:
    deadline = time.monotonic() + limit
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(0.05)
    return False


def _share_one_design() -> None:
    """Every row has the same plant: make the design once in this process (it is not what is tested)."""
    from foilc_hil.design import pipeline

    design = pipeline.build_design
    cache: dict[tuple[str, int, int], Any] = {}

    def shared(config: Any, law: str, n_samples: int, *, input_delay: int) -> Any:
        if (law, n_samples, input_delay) not in cache:
            cache[(law, n_samples, input_delay)] = design(config, law, n_samples, input_delay=input_delay)
        return cache[(law, n_samples, input_delay)]

    pipeline.build_design = shared


def _hurt_when_a_trial_is_logged(emulator: subprocess.Popen[bytes], out: Path, signal_name: str) -> threading.Thread:
    def hurt() -> None:
        _wait(lambda: completed_trials_on_disk(out) >= 1, 120.0)
        os.kill(emulator.pid, signal.Signals[signal_name])

    thread = threading.Thread(target=hurt, daemon=True)
    thread.start()
    return thread


def _start_emulator(workdir: Path, row: XRow) -> subprocess.Popen[bytes]:
    command = [sys.executable, "-m", "plant_emulator", "--config", str(workdir / "xproc.yaml"), "--bus",
               f"udp_multicast:{GROUP}", "--mode", "lockstep"]
    if row.emulator_inject:
        command += ["--inject", row.emulator_inject]
    with (workdir / "emulator.err").open("w") as err:
        return subprocess.Popen(command, stderr=err, cwd=ROOT)


def orchestrate_row(workdir: Path, row: XRow, emulator: subprocess.Popen[bytes]) -> dict[str, Any]:
    """Inside the netns: the bench (``foilc_hil.cli.main`` in this process) against ``emulator``, and the fault."""
    from foilc_hil.cli import main

    config, out, emulator_err = workdir / "xproc.yaml", workdir / "run.mcap", workdir / "emulator.err"
    try:
        if not _wait(lambda: "ready" in emulator_err.read_text(), 60.0):
            return {"error": "the emulator never said ready", "emulator": emulator_err.read_text()}
        hurt = _hurt_when_a_trial_is_logged(emulator, out, row.signal_name) if row.signal_name else None
        stdout, stderr = io.StringIO(), io.StringIO()
        with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
            code = main(["run", "--config", str(config), "--bus", f"udp_multicast:{GROUP}", "--out", str(out),
                         "--json", "--quiet"])
        if hurt is not None:
            hurt.join(timeout=10)
        if row.signal_name == "SIGSTOP":
            os.kill(emulator.pid, signal.SIGCONT)
            time.sleep(1.2)  # its heartbeat consumer (1 s) and the frames queued while it was stopped
    finally:
        if emulator.poll() is None:
            emulator.send_signal(signal.SIGINT)
            emulator.wait(timeout=30)
    return {"bench_rc": code, "bench": stdout.getvalue(), "bench_err": stderr.getvalue(),
            "emulator_rc": emulator.returncode, "emulator": emulator_err.read_text()}


def orchestrate(workdir: Path) -> dict[str, Any]:
    """Every row in turn, each against its own emulator process; what both ends said, by fault.

    The emulators all start at once, on one bus, row ``i``'s drive with node id ``i + 1``: while a row runs, the
    drives of the rows still to come idle in PRE-OPERATIONAL (they send heartbeats, foreign to the bench, and
    ignore its SYNCs), so the rows wait for no process start but the first. The NMT row goes first: its drive counts
    the SYNCs it receives, and no other bench has sent one yet.
    """
    emulators = []
    for index, row in enumerate(XPROC_MATRIX):
        row_dir = workdir / f"row{index}"
        row_dir.mkdir()
        document = bench_document({}, {"node_id": index + 1}, trials=XPROC_TRIALS)
        document["emulator"] = {"timing": "lockstep"}
        (row_dir / "xproc.yaml").write_text(yaml.safe_dump(document), encoding="utf-8")
        emulators.append((row, row_dir, _start_emulator(row_dir, row)))
    _share_one_design()
    results = {}
    for index, (row, row_dir, emulator) in enumerate(emulators):
        started = time.monotonic()
        result = orchestrate_row(row_dir, row, emulator)
        results[row.fault] = {**result, "workdir": str(row_dir), "node": index + 1,
                              "seconds": round(time.monotonic() - started, 2)}
    return results


@pytest.fixture(scope="module")
def xproc_results(tmp_path_factory: pytest.TempPathFactory) -> dict[str, dict[str, Any]]:
    """Every row, in turn, in one private netns, run once for the module."""
    reason = unshare_available()
    if reason is not None:
        pytest.skip(reason)
    workdir = tmp_path_factory.mktemp("xproc")
    module = "tests.crossprocess.test_fault_matrix_xproc"
    script = f"{NETNS_SETUP}; exec {shlex.quote(sys.executable)} -m {module} {shlex.quote(str(workdir))}"
    environment = {"PYTHONPATH": str(ROOT), "PATH": "/usr/sbin:/usr/bin:/sbin:/bin"}
    result = subprocess.run(["unshare", "--net", "--", "sh", "-c", script], capture_output=True, text=True,
                            timeout=600, cwd=ROOT, env=environment)
    assert result.returncode == 0, result.stderr
    results: dict[str, dict[str, Any]] = json.loads(result.stdout)
    return results


def _final_state(emulator_err: str) -> State402 | None:
    """The drive's final state from the emulator's last line (``...; drive STATE, NMT STATE``)."""
    for line in reversed(emulator_err.strip().splitlines()):
        if "; drive " in line:
            return State402[line.split("; drive ", 1)[1].split(",", 1)[0]]
    return None


@pytest.mark.parametrize("row", XPROC_MATRIX, ids=[row.signal_name or row.emulator_inject for row in XPROC_MATRIX])
def test_process_fault_row(row: XRow, xproc_results: dict[str, dict[str, Any]]) -> None:
    result = xproc_results[row.fault]
    assert "error" not in result, result
    assert result["bench_rc"] == 1, result
    lines = result["bench_err"].strip().splitlines()
    assert lines and lines[-1].startswith("foilc-hil run: ") and row.names in lines[-1], result["bench_err"]
    error = json.loads(result["bench"])["error"]
    assert row.names in error["message"]
    stop = error["drive_stop"]
    assert stop["confirmed"] is (row.stop is Stop.CONFIRMED)
    node = result["node"]
    said = f"drive {node} confirmed disabled" if row.stop is Stop.CONFIRMED else f"drive {node} NOT confirmed"
    assert said in lines[-1]
    final = _final_state(result["emulator"])
    if row.signal_name == "SIGKILL":
        assert result["emulator_rc"] == -signal.SIGKILL and final is None  # gone: it can tell nothing
    else:
        assert final in STOPPED_STATES, result["emulator"]
    if row.emulator_inject:
        assert f"injected {row.emulator_inject}: started at SYNC" in result["emulator"]
    check_log(Path(result["workdir"]) / "run.mcap", None, XPROC_TRIALS - 1)


if __name__ == "__main__":
    print(json.dumps(orchestrate(Path(sys.argv[1]))))
