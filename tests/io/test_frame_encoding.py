"""The /can documents written from templates (one frame, or a batch as columns) or by the compiled kernel (a batch,
as MCAP records) are orjson's text of the same document, byte for byte, in records laid out as the MCAP specification
says; frames neither covers are told apart, and frames logged as columns make the same file as frames logged one by
one."""

from __future__ import annotations

import binascii
import io
import random
import struct
from collections.abc import Callable
from pathlib import Path

import can
import orjson
import pytest

from foilc_hil.io.mcap_log import McapLogWriter, frame_fields, read_log
from foilc_hil.io.mcap_writer import (
    Direction,
    McapFileWriter,
    classic_frames_documents,
    frame_json,
)


def _document(msg: can.Message, timestamp: float, direction: str) -> bytes:
    """The independent truth: the fixed /can record as a dict, encoded by orjson."""
    return orjson.dumps({
        "timestamp": timestamp,
        "id": msg.arbitration_id,
        "extended": msg.is_extended_id,
        "dlc": msg.dlc,
        "data": binascii.b2a_base64(msg.data, newline=False).decode("ascii"),
        "dir": direction,
    })


def _classic_frames(count: int, seed: int) -> list[can.Message]:
    rng = random.Random(seed)
    frames = []
    for _ in range(count):
        extended = rng.random() < 0.3
        data = bytes(rng.randrange(256) for _ in range(rng.randrange(9)))
        timestamp = rng.choice([0.0, rng.uniform(0.001, 1e4), 1.7e9 + rng.random(), float(rng.randrange(1, 10**6))])
        frames.append(can.Message(arbitration_id=rng.randrange(1 << (29 if extended else 11)), data=data,
                                  is_extended_id=extended, timestamp=timestamp))
    return frames


def _records(data: bytes) -> list[tuple[int, int, int, int, int, bytes]]:
    """Message records parsed by the MCAP specification's layout: (offset, channel, sequence, log, publish, data)."""
    records, at = [], 0
    while at < len(data):
        opcode, length, channel, sequence, log_time, publish_time = struct.unpack_from("<BQHIQQ", data, at)
        assert opcode == 0x05
        records.append((at, channel, sequence, log_time, publish_time, data[at + 31 : at + 9 + length]))
        at += 9 + length
    return records


def test_a_batch_of_classic_frames_is_each_frames_own_text() -> None:
    """The batch spelling (the one every batch of classic frames takes) is, frame for frame, the single-frame one."""
    frames = _classic_frames(500, seed=3)
    directions: list[Direction] = ["tx" if i % 3 else "rx" for i in range(len(frames))]
    log_times = [1_700_000_000_000_000_000 + 1000 * i for i in range(len(frames))]
    stamps = [m.timestamp or log_time / 1e9 for m, log_time in zip(frames, log_times, strict=True)]
    _, ids, extended, dlcs, datas = list(zip(*(frame_fields(m) for m in frames), strict=True))[:5]
    documents = classic_frames_documents(stamps, ids, extended, dlcs, datas, [None] * len(frames), directions)
    assert documents is not None
    texts = [frame_json(frame_fields(m), t, d) for m, t, d in zip(frames, stamps, directions, strict=True)]
    assert documents == texts
    # and the text is orjson's document of the frame (an independent spelling)
    assert texts == [_document(m, t, d) for m, t, d in zip(frames, stamps, directions, strict=True)]


def test_frames_the_batch_does_not_cover_are_written_one_by_one(tmp_path: Path) -> None:
    classic = _classic_frames(3, seed=5)
    odd = [
        can.Message(arbitration_id=0x181, is_remote_frame=True, dlc=2, is_extended_id=False, timestamp=1.0),
        can.Message(arbitration_id=0x181, data=b"\x01", is_extended_id=False, timestamp=1.0, channel="vcan0"),
        can.Message(arbitration_id=0x181, data=b"\x01", is_extended_id=False, timestamp=1.0, channel=0),
        can.Message(arbitration_id=0x181, data=b"\x01", is_extended_id=False, timestamp=1e-05),  # exponent
        can.Message(arbitration_id=0x181, data=b"\x01", is_extended_id=False, timestamp=float("inf")),
    ]
    path = tmp_path / "odd.mcap"
    with McapLogWriter(path, config_yaml=None, fsync=False) as writer:
        for msg in [*classic, *odd[:4]]:
            writer.log_frame(msg, "tx", log_time_ns=1)
    frames = read_log(path).frames
    assert [frame["timestamp"] for frame in frames] == [m.timestamp or 1e-9 for m in classic] + [1.0, 1.0, 1.0, 1e-05]
    assert frames[3]["remote"] is True and "channel" not in frames[3]
    assert frames[4]["channel"] == "vcan0" and frames[5]["channel"] == 0
    # one by one, each is orjson's text of its document (non-finite as null, the optional fields added)
    assert frame_json(frame_fields(odd[3]), 1e-05, "rx") == _document(odd[3], 1e-05, "rx")
    assert frame_json(frame_fields(odd[4]), float("inf"), "rx") == _document(odd[4], float("inf"), "rx")


