"""The small lockstep bench many tests run (``foilc-hil run`` on the embedded emulator, first-order axis) and readers of
the logs it writes: the messages through the standard ``mcap`` reader, the trials completed in a log being written.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml
from mcap.reader import make_reader

NODE = 1
SAMPLE_TIME = 0.005
SAMPLES = 200  # 1 s trials


def bench_config(tmp_path: Path, **bench: Any) -> Path:
    """A small first-order axis (paper eq. 48 scaled to rpm-like numbers) tracking a 200-sample step-and-ramp."""
    document = {
        "plant": {"model": "first_order", "a": -1.23, "b": 1.68, "c": 1.0},
        "reference": {
            "profile": "piecewise",
            "segments": [
                {"duration": 0.3, "start": 0.0, "end": 30.0},
                {"duration": 0.4, "start": 30.0},
                {"duration": 0.3, "start": 30.0, "end": 10.0},
            ],
        },
        "sample_time": SAMPLE_TIME,
        "trials": 4,
        "tuning": {"kp": 0.2, "r": 0.5},
        "drive": {
            "node_id": NODE,
            "mode": "csv",
            "velocity_scale": 1000.0,
            "velocity_limit": 500.0,
            # generous heartbeat supervision: the test machine is shared and can stall a process for a while
            "heartbeat_timeout_factor": 10.0,
            "heartbeat_consumer_ms": 2000,
        },
        "bench": {"settle_time": 0.02, "settle_tolerance": 0.05, **bench},
    }
    path = tmp_path / "bench.yaml"
    path.write_text(yaml.safe_dump(document), encoding="utf-8")
    return path


def read_mcap(path: Path) -> tuple[dict[str, list[dict[str, Any]]], dict[str, dict[str, str]]]:
    """Messages by topic (decoded JSON) and metadata records, through the standard mcap reader."""
    by_topic: dict[str, list[dict[str, Any]]] = {}
    with path.open("rb") as stream:
        reader = make_reader(stream)
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            assert schema is not None and schema.encoding == "jsonschema"
            assert channel.message_encoding == "json"
            by_topic.setdefault(channel.topic, []).append(json.loads(message.data))
        metadata = {record.name: dict(record.metadata) for record in reader.iter_metadata()}
    return by_topic, metadata


def read_log(path: Path) -> dict[str, list[dict[str, Any]]]:
    """Every message by topic, through the standard mcap reader (it must open the file as it is)."""
    by_topic: dict[str, list[dict[str, Any]]] = {}
    with path.open("rb") as stream:
        reader = make_reader(stream)
        for _, channel, message in reader.iter_messages(log_time_order=False):
            by_topic.setdefault(channel.topic, []).append(json.loads(message.data))
    return by_topic


def assert_completed_trials_intact(topics: dict[str, list[dict[str, Any]]], minimum: int) -> list[int]:
    """At least ``minimum`` trials completed; each has its /ilc/trial record and all its samples."""
    trials = [t["trial"] for t in topics.get("/ilc/trial", [])]
    assert len(trials) >= minimum, f"only {trials} completed"
    assert trials == list(range(1, len(trials) + 1))
    samples = topics.get("/ilc/sample", [])
    for k in trials:
        assert sum(1 for s in samples if s["trial"] == k) == SAMPLES
    return trials


@dataclass
class MidTrial:
    """Whether :func:`when_mid_trial`'s action ran."""

    fired: bool = False


def when_mid_trial(emulator: Any, completed: int, action: Callable[[], None]) -> MidTrial:
    """Run ``action`` once, a quarter into the first trial that moves the axis after the first ``completed`` trials.

    Counted on the emulated drive's own lockstep cycles (its ``trace`` hook, called at the end of each SYNC in the
    bench's thread, on the synchronous in-process bus): a trial begins where the drive's target velocity turns
    non-zero after the settle phase's exact zeros. Trial 1 commands the law's initial feedforward, exactly zero, so
    trial ``k > 1`` begins at the ``(k - 1)``-th such turn; a quarter of a trial's cycles into trial
    ``max(completed, 1) + 1`` the action runs, inside that cycle. A watcher thread polling the log raced the
    lockstep loop, which no longer waits on another thread. The target is read from the drive's object dictionary
    (its local data store, no bus traffic).
    """
    trigger = MidTrial()
    starts = 0
    moving = False
    left: int | None = None

    def on_cycle(_snapshot: Any) -> None:
        nonlocal starts, moving, left
        if trigger.fired:
            return
        target = emulator.drive.node.sdo[0x60FF].raw
        starts += int(target != 0 and not moving)
        moving = target != 0
        if left is None and starts >= max(completed, 1):
            left = SAMPLES // 4
        if left is not None:
            left -= 1
            if left <= 0:
                trigger.fired = True
                action()

    emulator.drive.trace = on_cycle
    return trigger


def completed_trials_on_disk(path: Path) -> int:
    """Completed trials in a log still being written (F's damage-tolerant reader reads up to the last chunk)."""
    if not path.exists():
        return 0
    from foilc_hil.io.mcap_log import McapLogReader

    try:
        with McapLogReader(path) as reader:
            return len(reader.read().completed_trials)
    except Exception:  # a file in the middle of its first write
        return 0
