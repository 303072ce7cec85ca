"""The virtual drive's SDO server, NMT slave and PDO configuration, seen from a plain canopen master."""

from __future__ import annotations

import struct
import time

import pytest
from canopen.sdo import SdoAbortedError, SdoCommunicationError

from drivers.cia301 import CobIdEntry, FunctionCode, NmtCommand, NmtState, SdoAbortCode, cob_id
from drivers.cia402 import Obj, State402
from tests.support.emulator_harness import NODE_ID, Harness

pytestmark = pytest.mark.timeout(60)


def _abort_code(excinfo: pytest.ExceptionInfo[SdoAbortedError]) -> int:
    return int(excinfo.value.code)


def test_expedited_write_and_read_back() -> None:
    with Harness() as h:
        h.node.sdo[Obj.PROFILE_ACCELERATION].raw = 123456
        assert h.node.sdo[Obj.PROFILE_ACCELERATION].raw == 123456
        assert h.node.sdo[Obj.DEVICE_TYPE].raw == 0x00020192  # EDS default, expedited 4-byte upload


def test_segmented_upload_and_download() -> None:
    with Harness() as h:
        assert h.node.sdo.upload(0x1008, 0) == b"FOILC servo"  # 11 bytes: segmented upload
        payload = struct.pack("<I", 7654321)
        h.node.sdo.download(Obj.PROFILE_DECELERATION, 0, payload, force_segment=True)  # segmented download
        assert h.node.sdo[Obj.PROFILE_DECELERATION].raw == 7654321


@pytest.mark.parametrize(
    ("index", "subindex", "value", "expected"),
    [
        pytest.param(0x2FFF, 0, None, SdoAbortCode.NO_OBJECT, id="unknown-object-read"),
        pytest.param(0x2FFF, 0, b"\x01\x00", SdoAbortCode.NO_OBJECT, id="unknown-object-write"),
        pytest.param(0x1018, 9, None, SdoAbortCode.NO_SUBINDEX, id="unknown-subindex"),
        pytest.param(0x2000, 0, struct.pack("<I", 5), SdoAbortCode.READ_ONLY, id="read-only-manufacturer"),
        pytest.param(Obj.STATUSWORD, 0, struct.pack("<H", 5), SdoAbortCode.READ_ONLY, id="read-only-statusword"),
        pytest.param(0x2001, 0, struct.pack("<H", 0), SdoAbortCode.VALUE_TOO_LOW, id="below-low-limit"),
        pytest.param(0x2001, 0, struct.pack("<H", 10001), SdoAbortCode.VALUE_TOO_HIGH, id="above-high-limit"),
        pytest.param(Obj.MODES_OF_OPERATION, 0, struct.pack("<b", 5), SdoAbortCode.INVALID_VALUE,
                     id="unsupported-mode"),
        pytest.param(Obj.MODES_OF_OPERATION, 0, struct.pack("<b", 11), SdoAbortCode.VALUE_TOO_HIGH,
                     id="mode-above-limit"),
        pytest.param(Obj.CONTROLWORD, 0, b"\x06", SdoAbortCode.LENGTH_MISMATCH, id="wrong-length"),
        pytest.param(0x1600, 1, struct.pack("<I", 0x20010010), SdoAbortCode.CANNOT_MAP, id="non-mappable"),
        pytest.param(0x1600, 1, struct.pack("<I", 0x60410010), SdoAbortCode.CANNOT_MAP,
                     id="read-only-into-rpdo"),
        pytest.param(0x1A00, 1, struct.pack("<I", 0x2FFF0010), SdoAbortCode.NO_OBJECT, id="map-unknown-object"),
    ],
)
def test_abort_codes(index: int, subindex: int, value: bytes | None, expected: int) -> None:
    with Harness() as h:
        with pytest.raises(SdoAbortedError) as excinfo:
            if value is None:
                h.node.sdo.upload(index, subindex)
            else:
                h.node.sdo.download(index, subindex, value)
        assert _abort_code(excinfo) == expected
        if value is not None and index in h.drive.od:  # an aborted write leaves the old value
            assert h.node.sdo.upload(index, subindex) != value or expected == SdoAbortCode.NO_SUBINDEX


