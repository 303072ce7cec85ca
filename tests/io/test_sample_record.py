"""The typed sample record: built once by the producer, encoded by the writer, read back field for field."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from foilc_hil.io.log_process import ProcessLogWriter
from foilc_hil.io.mcap_log import McapLogWriter, read_log
from foilc_hil.io.records import SampleRecord, TimingRecord


def _records() -> list[SampleRecord]:
    siso = SampleRecord(trial=2, t=0.25, reference=1.0, output=0.1 + 0.2, control=-1 / 3, error=0.7, E=None, sample=5)
    mimo = SampleRecord(1, 0.0, np.array([1.0, 2.0]), np.float64(0.5), [0.25, -0.5], np.array([1e-300, -2.5]), 0.125)
    return [siso, mimo]


@pytest.mark.parametrize("process", [False, True], ids=["in-process", "writer-process"])
def test_records_round_trip_through_the_writer(tmp_path: Path, process: bool) -> None:
    out = tmp_path / "records.mcap"
    writer = (ProcessLogWriter(out, config_yaml=None, fsync=False) if process
              else McapLogWriter(out, config_yaml=None, fsync=False))
    with writer:
        for record in _records():
            writer.write_sample(record)
    samples = read_log(out).samples
    assert samples == [
        {"trial": 2, "t": 0.25, "reference": 1.0, "output": 0.30000000000000004, "control": -1 / 3, "error": 0.7,
         "E": None, "sample": 5},
        {"trial": 1, "t": 0.0, "reference": [1.0, 2.0], "output": 0.5, "control": [0.25, -0.5],
         "error": [1e-300, -2.5], "E": 0.125},  # no sample index given: no field
    ]


def test_the_positional_spelling_builds_the_same_record(tmp_path: Path) -> None:
    record = _records()[0]
    paths = tmp_path / "typed.mcap", tmp_path / "positional.mcap"
    with McapLogWriter(paths[0], config_yaml=None, fsync=False) as typed:
        typed.write_sample(record)
    with McapLogWriter(paths[1], config_yaml=None, fsync=False) as positional:
        positional.log_sample(
            record.trial, record.t, record.reference, record.output, record.control, record.error, record.E,
            sample=record.sample,
        )
    assert read_log(paths[0]).samples == read_log(paths[1]).samples == [record.to_json()]


def test_sample_record_is_immutable_and_has_no_dict() -> None:
    record = _records()[0]
    with pytest.raises(AttributeError):
        record.trial = 3  # type: ignore[misc]
    assert not hasattr(record, "__dict__")


@pytest.mark.parametrize("process", [False, True], ids=["in-process", "writer-process"])
def test_timing_records_round_trip_typed_and_positional(tmp_path: Path, process: bool) -> None:
    out = tmp_path / "timing.mcap"
    writer = (ProcessLogWriter(out, config_yaml=None, fsync=False) if process
              else McapLogWriter(out, config_yaml=None, fsync=False))
    typed = TimingRecord(7, 2, 3, np.float64(12.5), 1000.0, None, True, lost_feedback=True)
    with writer:
        writer.write_timing(typed)
        writer.log_timing(8, 2, 4, 0.0, 999.5, 250.0, False)
    assert read_log(out).timing == [
        {"cycle": 7, "trial": 2, "sample": 3, "lateness_us": 12.5, "period_us": 1000.0, "feedback_latency_us": None,
         "missed": True, "lost_feedback": True},
        {"cycle": 8, "trial": 2, "sample": 4, "lateness_us": 0.0, "period_us": 999.5, "feedback_latency_us": 250.0,
         "missed": False, "lost_feedback": False},
    ]
    with pytest.raises(AttributeError):
        typed.cycle = 9  # type: ignore[misc]


@pytest.mark.parametrize("process", [False, True], ids=["in-process", "writer-process"])
def test_a_timing_block_is_logged_as_its_records(tmp_path: Path, process: bool) -> None:
    from foilc_hil.io.records import TimingBlock

    block = TimingBlock(70, 2, np.array([12.5, 0.0, 1 / 3]), np.array([1000.0, 999.5, 0.1 + 0.2]),
                        np.array([np.nan, 250.0, 1e-300]), np.array([True, False, False]),
                        np.array([True, False, True]))
    out = tmp_path / "timing.mcap"
    writer = (ProcessLogWriter(out, config_yaml=None, fsync=False) if process
              else McapLogWriter(out, config_yaml=None, fsync=False))
    with writer:
        writer.write_timing_block(block)
    assert read_log(out).timing == [
        {"cycle": 70, "trial": 2, "sample": 0, "lateness_us": 12.5, "period_us": 1000.0, "feedback_latency_us": None,
         "missed": True, "lost_feedback": True},
        {"cycle": 71, "trial": 2, "sample": 1, "lateness_us": 0.0, "period_us": 999.5, "feedback_latency_us": 250.0,
         "missed": False, "lost_feedback": False},
        {"cycle": 72, "trial": 2, "sample": 2, "lateness_us": 1 / 3, "period_us": 0.30000000000000004,
         "feedback_latency_us": 1e-300, "missed": False, "lost_feedback": True},
    ]
    assert TimingBlock.from_columns(70, 2, block.columns()).missed.tolist() == [True, False, False]
