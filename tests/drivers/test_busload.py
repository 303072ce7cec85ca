"""Bus load: the CRC, bit stuffing and worst-case frame lengths against independent truths."""

from __future__ import annotations

import can
import pytest
from hypothesis import given
from hypothesis import strategies as st

from benchmarks.can_wire import crc15, measured_load, stuffed_bits, wire_bits
from drivers.busload import CyclicFrame, schedule_load, worst_case_bits
from foilc_hil.errors import ConfigError
from tests.support.fuzz_settings import fuzz_settings


def _destuff(bits: list[int]) -> list[int]:
    """A receiver's de-stuffing, written independently of the sender: drop the bit after five equal bits."""
    out: list[int] = []
    previous, run, skip = -1, 0, False
    for bit in bits:
        if skip:
            assert bit != previous, "a stuff bit must have the opposite value"
            previous, run, skip = bit, 1, False
            continue
        run = run + 1 if bit == previous else 1
        previous = bit
        out.append(bit)
        skip = run == 5
    return out


frames = st.builds(
    can.Message,
    arbitration_id=st.integers(0, 0x7FF),
    data=st.binary(min_size=0, max_size=8),
    is_extended_id=st.just(False),
) | st.builds(
    can.Message,
    arbitration_id=st.integers(0, 0x1FFFFFFF),
    data=st.binary(min_size=0, max_size=8),
    is_extended_id=st.just(True),
)


def test_crc15_check_value() -> None:
    # CRC-15/CAN of the ASCII string "123456789" is 0x059E in the CRC catalogue (check value of the algorithm)
    bits = [(byte >> shift) & 1 for byte in b"123456789" for shift in range(7, -1, -1)]
    assert crc15(bits) == 0x059E


def test_all_dominant_frame_is_counted_by_hand() -> None:
    # ID 0, no data: SOF, 11 ID bits, RTR, IDE, r0 and DLC are 19 zeros and the CRC of zeros is zero, so 34 zeros.
    # A stuff bit follows every fifth zero (each stuff bit '1' ends the run): after bits 5, 10, ..., 30 -> 6 stuff
    # bits. 34 + 6 + 13 (CRC delimiter, ACK, EOF, interframe space) = 53.
    assert wire_bits(can.Message(arbitration_id=0, data=b"", is_extended_id=False)) == 53


@pytest.mark.parametrize("size", range(9))
def test_worst_case_matches_the_closed_forms(size: int) -> None:
    # the closed forms of Davis et al. (2007): 55 + 10 s bits for 11-bit identifiers, 80 + 10 s for 29-bit ones
    assert worst_case_bits(size) == 55 + 10 * size
    assert worst_case_bits(size, extended=True) == 80 + 10 * size


@fuzz_settings(200)
@given(frames)
def test_stuffing_round_trips_and_respects_the_bound(msg: can.Message) -> None:
    sent = stuffed_bits(msg)
    for index in range(len(sent) - 5):
        assert len(set(sent[index:index + 6])) == 2, "six equal bits in a row on the wire"
    section = _destuff(sent)
    crc_free = section[:-15]
    # appending a CRC makes the remainder of the whole section zero
    assert crc15(section) == 0
    assert crc15(crc_free) == int("".join(map(str, section[-15:])), 2)
    overhead = 54 if msg.is_extended_id else 34
    assert len(section) == overhead + 8 * len(msg.data)
    assert wire_bits(msg) <= worst_case_bits(len(msg.data), extended=msg.is_extended_id)


def test_four_axes_at_one_kilohertz_do_not_fit_classical_can() -> None:
    # per axis an 8-byte RPDO and two 8-byte TPDOs (135 bits each), one SYNC (55 bits) for all: 4 * 405 + 55 = 1675
    axes = [CyclicFrame(f"{kind} axis {axis}", 8) for axis in range(1, 5) for kind in ("RPDO1", "TPDO1", "TPDO2")]
    load = schedule_load([CyclicFrame("SYNC", 0), *axes], bitrate=1_000_000, period=0.001)
    assert load.bits_per_cycle == 1675
    assert load.load == pytest.approx(1.675)
    assert not load.fits
    with pytest.raises(ConfigError) as caught:
        load.check(key="sample_time")
    text = str(caught.value)
    assert "sample_time" in text and "167.5%" in text and "2.393 ms" in text
    widened = schedule_load(load.frames, bitrate=load.bitrate, period=load.min_period, limit=load.limit)
    assert widened.load == pytest.approx(load.limit)
    assert widened.check() is widened


def test_one_axis_fits() -> None:
    load = schedule_load([CyclicFrame("SYNC", 0), CyclicFrame("RPDO1", 6), CyclicFrame("TPDO1", 6)],
                         bitrate=1_000_000, period=0.001)
    assert load.fits and load.bits_per_cycle == 55 + 2 * 115


def test_measured_load_of_a_synthetic_log() -> None:
    messages = [can.Message(timestamp=k * 0.001, arbitration_id=0x181, data=bytes([k % 256] * 8),
                            is_extended_id=False) for k in range(101)]
    expected = sum(wire_bits(m) for m in messages[:-1]) / (1_000_000 * 0.1)
    assert measured_load(messages, bitrate=1_000_000) == pytest.approx(expected)
    assert 0.111 <= measured_load(messages, bitrate=1_000_000) <= 0.135
    assert measured_load(messages[:1], bitrate=1_000_000) == 0.0


def test_fd_frames_are_outside_the_classical_model() -> None:
    with pytest.raises(ValueError, match="classical"):
        wire_bits(can.Message(arbitration_id=1, data=bytes(12), is_fd=True))
