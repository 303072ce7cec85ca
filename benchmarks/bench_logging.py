"""What logging costs the real-time loop: direct MCAP writing versus the queued writer, side by side.

``python -m benchmarks.bench_logging [--out FILE] [--cycles N]`` prints (or writes) one JSON document:

- ``per_call_ns``: median cost on the caller's thread of one ``log_frame`` and one ``log_sample`` call, direct
  (JSON + chunk building on the caller) and queued (one tuple on a ``SimpleQueue``);
- ``drain``: how many messages per second the background thread writes (zstd chunks);
- ``periodic_loop``: a 1 kHz loop (absolute deadlines, sleep) logging what a bench cycle logs -- 3 frames, one
  sample, one timing record -- with each writer (none, direct, queued: a writer thread, process: the writer process
  ``run`` uses), an ``end_trial`` every 600 cycles: time spent in the logging calls per cycle and wake-up lateness
  percentiles (the GIL is shared with the writer thread, so the queued case shows its contention too).

- ``comparisons`` (what ``make bench`` renders): frames written and read per second on one stream of CAN frames,
  our MCAP writer/reader against python-can's ``BLFWriter``/``BLFReader`` and ``ASCWriter``/``ASCReader``; the cost
  of building the typed records against a frozen slotted dataclass of the same fields (what ``SampleRecord`` was).

Never asserted in tests (wall-clock numbers depend on the machine); ``make bench`` users read them.
"""

from __future__ import annotations

import functools
import statistics
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import can
import numpy as np

from benchmarks.comparison import Comparison, comparisons_json, repeat, seconds
from benchmarks.output import emit, json_parser
from benchmarks.queued_writer import QueuedLogWriter
from foilc_hil.io.log_process import ProcessLogWriter
from foilc_hil.io.mcap_log import McapLogWriter, read_log
from foilc_hil.io.mcap_writer import FRAME_BATCH
from foilc_hil.io.records import SampleRecord, TimingRecord

CONFIG_YAML = "sample_time: 0.001\n"


def _frame(i: int) -> can.Message:
    return can.Message(arbitration_id=0x201, data=bytes([i & 0xFF, 1, 2, 3]), is_extended_id=False)


def _per_call(call: Callable[[int], None], calls: int, batches: int = 7) -> float:
    """Median over batches of the mean ns per call."""
    results = []
    for _ in range(batches):
        start = time.perf_counter_ns()
        for i in range(calls):
            call(i)
        results.append((time.perf_counter_ns() - start) / calls)
    return float(statistics.median(results))


def per_call_costs(directory: Path, calls: int = 5000) -> dict[str, Any]:
    msg = _frame(1)
    document: dict[str, Any] = {}
    direct = McapLogWriter(directory / "direct.mcap", config_yaml=CONFIG_YAML, fsync=False)
    queued = QueuedLogWriter.open(directory / "queued.mcap", config_yaml=CONFIG_YAML, fsync=False)
    try:
        writers: tuple[tuple[str, McapLogWriter | QueuedLogWriter], ...] = (("direct", direct), ("queued", queued))
        for name, writer in writers:

            def frame(i: int, writer: McapLogWriter | QueuedLogWriter = writer) -> None:
                writer.log_frame(msg, "tx")

            def sample(i: int, writer: McapLogWriter | QueuedLogWriter = writer) -> None:
                writer.log_sample(1, i * 1e-3, 1.0, 0.5, 0.25, 0.5, 0.4)

            frame_ns = _per_call(frame, calls)
            if isinstance(writer, QueuedLogWriter):
                writer.sync()  # each measurement starts with an idle writer thread (it still competes during it)
            sample_ns = _per_call(sample, calls)
            if isinstance(writer, QueuedLogWriter):
                writer.sync()
            document[name] = {"log_frame": frame_ns, "log_sample": sample_ns}
    finally:
        queued.close()
        direct.close()
    return document


