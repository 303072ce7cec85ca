"""The bench's fault policy (``bench.faults``) and NMT supervision, against the real emulator on a ``virtual`` bus.

The emulator is hurt through its own objects, outside the bench: its TPDO sender skips the TPDO sets of chosen
SYNCs (a lost feedback), or its CAN link sends chosen TPDO1 frames one byte short (a bad frame). Every run is in
lockstep, where a SYNC's feedback only counts as lost when the wait's bound (``watchdog_cycles`` x 0.1 s)
expires, so no test depends on how fast the machine is.
"""

from __future__ import annotations

import json
import threading
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest

from drivers.bus import open_bus
from drivers.cia301 import FunctionCode, NmtCommand, cob_id
from drivers.cia402 import State402
from drivers.drive import DISABLED_STATES
from foilc_hil.cli import main
from foilc_hil.config import load_config
from foilc_hil.errors import DriveNmtStateError
from foilc_hil.loop.rig import RunRequest, run_rig
from tests.support.bench import NODE, assert_completed_trials_intact, bench_config, read_log, when_mid_trial

TPDO1 = cob_id(FunctionCode.TPDO1, NODE)


class Countdown:
    """How many more times a fault hook acts; armed from the watcher thread, spent on the emulator's thread."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._left = 0
        self.acted = 0

    def arm(self, times: int) -> None:
        with self._lock:
            self._left = times

    def take(self) -> bool:
        with self._lock:
            if self._left <= 0:
                return False
            self._left -= 1
            self.acted += 1
            return True


@pytest.fixture
def emulator_factory(tmp_path: Path) -> Iterator[Callable[..., tuple[Any, Path]]]:
    """Start the real emulator on its own virtual channel with ``bench:`` settings; stopped at teardown."""
    from plant_emulator.embedded import EmbeddedEmulator

    started: list[Any] = []

    def start(**bench: Any) -> tuple[Any, Path]:
        config_path = bench_config(tmp_path, watchdog_cycles=3, **bench)
        emulator = EmbeddedEmulator.from_config(load_config(config_path))
        emulator.__enter__()
        started.append(emulator)
        return emulator, config_path

    yield start
    for emulator in started:
        emulator.__exit__(None, None, None)


def drop_tpdo_sets(emulator: Any) -> Countdown:
    """The emulator skips sending its TPDO set at the next SYNCs while the countdown lasts."""
    countdown = Countdown()
    send = emulator.drive.pdos.send_synchronous

    def maybe_send() -> None:
        if not countdown.take():
            send()

    emulator.drive.pdos.send_synchronous = maybe_send
    return countdown


def shorten_tpdo1(emulator: Any, every: int = 2) -> Countdown:
    """While the countdown lasts, every ``every``-th TPDO1 goes out one byte short (wrong DLC); at most one in a
    row with ``every >= 2``, so the incomplete sets never make consecutive lost feedbacks."""
    countdown = Countdown()
    node = emulator.drive.node  # the drive sends its PDOs with EmulatedNode.transmit
    send = node.transmit
    seen = [0]

    def maybe_short(can_id: int, data: bytes) -> None:
        if can_id == TPDO1:
            seen[0] += 1
            if seen[0] % every == 0 and countdown.take():
                data = bytes(data)[:-1]
        send(can_id, data)

    node.transmit = maybe_short
    return countdown


def run(config_path: Path, channel: str, out: Path, trials: int, capsys: pytest.CaptureFixture[str]) -> tuple[
    int, dict[str, Any] | None, list[str]
]:
    """``foilc-hil run --json`` against ``channel``: exit code, the JSON document (if any) and stderr's lines."""
    code = main(["run", "--config", str(config_path), "--bus", f"inprocess:{channel}", "--trials", str(trials),
                 "--out", str(out), "--quiet", "--json"])
    captured = capsys.readouterr()
    document = json.loads(captured.out) if captured.out.strip() else None
    return code, document, captured.err.strip().splitlines()


