"""Our MCAP writer against foxglove-sdk's (issue 29 target 5): frames and samples per second, and the bytes written.

Both write the log's layout from the same input, as ``run``'s writer process receives it: frames as
``frame_fields`` tuples in batches of 512 (128 items of 4 frames: a lockstep cycle's SYNC, two TPDOs, the RPDO), and
each trial's samples as the float64 columns of a :class:`~foilc_hil.io.records.TrialSamples`; a chunk closes at each
trial's end. The JSON documents are the project's on both sides (``classic_frames_documents``,
``trial_samples_documents``: the log's bytes), so what differs is the writer: ours
(:class:`~foilc_hil.io.mcap_writer.McapFileWriter`: records, chunks, zstd and indexes in Python and zstandard; the
writer process's configuration) against foxglove-sdk's ``MCAPWriter`` (Rust) fed through
its channels (``Channel.log``: one call a message), the same schemas, channel metadata, metadata records, zstd and
chunk size. Neither syncs the file (the disk is not under test).

What foxglove-sdk cannot write of the layout: a ``/can`` message's publish time is the frame's bus timestamp in ours,
and ``Channel.log`` takes a log time only (publish time = log time); the header's library is its own. Counted below
(``layout_differences``), beside the rates.

Each figure is CPU seconds of this process (all its threads: foxglove-sdk compresses in its own) over the messages,
the median of alternated repetitions; wall seconds are kept too. ``python -m benchmarks.bench_foxglove_writer``.
"""

from __future__ import annotations

import os
import tempfile
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from benchmarks.comparison import Comparison, Figure
from benchmarks.output import emit, json_parser
from foilc_hil.io.mcap_writer import McapFileWriter, classic_frames_documents, trial_samples_documents
from foilc_hil.io.records import TrialSamples
from foilc_hil.io.schemas import (
    MESSAGE_ENCODING,
    METADATA_CONFIG,
    SCHEMA_ENCODING,
    TOPIC_CAN,
    TOPIC_SAMPLE,
    TOPICS,
    channel_metadata,
    schema_bytes,
)

CONFIG_YAML = "sample_time: 0.001\n"
BATCH_FRAMES = 512
CHUNK_SIZE = 4 * 1024 * 1024
#: a lockstep cycle's frames: SYNC (tx), TPDO1 and TPDO2 (rx), RPDO1 (tx)
_CYCLE = ((0x080, 0, "tx"), (0x181, 6, "rx"), (0x281, 6, "rx"), (0x201, 6, "tx"))


@dataclass(frozen=True)
class Workload:
    """What a run hands its writer: per trial, its frames (fields, directions, log times) and its samples."""

    frames: list[tuple[list[tuple[Any, ...]], list[str], list[int]]]  # one entry per trial
    samples: list[TrialSamples]

    @property
    def frame_count(self) -> int:
        return sum(len(fields) for fields, _, _ in self.frames)

    @property
    def sample_count(self) -> int:
        return sum(len(samples.control) for samples in self.samples)


def workload(trials: int, samples: int, *, frames: bool = True, rows: bool = True) -> Workload:
    """``trials`` trials of ``samples`` cycles (4 frames a cycle when ``frames``, one row a sample when ``rows``)."""
    rng = np.random.default_rng(29)
    t0, ns0 = 1.7e9, 1_700_000_000_000_000_000
    per_trial, all_samples = [], []
    for k in range(trials):
        fields, directions, times = [], [], []
        for i in range(samples if frames else 0):
            for j, (cob, dlc, direction) in enumerate(_CYCLE):
                n = (k * samples + i) * 4 + j
                data = bytes(rng.integers(0, 256, dlc, dtype=np.uint8))
                # a received frame carries its bus stamp (30 us before the writer logs it); the bench's own, none
                stamp = t0 + n * 2.5e-4 - 30e-6 if direction == "rx" else 0.0
                fields.append((stamp, cob, False, dlc, data, False, False, False, False, False, None))
                directions.append(direction)
                times.append(ns0 + n * 250_000)
        per_trial.append((fields, directions, times))
        if rows:
            columns = rng.standard_normal((5, samples))
            all_samples.append(TrialSamples(k + 1, 0.001, *columns))
    return Workload(per_trial, all_samples)


