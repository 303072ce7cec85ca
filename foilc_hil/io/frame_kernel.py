"""A compiled kernel that writes a batch of classic CAN frames as MCAP ``Message`` records with their ``/can`` JSON.

What :func:`foilc_hil.io.mcap_writer.frame_json` and ``ChunkedMcapWriter.add_message`` do per frame in Python (about
30 operations), done for a whole batch in one numba loop: the JSON text of each frame (its timestamp as the text
Python's ``repr`` gives, computed by the caller; the identifier and DLC in decimal; the payload in base64), then the
record's header (opcode 0x05, record length, channel, sequence, log and publish times; MCAP specification,
"Message"), and each record's offset for the chunk's message index. ``cache=True``: compiled once per machine, not
per process.
"""

from __future__ import annotations

import numba
import numpy as np

__all__ = ["encode_frames"]

_B64 = np.frombuffer(b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/", dtype=np.uint8)
_TIMESTAMP = np.frombuffer(b'{"timestamp":', dtype=np.uint8)
_ID = np.frombuffer(b',"id":', dtype=np.uint8)
_EXTENDED = np.frombuffer(b',"extended":', dtype=np.uint8)
_TRUE = np.frombuffer(b"true", dtype=np.uint8)
_FALSE = np.frombuffer(b"false", dtype=np.uint8)
_DLC = np.frombuffer(b',"dlc":', dtype=np.uint8)
_DATA = np.frombuffer(b',"data":"', dtype=np.uint8)
_TX = np.frombuffer(b'","dir":"tx"}', dtype=np.uint8)
_RX = np.frombuffer(b'","dir":"rx"}', dtype=np.uint8)
_MESSAGE_OPCODE = 0x05
_HEADER = 1 + 8 + 2 + 4 + 8 + 8  # opcode, record length, channel, sequence, log time, publish time
_FIELDS = _HEADER - 9  # the record length counts what follows the opcode and the length itself

#: bytes of one frame's record besides its timestamp text and payload: header, the constant JSON text, an identifier
#: and a DLC of up to 20 digits each, the base64 padding
FIXED_BYTES = _HEADER + 13 + 6 + 12 + 5 + 7 + 9 + 13 + 2 * 20 + 4


@numba.njit(cache=True, nogil=True)
def _put(out: np.ndarray, at: int, text: np.ndarray) -> int:
    for k in range(text.size):
        out[at + k] = text[k]
    return at + text.size


@numba.njit(cache=True, nogil=True)
def _put_decimal(out: np.ndarray, at: int, value: int) -> int:
    if value == 0:
        out[at] = 48
        return at + 1
    digits = 0
    rest = value
    while rest > 0:
        digits += 1
        rest //= 10
    for k in range(digits - 1, -1, -1):
        out[at + k] = 48 + value % 10
        value //= 10
    return at + digits


@numba.njit(cache=True, nogil=True)
def _put_le(out: np.ndarray, at: int, value: int, size: int) -> int:
    for k in range(size):
        out[at + k] = (value >> (8 * k)) & 0xFF
    return at + size


@numba.njit(cache=True, nogil=True)
def _put_base64(out: np.ndarray, at: int, data: np.ndarray, start: int, end: int) -> int:
    k = start
    while k + 3 <= end:
        chunk = (int(data[k]) << 16) | (int(data[k + 1]) << 8) | int(data[k + 2])
        out[at] = _B64[chunk >> 18]
        out[at + 1] = _B64[(chunk >> 12) & 63]
        out[at + 2] = _B64[(chunk >> 6) & 63]
        out[at + 3] = _B64[chunk & 63]
        at += 4
        k += 3
    left = end - k
    if left == 1:
        chunk = int(data[k]) << 16
        out[at] = _B64[chunk >> 18]
        out[at + 1] = _B64[(chunk >> 12) & 63]
        out[at + 2] = 61
        out[at + 3] = 61
        at += 4
    elif left == 2:
        chunk = (int(data[k]) << 16) | (int(data[k + 1]) << 8)
        out[at] = _B64[chunk >> 18]
        out[at + 1] = _B64[(chunk >> 12) & 63]
        out[at + 2] = _B64[(chunk >> 6) & 63]
        out[at + 3] = 61
        at += 4
    return at


@numba.njit(cache=True, nogil=True)
def encode_frames(
    texts: np.ndarray,
    text_ends: np.ndarray,
    ids: np.ndarray,
    extended: np.ndarray,
    dlcs: np.ndarray,
    payload: np.ndarray,
    payload_ends: np.ndarray,
    sent: np.ndarray,
    log_times: np.ndarray,
    publish_times: np.ndarray,
    channel_id: int,
    sequence: int,
    out: np.ndarray,
    offsets: np.ndarray,
) -> int:
    """Write the records of ``ids.size`` frames into ``out`` (large enough: :data:`FIXED_BYTES` a frame plus the
    texts and twice the payload); ``offsets[i]`` gets record ``i``'s offset. The bytes written.

    Frame ``i``: timestamp text ``texts[text_ends[i - 1]:text_ends[i]]``, payload
    ``payload[payload_ends[i - 1]:payload_ends[i]]``, ``sent[i]``: ``"dir": "tx"`` (else ``"rx"``); its sequence
    number is ``sequence + i`` modulo 2**32.
    """
    at = 0
    text_start = 0
    payload_start = 0
    for i in range(ids.size):
        offsets[i] = at
        body = at + _HEADER
        end = _put(out, body, _TIMESTAMP)
        end = _put(out, end, texts[text_start : text_ends[i]])
        end = _put(out, end, _ID)
        end = _put_decimal(out, end, ids[i])
        end = _put(out, end, _EXTENDED)
        end = _put(out, end, _TRUE if extended[i] else _FALSE)
        end = _put(out, end, _DLC)
        end = _put_decimal(out, end, dlcs[i])
        end = _put(out, end, _DATA)
        end = _put_base64(out, end, payload, payload_start, payload_ends[i])
        end = _put(out, end, _TX if sent[i] else _RX)
        out[at] = _MESSAGE_OPCODE
        header = _put_le(out, at + 1, end - body + _FIELDS, 8)
        header = _put_le(out, header, channel_id, 2)
        header = _put_le(out, header, (sequence + i) & 0xFFFFFFFF, 4)
        header = _put_le(out, header, log_times[i], 8)
        _put_le(out, header, publish_times[i], 8)
        text_start = text_ends[i]
        payload_start = payload_ends[i]
        at = end
    return at