def test_pdo_too_long_is_refused() -> None:
    with Harness() as h:
        mapping = 0x1A00
        h.node.sdo.download(mapping, 0, b"\x00")
        for sub, entry in enumerate((0x606C0020, 0x60640020, 0x60410010), start=1):
            h.node.sdo.download(mapping, sub, struct.pack("<I", entry))
        with pytest.raises(SdoAbortedError) as excinfo:
            h.node.sdo.download(mapping, 0, b"\x03")  # 80 bits
        assert _abort_code(excinfo) == SdoAbortCode.PDO_TOO_LONG


def _remap(h: Harness, communication: int, mapping: int, entries: list[int], transmission_type: int) -> None:
    """The CiA 301 remapping procedure: invalidate the PDO, zero the count, write entries, count, re-validate."""
    cob = CobIdEntry.decode(h.node.sdo[communication][1].raw).can_id
    h.node.sdo[communication][1].raw = CobIdEntry(cob, valid=False).encode()
    h.node.sdo[communication][2].raw = transmission_type
    h.node.sdo.download(mapping, 0, b"\x00")
    for sub, entry in enumerate(entries, start=1):
        h.node.sdo.download(mapping, sub, struct.pack("<I", entry))
    h.node.sdo.download(mapping, 0, bytes([len(entries)]))
    h.node.sdo[communication][1].raw = cob


def test_pdo_remap_over_sdo_changes_the_traffic() -> None:
    """The master remaps TPDO1 and RPDO1 over SDO; the frames follow the new maps and transmission type."""
    with Harness() as h:
        # statusword, mode display, torque actual; every second SYNC
        _remap(h, 0x1800, 0x1A00, [0x60410010, 0x60610008, 0x60770010], transmission_type=2)
        _remap(h, 0x1400, 0x1600, [0x60400010, 0x60600008], transmission_type=1)  # controlword + mode
        assert h.node.sdo.upload(0x1A00, 0) == b"\x03"

        h.start()
        h.send(h.rpdo1, struct.pack("<Hb", 0x0006, 10))  # shutdown + CST, applied at the next SYNC
        h.sync()
        h.sync(wait_for=h.tpdo1)  # type 2: the second SYNC sends
        frames = h.recorder.wait_count(h.tpdo1, 1)
        assert len(frames) == 1  # nothing on the first SYNC
        statusword, mode, torque = struct.unpack("<HbH", frames[-1])
        assert len(frames[-1]) == 5
        assert mode == 10 and torque == 0
        assert statusword & 0x6F == 0x21  # ready to switch on
        h.sync()
        assert h.recorder.count(h.tpdo1) == 1
        h.sync(wait_for=h.tpdo1)
        assert h.recorder.count(h.tpdo1) == 2


def test_rpdo_values_take_effect_at_the_next_sync() -> None:
    with Harness() as h:
        h.start()
        h.send(h.rpdo1, struct.pack("<Hi", 0x0006, 0))
        time.sleep(0.1)
        h.node.sdo.upload(0x1000, 0)  # the RPDO has certainly been received by now
        assert h.drive.state is State402.SWITCH_ON_DISABLED
        h.sync(wait_for=h.tpdo1)
        assert h.drive.state is State402.READY_TO_SWITCH_ON
        statusword = struct.unpack_from("<H", h.recorder.frames[h.tpdo1][-1])[0]
        assert statusword & 0x6F == 0x21  # the TPDO of that SYNC already shows it


def test_event_driven_and_acyclic_tpdos() -> None:
    with Harness() as h:
        h.node.sdo[0x1800][1].raw = CobIdEntry(h.tpdo1, valid=False).encode()  # disable while changing the type
        h.node.sdo[0x1800][2].raw = 255
        h.node.sdo[0x1800][1].raw = h.tpdo1
        h.node.sdo[0x1801][2].raw = 0  # TPDO2 acyclic synchronous: on SYNC, only when changed
        h.start()
        tpdo2 = cob_id(FunctionCode.TPDO2, NODE_ID)
        h.sync(wait_for=tpdo2)  # first SYNC: TPDO2 content is new
        h.sync()
        h.sync()
        assert h.recorder.count(tpdo2) == 1  # unchanged afterwards: not sent again
        before = h.recorder.count(h.tpdo1)
        h.node.sdo[Obj.CONTROLWORD].raw = 0x0006  # a state change is an event
        frames = h.recorder.wait_count(h.tpdo1, before + 1)
        assert struct.unpack_from("<H", frames[-1])[0] & 0x6F == 0x21


