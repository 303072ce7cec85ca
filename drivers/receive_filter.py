"""A node's receive path sees only its own frames, filtered before Python: :class:`FilteredNetwork`.

A drive on a shared bus subscribes to a handful of COB-IDs (NMT, SYNC, its RPDOs and SDO requests, the master's
heartbeat); the other nodes' PDOs, SDOs and heartbeats are foreign to it. With four drives on one bus most frames
are foreign, and each one cost the drive's receive thread a wake-up, the GIL and a decode in Python before canopen
dropped it. Here the bus itself drops them, below Python:

``socketcan``
    ``CAN_RAW_FILTER`` through python-can's ``can_filters`` (:meth:`can.BusABC.set_filters`, which python-can's
    socketcan bus hands to the kernel and then does not filter again in Python).
``udp_multicast``
    python-can filters in Python, in ``BusABC.recv`` after unpacking every datagram: no help. Instead a classic BPF
    socket filter (``SO_ATTACH_FILTER``) on the bus's UDP socket reads the arbitration id inside python-can's msgpack
    payload (:func:`udp_id_filter`) and drops the datagram in the kernel. The program checks the fixed layout
    ``pack_message`` writes (a map of 11 keys, ``"timestamp"`` first as a float64, then ``"arbitration_id"``) and
    parses the id's msgpack integer encoding; a datagram of any other layout is passed to Python whole (never lost:
    canopen's dispatch drops a foreign one there).

Any other interface, or a bus object that is not python-can's own (a fault-injecting wrapper), is left unfiltered;
:attr:`FilteredNetwork.filter_kind` says which applies.

The filter follows the subscriptions: every :meth:`FilteredNetwork.subscribe` and ``unsubscribe`` (start-up, a PDO
remap, a new SYNC COB-ID, reset communication) installs the new set at once, so a frame of a COB-ID subscribed to
is never filtered out.

Thread safety: subscriptions change on the threads canopen calls them from (the control thread, the receive thread
handling an SDO write); installing a filter is one ``setsockopt``, atomic for the receiving socket.
"""

from __future__ import annotations

import ctypes
import enum
import os
import socket
import struct
from collections.abc import Callable, Iterable

import can
import canopen

__all__ = [
    "UDP_HEADER",
    "FilterKind",
    "FilteredNetwork",
    "install_id_filter",
    "udp_id_filter",
]

#: bytes before the datagram's payload where a socket filter reads it: the filter sees the UDP header at offset 0
UDP_HEADER = 8
_SO_ATTACH_FILTER = getattr(socket, "SO_ATTACH_FILTER", 26)  # Linux's <asm-generic/socket.h>
_ACCEPT, _DROP = 0xFFFFFFFF, 0  # a socket filter returns the bytes to keep: all, or none
_STANDARD_MASK, _EXTENDED_MASK = 0x7FF, 0x1FFFFFFF  # every bit of an 11-bit and of a 29-bit identifier


@enum.unique
class _Bpf(enum.IntEnum):
    """Classic BPF opcodes (<linux/filter.h>) the program uses."""

    LD_B_ABS = 0x30
    LD_H_ABS = 0x28
    LD_W_ABS = 0x20
    JEQ_K = 0x15
    JGE_K = 0x35
    RET_K = 0x06


@enum.unique
class _Msgpack(enum.IntEnum):
    """The msgpack type bytes of python-can's ``pack_message`` layout (msgpack spec)."""

    FIXMAP_11 = 0x8B  # the message dict: 11 keys
    FIXSTR_9 = 0xA9  # "timestamp"
    FLOAT64 = 0xCB  # its value
    FIXSTR_14 = 0xAE  # "arbitration_id"
    UINT8 = 0xCC
    UINT16 = 0xCD
    UINT32 = 0xCE
    FIXINT_END = 0x80  # positive fixint: 0x00..0x7f is the value itself


#: byte offsets in the payload of ``pack_message``'s layout (each key's string and value at a fixed place)
_MAP, _KEY1, _KEY1_TEXT, _VALUE1, _KEY2, _KEY2_TEXT, _ID = 0, 1, 2, 11, 20, 21, 35
_ARBI = int.from_bytes(b"arbi", "big")  # the first four letters of the second key, as a big-endian word


class FilterKind(enum.StrEnum):
    """Where a bus's frames of foreign COB-IDs are dropped."""

    CAN_RAW_FILTER = "can_raw_filter"  # socketcan: the kernel's CAN_RAW_FILTER
    BPF = "bpf"  # udp_multicast: a classic BPF socket filter on the UDP socket
    NONE = "none"  # not filtered below Python: canopen drops them after python-can decoded them