@pytest.mark.slow
def test_one_lost_feedback_is_counted_held_and_replays(
    emulator_factory: Callable[..., tuple[Any, Path]], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    emulator, config_path = emulator_factory()  # default policy: lost_feedback 3, bad_frame count
    drops = drop_tpdo_sets(emulator)
    out = tmp_path / "lost.mcap"
    watcher = when_mid_trial(emulator, 0, lambda: drops.arm(1))
    code, document, err = run(config_path, emulator.channel, out, 2, capsys)
    assert watcher.fired
    assert code == 0, err
    assert drops.acted == 1
    assert document is not None
    assert document["faults"]["lost_feedback"] == 1
    per_trial = [t["lost_feedback"] for t in document["faults"]["trials"]]
    assert sorted(per_trial) == [0, 1]  # in the first trial whose command moved the axis
    topics = read_log(out)
    assert_completed_trials_intact(topics, 2)
    assert [t["lost_feedback"] for t in topics["/ilc/trial"]] == per_trial
    assert [t["bad_frames"] for t in topics["/ilc/trial"]] == [0, 0]
    # the logged output of the lost sample is the held feedback the law saw (exactly which value: the loop-alone
    # test below), so the law replays bit for bit
    assert main(["replay", str(out), "--verify", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["verified"] is True


@pytest.mark.slow
def test_one_loss_more_than_tolerated_aborts_naming_the_count(
    emulator_factory: Callable[..., tuple[Any, Path]], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    emulator, config_path = emulator_factory(faults={"lost_feedback": 2})
    drops = drop_tpdo_sets(emulator)
    out = tmp_path / "lost3.mcap"
    watcher = when_mid_trial(emulator, 0, lambda: drops.arm(3))
    code, _, err = run(config_path, emulator.channel, out, 2, capsys)
    assert watcher.fired
    assert code == 1
    assert len(err) == 1 and err[0].startswith("foilc-hil run: "), err
    assert "3 consecutive SYNCs without feedback" in err[0] and "tolerates 2" in err[0], err[0]
    assert f"drive {NODE} confirmed disabled" in err[0], err[0]
    assert emulator.drive.state in DISABLED_STATES


@pytest.mark.slow
def test_wrong_dlc_tpdos_are_counted_by_default(
    emulator_factory: Callable[..., tuple[Any, Path]], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    emulator, config_path = emulator_factory()
    short = shorten_tpdo1(emulator)
    out = tmp_path / "short.mcap"
    watcher = when_mid_trial(emulator, 0, lambda: short.arm(20))
    code, document, err = run(config_path, emulator.channel, out, 2, capsys)
    assert watcher.fired
    assert code == 0, err
    assert short.acted == 20
    assert document is not None
    assert document["faults"]["bad_frames"] == 20
    # each short TPDO1 leaves its SYNC's set incomplete: a lost feedback. On the embedded emulator's synchronous bus
    # an honest answer is never slow, so exactly those
    assert document["faults"]["lost_feedback"] == 20
    trials = read_log(out)["/ilc/trial"]
    assert sum(t["bad_frames"] for t in trials) == 20
    assert sum(t["lost_feedback"] for t in trials) == 20


@pytest.mark.slow
def test_wrong_dlc_tpdo_aborts_with_exit_1_under_abort(
    emulator_factory: Callable[..., tuple[Any, Path]], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    emulator, config_path = emulator_factory(faults={"bad_frame": "abort"})
    short = shorten_tpdo1(emulator)
    out = tmp_path / "short-abort.mcap"
    watcher = when_mid_trial(emulator, 0, lambda: short.arm(20))
    code, document, err = run(config_path, emulator.channel, out, 2, capsys)
    assert watcher.fired
    assert code == 1  # a run-time failure of the link, never exit 2 (usage)
    assert document is not None and document["error"]["type"] == "BadFrameError"
    assert document["error"]["exit_code"] == 1
    assert len(err) == 1 and err[0].startswith("foilc-hil run: "), err
    assert "DLC 5 does not match the mapped length 6" in err[0], err[0]
    assert f"drive {NODE} confirmed disabled" in err[0], err[0]
    assert emulator.drive.state in DISABLED_STATES


@pytest.mark.slow
def test_nmt_stop_mid_trial_raises_the_typed_error_in_process(
    emulator_factory: Callable[..., tuple[Any, Path]], tmp_path: Path
) -> None:
    emulator, config_path = emulator_factory()
    # the heartbeat (10 ms) reports the NMT change before the feedback watchdog (4 SYNCs = 20 ms of lockstep time)
    config = load_config(config_path, {"bus.interface": "inprocess", "bus.channel": emulator.channel,
                                       "drive.heartbeat_producer_ms": 10})
    out = tmp_path / "nmt.mcap"

    def nmt_stop() -> None:
        with open_bus(emulator.bus_config) as bus:  # a third node on the emulator's channel
            bus.send(can.Message(arbitration_id=0, data=[int(NmtCommand.STOP), NODE], is_extended_id=False))

    watcher = when_mid_trial(emulator, 0, nmt_stop)
    with pytest.raises(DriveNmtStateError, match=rf"node {NODE} left NMT OPERATIONAL: its heartbeat reports STOPPED"):
        run_rig(RunRequest(config=config, out=out, trials=3))
    assert watcher.fired
    assert emulator.drive.state is not State402.OPERATION_ENABLED
    assert emulator.drive.state in DISABLED_STATES


# --- the loop alone (no CAN): exactly what the law is given for a lost feedback --------------------------------


class _LossyDrive:
    """Answers each SYNC with the SYNC's number as velocity, except the SYNCs in ``lost`` (no answer in time)."""

    bad_frames = 0  # no bus: nothing to decode

    def __init__(self, lost: set[int]) -> None:
        self.lost = lost
        self.count = 0
        self.quick_stops = 0

    def sync(self) -> int:
        self.count += 1
        return self.count

    def wait_feedback(self, timeout: float) -> Any:
        from drivers.drive import Feedback
        from foilc_hil.errors import FeedbackTimeoutError

        if self.count in self.lost:
            raise FeedbackTimeoutError(f"no TPDO set answered SYNC {self.count}")
        return Feedback(self.count, 0x27, State402.OPERATION_ENABLED, float(self.count), 0.0, 0, 0.0)

    def set_target(self, value: float) -> float:
        return value

    def quick_stop(self) -> None:
        self.quick_stops += 1


class _RecordingLaw:
    """Records the output it is given at each sample; commands zero."""

    def __init__(self) -> None:
        self.given: list[float] = []
        self.feedforward = np.zeros(4)

    def begin_trial(self) -> None:
        self.given.clear()

    def command(self, t: int, output: np.ndarray) -> np.ndarray:
        self.given.append(float(output[0]))
        return np.zeros(1)

    def end_trial(self, reference: np.ndarray, output: np.ndarray, applied: np.ndarray | None = None) -> Any:
        from foilc_hil.laws.learning import TrialUpdate
        from foilc_hil.metrics import TrialMetrics

        error = reference - output
        metrics = TrialMetrics(trial=1, sse=float(error @ error), rmse=0.0, max_abs_error=0.0, rmse_learnable=0.0,
                               max_abs_error_learnable=0.0)
        return TrialUpdate(trial=1, error=error, E=error, metrics=metrics)

    def restore(self, feedforward: np.ndarray) -> None:
        self.feedforward = feedforward


def _lossy_loop(lost: set[int], max_lost: int) -> tuple[Any, _LossyDrive, _RecordingLaw]:
    from foilc_hil.loop.bench import TrialLoop
    from foilc_hil.loop.settings import LoopSettings

    drive = _LossyDrive(lost)
    law = _RecordingLaw()
    settings = LoopSettings(sample_time=0.01, settle_between_trials=False, max_lost_feedback=max_lost)
    return TrialLoop(drive, law, np.zeros(4), None, settings), drive, law


def test_the_law_is_given_the_last_good_feedback_for_a_lost_one() -> None:
    loop, drive, law = _lossy_loop({3}, max_lost=1)
    outcome = loop.run(1)
    assert law.given == [1.0, 2.0, 2.0, 4.0]  # SYNC 3 went unanswered: sample 2 holds SYNC 2's feedback
    assert outcome.faults.lost_feedback == 1
    assert [faults.lost_feedback for faults in outcome.trial_faults] == [1]
    assert outcome.timing is not None and outcome.timing.missing_feedback == 1
    assert drive.quick_stops == 0


def test_losses_in_a_row_beyond_the_limit_abort_after_quick_stop() -> None:
    from foilc_hil.errors import FeedbackTimeoutError

    loop, drive, law = _lossy_loop({2, 3}, max_lost=1)
    with pytest.raises(FeedbackTimeoutError, match=r"2 consecutive SYNCs without feedback.*tolerates 1"):
        loop.run(1)
    assert law.given == [1.0, 1.0]  # SYNC 2 lost and held; SYNC 3, the second in a row, aborts
    assert drive.quick_stops == 1


def test_timing_records_carry_the_lost_feedback_flag() -> None:
    from foilc_hil.io.records import TimingBlock
    from foilc_hil.loop.log_sink import McapSink
    from foilc_hil.loop.scheduler import CycleBlock

    class Writer:
        def __init__(self) -> None:
            self.flags: list[bool] = []

        def write_timing_block(self, block: TimingBlock) -> None:
            self.flags.extend(record.lost_feedback for record in block.records())

        def add_metadata(self, name: str, data: Any) -> None:  # the sink names its /ilc/sample layout
            pass

    writer = Writer()
    # columns of TimingRecorder.FIELDS: sync time, deadline, lateness, feedback latency, compute, skipped, late,
    # missing, missed
    rows = np.array([[0.01 * cycle, np.nan, 0.0, np.nan if lost else 50e-6, 1e-6, 0, 0, float(lost), 0]
                     for cycle, lost in enumerate([False, True, False])])
    McapSink(writer, None).timing(CycleBlock(rows, 0, "trial", 1))  # type: ignore[arg-type]
    assert writer.flags == [False, True, False]
