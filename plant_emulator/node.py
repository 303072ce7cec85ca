"""The drive's canopen node: ``LocalNode`` with a post-store hook and typed access to its object store.

Every service object of the virtual drive (:mod:`plant_emulator.device`) holds this node, as canopen's own
services (``node.sdo``, ``node.nmt``, ``node.emcy``) hold theirs: it carries the object dictionary, the store, the
NMT state, the network the drive runs on and whether the drive still answers at all.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import canopen
from canopen import objectdictionary as cod

from drivers.cia301 import NmtState
from drivers.cia402 import Obj
from drivers.errors import EdsError
from drivers.od import DEFAULT_EDS, load_od
from drivers.pdo import data_frame

__all__ = ["EmulatedNode", "load_object_dictionary"]


def load_object_dictionary(node_id: int, eds: str | Path | None = None) -> cod.ObjectDictionary:
    """The drive's object dictionary from ``eds`` (default: the shipped ``configs/foilc_servo.eds``).

    Raises
    ------
    drivers.errors.EdsError
        If the file is missing or malformed, or lacks an object the drive needs.
    """
    od = load_od(eds, node_id)
    source = str(eds) if eds is not None else str(DEFAULT_EDS)
    for index in (Obj.TARGET_VELOCITY, Obj.VELOCITY_ACTUAL_VALUE, Obj.PRODUCER_HEARTBEAT_TIME):
        if index not in od:
            raise EdsError(f"lacks object 0x{int(index):04X} ({index.name.lower()})", source=source)
    return od


_NMT_STATES = {int(state): state for state in NmtState}  # a dict lookup, not EnumType.__call__
_OPERATIONAL = int(NmtState.OPERATIONAL)


@dataclass(frozen=True, slots=True)
class _Codec:
    """How one object is read from and produced into the store: its OD entry and the struct calls.

    ``pack`` is None where the value needs canopen's ``encode_raw`` (not an integer, or the EDS gives a range it
    warns about); ``unpack`` is None where the type has no fixed size.
    """

    variable: cod.ODVariable
    unpack: Callable[[bytes], tuple[Any, ...]] | None
    size: int
    pack: Callable[[int], bytes] | None
    low: int
    high: int


def _no_reaction(index: int, subindex: int) -> None:
    """The post-store hook until the device wires its own."""


class EmulatedNode(canopen.LocalNode):
    """``LocalNode`` with a post-store hook and the drive's run-time flags.

    canopen runs write callbacks *before* storing (so they can veto with an SDO abort), but the PDO engine and
    the state machine must see the value *in* the store: :meth:`set_data` calls :attr:`after_write` once the
    value is stored. This override is the only change to canopen's behaviour.

    Attributes
    ----------
    after_write
        ``after_write(index, subindex)`` after every store from the bus (SDO download or RPDO).
    link
        The network while the drive runs (None before ``start`` and after ``stop``).
    alive
        False before ``start`` and after ``stop_responding``: every handler returns at once.
    """

    def __init__(self, node_id: int, od: cod.ObjectDictionary) -> None:
        super().__init__(node_id, od)
        self.node_id = node_id  # canopen types ``id`` as optional; a local node always has one
        self.after_write: Callable[[int, int], None] = _no_reaction
        self.link: canopen.Network | None = None
        self.alive = False
        self._codecs: dict[tuple[int, int], _Codec] = {}

    def set_data(self, index: int, subindex: int, data: bytes, check_writable: bool = False) -> None:
        super().set_data(index, subindex, data, check_writable=check_writable)
        self.after_write(index, subindex)

    @property
    def nmt_state(self) -> NmtState:
        """The present NMT state."""
        state = self.nmt._state  # canopen keeps the state byte private
        return _NMT_STATES.get(state) or NmtState(state)

    @property
    def operational(self) -> bool:
        """Whether the NMT state is OPERATIONAL (the raw state byte compared: RPDOs ask this every cycle)."""
        return self.nmt._state == _OPERATIONAL

    @property
    def sending(self) -> bool:
        """Whether frames may go out: on a network, alive (the NMT-state rules are each service's own)."""
        return self.link is not None and self.alive

    def transmit(self, can_id: int, data: bytes) -> None:
        """Send a data frame on the drive's network, as canopen's ``Network.send_message`` does (under its send
        lock, then its check of the receive path), with the frame built by :func:`drivers.pdo.data_frame`."""
        link = self.link
        if link is None or link.bus is None:
            return
        with link.send_lock:
            link.bus.send(data_frame(can_id, data))
        notifier = link.notifier
        if notifier is not None and notifier.exception is not None:  # what canopen's check() tests, without its call
            link.check()

    def has(self, index: int) -> bool:
        """Whether the object dictionary has object ``index``."""
        return index in self.object_dictionary

    def variable(self, index: int, subindex: int = 0) -> cod.ODVariable:
        """The OD entry of ``index:subindex`` (a plain variable ignores the sub-index)."""
        obj = self.object_dictionary[index]
        if isinstance(obj, cod.ODVariable):
            return obj
        return obj[subindex]

    def read(self, index: int, subindex: int = 0) -> Any:
        """The decoded value in the store."""
        codec = self._codecs.get((index, subindex)) or self._codec(index, subindex)
        if codec.unpack is not None and not self._read_callbacks:
            try:  # the stored bytes straight from the store (a miss is rare: canopen's path below handles it)
                data = self.data_store[index][subindex]
            except KeyError:
                pass
            else:
                if len(data) == codec.size:
                    return codec.unpack(data)[0]
        return codec.variable.decode_raw(self.get_data(index, subindex))

    def produce(self, index: int, value: int | float, subindex: int = 0) -> None:
        """Store a value the drive itself produces (no callbacks: it is not a write from the bus).

        An integer object saturates at its type's range, as a drive's own counters do; a missing object is
        skipped (an EDS may omit optional feedback).
        """
        codec = self._codecs.get((index, subindex))
        if codec is None:
            if index not in self.object_dictionary:
                return
            codec = self._codec(index, subindex)
        if codec.pack is not None:  # an integer without an EDS range: clamp and pack, nothing to warn about
            raw, low, high = round(value), codec.low, codec.high
            data = codec.pack(low if raw < low else high if raw > high else raw)
        else:
            var = codec.variable
            if var.data_type in cod.INTEGER_TYPES:
                value = min(max(round(value), codec.low), codec.high)
            data = var.encode_raw(value)
        try:  # not setdefault: that builds an empty dict on every call, and this runs four times a cycle
            self.data_store[index][subindex] = data
        except KeyError:
            self.data_store[index] = {subindex: data}

    def _codec(self, index: int, subindex: int) -> _Codec:
        """The codec of ``index:subindex``, made once (the object dictionary never changes while the drive runs).

        Every cycle reads and produces a handful of objects; canopen's ``get_data`` / ``decode_raw`` /
        ``encode_raw`` look the object up and test its type on every call, which cost more than the physics.
        """
        var = self.variable(index, subindex)
        unpack = size = None
        packer = var.STRUCT_TYPES.get(var.data_type) if var.data_type is not None else None
        if packer is not None:
            unpack, size = packer.unpack, packer.size
        low = high = 0
        pack = None
        if var.data_type in cod.INTEGER_TYPES:
            bits = len(var)
            signed = var.data_type in cod.SIGNED_TYPES
            low, high = (-(1 << (bits - 1)), (1 << (bits - 1)) - 1) if signed else (0, (1 << bits) - 1)
            if packer is not None and var.min is None and var.max is None:
                pack = packer.pack
        codec = _Codec(var, unpack, size or 0, pack, low, high)
        self._codecs[(index, subindex)] = codec
        return codec

    def reset_store(self, area: range | None) -> None:
        """Every object in ``area`` (all when None) back to its EDS value, pre-encoded in the store."""
        store = self.data_store
        for index in list(store):
            if area is None or index in area:
                del store[index]
        for index in list(self.object_dictionary.indices):
            if area is not None and index not in area:
                continue
            obj = self.object_dictionary[index]
            variables = [obj] if isinstance(obj, cod.ODVariable) else list(obj.values())
            for var in variables:
                initial = var.value if var.value is not None else var.default
                if initial is None or var.data_type not in var.STRUCT_TYPES:
                    continue
                store.setdefault(var.index, {})[var.subindex] = var.encode_raw(initial)