def write_ours(path: Path, load: Workload) -> None:
    """``run``'s writer process's writer, fed as the process feeds it."""
    writer = McapFileWriter(path, config_yaml=CONFIG_YAML, fsync=False, chunk_size=CHUNK_SIZE)
    for k, (fields, directions, times) in enumerate(load.frames):
        for start in range(0, len(fields), BATCH_FRAMES):
            end = start + BATCH_FRAMES
            writer.log_frames(fields[start:end], directions[start:end], times[start:end])  # type: ignore[arg-type]
        if k < len(load.samples):
            writer.write_trial_samples(load.samples[k], times[-1] if times else 0)
        writer.end_trial()
    writer.close()


def write_foxglove(path: Path, load: Workload) -> None:
    """foxglove-sdk's ``MCAPWriter`` on its own context: the log's channels and metadata, the same documents."""
    import foxglove
    from foxglove.mcap import MCAPCompression, MCAPWriteOptions

    context = foxglove.Context()
    metadata = channel_metadata(CONFIG_YAML)
    channels = {
        topic: foxglove.Channel(topic, schema=foxglove.Schema(name=name, encoding=SCHEMA_ENCODING,
                                                              data=schema_bytes(schema)),
                                message_encoding=MESSAGE_ENCODING, context=context, metadata=dict(metadata[topic]))
        for topic, (name, schema) in TOPICS.items()
    }
    options = MCAPWriteOptions(compression=MCAPCompression.Zstd, chunk_size=CHUNK_SIZE)
    writer = foxglove.open_mcap(path, context=context, writer_options=options, allow_overwrite=True)
    writer.write_metadata(METADATA_CONFIG, {"yaml": CONFIG_YAML})
    log_frame, log_sample = channels[TOPIC_CAN].log, channels[TOPIC_SAMPLE].log
    for k, (fields, directions, times) in enumerate(load.frames):
        for start in range(0, len(fields), BATCH_FRAMES):
            end = start + BATCH_FRAMES
            batch, batch_times = fields[start:end], times[start:end]
            columns = list(zip(*batch, strict=True))
            stamps = [stamp or t / 1e9 for stamp, t in zip(columns[0], batch_times, strict=True)]
            documents = classic_frames_documents(stamps, columns[1], columns[2], columns[3], columns[4], columns[10],
                                                 directions[start:end])
            assert documents is not None
            for document, log_time in zip(documents, batch_times, strict=True):
                log_frame(document, log_time=log_time)
        if k < len(load.samples):
            rows = trial_samples_documents(load.samples[k])
            assert rows is not None
            log_time = times[-1] if times else 0
            for row in rows:
                log_sample(row, log_time=log_time)
        writer.flush()  # a trial's chunk, as end_trial closes ours
    writer.close()
    for channel in channels.values():
        channel.close()


def _measure(write: Callable[[Path, Workload], None], path: Path, load: Workload) -> tuple[float, float, int]:
    """CPU seconds (every thread of this process), wall seconds and bytes of one write of ``load``."""
    path.unlink(missing_ok=True)
    cpu, wall = time.process_time(), time.perf_counter()
    write(path, load)
    return time.process_time() - cpu, time.perf_counter() - wall, path.stat().st_size


