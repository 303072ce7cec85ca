"""EDS loading: the shipped EDS is a consistent CiA 402 servo; broken or missing files name themselves."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from canopen.objectdictionary import ObjectDictionary, ODRecord, ODVariable, datatypes

from drivers.cia402 import SUPPORTED_MODE_BITS, Obj, OperationMode
from drivers.od import DEFAULT_EDS, MAX_EDS_BYTES, REQUIRED_OBJECTS, load_od, mapped_variable
from drivers.pdo import PDO_DISABLED, MappedVariable
from foilc_hil.errors import EdsError


def _var(od: ObjectDictionary, index: int, subindex: int = 0) -> ODVariable:
    variable = od.get_variable(index, subindex)
    assert isinstance(variable, ODVariable), f"0x{index:04X}:{subindex:02X} missing"
    return variable


def _default(od: ObjectDictionary, index: int, subindex: int = 0) -> int:
    value = _var(od, index, subindex).default
    assert isinstance(value, int)
    return value


def test_shipped_eds_loads_and_describes_a_402_servo() -> None:
    od = load_od(node_id=5)
    for index in REQUIRED_OBJECTS:
        assert index in od
    assert _var(od, Obj.DEVICE_TYPE).default == 0x00020192
    identity = od[Obj.IDENTITY]
    assert isinstance(identity, ODRecord) and all(sub in identity for sub in (1, 2, 3, 4))
    modes = _default(od, Obj.SUPPORTED_DRIVE_MODES)
    assert all(modes & SUPPORTED_MODE_BITS[mode] for mode in OperationMode)
    # limits where they matter
    assert (_var(od, Obj.MODES_OF_OPERATION).min, _var(od, Obj.MODES_OF_OPERATION).max) == (3, 10)
    assert (_var(od, Obj.QUICK_STOP_OPTION).min, _var(od, Obj.QUICK_STOP_OPTION).max) == (0, 8)
    assert _var(od, Obj.MODES_OF_OPERATION).data_type == datatypes.INTEGER8
    # PDO-mappable where the cyclic path needs it, and the two test objects
    assert _var(od, Obj.CONTROLWORD).pdo_mappable and _var(od, Obj.CONTROLWORD).writable
    assert _var(od, Obj.STATUSWORD).pdo_mappable and not _var(od, Obj.STATUSWORD).writable
    assert not _var(od, 0x2000).writable  # read-only manufacturer object
    assert _var(od, 0x2001).writable and not _var(od, 0x2001).pdo_mappable
    # consumer heartbeat is an array with at least one entry
    assert _var(od, Obj.CONSUMER_HEARTBEAT_TIME, 1).data_type == datatypes.UNSIGNED32


def test_default_pdos_match_the_documented_layout() -> None:
    od = load_od(node_id=5)

    def mapping(index: int) -> list[int]:
        count = _default(od, index, 0)
        return [_default(od, index, sub) for sub in range(1, count + 1)]

    assert mapping(0x1600) == [0x60400010, 0x60FF0020]
    assert mapping(0x1601) == [0x60400010, 0x60710010]
    assert mapping(0x1A00) == [0x60410010, 0x606C0020]
    assert mapping(0x1A01) == [0x60770010, 0x60640020]
    assert _var(od, 0x1800, 1).default == 0x185  # $NODEID resolved
    assert _default(od, 0x1402, 1) & PDO_DISABLED
    for com in (0x1400, 0x1401, 0x1800, 0x1801):
        assert _var(od, com, 2).default == 1  # every SYNC
    # every default mapping entry names a PDO-mappable object of the size it says
    for index in (0x1600, 0x1601, 0x1A00, 0x1A01):
        for entry in mapping(index):
            target = _var(od, entry >> 16, (entry >> 8) & 0xFF)
            assert target.pdo_mappable
            assert len(target) == entry & 0xFF


def test_mapped_variable_sizes_from_eds_and_standard() -> None:
    od = load_od()
    assert mapped_variable(od, Obj.TARGET_VELOCITY) == MappedVariable(0x60FF, 0, 32, signed=True)
    assert mapped_variable(od, Obj.STATUSWORD) == MappedVariable(0x6041, 0, 16, signed=False)
    assert mapped_variable(None, Obj.TARGET_TORQUE) == MappedVariable(0x6071, 0, 16, signed=True)
    with pytest.raises(EdsError, match="0x5FFF:00"):
        mapped_variable(None, 0x5FFF)
    with pytest.raises(EdsError, match="not an integer"):
        mapped_variable(od, 0x1008)  # VISIBLE_STRING


def test_missing_file_names_it(tmp_path: Path) -> None:
    missing = tmp_path / "nope.eds"
    with pytest.raises(EdsError, match=f"{missing}: EDS file not found"):
        load_od(missing)


def test_special_files_are_refused_with_their_cause(tmp_path: Path) -> None:
    """/dev/zero, a FIFO or a directory named as the EDS: refused at once with what it is (it was "not found", and a
    FIFO would have blocked the read)."""
    fifo = tmp_path / "drive.eds"
    os.mkfifo(fifo)
    for path, kind in ((Path("/dev/zero"), "not a regular file"), (fifo, "not a regular file"),
                       (tmp_path, "a directory")):
        with pytest.raises(EdsError, match=f"{path}: is {kind}"):
            load_od(path)


def test_an_eds_past_the_cap_is_refused_before_it_is_read(tmp_path: Path) -> None:
    """A 50 MB EDS-syntax file took canopen's parser 30 s and 1.7 GB; the size is checked before any read."""
    big = tmp_path / "big.eds"
    with big.open("wb") as stream:
        stream.truncate(MAX_EDS_BYTES + 1)  # sparse: the test writes nothing
    with pytest.raises(EdsError, match=f"{big}: is {MAX_EDS_BYTES + 1} bytes; an EDS is at most {MAX_EDS_BYTES}"):
        load_od(big)