def drain_rate(directory: Path, messages: int = 50_000) -> dict[str, Any]:
    queued = QueuedLogWriter.open(directory / "drain.mcap", config_yaml=CONFIG_YAML, fsync=False)
    msg = _frame(2)
    start = time.perf_counter()
    for i in range(messages // 2):
        queued.log_frame(msg, "tx")
        queued.log_sample(1, i * 1e-3, 1.0, 0.5, 0.25, 0.5, 0.4)
    enqueued = time.perf_counter()
    queued.sync()
    done = time.perf_counter()
    queued.close()
    return {
        "messages": messages,
        "enqueue_s": enqueued - start,
        "written_s": done - start,
        "messages_per_s": messages / (done - start),
    }


def _percentiles(values: Sequence[float]) -> dict[str, float]:
    array = np.asarray(values, dtype=float)
    return {
        "p50": float(np.percentile(array, 50)),
        "p99": float(np.percentile(array, 99)),
        "p999": float(np.percentile(array, 99.9)),
        "max": float(array.max()),
    }


def periodic_loop(directory: Path, kind: str, cycles: int, period: float = 1e-3) -> dict[str, Any]:
    """A 1 kHz loop logging one bench cycle's messages per cycle with the ``kind`` writer."""
    if kind == "direct":
        writer: McapLogWriter | QueuedLogWriter | ProcessLogWriter = McapLogWriter(
            directory / "loop-direct.mcap", config_yaml=CONFIG_YAML
        )
    elif kind == "queued":
        writer = QueuedLogWriter.open(directory / "loop-queued.mcap", config_yaml=CONFIG_YAML)
    elif kind == "process":
        writer = ProcessLogWriter.open(directory / "loop-process.mcap", config_yaml=CONFIG_YAML)
    else:
        writer = None  # type: ignore[assignment]
    frames = [_frame(i) for i in range(3)]
    logging_us: list[float] = []
    lateness_us: list[float] = []
    start = time.perf_counter()
    for cycle in range(cycles):
        deadline = start + (cycle + 1) * period
        remaining = deadline - time.perf_counter()
        if remaining > 0:
            time.sleep(remaining)
        woke = time.perf_counter()
        lateness_us.append((woke - deadline) * 1e6)
        if writer is not None:
            t0 = time.perf_counter()
            for msg in frames:
                writer.log_frame(msg, "tx")
            writer.log_sample(1, cycle * period, 1.0, 0.5, 0.25, 0.5, 0.4, sample=cycle % 600)
            writer.log_timing(cycle, 1, cycle % 600, lateness_us[-1], period * 1e6, 200.0, False)
            if cycle % 600 == 599:
                writer.end_trial()
            logging_us.append((time.perf_counter() - t0) * 1e6)
    if writer is not None:
        writer.close()
    result: dict[str, Any] = {
        "cycles": cycles,
        "period_us": period * 1e6,
        "wake_lateness_us": _percentiles(lateness_us),
    }
    if logging_us:
        result["logging_call_us_per_cycle"] = _percentiles(logging_us)
    return result


def _stream(frames: int) -> list[can.Message]:
    """One bench-like stream: SYNC, RPDO, TPDO pairs with bus timestamps."""
    ids = (0x080, 0x201, 0x181, 0x281)
    return [
        can.Message(
            arbitration_id=ids[i % 4],
            data=bytes([i & 0xFF, 1, 2, 3, 4, 5, 6, 7][: 8 if i % 4 else 0]),
            timestamp=1000.0 + i * 2.5e-4,
            is_extended_id=False,
            dlc=8 if i % 4 else 0,
        )
        for i in range(frames)
    ]


def _write_rate(path: Path, stream: list[can.Message], kind: str) -> float:
    """Frames per second through one writer, file closed."""
    if kind == "mcap":
        writer = McapLogWriter(path, config_yaml=None, fsync=False)
        log = writer.on_message_received
    else:
        writer = can.BLFWriter(path) if kind == "blf" else can.ASCWriter(path)  # type: ignore[assignment]
        log = writer.on_message_received

    def write() -> None:
        for msg in stream:
            log(msg)
        writer.stop()

    return len(stream) / seconds(write)


def _read_rate(path: Path, kind: str) -> float:
    """Frames per second read back (decoded into python-can messages or frame documents)."""
    if kind == "mcap":
        return len(read_log(path).frames) / seconds(lambda: read_log(path))
    reader = can.BLFReader if kind == "blf" else can.ASCReader
    count = [0]

    def read() -> None:
        with reader(path) as frames:
            count[0] = sum(1 for _ in frames)

    elapsed = seconds(read)
    return count[0] / elapsed


@dataclass(frozen=True, slots=True)
class _FrozenSample:
    """What ``SampleRecord`` was before it became a named tuple: the peer of the record-cost row."""

    trial: int
    t: float
    reference: Any
    output: Any
    control: Any
    error: Any
    E: Any = None
    sample: int | None = None


def writer_comparisons(directory: Path, frames: int = 50_000, repeats: int = 3) -> list[Comparison]:
    """MCAP vs BLF vs ASC, written and read; typed-record construction."""
    stream = _stream(frames)
    rows = []
    kinds = ("mcap", "blf", "asc")
    # the compiled frame kernel is loaded at the first batch (numba's import and cache, once per process): outside
    # the timing, as python-can's writers were imported before it
    _write_rate(directory / "warm-up.mcap", stream[:FRAME_BATCH], "mcap")
    rates = {
        kind: repeat(functools.partial(_write_rate, directory / f"w.{kind}", stream, kind), repeats) for kind in kinds
    }
    for peer, name in (("blf", "python-can BLFWriter"), ("asc", "python-can ASCWriter")):
        rows.append(
            Comparison(
                f"frames written per second ({frames} frames, file closed)",
                "frames/s",
                True,
                rates["mcap"],
                rates[peer],
                name,
                min_ratio=1.0 if peer == "blf" else None,
                note="each frame is a JSON document (the log's contract) in an MCAP record with an index entry. Per "
                "frame: one row of values appended (about 15 Python operations, the floor: BLF's whole path is about "
                "40); per batch of 1024, the JSON text and the records by a compiled kernel, the timestamps' repr "
                "(shortest round trip, about 0.25 us a frame) by C loops. Before: orjson, then templates (0.58x)"
                if peer == "blf"
                else "",
            )
        )
    reads = {kind: repeat(functools.partial(_read_rate, directory / f"w.{kind}", kind), repeats) for kind in kinds}
    for peer, name in (("blf", "python-can BLFReader"), ("asc", "python-can ASCReader")):
        rows.append(
            Comparison(
                f"frames read per second ({frames} frames)",
                "frames/s",
                True,
                reads["mcap"],
                reads[peer],
                name,
                note="ours decodes each message's JSON into a frame document" if peer == "blf" else "",
            )
        )
    calls = 100_000

    def build(make: Callable[[int], object]) -> float:
        def loop() -> None:
            for i in range(calls):  # nothing kept: the garbage collector would dominate both sides
                make(i)

        return seconds(loop) / calls * 1e9

    rows.append(
        Comparison(
            "building one /ilc/sample record",
            "ns",
            False,
            repeat(lambda: build(lambda i: SampleRecord(1, i * 1e-3, 1.0, 0.5, 0.25, 0.5, 0.4, i)), repeats),
            repeat(lambda: build(lambda i: _FrozenSample(1, i * 1e-3, 1.0, 0.5, 0.25, 0.5, 0.4, i)), repeats),
            "frozen slotted dataclass (SampleRecord before)",
        )
    )
    rows.append(
        Comparison(
            "building one /timing record",
            "ns",
            False,
            repeat(lambda: build(lambda i: TimingRecord(i, 1, i, 12.5, 1000.0, 250.0, False)), repeats),
            note="the typed record the queue carries (was a 10-field tuple, then a dict)",
        )
    )
    return rows


def collect(cycles: int = 3000) -> dict[str, Any]:
    with tempfile.TemporaryDirectory(prefix="foilc-bench-log-") as name:
        directory = Path(name)
        return {
            "per_call_ns": per_call_costs(directory),
            "drain": drain_rate(directory),
            "periodic_loop": {
                kind: periodic_loop(directory, kind, cycles) for kind in ("none", "direct", "queued", "process")
            },
            "comparisons": comparisons_json(writer_comparisons(directory)),
        }


def main(argv: Sequence[str] | None = None) -> int:
    parser = json_parser("python -m benchmarks.bench_logging", __doc__)
    parser.add_argument("--cycles", type=int, default=3000, help="cycles of the 1 kHz loop per writer")
    args = parser.parse_args(argv)
    emit(collect(args.cycles), args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
