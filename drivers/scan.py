"""Node discovery on a CAN bus (``commission scan``, :meth:`drivers.network.DriveNetwork.scan`): which CANopen
nodes are on the bus, what they are and in which NMT state.

Discovery runs three passes, cheapest and least intrusive first, all on one python-can bus:

1. **Listen** for ``timeout`` seconds to heartbeats and boot-ups (COB-ID ``0x700 + id``): every node with a
   producer heartbeat time (0x1017) shows up with its NMT state, without sending anything.
2. Optional **NMT reset communication** to all nodes (``--nmt-reset``): each node answers with its boot-up message.
   It resets the communication parameters (PDO mapping, heartbeat times) of every node on the bus, so it is never
   done by default.
3. **SDO probe** for silent nodes (heartbeat disabled): one SDO upload request of 0x1000 to every node id of the
   range not yet found, sent back to back (no node guarding, no waiting per node), then any SDO answer from
   ``0x580 + id`` -- data or abort -- proves the node exists.

Each node found is then read over SDO: device type 0x1000 and identity 0x1018:1..4. A node found only by SDO has
NMT state ``unknown`` (an SDO server answers in pre-operational and operational alike).
"""

from __future__ import annotations

import struct
import threading
from collections.abc import Sequence
from dataclasses import dataclass, field
from enum import IntEnum, unique
from typing import Any

import can
import canopen
from canopen.sdo import SdoAbortedError, SdoCommunicationError

from drivers.cia301 import (
    NMT_COB_ID,
    FunctionCode,
    NmtCommand,
    NmtState,
    cob_id,
    heartbeat_state,
    sdo_abort_text,
    split_cob_id,
)
from drivers.cia402 import IdentitySub, Obj
from drivers.errors import DriveError
from drivers.inprocess import connect_network, timebase_of

__all__ = ["NodeReport", "ScanResult", "SdoCommand", "render_scan", "scan_bus"]

DEVICE_PROFILE_MASK = 0xFFFF


@unique
class SdoCommand(IntEnum):
    """SDO command specifiers (byte 0) the probe sends and recognises (CiA 301 SDO protocol)."""

    INITIATE_UPLOAD_REQUEST = 0x40
    ABORT = 0x80


@dataclass(frozen=True)
class NodeReport:
    """One node found on the bus.

    Attributes
    ----------
    node_id
        Its CANopen node id.
    found_by
        How it was found: ``"heartbeat"``, ``"boot-up"``, ``"sdo"``.
    nmt_state
        The NMT state its heartbeat reported (a :class:`~drivers.cia301.NmtState` name), or ``"unknown"`` (found by
        SDO only).
    device_type, profile
        0x1000 and its low 16 bits (402 for a drive); ``None`` where the read failed.
    vendor_id, product_code, revision, serial
        The identity object 0x1018:1..4; ``None`` where a read failed.
    errors
        What failed while identifying it (SDO aborts, no answer).
    """

    node_id: int
    found_by: tuple[str, ...]  # "heartbeat", "boot-up", "sdo"
    nmt_state: str  # NmtState name, or "unknown" (found by SDO only)
    device_type: int | None = None
    profile: int | None = None  # low 16 bits of 0x1000 (402 for a drive)
    vendor_id: int | None = None
    product_code: int | None = None
    revision: int | None = None
    serial: int | None = None
    errors: tuple[str, ...] = ()

    def to_json(self) -> dict[str, Any]:
        return {
            "node_id": self.node_id,
            "found_by": list(self.found_by),
            "nmt_state": self.nmt_state,
            "device_type": self.device_type,
            "profile": self.profile,
            "identity": {
                "vendor_id": self.vendor_id,
                "product_code": self.product_code,
                "revision": self.revision,
                "serial": self.serial,
            },
            "errors": list(self.errors),
        }


@dataclass(frozen=True)
class ScanResult:
    """All nodes found, sorted by node id.

    Attributes
    ----------
    nodes
        One :class:`NodeReport` per node found.
    node_range
        The lowest and highest node id looked for.
    listened
        Seconds spent listening to heartbeats.
    nmt_reset
        Whether NMT reset communication was broadcast first.
    """

    nodes: tuple[NodeReport, ...]
    node_range: tuple[int, int]
    listened: float
    nmt_reset: bool

    def to_json(self) -> dict[str, Any]:
        return {
            "nodes": [node.to_json() for node in self.nodes],
            "node_range": list(self.node_range),
            "listen_seconds": self.listened,
            "nmt_reset": self.nmt_reset,
        }


@dataclass
class _Discovery(can.Listener):
    """Collects heartbeats, boot-ups and SDO answers from the Notifier thread."""

    nodes: Sequence[int]
    heartbeat_state: dict[int, int] = field(default_factory=dict)
    found_by: dict[int, set[str]] = field(default_factory=dict)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def on_message_received(self, msg: can.Message) -> None:
        if msg.is_error_frame or msg.is_remote_frame or msg.is_extended_id:
            return
        function, node_id = split_cob_id(msg.arbitration_id)
        if node_id not in self.nodes:
            return
        with self.lock:
            if function == FunctionCode.HEARTBEAT and len(msg.data) == 1:
                state = heartbeat_state(msg.data[0])
                self.heartbeat_state[node_id] = state
                how = "boot-up" if state == NmtState.INITIALISING else "heartbeat"
                self.found_by.setdefault(node_id, set()).add(how)
            elif function == FunctionCode.SDO_TX and len(msg.data) == 8:
                self.found_by.setdefault(node_id, set()).add("sdo")


