"""The /can documents formatted from templates (one frame, or a batch in C loops) are orjson's text of the same
document, byte for byte; frames the templates do not cover are told apart."""

from __future__ import annotations

import binascii
import random

import can
import orjson

from foilc_hil.io.mcap_log import Direction, classic_frames_json, frame_fields, frame_json


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


def test_a_batch_of_classic_frames_is_orjsons_text() -> None:
    frames = _classic_frames(500, seed=3)
    directions: list[Direction] = ["tx" if i % 3 else "rx" for i in range(len(frames))]
    log_times = [1_700_000_000_000_000_000 + 1000 * i for i in range(len(frames))]
    encoded = classic_frames_json([frame_fields(m) for m in frames], directions, log_times)
    assert encoded is not None
    documents, publish_times = encoded
    stamps = [m.timestamp or log_time / 1e9 for m, log_time in zip(frames, log_times, strict=True)]
    assert documents == [_document(m, t, d) for m, t, d in zip(frames, stamps, directions, strict=True)]
    assert publish_times == [round(t * 1e9) for t in stamps]
    # one frame at a time: the same text
    assert [frame_json(frame_fields(m), t, d) for m, t, d in zip(frames, stamps, directions, strict=True)] == documents


def test_frames_the_templates_do_not_cover_fall_back() -> None:
    classic = _classic_frames(3, seed=5)
    odd = [
        can.Message(arbitration_id=0x181, is_remote_frame=True, dlc=2, is_extended_id=False, timestamp=1.0),
        can.Message(arbitration_id=0x181, data=b"\x01", is_extended_id=False, timestamp=1.0, channel="vcan0"),
        can.Message(arbitration_id=0x181, data=b"\x01", is_extended_id=False, timestamp=1e-05),  # exponent
        can.Message(arbitration_id=0x181, data=b"\x01", is_extended_id=False, timestamp=float("inf")),
    ]
    for msg in odd:
        batch = [*classic, msg]
        assert classic_frames_json([frame_fields(m) for m in batch], ["tx"] * 4, [1] * 4) is None
    # one by one, each is still orjson's text of its document (non-finite as null, the optional fields added)
    assert frame_json(frame_fields(odd[2]), 1e-05, "rx") == _document(odd[2], 1e-05, "rx")
    assert frame_json(frame_fields(odd[3]), float("inf"), "rx") == _document(odd[3], float("inf"), "rx")
    remote = orjson.loads(frame_json(frame_fields(odd[0]), 1.0, "tx"))
    assert remote["remote"] is True and "channel" not in remote
    assert orjson.loads(frame_json(frame_fields(odd[1]), 1.0, "tx"))["channel"] == "vcan0"
