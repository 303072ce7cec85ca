"""The MCAP log written by a child process: the same file as the in-process writer, complete whatever happens to
the bench's process, errors raised on the bench's side, and the child never left behind."""

from __future__ import annotations

import marshal
import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import can
import numpy as np
import pytest

from foilc_hil.errors import LogFormatError
from foilc_hil.io import log_process
from foilc_hil.io.log_process import ProcessLogWriter
from foilc_hil.io.mcap_log import LogWriteError, McapLogWriter, read_log
from foilc_hil.io.records import SampleRecord, TimingRecord, TrialSamples

PATIENCE = 60.0  # s: a bound for waits on other threads (a loaded machine is slow, never wrong)

DESIGN = {"gain": np.array([[0.5, -1.25]]), "rho": np.float64(0.75), "name": "foilc"}


def _log_run(writer: McapLogWriter | ProcessLogWriter) -> None:
    """Two trials of everything a run logs, with numpy values, odd frames and fixed log times where the API
    takes none (so both writers' files can be compared document for document)."""
    frames = [
        can.Message(arbitration_id=0x80, data=b"", is_extended_id=False, timestamp=1000.0),
        can.Message(arbitration_id=0x201, data=bytes([1, 2, 3, 4, 5, 6]), is_extended_id=False),  # no timestamp
        can.Message(arbitration_id=0x1ABCDEF, data=bytes(8), is_extended_id=True, timestamp=1e-5),
        can.Message(arbitration_id=0x181, is_remote_frame=True, dlc=2, is_extended_id=False, channel="vcan0"),
    ]
    writer.add_metadata("foilc_hil.layout", {"ilc_sample": "2"})
    for trial in (1, 2):
        for i in range(300):
            writer.on_message_received(frames[i % 4])
            writer.write_sample(SampleRecord(trial, (i + 1) * 1e-3, 1.0, np.float64(i / 7), [0.25, i / 3],
                                             float("nan") if i == 5 else i / 11, None if i % 2 else 0.5, i))
            writer.write_timing(TimingRecord(i, trial, i, np.float64(i * 0.1), 1000.0, None, bool(i % 3), i == 4))
        writer.log_trial({"trial": trial, "sse": 1.5, "rmse": np.float64(0.25), "max_abs_error": 2.0},
                         final_output=0.125, command_limits=np.array([-1.0, 1.0]))
        writer.end_trial()


def _contents(path: Path) -> dict[str, object]:
    contents = read_log(path)
    # a frame without a bus timestamp gets its log time (now): the one field the two files cannot share
    frames = [{k: v for k, v in frame.items() if k != "timestamp" or v < 1e6} for frame in contents.frames]
    return {"frames": frames, "samples": contents.samples, "timing": contents.timing, "trials": contents.trials,
            "metadata": contents.metadata, "truncated": contents.truncated}


@pytest.mark.slow
def test_the_child_writes_what_the_in_process_writer_writes(tmp_path: Path) -> None:
    direct, child = tmp_path / "direct.mcap", tmp_path / "child.mcap"
    with McapLogWriter(direct, config_yaml="trials: 2\n", design=DESIGN, fsync=False) as writer:
        _log_run(writer)
    with ProcessLogWriter(child, config_yaml="trials: 2\n", design=DESIGN, fsync=False) as process_writer:
        _log_run(process_writer)
    expected = _contents(direct)
    assert _contents(child) == expected
    assert expected["truncated"] is False and len(expected["samples"]) == 600  # type: ignore[arg-type]
    assert read_log(child).design == {"gain": [[0.5, -1.25]], "rho": 0.75, "name": "foilc"}
    assert read_log(child).samples[5]["error"] is None  # NaN is null, as in the in-process file


