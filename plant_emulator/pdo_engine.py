"""The virtual drive's PDO engine: RPDOs and TPDOs run from the mapping in the object dictionary.

``LocalNode`` has no PDO engine for a slave (its ``PdoMap``s are master-side). This one reads 0x1400/0x1600
(RPDO) and 0x1800/0x1A00 (TPDO), rebuilt whenever the master rewrites them over SDO, with transmission types 0
(acyclic synchronous), 1..240 (every n-th SYNC) and 254/255 (event-driven; the event timer 0x18xx:05 is honoured,
the inhibit time is not). The SYNC counter byte and the SYNC start value (0x18xx:06) are ignored: every SYNC
counts. A synchronous RPDO is held until the next SYNC latches it (:meth:`PdoEngine.latch`).
"""

from __future__ import annotations

import threading
import time
from collections.abc import Callable
from dataclasses import dataclass

from canopen import objectdictionary as cod

from drivers.cia301 import RPDO_BASES, TPDO_BASES, CobIdEntry, FunctionCode, NmtState, cob_id
from drivers.cia402 import Obj
from drivers.inprocess import subscribe_cyclic
from drivers.pdo import MappingEntry
from plant_emulator.node import EmulatedNode
from plant_emulator.sdo_guard import PDO_CHANNELS

__all__ = ["PDO_AREAS", "MappedObject", "PdoChannel", "PdoEngine"]

SYNC_TYPE_MAX = 240
TRANS_ACYCLIC = 0
TRANS_EVENT_TYPES = (254, 255)
EVENT_TIMER_SUBINDEX = 5
PDO_AREAS = (
    range(Obj.RPDO_COMMUNICATION, Obj.RPDO_COMMUNICATION + PDO_CHANNELS),
    range(Obj.RPDO_MAPPING, Obj.RPDO_MAPPING + PDO_CHANNELS),
    range(Obj.TPDO_COMMUNICATION, Obj.TPDO_COMMUNICATION + PDO_CHANNELS),
    range(Obj.TPDO_MAPPING, Obj.TPDO_MAPPING + PDO_CHANNELS),
)
# an RPDO carrying these acts on the application (mode first, so a controlword in the same frame acts in it)
_APPLICATION_OBJECTS = (Obj.MODES_OF_OPERATION, Obj.CONTROLWORD)


@dataclass(frozen=True)
class MappedObject:
    """One mapped entry of a PDO: where its bytes sit in the frame and in the store."""

    index: int
    subindex: int
    offset: int  # byte offset in the frame
    size: int  # bytes


@dataclass
class PdoChannel:
    """One RPDO or TPDO as the OD currently configures it."""

    number: int  # 1-based
    cob_id: int
    valid: bool
    transmission_type: int
    event_timer_ms: int
    entries: tuple[MappedObject, ...]
    length: int  # bytes
    reactions: tuple[tuple[int, int], ...] = ()  # RPDO: the mapped objects the application acts on, mode first
    sync_count: int = 0
    pending: bytes | None = None  # RPDO: received since the last SYNC, latched at the next
    last_sent: bytes | None = None  # TPDO: for acyclic / event-driven change detection
    last_sent_time: float = 0.0

    @property
    def synchronous(self) -> bool:
        """Transmission types 0..240 act on SYNC."""
        return self.transmission_type <= SYNC_TYPE_MAX