def scan_bus(
    bus: can.BusABC,
    *,
    nodes: Sequence[int],
    listen: float = 1.2,
    nmt_reset: bool = False,
    sdo_timeout: float = 0.3,
) -> ScanResult:
    """Discover the nodes among ``nodes`` on ``bus`` (see the module docstring) and read their identity.

    Parameters
    ----------
    bus
        An open python-can bus (not shut down here).
    nodes
        Node ids to look for (1..127).
    listen
        Seconds to listen to heartbeats (and boot-ups after the optional reset).
    nmt_reset
        Broadcast NMT reset communication first (resets every node's communication parameters).
    sdo_timeout
        Seconds to wait for SDO answers of the probe and of each identity read.

    Returns
    -------
    ScanResult
        The nodes found, sorted by node id.

    Raises
    ------
    DriveError
        A frame cannot be sent.
    """
    discovery = _Discovery(nodes=tuple(nodes))
    network = canopen.Network(bus)
    network.listeners.append(discovery)  # type: ignore[arg-type]  # any can.Listener works in the Notifier
    connect_network(network)
    timebase = timebase_of(bus)  # on the embedded emulators' lockstep channel, listening lets lockstep time pass
    try:
        if nmt_reset:
            _send(bus, NMT_COB_ID, bytes([int(NmtCommand.RESET_COMMUNICATION), 0]))
        timebase.sleep(listen)
        with discovery.lock:
            silent = [node for node in nodes if node not in discovery.found_by]
        request = struct.pack("<BHB4x", int(SdoCommand.INITIATE_UPLOAD_REQUEST), int(Obj.DEVICE_TYPE), 0)
        for node in silent:
            _send(bus, cob_id(FunctionCode.SDO_RX, node), request)
        if silent:
            timebase.sleep(sdo_timeout)
        with discovery.lock:
            found = {node: set(how) for node, how in discovery.found_by.items()}
            states = dict(discovery.heartbeat_state)
        reports = [
            _identify(network, node, sorted(found[node]), states.get(node), sdo_timeout) for node in sorted(found)
        ]
    finally:
        # not network.disconnect(): that would shut the caller's bus down
        if network.notifier is not None:
            network.notifier.stop(network.NOTIFIER_SHUTDOWN_TIMEOUT)
    return ScanResult(tuple(reports), (min(nodes), max(nodes)), listen, nmt_reset)


def _send(bus: can.BusABC, arbitration_id: int, data: bytes) -> None:
    try:
        bus.send(can.Message(arbitration_id=arbitration_id, data=data, is_extended_id=False))
    except can.CanError as exc:
        raise DriveError(f"cannot send 0x{arbitration_id:03X} on the bus: {exc}") from exc


def _identify(
    network: canopen.Network, node_id: int, found_by: list[str], state: int | None, sdo_timeout: float
) -> NodeReport:
    node = canopen.RemoteNode(node_id, canopen.ObjectDictionary())
    node.sdo.RESPONSE_TIMEOUT = sdo_timeout
    network.add_node(node)
    errors: list[str] = []

    def read_u32(index: int, subindex: int) -> int | None:
        try:
            data = node.sdo.upload(index, subindex)
        except SdoAbortedError as exc:
            errors.append(f"0x{index:04X}:{subindex:02X}: {sdo_abort_text(exc.code)}")
            return None
        except SdoCommunicationError as exc:
            errors.append(f"0x{index:04X}:{subindex:02X}: no SDO answer ({exc})")
            return None
        return int.from_bytes(bytes(data[:4]).ljust(4, b"\0"), "little")

    try:
        device_type = read_u32(Obj.DEVICE_TYPE, 0)
        identity = [read_u32(Obj.IDENTITY, sub) for sub in IdentitySub]
    finally:
        network.nodes.pop(node_id, None)
        network.unsubscribe(node.sdo.tx_cobid)
    state_name = "unknown"
    if state is not None:
        try:
            state_name = NmtState(state).name
        except ValueError:
            state_name = f"0x{state:02X}"
    return NodeReport(
        node_id=node_id,
        found_by=tuple(found_by),
        nmt_state=state_name,
        device_type=device_type,
        profile=None if device_type is None else device_type & DEVICE_PROFILE_MASK,
        vendor_id=identity[0],
        product_code=identity[1],
        revision=identity[2],
        serial=identity[3],
        errors=tuple(errors),
    )


def render_scan(result: ScanResult) -> str:
    """The human-readable table."""
    if not result.nodes:
        return f"no node answered in {result.node_range[0]}..{result.node_range[1]}"
    lines = [f"{'node':>4}  {'NMT':<16} {'profile':>7}  {'vendor':>10} {'product':>10} {'revision':>10} "
             f"{'serial':>10}  found by"]
    for node in result.nodes:
        def hex32(value: int | None) -> str:
            return "-" if value is None else f"0x{value:08X}"

        profile = "-" if node.profile is None else str(node.profile)
        lines.append(
            f"{node.node_id:>4}  {node.nmt_state:<16} {profile:>7}  {hex32(node.vendor_id):>10} "
            f"{hex32(node.product_code):>10} {hex32(node.revision):>10} {hex32(node.serial):>10}  "
            f"{', '.join(node.found_by)}"
        )
        for error in node.errors:
            lines.append(f"      ! {error}")
    return "\n".join(lines)