def test_nmt_reset_node_restores_defaults_and_boots() -> None:
    with Harness() as h:
        heartbeat = cob_id(FunctionCode.HEARTBEAT, NODE_ID)
        h.node.sdo[Obj.PROFILE_ACCELERATION].raw = 42
        h.node.sdo[Obj.PRODUCER_HEARTBEAT_TIME].raw = 500
        h.node.sdo[Obj.CONTROLWORD].raw = 0x0006
        assert h.drive.state is State402.READY_TO_SWITCH_ON
        boots = h.recorder.frames[heartbeat].count(b"\x00")
        h.nmt(NmtCommand.RESET_COMMUNICATION)
        assert h.node.sdo[Obj.PRODUCER_HEARTBEAT_TIME].raw == 1000  # communication area back to the EDS
        assert h.node.sdo[Obj.PROFILE_ACCELERATION].raw == 42  # application area kept
        assert h.drive.state is State402.READY_TO_SWITCH_ON
        h.nmt(NmtCommand.RESET_NODE)
        assert h.node.sdo[Obj.PROFILE_ACCELERATION].raw == 10000000  # everything back to the EDS
        assert h.drive.state is State402.SWITCH_ON_DISABLED
        assert h.drive.nmt_state is NmtState.PRE_OPERATIONAL
        assert h.recorder.frames[heartbeat].count(b"\x00") == boots + 2  # a boot-up message per reset


@pytest.mark.slow
def test_nmt_states_gate_pdo_and_sdo() -> None:
    with Harness() as h:
        h.sync()  # pre-operational: no PDO
        assert h.recorder.count(h.tpdo1) == 0
        h.start()
        assert h.drive.nmt_state is NmtState.OPERATIONAL
        h.sync(wait_for=h.tpdo1)
        h.nmt(NmtCommand.STOP)
        assert h.drive.nmt_state is NmtState.STOPPED
        h.node.sdo.RESPONSE_TIMEOUT = 0.2
        with pytest.raises(SdoCommunicationError):
            h.node.sdo.upload(0x1000, 0)  # no SDO in stopped
        h.nmt(NmtCommand.ENTER_PRE_OPERATIONAL)
        assert h.node.sdo[Obj.DEVICE_TYPE].raw == 0x00020192


@pytest.mark.slow
def test_heartbeat_producer_follows_0x1017() -> None:
    with Harness() as h:
        heartbeat = cob_id(FunctionCode.HEARTBEAT, NODE_ID)
        h.node.sdo[Obj.PRODUCER_HEARTBEAT_TIME].raw = 20
        start = h.recorder.count(heartbeat)
        time.sleep(0.5)
        beats = h.recorder.count(heartbeat) - start
        assert 10 <= beats <= 40  # about 25 at 20 ms; loose bounds: shared CI machine
        assert h.recorder.frames[heartbeat][-1] == bytes([NmtState.PRE_OPERATIONAL])
        h.start()
        time.sleep(0.1)
        assert h.recorder.frames[heartbeat][-1] == bytes([NmtState.OPERATIONAL])
        h.node.sdo[Obj.PRODUCER_HEARTBEAT_TIME].raw = 0
        time.sleep(0.05)
        stopped_at = h.recorder.count(heartbeat)
        time.sleep(0.2)
        assert h.recorder.count(heartbeat) == stopped_at


def test_canopen_pdo_save_remaps_the_drive() -> None:
    """canopen's own PdoMap.save() (an independent master's remapping code) works on the shipped EDS.

    It needs the mapping objects 0x1600.. / 0x1A00.. declared as RECORDs (CiA 306); as ARRAYs canopen zeroes
    sub-index 0, reads it back to count the entries and writes none.
    """
    with Harness() as h:
        h.node.tpdo.read()
        tpdo1 = h.node.tpdo[1]
        tpdo1.clear()
        tpdo1.add_variable(0x6041)
        tpdo1.add_variable(0x6061)
        tpdo1.trans_type = 1
        tpdo1.enabled = True
        tpdo1.save()
        assert h.node.sdo.upload(0x1A00, 0) == b"\x02"
        assert h.node.sdo.upload(0x1A00, 2) == struct.pack("<I", 0x60610008)

        h.start()
        h.sync(wait_for=h.tpdo1)
        frame = h.recorder.wait_count(h.tpdo1, 1)[-1]
        assert len(frame) == 3  # statusword (2 bytes) + mode display (1 byte)
