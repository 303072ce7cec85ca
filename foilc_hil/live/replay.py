"""A log streamed to a live view (``replay F.mcap --live``): its messages at their recorded pace, or ``rate`` times
faster, on the channels a run's live view has.

Every message of the log goes out in file order, as logged (its JSON document, its log time as the message's
timestamp), on its own channel, each at ``first + (log_time - first_log_time) / rate`` on one clock from one start
instant (a message late by the stream's own work does not delay the ones after it); ``/can`` is limited to
``can_rate`` frames a second of wall time, as a run's. ``/drive/state`` is rebuilt from the logged frames: the
statusword and velocity of each node's TPDO and the controlword of its RPDO (the PDO mapping the run logged,
``foilc_hil.pdo_mapping`` and the per-axis records), the velocity in plant units (the logged ``drive.velocity_scale``),
``cycle`` the count of logged SYNCs, sent at each change and every :data:`~foilc_hil.live.publisher.STATE_PERIOD`
of recorded time. A damaged log is streamed up to the damage (:attr:`StreamReport.damage` says where).
"""

from __future__ import annotations

import base64
import time
from collections.abc import Callable, Mapping
from dataclasses import asdict, dataclass, field
from typing import TYPE_CHECKING, Any, Final

import orjson

from drivers.cia301 import SYNC_COB_ID
from drivers.cia402 import Obj, decode_state
from foilc_hil.io.mcap_log import McapLogReader
from foilc_hil.io.schemas import (
    METADATA_AXIS_PREFIX,
    METADATA_CONFIG,
    METADATA_PDO_MAPPING,
    TOPIC_CAN,
    TOPIC_DRIVE_STATE,
)
from foilc_hil.live.messages import DriveState, drive_state_document
from foilc_hil.live.publisher import STATE_PERIOD

if TYPE_CHECKING:
    from foilc_hil.live.server import LiveServer

__all__ = ["StreamReport", "WireStates", "stream_log"]

_SLEEP_FLOOR: Final = 0.001
"""Seconds ahead of schedule below which a message goes out at once (no sleep for each of a burst's messages)."""


@dataclass
class StreamReport:
    """What :func:`stream_log` sent (``replay --live --json``'s ``live``).

    Attributes
    ----------
    published
        Messages sent, by topic.
    frames_skipped
        ``/can`` frames over the rate limit.
    duration
        Seconds from the first message to the last.
    damage
        Where the log broke off (empty: it did not).
    """

    published: dict[str, int] = field(default_factory=dict)
    frames_skipped: int = 0
    duration: float = 0.0
    damage: str = ""

    def to_json(self) -> dict[str, Any]:
        return asdict(self)


@dataclass(frozen=True)
class _Field:
    """One mapped object in one PDO: bit offset, width, sign."""

    offset: int
    bits: int
    signed: bool

    def decode(self, data: bytes) -> int:
        raw = int.from_bytes(data, "little") >> self.offset & ((1 << self.bits) - 1)
        return raw - (1 << self.bits) if self.signed and raw >> (self.bits - 1) else raw


def _fields(variables: Any) -> dict[int, _Field]:
    """Object index -> where it sits in a PDO of ``variables`` (``drivers.pdo.MappedVariable``)."""
    found: dict[int, _Field] = {}
    offset = 0
    for variable in variables:
        found.setdefault(int(variable.index), _Field(offset, int(variable.bits), bool(variable.signed)))
        offset += int(variable.bits)
    return found