class PdoEngine:
    """RPDO reception and SYNC latch, TPDO transmission (synchronous, acyclic, event-driven).

    Parameters
    ----------
    node
        The drive's node (store, network, NMT state).
    lock
        The drive's lock; RPDO reception takes it.
    on_write
        ``on_write(index, subindex)`` after an RPDO stored the controlword or the mode (the application reacts).
    on_length_error
        Called for an RPDO shorter than its mapping (CiA 301: EMCY 0x8210, frame ignored).
    """

    def __init__(
        self,
        node: EmulatedNode,
        lock: threading.RLock,
        *,
        on_write: Callable[[int, int], None],
        on_length_error: Callable[[], None],
    ) -> None:
        self.node = node
        self._lock = lock
        self._on_write = on_write
        self._on_length_error = on_length_error
        self._rpdos: dict[int, PdoChannel] = {}  # by COB-ID
        self._tpdos: list[PdoChannel] = []
        self._event_tpdos: list[PdoChannel] = []  # the valid event-driven ones (none in a cyclic run)
        self._sync_tpdos: list[PdoChannel] = []  # the valid synchronous ones (0..240), sent at SYNC
        self._subscribed_rpdo_ids: set[int] = set()

    # --- configuration ----------------------------------------------------------------------------------------

    def rebuild(self) -> None:
        """Read every PDO from the OD again; keep a pending RPDO whose mapping did not change."""
        od = self.node.object_dictionary
        rpdos: dict[int, PdoChannel] = {}
        tpdos: list[PdoChannel] = []
        for n in range(PDO_CHANNELS):
            if Obj.RPDO_COMMUNICATION + n in od and Obj.RPDO_MAPPING + n in od:
                channel = self._read_channel(Obj.RPDO_COMMUNICATION + n, Obj.RPDO_MAPPING + n, n, RPDO_BASES)
                old = self._rpdos.get(channel.cob_id)
                if old is not None and old.number == channel.number and old.entries == channel.entries:
                    channel.pending = old.pending
                rpdos[channel.cob_id] = channel
            if Obj.TPDO_COMMUNICATION + n in od and Obj.TPDO_MAPPING + n in od:
                tpdos.append(self._read_channel(Obj.TPDO_COMMUNICATION + n, Obj.TPDO_MAPPING + n, n, TPDO_BASES))
        self._rpdos = {cob: ch for cob, ch in rpdos.items() if ch.valid}
        self._tpdos = tpdos
        self._event_tpdos = [tpdo for tpdo in tpdos if tpdo.valid and tpdo.transmission_type in TRANS_EVENT_TYPES]
        self._sync_tpdos = [tpdo for tpdo in tpdos if tpdo.valid and tpdo.synchronous]
        self._subscribe_rpdos()

    def _subscribe_rpdos(self) -> None:
        network = self.node.link
        if network is None:
            return
        wanted = set(self._rpdos)
        for cob in self._subscribed_rpdo_ids - wanted:
            network.unsubscribe(cob, self.on_rpdo)
        for cob in wanted - self._subscribed_rpdo_ids:
            subscribe_cyclic(network, cob, self.on_rpdo)
        self._subscribed_rpdo_ids = wanted

    def _read_channel(
        self, communication: int, mapping: int, n: int, bases: tuple[FunctionCode, ...]
    ) -> PdoChannel:
        node = self.node
        raw_cob = CobIdEntry.decode(int(node.read(communication, 1)))
        trans = int(node.read(communication, 2))
        event_timer = 0
        com_obj = node.object_dictionary[communication]
        if not isinstance(com_obj, cod.ODVariable) and EVENT_TIMER_SUBINDEX in com_obj:
            event_timer = int(node.read(communication, EVENT_TIMER_SUBINDEX))
        entries: list[MappedObject] = []
        offset = 0
        for sub in range(1, int(node.read(mapping, 0)) + 1):
            entry = MappingEntry.decode(int(node.read(mapping, sub)))
            size = entry.bits // 8
            entries.append(MappedObject(entry.index, entry.subindex, offset, size))
            offset += size
        cob = raw_cob.can_id
        if cob == 0 and n < len(bases):
            cob = cob_id(bases[n], node.node_id)  # 0: the predefined connection set
        reactions = sorted(((e.index, e.subindex) for e in entries if e.index in _APPLICATION_OBJECTS),
                           key=lambda key: key[0] != Obj.MODES_OF_OPERATION)
        return PdoChannel(
            number=n + 1,
            cob_id=cob,
            valid=raw_cob.valid,
            transmission_type=trans,
            event_timer_ms=event_timer,
            entries=tuple(entries),
            length=offset,
            reactions=tuple(reactions),
        )

    # --- RPDO -------------------------------------------------------------------------------------------------

    def on_rpdo(self, can_id: int, data: bytearray, timestamp: float) -> None:
        """Network callback: a synchronous RPDO waits for the next SYNC, an event-driven one acts now."""
        node = self.node
        if not node.alive or not node.operational:
            return
        with self._lock:
            channel = self._rpdos.get(can_id)
            if channel is None or not channel.valid:
                return
            if len(data) < channel.length:
                self._on_length_error()
                return
            if channel.transmission_type <= SYNC_TYPE_MAX:  # channel.synchronous, without the property's call
                channel.pending = bytes(data)  # takes effect at the next SYNC
            else:
                self._store_rpdo(channel, bytes(data))

    def latch(self) -> None:
        """At SYNC: the synchronous RPDOs received since the last SYNC become the active command."""
        for channel in self._rpdos.values():
            if channel.pending is not None:
                data_now, channel.pending = channel.pending, None
                self._store_rpdo(channel, data_now)

    def drop_pending(self) -> None:
        """Forget RPDOs not yet latched (the drive left OPERATIONAL: they will never apply)."""
        for channel in self._rpdos.values():
            channel.pending = None

    def _store_rpdo(self, channel: PdoChannel, data: bytes) -> None:
        store = self.node.data_store
        for entry in channel.entries:
            value = data[entry.offset:entry.offset + entry.size]
            try:  # not setdefault: it builds an empty dict on every call
                store[entry.index][entry.subindex] = value
            except KeyError:
                store[entry.index] = {entry.subindex: value}
        for index, subindex in channel.reactions:
            self._on_write(index, subindex)

    # --- TPDO -------------------------------------------------------------------------------------------------

    def send_synchronous(self) -> None:
        """At SYNC: sample and send the TPDOs due (acyclic ones only when changed), then the event-driven."""
        for tpdo in self._sync_tpdos:
            if tpdo.transmission_type == TRANS_ACYCLIC:
                self._send_tpdo(tpdo, only_if_changed=True)
            else:
                tpdo.sync_count += 1
                if tpdo.sync_count >= tpdo.transmission_type:
                    tpdo.sync_count = 0
                    self._send_tpdo(tpdo, only_if_changed=False)
        if self._event_tpdos:  # none in a cyclic run: no call
            self.send_event_driven()

    def send_event_driven(self, *, timer_only: bool = False) -> None:
        """Event-driven TPDOs: those whose event timer ran out, and (unless ``timer_only``) those that changed."""
        if not self._event_tpdos or not self.node.sending or self.node.nmt_state is not NmtState.OPERATIONAL:
            return
        now = time.monotonic()
        for tpdo in self._event_tpdos:
            timer_due = tpdo.event_timer_ms > 0 and now - tpdo.last_sent_time >= tpdo.event_timer_ms / 1000
            if timer_due:
                self._send_tpdo(tpdo, only_if_changed=False)
            elif not timer_only:
                self._send_tpdo(tpdo, only_if_changed=True)

    def _send_tpdo(self, channel: PdoChannel, *, only_if_changed: bool) -> None:
        store = self.node.data_store
        payload = b"".join([store[entry.index][entry.subindex] for entry in channel.entries])
        if only_if_changed and payload == channel.last_sent:
            return
        channel.last_sent = payload
        if channel.transmission_type in TRANS_EVENT_TYPES:  # only an event timer reads it: no clock for the rest
            channel.last_sent_time = time.monotonic()
        self.node.transmit(channel.cob_id, payload)