def layout_differences(ours: Path, theirs: Path) -> dict[str, Any]:
    """What the two files hold differently: per topic, documents and log times (should be none), and publish times."""
    from mcap.reader import make_reader

    def read(path: Path) -> dict[str, list[tuple[bytes, int, int]]]:
        found: dict[str, list[tuple[bytes, int, int]]] = {}
        with path.open("rb") as stream:
            for _, channel, message in make_reader(stream).iter_messages(log_time_order=False):
                found.setdefault(channel.topic, []).append((message.data, message.log_time, message.publish_time))
        return found

    a, b = read(ours), read(theirs)
    result: dict[str, Any] = {}
    for topic in sorted(set(a) | set(b)):
        left, right = a.get(topic, []), b.get(topic, [])
        result[topic] = {
            "messages": [len(left), len(right)],
            "documents_differ": sum(x[0] != y[0] for x, y in zip(left, right, strict=False)),
            "log_times_differ": sum(x[1] != y[1] for x, y in zip(left, right, strict=False)),
            "publish_times_differ": sum(x[2] != y[2] for x, y in zip(left, right, strict=False)),
        }
    return result


def writer_comparisons(directory: Path, repeats: int = 5, trials: int = 10, samples: int = 6000
                       ) -> tuple[dict[str, Any], list[Comparison]]:
    """Frames/s, samples/s and bytes of both writers (alternated), and how their files differ."""
    loads = {"frames": workload(trials, samples, rows=False), "samples": workload(trials, samples, frames=False),
             "run": workload(trials, samples)}
    measured: dict[str, dict[str, list[tuple[float, float, int]]]] = {name: {"ours": [], "foxglove": []}
                                                                       for name in loads}
    for _ in range(repeats):
        for name, load in loads.items():
            measured[name]["ours"].append(_measure(write_ours, directory / f"ours-{name}.mcap", load))
            measured[name]["foxglove"].append(_measure(write_foxglove, directory / f"fox-{name}.mcap", load))
    counts = {"frames": loads["frames"].frame_count, "samples": loads["samples"].sample_count}
    rows = []
    for name, unit in (("frames", "frames/s"), ("samples", "samples/s")):
        rate = {side: Figure(tuple(counts[name] / cpu for cpu, _, _ in runs)) for side, runs in measured[name].items()}
        rows.append(Comparison(
            target=f"MCAP writer: {name} written per CPU second ({trials} trials x {samples} cycles)", unit=unit,
            higher_is_better=True, project=rate["ours"], peer=rate["foxglove"],
            peer_name="foxglove-sdk MCAPWriter (Channel.log per message, same documents, zstd, same chunk size)",
            note="target 5: the faster writer stays; CPU of every thread of the process (foxglove-sdk compresses "
            "in its own)"))
    size = {side: Figure(tuple(float(b) for _, _, b in runs)) for side, runs in measured["run"].items()}
    rows.append(Comparison(
        target=f"MCAP writer: bytes of a run's log ({trials} trials x {samples} cycles, 4 frames and 1 row a cycle)",
        unit="bytes", higher_is_better=False, project=size["ours"], peer=size["foxglove"],
        peer_name="foxglove-sdk MCAPWriter", note="zstd, 4 MiB chunks closed at every trial on both sides"))
    details = {
        "runs": {name: {side: [{"cpu_s": c, "wall_s": w, "bytes": b} for c, w, b in runs]
                        for side, runs in sides.items()} for name, sides in measured.items()},
        "counts": counts,
        "layout_differences": layout_differences(directory / "ours-run.mcap", directory / "fox-run.mcap"),
    }
    return details, rows


def main(argv: Sequence[str] | None = None) -> int:
    parser = json_parser("python -m benchmarks.bench_foxglove_writer", __doc__)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--trials", type=int, default=10)
    parser.add_argument("--samples", type=int, default=6000)
    args = parser.parse_args(argv)
    with tempfile.TemporaryDirectory() as directory:
        details, rows = writer_comparisons(Path(directory), args.repeats, args.trials, args.samples)
    emit({"details": details, "comparisons": [row.to_json() for row in rows], "cpus": os.cpu_count()}, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