@pytest.mark.parametrize("channel", ["vcan0", "foilc-hil-bench", 'a "quoted" \\ name', "k\u00e4nal\n", ""])
@pytest.mark.parametrize("timestamp", [1.0, 1700000000.123456, 1e-05, float("nan")])
def test_a_classic_frame_of_a_named_channel_is_orjsons_text(channel: str, timestamp: float) -> None:
    msg = can.Message(arbitration_id=0x181, data=b"\x37\x02", is_extended_id=False, channel=channel)
    expected = orjson.loads(_document(msg, timestamp, "rx"))
    expected["channel"] = channel
    assert frame_json(frame_fields(msg), timestamp, "rx") == orjson.dumps(expected)


def _frame_columns(frames: list[can.Message]) -> list[tuple[object, ...]]:
    return list(zip(*(frame_fields(m) for m in frames), strict=True))


def test_a_batch_of_documents_is_each_frames_own_text() -> None:
    frames = _classic_frames(400, seed=11)
    names = [None, "vcan0", 'a "quoted" \\ name', "k\u00e4nal\n", ""]
    for i, msg in enumerate(frames):
        msg.channel = names[i % len(names)]
        msg.timestamp = msg.timestamp or 1.5 + i  # resolved, as the writer passes them
    directions: list[Direction] = ["rx" if i % 4 else "tx" for i in range(len(frames))]
    stamps, ids, extended, dlcs, datas, *_, channels = _frame_columns(frames)
    documents = classic_frames_documents(stamps, ids, extended, dlcs, datas, channels, directions)  # type: ignore[arg-type]
    expected = [frame_json(frame_fields(m), m.timestamp, d) for m, d in zip(frames, directions, strict=True)]
    assert documents == expected
    # and each is orjson's text of the frame's document
    for msg, direction, document in zip(frames[:40], directions, expected, strict=False):
        truth = orjson.loads(_document(msg, msg.timestamp, direction))
        if msg.channel is not None:
            truth["channel"] = msg.channel
        assert document == orjson.dumps(truth)
    # what the templates cannot spell is refused as a batch (the writer then goes frame by frame)
    for odd_stamp in (1e-05, 1e16, float("nan"), float("-inf")):
        assert classic_frames_documents(
            (*stamps[:3], odd_stamp), ids[:4], extended[:4], dlcs[:4], datas[:4], channels[:4], directions[:4],  # type: ignore[arg-type]
        ) is None
    assert classic_frames_documents(stamps[:2], ids[:2], extended[:2], dlcs[:2], datas[:2], channels[:2],  # type: ignore[arg-type]
                                    ["tx", "up"]) is None


def _file_bytes(log: Callable[[McapFileWriter], None]) -> bytes:
    stream = io.BytesIO()
    writer = McapFileWriter(stream, config_yaml=None, fsync=False, compression="none")
    log(writer)
    writer.close()
    return stream.getvalue()


def test_frames_logged_as_columns_make_the_file_frame_by_frame_logging_makes() -> None:
    classic = _classic_frames(300, seed=13)
    for i, msg in enumerate(classic):
        msg.channel = "foilc-hil-embedded" if i % 2 else None
    odd = can.Message(arbitration_id=0x181, is_remote_frame=True, dlc=2, is_extended_id=False, channel=0)
    runs = [classic[:150], [*classic[150:200], odd, *classic[200:]]]  # a run of classic frames, then one with a rare
    rows = [[(frame_fields(m), "rx" if i % 3 else "tx", 1_000_000 + i) for i, m in enumerate(run)] for run in runs]

    def by_columns(writer: McapFileWriter) -> None:
        for run in rows:
            fields, directions, log_times = zip(*run, strict=True)
            writer.log_frames(fields, directions, log_times)

    def one_by_one(writer: McapFileWriter) -> None:
        for run in rows:
            for row in run:
                writer.log_frame_fields(*row)  # type: ignore[arg-type]

    assert _file_bytes(by_columns) == _file_bytes(one_by_one)


@pytest.mark.parametrize("stamp", ["1.0", None, True, b"\x00"])
def test_a_frame_whose_timestamp_is_not_a_number_is_refused(stamp: object) -> None:
    fields = (stamp, 0x181, False, 1, b"\x01",
              False, False, False, False, False, None)
    writer = McapFileWriter(io.BytesIO(), config_yaml=None, fsync=False)
    with pytest.raises(TypeError, match=f"timestamp must be a number, not {type(stamp).__name__}"):
        writer.log_frames([fields], ["tx"], [1])
    writer.close()
