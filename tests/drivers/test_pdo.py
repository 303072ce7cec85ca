"""PDO codecs: struct layouts from a mapping, round trips, DLC checks; layouts' object indices."""

from __future__ import annotations

import struct

import can
import pytest
from hypothesis import given
from hypothesis import strategies as st

from drivers.pdo import MappedVariable, PdoCodec, PdoDirection, PdoLayout, data_frame
from foilc_hil.errors import ProtocolError

CONTROLWORD = MappedVariable(0x6040, 0, 16, signed=False)
TARGET_VELOCITY = MappedVariable(0x60FF, 0, 32, signed=True)
TARGET_TORQUE = MappedVariable(0x6071, 0, 16, signed=True)
MODE = MappedVariable(0x6060, 0, 8, signed=True)


def test_mapping_entry_round_trip() -> None:
    assert CONTROLWORD.mapping_entry == 0x60400010
    assert TARGET_VELOCITY.mapping_entry == 0x60FF0020
    assert MappedVariable.from_entry(0x60FF0020, signed=True) == TARGET_VELOCITY


def test_encode_is_little_endian_in_mapping_order() -> None:
    codec = PdoCodec([CONTROLWORD, TARGET_VELOCITY])
    assert codec.size == 6
    # independent truth: CiA 301 byte order written out by hand
    assert codec.encode(0x000F, -2) == bytes([0x0F, 0x00, 0xFE, 0xFF, 0xFF, 0xFF])
    assert codec.decode(bytes([0x37, 0x02, 0xE8, 0x03, 0x00, 0x00])) == (0x0237, 1000)


def test_mapping_longer_than_a_frame_is_rejected() -> None:
    with pytest.raises(ProtocolError, match="9 bytes"):
        PdoCodec([CONTROLWORD, TARGET_VELOCITY, TARGET_TORQUE, MODE], "RPDO1")


@given(st.integers(0, 0xFFFF), st.integers(-(2**31), 2**31 - 1), st.integers(-(2**15), 2**15 - 1))
def test_round_trip_fits_a_frame(controlword: int, velocity: int, torque: int) -> None:
    codec = PdoCodec([CONTROLWORD, TARGET_VELOCITY, TARGET_TORQUE])
    data = codec.encode(controlword, velocity, torque)
    assert len(data) == 8
    assert codec.decode(data) == (controlword, velocity, torque)
    assert struct.unpack("<Hih", data) == (controlword, velocity, torque)


@pytest.mark.parametrize("length", [0, 5, 7, 8])
def test_wrong_dlc_is_a_protocol_error(length: int) -> None:
    codec = PdoCodec([CONTROLWORD, TARGET_VELOCITY], "TPDO1 (0x185)")
    with pytest.raises(ProtocolError, match=rf"TPDO1 \(0x185\): DLC {length} does not match the mapped length 6"):
        codec.decode(bytes(length))


def test_out_of_range_value_is_a_protocol_error() -> None:
    codec = PdoCodec([CONTROLWORD], "RPDO1")
    with pytest.raises(ProtocolError, match="RPDO1: cannot encode"):
        codec.encode(0x1_0000)


def test_unsupported_sizes_and_empty_mappings() -> None:
    with pytest.raises(ProtocolError, match="24-bit"):
        MappedVariable(0x2000, 0, 24, signed=False)
    with pytest.raises(ProtocolError, match="at least one object"):
        PdoCodec([])


def test_limits_follow_the_type() -> None:
    assert (TARGET_TORQUE.minimum, TARGET_TORQUE.maximum) == (-32768, 32767)
    assert (CONTROLWORD.minimum, CONTROLWORD.maximum) == (0, 65535)


def test_layout_indices() -> None:
    rpdo2 = PdoLayout(PdoDirection.RPDO, 2, 0x305, (CONTROLWORD, TARGET_TORQUE))
    tpdo4 = PdoLayout(PdoDirection.TPDO, 4, 0x485, (CONTROLWORD,))
    assert (rpdo2.communication_index, rpdo2.mapping_index) == (0x1401, 0x1601)
    assert (tpdo4.communication_index, tpdo4.mapping_index) == (0x1803, 0x1A03)
    assert rpdo2.name == "RPDO2 (0x305)"
    assert rpdo2.codec().encode(6, -1) == b"\x06\x00\xff\xff"


def test_data_frame_is_the_message_python_can_would_build() -> None:
    built = data_frame(0x201, b"\x0f\x00\x10\x27\x00\x00")
    reference = can.Message(arbitration_id=0x201, data=b"\x0f\x00\x10\x27\x00\x00", is_extended_id=False)
    for name in set(can.Message.__slots__) - {"__weakref__"}:
        assert getattr(built, name) == getattr(reference, name), name  # an unset slot raises AttributeError here
    assert isinstance(built.data, bytearray) and built.equals(reference)