class WireStates:
    """Each node's drive state as the logged frames show it (``/drive/state`` of a replay).

    :meth:`learn` reads the PDO mappings and velocity scales from the log's metadata (called again as more
    metadata is read: the mapping is logged after the drive was configured); :meth:`frame` takes one ``/can``
    document and returns the node's state when it was a TPDO carrying its statusword.
    """

    def __init__(self) -> None:
        self._tpdo: dict[int, tuple[int, dict[int, _Field]]] = {}  # COB-ID -> node, fields
        self._rpdo: dict[int, tuple[int, dict[int, _Field]]] = {}
        self._scale: dict[int, float] = {}
        self._seen = 0  # metadata records learned from
        self._syncs = 0
        self._words: dict[int, dict[str, Any]] = {}  # node -> statusword, velocity, controlword as last seen

    def learn(self, metadata: Mapping[str, Mapping[str, str]]) -> None:
        """The mappings and velocity scales of ``metadata`` (every record read so far)."""
        if len(metadata) == self._seen:
            return
        self._seen = len(metadata)
        from foilc_hil.io.pdo_mapping import decode_pdo_mapping

        scale = _velocity_scale(metadata.get(METADATA_CONFIG))
        for name, record in metadata.items():
            if name != METADATA_PDO_MAPPING and not (name.startswith(METADATA_AXIS_PREFIX)
                                                     and name.endswith(".pdo_mapping")):
                continue
            try:
                rpdos, tpdos = decode_pdo_mapping(dict(record))
            except (KeyError, TypeError, ValueError):  # a malformed record: no states from it
                continue
            for layouts, table in ((tpdos, self._tpdo), (rpdos, self._rpdo)):
                for layout in layouts:
                    node = int(layout.cob_id) & 0x7F
                    table[int(layout.cob_id)] = (node, _fields(layout.variables))
                    own = metadata.get(f"{METADATA_AXIS_PREFIX}.{node}.config")
                    self._scale[node] = _velocity_scale(own) if own is not None else scale

    def frame(self, document: Mapping[str, Any]) -> DriveState | None:
        """One ``/can`` document; the node's state when it was a TPDO with a statusword, else ``None``."""
        cob, tx = int(document.get("id", -1)), document.get("dir") == "tx"
        if tx and cob == SYNC_COB_ID:
            self._syncs += 1
            return None
        entry = (self._rpdo if tx else self._tpdo).get(cob)
        if entry is None:
            return None
        node, fields = entry
        data = base64.b64decode(document.get("data") or "")
        words = self._words.setdefault(node, {"statusword": None, "velocity": None, "controlword": None})
        for index, key in ((Obj.STATUSWORD, "statusword"), (Obj.VELOCITY_ACTUAL_VALUE, "velocity"),
                           (Obj.CONTROLWORD, "controlword")):
            where = fields.get(int(index))
            if where is not None and len(data) * 8 >= where.offset + where.bits:
                words[key] = where.decode(data)
        statusword = words["statusword"]
        if tx or statusword is None:
            return None
        try:
            state = decode_state(statusword)
        except ValueError:  # a pattern no state has (a bad frame the run counted): no state from it
            return None
        velocity = None if words["velocity"] is None else words["velocity"] / self._scale.get(node, 1.0)
        return DriveState(node, self._syncs, int(state), statusword, words["controlword"], velocity)


def _velocity_scale(record: Mapping[str, str] | None) -> float:
    """``drive.velocity_scale`` of a logged config record (its default where the text does not say or load)."""
    from drivers.config import DriveConfig
    from foilc_hil.errors import FoilcHilError
    from foilc_hil.schema import load_yaml_text

    default = float(DriveConfig().velocity_scale)
    if record is None or "yaml" not in record:
        return default
    try:
        document = load_yaml_text(record["yaml"]) or {}
        return float(DriveConfig.model_validate(document.get("drive") or {}).velocity_scale)
    except (FoilcHilError, ValueError, AttributeError, TypeError):
        return default


def stream_log(
    path: str, server: LiveServer, *, rate: float = 1.0, can_rate: float = 500.0,
    clock: Callable[[], float] = time.monotonic, sleep: Callable[[float], None] = time.sleep,
) -> StreamReport:
    """Send the log at ``path`` to ``server``'s viewers at ``rate`` times its recorded pace (see the module)."""
    report = StreamReport()
    states = WireStates()
    sent_states: dict[int, tuple[DriveState, int]] = {}  # node -> the last state sent, its log time
    first_log: int | None = None
    start = last_refill = clock()
    credit = 0.0
    with McapLogReader(path) as reader:
        for message in reader.iter_messages():
            if first_log is None:
                first_log = message.log_time_ns
            delay = start + (message.log_time_ns - first_log) / 1e9 / rate - clock()
            if delay > _SLEEP_FLOOR:
                sleep(delay)
            topic, log_time = message.topic, message.log_time_ns
            if topic == TOPIC_CAN:
                states.learn(reader.metadata)
                state = states.frame(message.data)
                if state is not None:
                    _send_state(server, state, log_time, sent_states, report)
                now = clock()
                credit = min(credit + can_rate * (now - last_refill), max(1.0, can_rate * 0.04))
                last_refill = now
                if credit < 1.0:
                    report.frames_skipped += 1
                    continue
                credit -= 1.0
            if server.wanted(topic):
                server.log(topic, orjson.dumps(message.data), log_time)
                report.published[topic] = report.published.get(topic, 0) + 1
        report.damage = reader.damage
    report.duration = clock() - start
    return report


def _send_state(server: LiveServer, state: DriveState, log_time: int, sent: dict[int, tuple[DriveState, int]],
                report: StreamReport) -> None:
    """``/drive/state`` at a change, or :data:`STATE_PERIOD` of recorded time after the last one sent."""
    last = sent.get(state.node)
    if last is not None and not state.changed_from(last[0]) and log_time - last[1] < STATE_PERIOD * 1e9:
        return
    sent[state.node] = (state, log_time)
    if server.wanted(TOPIC_DRIVE_STATE):
        server.log(TOPIC_DRIVE_STATE, drive_state_document(state), log_time)
        report.published[TOPIC_DRIVE_STATE] = report.published.get(TOPIC_DRIVE_STATE, 0) + 1
