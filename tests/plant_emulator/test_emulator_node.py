"""The drive node's cached object codecs (``EmulatedNode.read`` / ``produce``) against canopen's own path."""

from __future__ import annotations

from canopen import objectdictionary as cod

from drivers.cia402 import Obj
from plant_emulator.node import EmulatedNode, load_object_dictionary


def _integer_variables(node: EmulatedNode) -> list[cod.ODVariable]:
    found = []
    for index in node.object_dictionary.indices:
        obj = node.object_dictionary[index]
        for var in [obj] if isinstance(obj, cod.ODVariable) else list(obj.values()):
            if var.data_type in cod.INTEGER_TYPES:
                found.append(var)
    return found


def test_read_decodes_every_integer_object_as_canopen_does() -> None:
    node = EmulatedNode(1, load_object_dictionary(1))
    node.reset_store(None)
    variables = _integer_variables(node)
    assert len(variables) > 50  # the shipped EDS: the whole dictionary, not a handful
    for var in variables:
        expected = var.decode_raw(node.get_data(var.index, var.subindex))  # canopen: callbacks, store, defaults
        assert node.read(var.index, var.subindex) == expected, f"0x{var.index:04X}:{var.subindex}"


def test_produce_saturates_at_the_type_and_reads_back_through_canopen() -> None:
    node = EmulatedNode(1, load_object_dictionary(1))
    node.reset_store(None)
    for index, value, stored in ((Obj.VELOCITY_ACTUAL_VALUE, 1e12, 2**31 - 1),  # INTEGER32
                                 (Obj.VELOCITY_ACTUAL_VALUE, -1e12, -(2**31)),
                                 (Obj.STATUSWORD, -5, 0),  # UNSIGNED16
                                 (Obj.STATUSWORD, 0x1_0237, 0xFFFF),
                                 (Obj.TORQUE_ACTUAL_VALUE, 12.6, 13)):  # rounded, INTEGER16
        node.produce(index, value)
        var = node.variable(index)
        assert var.decode_raw(node.get_data(index, 0)) == stored
        assert node.read(index) == stored


def test_a_read_callback_still_answers_reads() -> None:
    node = EmulatedNode(1, load_object_dictionary(1))
    node.reset_store(None)
    node.produce(Obj.STATUSWORD, 0x0237)
    node.add_read_callback(lambda index, subindex, od: 0x0040 if index == Obj.STATUSWORD else None)
    assert node.read(Obj.STATUSWORD) == 0x0040  # canopen's callback wins over the store, as in get_data
    assert node.read(Obj.VELOCITY_ACTUAL_VALUE) == node.variable(Obj.VELOCITY_ACTUAL_VALUE).decode_raw(
        node.get_data(Obj.VELOCITY_ACTUAL_VALUE, 0))