def test_a_trial_sent_as_columns_is_written_as_its_rows(tmp_path: Path) -> None:
    rng = np.random.default_rng(3)
    grid = rng.standard_normal((250, 2))  # a run of two axes: each axis's columns are strided views
    error = grid[:, 0] - grid[:, 1]
    error[7] = np.nan
    trials = [
        TrialSamples(1, 0.001, grid[:, 0], grid[:, 1], rng.standard_normal(250), error, error * 0.5),
        TrialSamples(2, 0.001, grid[:, 1], grid[:, 0], np.arange(250), error, error, axis=3,  # ints: floats
                     latched=np.arange(250) - 1.0),  # what the drive latched: a column of its own
    ]
    direct, child = tmp_path / "direct.mcap", tmp_path / "child.mcap"
    with McapLogWriter(direct, config_yaml=None, fsync=False) as writer:
        for record in (record for samples in trials for record in samples.records()):
            writer.write_sample(record)
    with ProcessLogWriter(child, config_yaml=None, fsync=False) as process_writer:
        for samples in trials:
            process_writer.write_trial_samples(samples)
            assert process_writer.pending() == trials.index(samples) + 1  # one item a trial, not one a row
    rows = read_log(child).samples
    assert rows == read_log(direct).samples
    assert len(rows) == 500 and rows[7]["error"] is None and rows[250]["axis"] == 3 and "axis" not in rows[0]
    assert [row["t"] for row in rows[:3]] == [0.001, 2 * 0.001, 3 * 0.001]
    assert rows[251]["control"] == 1.0 and type(rows[251]["control"]) is float
    assert rows[251]["latched"] == 0.0 and "latched" not in rows[0]
    assert rows[1]["reference"] == float(grid[1, 0]) and rows[1]["output"] == float(grid[1, 1])


def test_sync_waits_for_the_child_and_end_trial_makes_the_trial_durable(tmp_path: Path) -> None:
    path = tmp_path / "sync.mcap"
    with ProcessLogWriter(path, config_yaml=None, fsync=True) as writer:
        writer.log_sample(1, 0.001, 1.0, 0.5, 0.25, 0.5, sample=0)
        writer.log_trial({"trial": 1, "sse": 1.0, "rmse": 1.0, "max_abs_error": 1.0})
        writer.end_trial(wait=True)
        assert writer.pending() == 0
        # the trial's chunk is in the file before the log is closed: a reader of the open file sees it
        assert read_log(path).completed_trials == [1]


def _process_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    with open(f"/proc/{pid}/stat") as stat:  # a zombie is gone for our purpose (its parent has not reaped it)
        return stat.read().split(")")[-1].split()[0] != "Z"


@pytest.mark.slow
def test_a_killed_bench_leaves_a_complete_file_and_no_writer_process(tmp_path: Path) -> None:
    path = tmp_path / "killed.mcap"
    script = textwrap.dedent(
        f"""
        import os, signal
        from foilc_hil.io.log_process import ProcessLogWriter
        log = ProcessLogWriter({str(path)!r}, config_yaml="x: 1\\n")
        print(log._process.pid, flush=True)
        for trial in (1, 2, 3):
            for i in range(200):
                log.log_sample(trial, i * 0.01, 1.0, 0.5, 0.25, 0.5)
            if trial < 3:
                log.log_trial({{"trial": trial, "sse": 1.0, "rmse": 1.0, "max_abs_error": 1.0}})
                log.end_trial()
        os.kill(os.getpid(), signal.SIGKILL)  # die mid-trial 3: no close
        """
    )
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])}
    result = subprocess.run([sys.executable, "-c", script], timeout=120, capture_output=True, text=True, env=env)
    assert result.returncode == -signal.SIGKILL, result.stderr
    child = int(result.stdout.split()[0])
    deadline = time.monotonic() + 60  # a liveness bound, not a speed assertion
    while _process_alive(child) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not _process_alive(child)
    contents = read_log(path)
    assert not contents.truncated  # the child saw the pipe end, wrote what it had, the summary and the footer
    assert contents.completed_trials == [1, 2]
    trials = [s["trial"] for s in contents.samples]
    assert trials[:400] == [1] * 200 + [2] * 200
    # of the trial in progress, what was sent (whole batches) is kept; the batch being filled died with the bench
    assert trials[400:] == [3] * len(trials[400:]) and 200 - log_process.BATCH < len(trials[400:]) <= 200
    assert contents.config_yaml == "x: 1\n"


@pytest.mark.slow
def test_a_full_disk_is_raised_on_the_bench_side() -> None:
    # the header does not fit: said at once, by the constructor (which waits for the child's first write)
    with pytest.raises(LogWriteError, match="No space left on device"):
        ProcessLogWriter("/dev/full", config_yaml="x: 1\n", fsync=False)


