"""The /can documents written from templates (one frame) or by the compiled kernel (a batch, as MCAP records) are
orjson's text of the same document, byte for byte, in records laid out as the MCAP specification says; frames
neither covers are told apart."""

from __future__ import annotations

import binascii
import random
import struct
from pathlib import Path

import can
import orjson
import pytest

from foilc_hil.io.mcap_log import McapLogWriter, frame_fields, read_log
from foilc_hil.io.mcap_writer import Direction, classic_frames_records, frame_json


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


def test_a_batch_of_classic_frames_is_orjsons_text_in_mcap_records() -> None:
    frames = _classic_frames(500, seed=3)
    directions: list[Direction] = ["tx" if i % 3 else "rx" for i in range(len(frames))]
    log_times = [1_700_000_000_000_000_000 + 1000 * i for i in range(len(frames))]
    sequence = (1 << 32) - 200  # the sequence number wraps within the batch
    stamps, ids, extended, dlcs, datas = list(zip(*(frame_fields(m) for m in frames), strict=True))[:5]
    encoded = classic_frames_records(stamps, ids, extended, dlcs, datas, directions, log_times, 3, sequence)
    assert encoded is not None
    data, offsets = encoded
    stamps = [m.timestamp or log_time / 1e9 for m, log_time in zip(frames, log_times, strict=True)]  # type: ignore[assignment]
    assert _records(data) == [
        (offset, 3, (sequence + i) % (1 << 32), log_times[i], round(stamps[i] * 1e9), _document(m, stamps[i], d))
        for i, (offset, m, d) in enumerate(zip(offsets, frames, directions, strict=True))
    ]
    # one frame at a time: the same text
    texts = [frame_json(frame_fields(m), t, d) for m, t, d in zip(frames, stamps, directions, strict=True)]
    assert texts == [record[-1] for record in _records(data)]


def test_frames_the_kernel_does_not_cover_are_written_one_by_one(tmp_path: Path) -> None:
    classic = _classic_frames(3, seed=5)
    odd = [
        can.Message(arbitration_id=0x181, is_remote_frame=True, dlc=2, is_extended_id=False, timestamp=1.0),
        can.Message(arbitration_id=0x181, data=b"\x01", is_extended_id=False, timestamp=1.0, channel="vcan0"),
        can.Message(arbitration_id=0x181, data=b"\x01", is_extended_id=False, timestamp=1.0, channel=0),
        can.Message(arbitration_id=0x181, data=b"\x01", is_extended_id=False, timestamp=1e-05),  # exponent
        can.Message(arbitration_id=0x181, data=b"\x01", is_extended_id=False, timestamp=float("inf")),
    ]
    stamps, ids, extended, dlcs, datas = list(zip(*(frame_fields(m) for m in [*classic, odd[3]]), strict=True))[:5]
    # orjson's spelling of 1e-05: not the kernel's
    assert classic_frames_records(stamps, ids, extended, dlcs, datas, ["tx"] * 4, [1] * 4, 1, 0) is None
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
