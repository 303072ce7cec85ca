"""``.mcap`` through python-can's own entry points: ``can.LogReader``, ``can.Logger``, a Notifier listener."""

from __future__ import annotations

import time
import uuid
from pathlib import Path

import can
import pytest

from foilc_hil.io.can_io import McapCanReader, McapCanWriter
from foilc_hil.io.mcap_log import McapLogWriter, read_log


def _frames() -> list[can.Message]:
    return [
        can.Message(
            timestamp=50.0 + 0.001 * i,
            arbitration_id=0x181 + (i % 3),
            data=bytes([i, 255 - i]),
            is_extended_id=False,
            is_rx=bool(i % 2),
        )
        for i in range(20)
    ] + [can.Message(timestamp=51.0, arbitration_id=0x18DAF110, data=b"", is_extended_id=True)]


def _same(a: can.Message, b: can.Message) -> None:
    assert (a.timestamp, a.arbitration_id, a.is_extended_id, a.dlc, bytes(a.data), a.is_rx) == (
        b.timestamp,
        b.arbitration_id,
        b.is_extended_id,
        b.dlc,
        bytes(b.data),
        b.is_rx,
    )


def test_can_logreader_finds_our_reader_and_yields_the_bench_frames(tmp_path: Path) -> None:
    path = tmp_path / "bench.mcap"
    frames = _frames()
    with McapLogWriter(path, config_yaml="trials: 1\n") as writer:
        for msg in frames:
            writer.log_frame(msg, "rx" if msg.is_rx else "tx")
        writer.log_sample(1, 0.0, 1.0, 0.0, 0.5, 1.0)  # other topics are skipped by the CAN reader
    reader = can.LogReader(path)
    assert isinstance(reader, McapCanReader)
    got = list(reader)
    assert len(got) == len(frames)
    for a, b in zip(got, frames, strict=True):
        _same(a, b)


def test_can_logger_writes_mcap_that_reads_back(tmp_path: Path) -> None:
    path = tmp_path / "capture.mcap"
    logger = can.Logger(path)
    assert isinstance(logger, McapCanWriter)
    frames = _frames()
    with logger:
        for msg in frames:
            logger.on_message_received(msg)
    assert not read_log(path).truncated
    for a, b in zip(can.LogReader(path), frames, strict=True):
        _same(a, b)


def test_writer_listens_on_a_virtual_bus(tmp_path: Path) -> None:
    channel = f"test-{uuid.uuid4()}"
    path = tmp_path / "bus.mcap"
    with can.Bus(interface="virtual", channel=channel) as rx_bus, can.Bus(interface="virtual", channel=channel) as tx:
        writer = McapLogWriter(path, config_yaml=None)
        notifier = can.Notifier(rx_bus, [writer])
        for i in range(10):
            tx.send(can.Message(arbitration_id=0x701, data=[i], is_extended_id=False))
        deadline = time.monotonic() + 5.0
        while time.monotonic() < deadline and writer.message_count("/can") < 10:
            time.sleep(0.01)
        notifier.stop()  # stops the listener, which closes the log
    assert writer.closed
    frames = list(can.LogReader(path))
    assert [bytes(m.data) for m in frames] == [bytes([i]) for i in range(10)]
    assert all(m.is_rx and m.timestamp > 0 for m in frames)


def test_truncated_capture_yields_frames_up_to_the_cut(tmp_path: Path) -> None:
    path = tmp_path / "cut.mcap"
    with McapLogWriter(path, config_yaml=None) as writer:
        for msg in _frames()[:10]:
            writer.log_frame(msg, "tx")
        writer.end_trial()
        for msg in _frames()[10:]:
            writer.log_frame(msg, "tx")
    path.write_bytes(path.read_bytes()[:-30])
    reader = McapCanReader(path)
    got = list(reader)
    assert reader.truncated
    assert len(got) >= 10
    assert [m.arbitration_id for m in got[:10]] == [m.arbitration_id for m in _frames()[:10]]


def test_non_mcap_file_is_refused_with_its_name(tmp_path: Path) -> None:
    from foilc_hil.errors import LogFormatError

    path = tmp_path / "x.mcap"
    path.write_text("date Sat Nov 21\n")
    with pytest.raises(LogFormatError, match=r"x\.mcap"):
        list(can.LogReader(path))