def udp_id_filter(ids: Iterable[int]) -> list[tuple[int, int, int, int]]:
    """The classic BPF program (``(code, jt, jf, k)`` rows) that passes python-can ``udp_multicast`` datagrams whose
    arbitration id is in ``ids`` and drops those of other ids; a datagram not in ``pack_message``'s layout passes.

    Offsets are from the UDP header, which a socket filter on a UDP socket sees at offset 0
    (``tests/crossprocess/test_receive_filter.py`` shows it on a real socket in a private network namespace).
    """
    wanted = sorted(set(ids))
    if len(wanted) > 200:  # jumps are 8-bit: each compare must reach the accept at the end
        raise ValueError(f"at most 200 ids in one filter, got {len(wanted)}")
    rows: list[tuple[str, int, int | str, int | str, int]] = []  # (label, code, jt, jf, k), jumps by label

    def load(code: _Bpf, offset: int, label: str = "") -> None:
        rows.append((label, code, 0, 0, UDP_HEADER + offset))

    def expect(value: int) -> None:  # the layout holds: go on; it does not: pass the datagram to Python
        rows.append(("", _Bpf.JEQ_K, 0, "accept", value))

    load(_Bpf.LD_B_ABS, _MAP)
    expect(_Msgpack.FIXMAP_11)
    load(_Bpf.LD_B_ABS, _KEY1)
    expect(_Msgpack.FIXSTR_9)
    load(_Bpf.LD_B_ABS, _VALUE1)
    expect(_Msgpack.FLOAT64)
    load(_Bpf.LD_B_ABS, _KEY2)
    expect(_Msgpack.FIXSTR_14)
    load(_Bpf.LD_W_ABS, _KEY2_TEXT)
    expect(_ARBI)
    load(_Bpf.LD_B_ABS, _ID)  # the id's type byte, or the id itself (a positive fixint)
    rows.append(("", _Bpf.JGE_K, 0, "compare", _Msgpack.FIXINT_END))
    widths = ((_Msgpack.UINT8, _Bpf.LD_B_ABS), (_Msgpack.UINT16, _Bpf.LD_H_ABS), (_Msgpack.UINT32, _Bpf.LD_W_ABS))
    rows += [("", _Bpf.JEQ_K, f"load{code:x}", 0, code) for code, _width in widths]
    rows.append(("", _Bpf.RET_K, 0, 0, _ACCEPT))  # another encoding (a negative id?): Python decides
    for code, width in widths:
        load(width, _ID + 1, f"load{code:x}")
        rows.append(("", _Bpf.JGE_K, "compare", "compare", 0))  # to the compares either way (no JA needed)
    rows.append(("compare", _Bpf.JEQ_K, "accept", 0, wanted[0]) if wanted else ("compare", _Bpf.RET_K, 0, 0, _DROP))
    rows += [("", _Bpf.JEQ_K, "accept", 0, can_id) for can_id in wanted[1:]]
    rows.append(("", _Bpf.RET_K, 0, 0, _DROP))
    rows.append(("accept", _Bpf.RET_K, 0, 0, _ACCEPT))
    return _resolve(rows)


def _resolve(rows: list[tuple[str, int, int | str, int | str, int]]) -> list[tuple[int, int, int, int]]:
    """Jump labels to the relative offsets classic BPF takes (forward only, 0..255)."""
    at = {label: index for index, (label, *_rest) in enumerate(rows) if label}

    def offset(index: int, target: int | str) -> int:
        if isinstance(target, int):
            return target
        jump = at[target] - index - 1
        if not 0 <= jump <= 255:
            raise ValueError(f"BPF jump to {target!r} out of range: {jump}")
        return jump

    return [(int(code), offset(i, jt), offset(i, jf), int(k)) for i, (_label, code, jt, jf, k) in enumerate(rows)]


def _attach_bpf(fd: int, program: list[tuple[int, int, int, int]]) -> None:
    """``setsockopt(SO_ATTACH_FILTER)`` with a ``struct sock_fprog`` built with ctypes (the kernel copies it)."""
    instructions = (ctypes.c_uint64 * len(program))(
        *[int.from_bytes(struct.pack("=HBBI", code, jt, jf, k), "little") for code, jt, jf, k in program])
    fprog = struct.pack("HL", len(program), ctypes.addressof(instructions))  # unsigned short len; filter pointer
    with socket.socket(fileno=os.dup(fd)) as sock:  # the same socket: a duplicate descriptor of it
        sock.setsockopt(socket.SOL_SOCKET, _SO_ATTACH_FILTER, fprog)


def install_id_filter(bus: can.BusABC, ids: Iterable[int]) -> FilterKind:
    """Let ``bus`` receive only frames whose arbitration id is in ``ids``, dropped below Python where it can be done
    (module docstring); the kind applied. An OS refusal leaves the bus unfiltered (:attr:`FilterKind.NONE`)."""
    wanted = sorted(set(ids))
    kind = type(bus).__name__
    try:
        if kind == "SocketcanBus":
            extended = [can_id > _STANDARD_MASK for can_id in wanted]
            bus.set_filters([{"can_id": can_id, "can_mask": _EXTENDED_MASK if wide else _STANDARD_MASK,
                              "extended": wide} for can_id, wide in zip(wanted, extended, strict=True)])
            return FilterKind.CAN_RAW_FILTER
        if kind == "UdpMulticastBus":
            _attach_bpf(bus.fileno(), udp_id_filter(wanted))
            return FilterKind.BPF
    except OSError:
        return FilterKind.NONE
    return FilterKind.NONE


class FilteredNetwork(canopen.Network):
    """A canopen ``Network`` whose bus receives only the COB-IDs subscribed to (module docstring).

    Parameters
    ----------
    bus
        The node's own bus object (python-can's), on which the filter is installed.
    """

    def __init__(self, bus: can.BusABC) -> None:
        self.filter_kind = FilterKind.NONE
        self._installed: tuple[int, ...] | None = None
        super().__init__(bus)  # canopen subscribes its own services here (LSS): the filter follows from the start

    def subscribe(self, can_id: int, callback: Callable[[int, bytearray, float], None]) -> None:
        super().subscribe(can_id, callback)
        self._refilter()

    def unsubscribe(self, can_id: int, callback: Callable[[int, bytearray, float], None] | None = None) -> None:
        super().unsubscribe(can_id, callback)
        self._refilter()

    def _refilter(self) -> None:
        ids = tuple(sorted(self.subscribers))
        if ids == self._installed or self.bus is None:
            return
        self.filter_kind = install_id_filter(self.bus, ids)
        self._installed = ids