def test_a_dead_writer_process_is_raised_at_the_next_end_trial(tmp_path: Path) -> None:
    writer = ProcessLogWriter(tmp_path / "dead.mcap", config_yaml=None, fsync=False)
    writer._process.kill()
    writer._process.wait()
    for i in range(3 * log_process.BATCH):
        writer.log_frame(can.Message(arbitration_id=0x181, data=bytes([i & 0xFF]), is_extended_id=False), "rx")
    with pytest.raises(LogWriteError, match="log writer process"):
        writer.end_trial()
    writer.close()


def test_bad_output_and_compression_fail_at_once(tmp_path: Path) -> None:
    with pytest.raises(LogFormatError, match=r"dir\.mcap: cannot create"):
        ProcessLogWriter(tmp_path / "no" / "such" / "dir.mcap", config_yaml=None)
    with pytest.raises(LogFormatError, match="compression must be one of"):
        ProcessLogWriter(tmp_path / "x.mcap", compression="brotli", config_yaml=None)  # type: ignore[arg-type]


def test_a_writer_process_that_cannot_start_is_said_at_once(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(log_process.sys, "executable", "/bin/false")  # exits at once, reads nothing
    with pytest.raises(LogWriteError, match=r"the log writer process (stopped|did not start)"):
        ProcessLogWriter(tmp_path / "never.mcap", config_yaml=None)


def test_opened_without_waiting_a_writer_says_at_started_whether_its_child_runs(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``wait=False`` (``run``: the child imports while the drive is commissioned): the constructor returns with the
    header not yet written, :meth:`started` waits for it; a child that cannot start is said there, and the writer is
    closed."""
    path = tmp_path / "later.mcap"
    with ProcessLogWriter(path, config_yaml="x: 1\n", fsync=False, wait=False) as writer:
        assert path.stat().st_size == 0  # nothing written by this process: the child writes the header
        writer.log_trial({"trial": 1, "sse": 1.0, "rmse": 1.0, "max_abs_error": 1.0})  # queued meanwhile
        writer.started()
        assert path.stat().st_size > 0
        writer.started()  # at once, the second time
    assert read_log(path).completed_trials == [1]
    monkeypatch.setattr(log_process.sys, "executable", "/bin/false")
    broken = ProcessLogWriter(tmp_path / "never.mcap", config_yaml=None, wait=False)
    with pytest.raises(LogWriteError, match=r"the log writer process (stopped|did not start)"):
        broken.started()
    assert broken.closed


def test_a_missing_trial_field_is_refused_at_the_call(tmp_path: Path) -> None:
    with ProcessLogWriter(tmp_path / "t.mcap", config_yaml=None, fsync=False) as writer:
        with pytest.raises(LogFormatError, match="lacks rmse, max_abs_error"):
            writer.log_trial({"trial": 1, "sse": 1.0})
        writer.log_trial({"trial": 1, "sse": 1.0, "rmse": 1.0, "max_abs_error": 1.0})
    assert read_log(tmp_path / "t.mcap").completed_trials == [1]


def test_the_backlog_stays_bounded_while_a_send_is_in_progress(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A producer that finds another thread sending leaves its items queued, but never more than MAX_BACKLOG."""
    monkeypatch.setattr(log_process, "MAX_BACKLOG", 3 * log_process.BATCH)
    with ProcessLogWriter(tmp_path / "b.mcap", config_yaml=None, fsync=False) as writer:
        deepest = 0
        held, release = threading.Event(), threading.Event()

        def hold() -> None:  # another thread in the middle of a send: this one must not send
            with writer._send_lock:
                held.set()
                release.wait()

        holder = threading.Thread(target=hold)
        holder.start()
        held.wait()
        try:
            for i in range(3 * log_process.BATCH):
                writer.log_sample(1, i * 0.01, 1.0, 0.5, 0.25, 0.5, sample=i)
                deepest = max(deepest, writer.pending())
        finally:
            release.set()
            holder.join()
        assert deepest == 3 * log_process.BATCH
        for i in range(3 * log_process.BATCH, 8 * log_process.BATCH):
            writer.log_sample(1, i * 0.01, 1.0, 0.5, 0.25, 0.5, sample=i)
            deepest = max(deepest, writer.pending())
        assert writer.pending() < log_process.BATCH
    samples = read_log(tmp_path / "b.mcap").samples
    assert [row["sample"] for row in samples] == list(range(8 * log_process.BATCH))


def test_received_frames_wait_for_the_loops_own_calls(tmp_path: Path) -> None:
    """Frames logged on the receiving thread never send a batch themselves (below the bound); the loop's next call
    does, and nothing is lost or reordered."""
    path = tmp_path / "rx.mcap"
    with ProcessLogWriter(path, config_yaml=None, fsync=False) as writer:
        for i in range(2 * log_process.BATCH):
            writer.on_message_received(can.Message(arbitration_id=0x181, data=bytes([i & 0xFF]), timestamp=1.0 + i,
                                                   is_extended_id=False))
        assert writer.pending() == 2 * log_process.BATCH
        writer.log_frame(can.Message(arbitration_id=0x80, data=b"", is_extended_id=False, timestamp=5000.0), "tx")
        assert writer.pending() == 0
    frames = read_log(path).frames
    assert [frame["timestamp"] for frame in frames] == [1.0 + i for i in range(2 * log_process.BATCH)] + [5000.0]
    assert [frame["dir"] for frame in frames] == ["rx"] * (2 * log_process.BATCH) + ["tx"]


@pytest.mark.slow
def test_the_writer_process_imports_no_python_can() -> None:
    """The child's start is what a run waits for before its drive is enabled: its module (and what it imports) must
    not pull in python-can (0.18 s of the 0.45 s it took)."""
    probe = ("import sys, foilc_hil.io.log_child; "
             "print(sorted(m for m in sys.modules if m == 'can' or m.startswith('can.')))")
    result = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120, check=True)
    assert result.stdout.strip() == "[]", result.stdout


def test_unframed_yields_whole_payloads_and_keeps_the_rest_for_the_next_call() -> None:
    """Both pipes' framing: a payload cut short stays in the buffer; a consumer that stops early loses nothing."""
    from foilc_hil.io.log_child import framed, unframed

    whole = framed(marshal.dumps((1, "a"))) + framed(marshal.dumps([2.5, None])) + framed(marshal.dumps("third"))
    buffer = bytearray(whole[:-3])  # the third payload not yet whole
    values = unframed(buffer)
    assert next(values) == (1, "a")  # stop after the first
    assert list(unframed(buffer)) == [[2.5, None]]
    buffer += whole[-3:]
    assert list(unframed(buffer)) == ["third"] and buffer == bytearray()


def _channel_units(path: Path) -> dict[str, str]:
    from mcap.reader import make_reader

    with path.open("rb") as stream:
        summary = make_reader(stream).get_summary()
    assert summary is not None
    return {channel.topic: channel.metadata["units"] for channel in summary.channels.values()}


@pytest.mark.slow
def test_the_child_labels_the_channels_with_the_units_the_loop_worked_out(tmp_path: Path) -> None:
    """The channels' units come from the config's ``drive:`` section; the loop's process works them out and the child
    writes them as the in-process writer does (the child never loads the config's models: half its start-up)."""
    config_yaml = "drive:\n  mode: cst\n  velocity_unit: rad/s\n  torque_unit: N m\n"
    direct, child = tmp_path / "direct.mcap", tmp_path / "child.mcap"
    with McapLogWriter(direct, config_yaml=config_yaml, fsync=False) as writer:
        _log_run(writer)
    with ProcessLogWriter(child, config_yaml=config_yaml, fsync=False) as process_writer:
        _log_run(process_writer)
    units = _channel_units(child)
    assert units == _channel_units(direct)
    assert '"control": "N m"' in units["/ilc/sample"] and '"output": "rad/s"' in units["/ilc/sample"]
    # the child's side, as the writer process runs it: an OPEN with the units given, then the end of the pipe
    probe = textwrap.dedent(f"""
        import marshal, os, sys
        from foilc_hil.io.log_child import WireOp, framed, serve
        from foilc_hil.io.schemas import TOPICS
        data_r, data_w = os.pipe()
        reply_r, reply_w = os.pipe()
        fd = os.open({str(tmp_path / "probe.mcap")!r}, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, 0o666)
        units = {{topic: {{"units": "{{}}"}} for topic in TOPICS}}
        opened = (int(WireOp.OPEN), "probe.mcap", "zstd", {config_yaml!r}, None, 1 << 20, False, units)
        os.write(data_w, framed(marshal.dumps([opened])))
        os.close(data_w)
        serve(data_r, reply_w, fd)
        print(sorted(m for m in sys.modules if m.split(".")[0] in ("pydantic", "can", "canopen")))
    """)
    result = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120, check=True)
    assert result.stdout.strip() == "[]", result.stdout
    assert read_log(tmp_path / "probe.mcap").truncated is False


