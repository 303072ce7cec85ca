"""The exact bits of classical CAN frames on the wire (CRC-15 computed, stuff bits inserted), and the load a log
shows: the benchmark's measure of a run's bus load (``benchmarks/bench_axes.py``) and the tests' oracle of the
worst-case bound the product plans with (:func:`drivers.busload.worst_case_bits`). Not product code: the product
plans on the worst case, because a frame's payload (and so its stuffing) is not known in advance.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence

import can

__all__ = ["crc15", "measured_load", "stuffed_bits", "wire_bits"]

_UNSTUFFED_TAIL = 13  # CRC delimiter 1 + ACK 2 + EOF 7 + interframe space 3
_CRC15_POLY = 0x4599  # x^15 + x^14 + x^10 + x^8 + x^7 + x^4 + x^3 + 1
_STUFF_RUN = 5


def crc15(bits: Sequence[int]) -> int:
    """The CAN CRC-15 of a bit sequence (SOF through the last data bit), as ISO 11898-1 computes it."""
    crc = 0
    for bit in bits:
        feedback = bit ^ ((crc >> 14) & 1)
        crc = (crc << 1) & 0x7FFF
        if feedback:
            crc ^= _CRC15_POLY
    return crc


def _bits(value: int, width: int) -> list[int]:
    return [(value >> shift) & 1 for shift in range(width - 1, -1, -1)]


def _stuffed_section(msg: can.Message) -> list[int]:
    """SOF through CRC of a classical frame, before stuffing (dominant = 0)."""
    dlc = msg.dlc
    remote = 1 if msg.is_remote_frame else 0
    if msg.is_extended_id:
        head = [0, *_bits(msg.arbitration_id >> 18, 11), 1, 1, *_bits(msg.arbitration_id & 0x3FFFF, 18), remote,
                0, 0]
    else:
        head = [0, *_bits(msg.arbitration_id, 11), remote, 0, 0]
    head += _bits(dlc, 4)
    if not msg.is_remote_frame:
        for byte in bytes(msg.data)[:dlc]:
            head += _bits(byte, 8)
    return head + _bits(crc15(head), 15)


def stuffed_bits(msg: can.Message) -> list[int]:
    """SOF through CRC of one classical frame as sent: a stuff bit of the opposite value after five equal bits.

    Raises
    ------
    ValueError
        For CAN FD and error frames, which this classical model does not describe.
    """
    if msg.is_fd or msg.is_error_frame:
        raise ValueError("the classical frame model describes data and remote frames only")
    out: list[int] = []
    run_value, run_length = -1, 0
    for bit in _stuffed_section(msg):
        out.append(bit)
        if bit == run_value:
            run_length += 1
        else:
            run_value, run_length = bit, 1
        if run_length == _STUFF_RUN:
            # the stuff bit has the opposite value and starts the next run
            out.append(1 - bit)
            run_value, run_length = 1 - bit, 1
    return out


def wire_bits(msg: can.Message) -> int:
    """Exact length on the wire, in bits, of one classical frame (stuff bits and interframe space included)."""
    return len(stuffed_bits(msg)) + _UNSTUFFED_TAIL




def measured_load(messages: Iterable[can.Message], *, bitrate: int) -> float:
    """The load a log shows: exact wire bits of its classical frames over the span of their timestamps.

    Frames the classical model does not describe (FD, error frames) are left out. Returns 0.0 for fewer than two
    frames (no span to divide by).
    """
    timed = sorted((msg.timestamp, wire_bits(msg)) for msg in messages if not (msg.is_fd or msg.is_error_frame))
    if len(timed) < 2 or timed[-1][0] <= timed[0][0]:
        return 0.0
    # the span runs from the first frame's start to the last frame's start: the last frame's bits lie outside it
    return sum(bits for _, bits in timed[:-1]) / (bitrate * (timed[-1][0] - timed[0][0]))