@pytest.mark.filterwarnings("ignore:The 'warn' method is deprecated:DeprecationWarning")  # canopen's own logger
@pytest.mark.parametrize(
    ("text", "reason"),
    [
        ("this is not an ini file\n", "not a valid EDS"),
        ("[1000]\nParameterName=Device type\n", "not a valid EDS"),  # no DataType / AccessType
        ("[1018sub1]\nParameterName=x\nDataType=0x0007\nAccessType=ro\n", "not a valid EDS"),  # orphan sub-index
        ("[1000]\nParameterName=Device type\nObjectType=0x7\nDataType=0x0007\nAccessType=ro\n", "lacks object 0x1001"),
    ],
)
def test_broken_eds_names_the_file(tmp_path: Path, text: str, reason: str) -> None:
    broken = tmp_path / "broken.eds"
    broken.write_text(text, encoding="utf-8")
    with pytest.raises(EdsError, match=reason) as caught:
        load_od(broken)
    assert str(broken) in str(caught.value)


def test_truncated_copy_of_the_shipped_eds_is_rejected(tmp_path: Path) -> None:
    text = DEFAULT_EDS.read_text(encoding="utf-8")
    cut = text[: text.index("[6040]")]  # loses controlword and everything after
    truncated = tmp_path / "truncated.eds"
    truncated.write_text(cut, encoding="utf-8")
    with pytest.raises(EdsError, match="lacks object 0x6040"):
        load_od(truncated)


def _described(od: ObjectDictionary) -> list[tuple[object, ...]]:
    """Every variable of ``od`` as the fields canopen parsed (its parent's index and name in place of the parent)."""
    rows: list[tuple[object, ...]] = []
    for index in sorted(od.indices):
        obj = od[index]
        variables = [obj] if isinstance(obj, ODVariable) else [obj[sub] for sub in sorted(obj.subindices)]
        for variable in variables:
            fields = {key: value for key, value in vars(variable).items() if key != "parent"}
            parent = variable.parent
            rows.append((index, variable.subindex, getattr(parent, "index", None), getattr(parent, "name", None),
                         sorted(fields.items(), key=lambda item: item[0]).__repr__()))
    return rows


def test_a_kept_parse_is_the_parse_and_every_load_is_its_own(tmp_path: Path) -> None:
    import canopen

    eds = tmp_path / "drive.eds"
    eds.write_text(DEFAULT_EDS.read_text(encoding="utf-8"), encoding="utf-8")
    first, second = load_od(eds, 7), load_od(eds, 7)  # the second from the kept parse
    fresh = canopen.import_od(str(eds), 7)  # canopen's own parse, nothing kept
    assert _described(second) == _described(fresh) == _described(first)
    assert (second.node_id, second.bitrate, second.device_information.product_name) == (
        fresh.node_id, fresh.bitrate, fresh.device_information.product_name)
    # $NODEID resolved for the node asked, not the one kept
    rpdo1 = (Obj.RPDO_COMMUNICATION, 1)  # COB-ID $NODEID+0x200
    assert _default(load_od(eds, 9), *rpdo1) == _default(canopen.import_od(str(eds), 9), *rpdo1) == 0x209
    assert _default(second, *rpdo1) == 0x207
    # each load is an object of its own: changing one changes no other
    _var(first, Obj.CONTROLWORD).default = 0x1234
    assert _var(second, Obj.CONTROLWORD).default != 0x1234
    assert _var(load_od(eds, 7), Obj.CONTROLWORD).default != 0x1234
    # a changed file is parsed again
    text = eds.read_text(encoding="utf-8")
    eds.write_text(text[: text.index("[6040]")], encoding="utf-8")
    with pytest.raises(EdsError, match="lacks object 0x6040"):
        load_od(eds, 7)