@pytest.mark.slow
def test_a_stopped_child_never_blocks_the_producer_and_is_reported(tmp_path: Path) -> None:
    """A writer process stopped (a hung disk) mid-run: every logging call still returns, the stall is handed to
    ``on_failure`` once as a LogWriteError naming the file, and the child, once continued, finishes the file."""
    out = tmp_path / "stalled.mcap"
    failures: list[LogWriteError] = []
    writer = ProcessLogWriter(out, config_yaml=None, fsync=False, stall_timeout=0.2)
    writer.on_failure = failures.append
    frame = can.Message(arbitration_id=0x181, data=bytes(8), is_extended_id=False, timestamp=1.0)
    writer.log_trial({"trial": 1, "sse": 1.0, "rmse": 1.0, "max_abs_error": 1.0})
    writer.end_trial(wait=True)
    assert writer.written_trials == [1]
    os.kill(writer.pid, signal.SIGSTOP)
    try:
        calls = 0
        while not failures:  # a blocking pipe write held this loop (and a moving axis) for as long as the stall
            writer.log_frame(frame, "tx")
            calls += 1
        assert calls > log_process.PIPE_BYTES // 64  # the pipe filled: the producer went on past it
        assert len(failures) == 1 and f"{out}: the log writer process (pid {writer.pid}) stalled" in str(failures[0])
        assert writer.stalled and writer.failed
        for _ in range(1000):  # dropped from now on, still without blocking
            writer.log_frame(frame, "tx")
        with pytest.raises(LogWriteError, match="stalled"):
            writer.close()
    finally:
        os.kill(writer.pid, signal.SIGCONT)
    writer._process.wait(timeout=60)
    assert read_log(out).trials[0]["trial"] == 1 and not read_log(out).truncated  # finished after it resumed


