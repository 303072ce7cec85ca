"""``.mcap`` through python-can's own entry points: ``can.LogReader``, ``can.Logger``, a Notifier listener."""

from __future__ import annotations

import json
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


@pytest.mark.slow
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


# --- every can.Message field survives the plugin ----------------------------------------------------------------


def _flagged_frames() -> list[can.Message]:
    """One frame per kind python-can knows: classic, remote, error, FD (64 bytes, BRS, ESI), extended, on channels."""
    return [
        can.Message(timestamp=1.0, arbitration_id=0x123, data=b"\x01\x02", is_extended_id=False, channel="vcan0"),
        can.Message(timestamp=1.1, arbitration_id=0x705, is_remote_frame=True, dlc=1, is_extended_id=False),
        can.Message(timestamp=1.2, arbitration_id=0x20000080, is_error_frame=True, dlc=8,
                    data=bytes(range(8)), is_extended_id=True, is_rx=True, channel=1),
        can.Message(timestamp=1.3, arbitration_id=0x181, data=bytes(range(64)), is_fd=True, bitrate_switch=True,
                    error_state_indicator=True, is_extended_id=False),
        can.Message(timestamp=1.4, arbitration_id=0x18DAF110, data=bytes(range(12)), is_fd=True,
                    is_extended_id=True, is_rx=True),
    ]


_FIELDS = ("timestamp", "arbitration_id", "is_extended_id", "is_remote_frame", "is_error_frame", "is_fd",
           "bitrate_switch", "error_state_indicator", "channel", "dlc", "is_rx")


def _fields(msg: can.Message) -> tuple[object, ...]:
    return (*(getattr(msg, name) for name in _FIELDS), bytes(msg.data))


def _conforms(value: object, schema: dict[str, object]) -> bool:
    """A minimal JSON Schema check of the keywords the MCAP schemas use (type, minimum, maximum, enum,
    required, properties): independent of the writer, which never consults the schema."""
    kinds: dict[str, type | tuple[type, ...]] = {
        "object": dict, "string": str, "boolean": bool, "number": (int, float), "integer": int,
    }
    types = schema.get("type")
    if types is not None:
        names = types if isinstance(types, list) else [types]
        if not any(isinstance(value, kinds[str(name)]) for name in names):
            return False
        if isinstance(value, bool) and "boolean" not in names:
            return False
    if "enum" in schema and value not in schema["enum"]:  # type: ignore[operator]
        return False
    if isinstance(value, (int, float)) and not isinstance(value, bool):
        if "minimum" in schema and value < schema["minimum"]:  # type: ignore[operator]
            return False
        if "maximum" in schema and value > schema["maximum"]:  # type: ignore[operator]
            return False
    if isinstance(value, dict):
        properties = schema.get("properties", {})
        assert isinstance(properties, dict)
        if any(key not in value for key in schema.get("required", [])):  # type: ignore[attr-defined]
            return False
        return all(_conforms(item, properties[key]) for key, item in value.items() if key in properties)
    return True


def test_every_message_flag_round_trips_through_the_plugin(tmp_path: Path) -> None:
    path = tmp_path / "flags.mcap"
    with can.Logger(path) as logger:
        for msg in _flagged_frames():
            logger.on_message_received(msg)
    got = list(can.LogReader(path))
    assert [_fields(m) for m in got] == [_fields(m) for m in _flagged_frames()]
    error = got[2]
    assert error.is_error_frame and error.arbitration_id != 0  # never a frame on 0x000, the NMT broadcast


def test_every_record_validates_against_the_files_own_schema(tmp_path: Path) -> None:
    from mcap.reader import make_reader

    path = tmp_path / "flags.mcap"
    with can.Logger(path) as logger:
        for msg in _flagged_frames():
            logger.on_message_received(msg)
    with path.open("rb") as stream:
        records = [(json.loads(schema.data), json.loads(message.data))
                   for schema, _, message in make_reader(stream).iter_messages() if schema is not None]
    assert len(records) == len(_flagged_frames())
    for schema, record in records:
        assert _conforms(record, schema), record
    assert max(record["dlc"] for _, record in records) == 64
    # the checker can fail: a dlc beyond the schema's maximum is refused
    assert not _conforms({**records[0][1], "dlc": 65}, records[0][0])


def test_can_logconvert_and_can_player_keep_the_flags_and_never_send_an_error_frame(tmp_path: Path) -> None:
    import sys

    from can import logconvert, player

    source = tmp_path / "flags.mcap"
    with can.Logger(source) as logger:
        for msg in _flagged_frames():
            logger.on_message_received(msg)
    converted = tmp_path / "converted.mcap"
    argv = sys.argv
    try:
        sys.argv = ["can_logconvert", str(source), str(converted)]
        logconvert.main()
    finally:
        sys.argv = argv
    assert [_fields(m) for m in can.LogReader(converted)] == [_fields(m) for m in _flagged_frames()]

    channel = f"test-player-{uuid.uuid4()}"
    with can.Bus(interface="virtual", channel=channel, fd=True) as listener:
        try:
            sys.argv = ["can_player", "-i", "virtual", "-c", channel, "--ignore-timestamps", str(source)]
            player.main()
        finally:
            sys.argv = argv
        sent: list[can.Message] = []
        while (received := listener.recv(0.2)) is not None:
            sent.append(received)
    assert not any(m.is_error_frame for m in sent)
    assert [m.arbitration_id for m in sent] == [m.arbitration_id for m in _flagged_frames() if not m.is_error_frame]
    assert sent[2].is_fd and sent[2].bitrate_switch and bytes(sent[2].data) == bytes(range(64))
