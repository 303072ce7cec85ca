"""CiA 301 codecs of :mod:`drivers.cia301` and :mod:`drivers.pdo`: one encoder/decoder per entry kind."""

from __future__ import annotations

import pytest

from drivers.cia301 import (
    SYNC_COB_ID,
    CobIdEntry,
    FunctionCode,
    HeartbeatConsumerEntry,
    NmtState,
    cob_id,
    heartbeat_state,
    split_cob_id,
)
from drivers.pdo import PDO_DISABLED, MappedVariable, MappingEntry
from foilc_hil.errors import ProtocolError


def test_function_codes_are_unique_and_emcy_is_a_member() -> None:
    assert FunctionCode.EMCY.name == "EMCY"
    assert "EMCY" in [code.name for code in FunctionCode]
    assert len({int(code) for code in FunctionCode}) == len(FunctionCode)  # no alias hides a member
    assert cob_id(FunctionCode.EMCY, 5) == 0x085
    assert SYNC_COB_ID == 0x080 and SYNC_COB_ID not in (cob_id(FunctionCode.EMCY, n) for n in range(1, 128))


@pytest.mark.parametrize(("node", "millis"), [(127, 200), (1, 1), (64, 0xFFFF), (0, 0)])
def test_heartbeat_consumer_entry_round_trips(node: int, millis: int) -> None:
    value = HeartbeatConsumerEntry(node, millis).encode()
    assert value & 0xFFFF == millis and value >> 16 == node  # CiA 301 layout: node id in bits 16..23
    assert HeartbeatConsumerEntry.decode(value) == HeartbeatConsumerEntry(node, millis)
    assert HeartbeatConsumerEntry.decode(value).active is (node != 0 and millis != 0)


def test_heartbeat_consumer_entry_ignores_reserved_bits_and_rejects_out_of_range() -> None:
    assert HeartbeatConsumerEntry.decode(0xAB_05_012C) == HeartbeatConsumerEntry(5, 300)
    with pytest.raises(ProtocolError):
        HeartbeatConsumerEntry(128, 100).encode()
    with pytest.raises(ProtocolError):
        HeartbeatConsumerEntry(1, 0x10000).encode()


def test_cob_id_entry_round_trips_and_reads_the_invalid_bit() -> None:
    assert CobIdEntry(0x185).encode() == 0x185
    assert CobIdEntry(0x185, valid=False).encode() == 0x185 | PDO_DISABLED
    assert CobIdEntry.decode(0x185 | PDO_DISABLED) == CobIdEntry(0x185, valid=False)
    assert CobIdEntry.decode(0x4000_0205) == CobIdEntry(0x205)  # bit 30 (RTR / SYNC producer) is not ours
    with pytest.raises(ProtocolError):
        CobIdEntry(0x800).encode()


def test_mapping_entry_is_the_codec_behind_mapped_variable() -> None:
    entry = MappingEntry.decode(0x60410010)
    assert entry == MappingEntry(0x6041, 0x00, 16)
    assert entry.encode() == 0x60410010
    assert MappingEntry.decode(0x1A000118) == MappingEntry(0x1A00, 0x01, 24)  # no size check: a device judges
    variable = MappedVariable.from_entry(0x606C0020, signed=True)
    assert (variable.index, variable.subindex, variable.bits) == (0x606C, 0, 32)
    assert variable.mapping_entry == 0x606C0020


@pytest.mark.parametrize("function", [code for code in FunctionCode if code not in (FunctionCode.NMT,)])
@pytest.mark.parametrize("node", [1, 64, 127])
def test_split_cob_id_inverts_cob_id(function: FunctionCode, node: int) -> None:
    assert split_cob_id(cob_id(function, node)) == (function, node)


def test_heartbeat_state_drops_the_toggle_bit() -> None:
    assert heartbeat_state(0x80 | NmtState.OPERATIONAL) == NmtState.OPERATIONAL
    assert heartbeat_state(NmtState.PRE_OPERATIONAL) == NmtState.PRE_OPERATIONAL
    assert heartbeat_state(0x00) == NmtState.INITIALISING