def test_the_data_pipe_is_never_closed_under_a_thread_that_writes_it(tmp_path: Path,
                                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """A failure found by one thread (the loop's, reading the child's error) ends the pipe while another thread
    sends (the update thread, in a full pipe's wait): the descriptor stays open until the sender lets the send lock
    go, and the sender writes nothing more. Before, it was closed at once: the sender's write failed with EBADF, and
    that became the run's error instead of the child's."""
    writer = ProcessLogWriter(tmp_path / "p.mcap", config_yaml=None, fsync=False)
    data = writer._data
    in_write, release = threading.Event(), threading.Event()
    real_write = writer._write
    seen: list[int] = []

    def waiting_write(payload: bytes) -> None:  # a sender inside the pipe's backpressure wait, lock held
        in_write.set()
        release.wait()
        seen.append(writer._data)
        real_write(payload)

    monkeypatch.setattr(writer, "_write", waiting_write)
    writer.log_sample(1, 0.0, 1.0, 0.5, 0.25, 0.5, sample=0)
    sender = threading.Thread(target=writer._send, kwargs={"block": True}, daemon=True)
    sender.start()
    try:
        assert in_write.wait(PATIENCE)
        writer._close_data()  # the other thread's failure path
        os.fstat(data)  # still open: the sender holds it
    finally:
        release.set()
        sender.join(PATIENCE)
    assert seen == [data] and writer._data == -1  # the sender ended it on its way out
    with pytest.raises(OSError):
        os.fstat(data)
    writer.close()  # the child read the end of the pipe and finished the file
    assert read_log(tmp_path / "p.mcap").samples == []  # what was unsent when the pipe ended is dropped, whole
