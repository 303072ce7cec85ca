"""The MCAP layout of a foilc-hil log: topics, JSON schemas, metadata record names.

Fixed by ``docs/interface.md`` ("MCAP layout"). Schema encoding ``jsonschema``, message encoding ``json``,
so Foxglove opens the files as they are. The schemas here are what is registered in every file; changing a field
name is a breaking change for users' scripts.

Signals in ``/ilc/sample`` (``reference``, ``output``, ``control``, ``error``, ``E``) are JSON numbers for a
single-input single-output axis and arrays of numbers (one entry per output or input) for a multi-variable one;
the schema allows both, so a SISO log plots directly in Foxglove. ``E`` (the fractional PD function of eq. (15))
is ``null`` for laws that do not form it (P-type).
"""

from __future__ import annotations

import json
from typing import Any, Final

import yaml

__all__ = [
    "CAN_FRAME_SCHEMA",
    "DIRECTIONS",
    "DRIVE_STATES",
    "DRIVE_STATE_SCHEMA",
    "ILC_SAMPLE_SCHEMA",
    "ILC_TRIAL_SCHEMA",
    "JSON_SCHEMA_DIALECT",
    "LIVE_TOPICS",
    "MESSAGE_ENCODING",
    "METADATA_AXIS_PREFIX",
    "METADATA_CLOSING",
    "METADATA_CONFIG",
    "METADATA_DESIGN",
    "METADATA_LAYOUT",
    "METADATA_PDO_MAPPING",
    "SAMPLE_LAYOUT",
    "SCHEMA_ENCODING",
    "TIMING_SCHEMA",
    "TOPICS",
    "TOPIC_CAN",
    "TOPIC_DRIVE_STATE",
    "TOPIC_SAMPLE",
    "TOPIC_TIMING",
    "TOPIC_TRIAL",
    "schema_bytes",
]

SCHEMA_ENCODING: Final = "jsonschema"
#: ``$schema`` of every schema: the dialect its keywords are read in (``contentEncoding``, ``oneOf``, type lists)
JSON_SCHEMA_DIALECT: Final = "https://json-schema.org/draft/2020-12/schema"
MESSAGE_ENCODING: Final = "json"

TOPIC_CAN: Final = "/can"
TOPIC_SAMPLE: Final = "/ilc/sample"
TOPIC_TRIAL: Final = "/ilc/trial"
TOPIC_TIMING: Final = "/timing"
#: the live view's drive state (``run --live``, ``replay --live``); never written to a log: see :data:`LIVE_TOPICS`
TOPIC_DRIVE_STATE: Final = "/drive/state"

#: metadata record holding ``{"yaml": <the resolved config as YAML text>}``
METADATA_CONFIG: Final = "foilc_hil.config"
#: metadata record holding the design (gains, certificates); each value is a JSON text (MCAP metadata is str -> str)
METADATA_DESIGN: Final = "foilc_hil.design"

#: a run of several axes (``axes:``) also writes, per axis, ``foilc_hil.axis.<node id>.config`` (``{"yaml": ...}``: the
#: axis's own single-axis config) and ``foilc_hil.axis.<node id>.design`` (its design, as ``foilc_hil.design``);
#: the ``foilc_hil.config`` and ``foilc_hil.design`` records are the whole document's and the first axis's design
METADATA_AXIS_PREFIX: Final = "foilc_hil.axis"

#: metadata record holding ``{"ilc_sample": "<version>", "closing": "1"}``: how ``/ilc/sample`` rows align (absent:
#: version 1), and that the writer closes the log with :data:`METADATA_CLOSING` (absent: a log written before it)
METADATA_LAYOUT: Final = "foilc_hil.layout"
#: the ``/ilc/sample`` layout the bench writes. 1 (logs without ``foilc_hil.layout``): row ``i`` has ``t = i Ts``,
#: ``output = y(i Ts)`` but ``reference``, ``error``, ``E`` at ``(i + 1) Ts``. 2: every field of row ``i`` is at
#: ``t = (i + 1) Ts`` -- ``output = y(t)``, ``error = reference - output`` exactly -- and ``control`` is the command
#: applied from ``t`` (computed from ``y(i Ts)``: the previous row's output, or ``/ilc/trial`` ``initial_output``).
SAMPLE_LAYOUT: Final = 2

#: metadata record holding the PDO mapping ``run`` installed: ``{"rpdos": <JSON>, "tpdos": <JSON>}``, each a list
#: of ``{"number", "cob_id", "transmission_type", "variables": [[index, subindex, bits, signed], ...]}``
#: (:func:`foilc_hil.io.pdo_mapping.encode_pdo_mapping`); ``export --format dbc`` reads it. Written after the drive
#: is configured.
METADATA_PDO_MAPPING: Final = "foilc_hil.pdo_mapping"
#: metadata record the writer adds when it closes the log: what it wrote, for ``replay --verify`` to hold the file
#: against (a trial, a sample or a frame gone is found, the last trial's included): ``{"trials": "[1, 2, ...]"`` (the
#: ``/ilc/trial`` records, in order), ``"samples": "[N1, N2, ...]"`` (``/ilc/sample`` rows of each trial),
#: ``"frames": "<count>"`` (``/can`` messages in all)}; each value JSON text. A log without it was cut (or written
#: before it existed).
METADATA_CLOSING: Final = "foilc_hil.closing"


#: values of ``/can`` ``dir``: sent by the bench, received by the bench
DIRECTIONS: Final = ("tx", "rx")

_SIGNAL: Final[dict[str, Any]] = {
    "oneOf": [
        {"type": "number"},
        {"type": "array", "items": {"type": "number"}},
    ],
}

def _flag(description: str) -> dict[str, Any]:
    return {"type": "boolean", "default": False, "description": description}


CAN_FRAME_SCHEMA: Final[dict[str, Any]] = {
    "$schema": JSON_SCHEMA_DIALECT,
    "title": "foilc_hil.CanFrame",
    "description": "One CAN frame the bench sent (tx) or received (rx); the flags are written only when set.",
    "type": "object",
    "properties": {
        "timestamp": {"type": "number", "description": "bus timestamp, seconds (python-can Message.timestamp)"},
        "id": {"type": "integer", "minimum": 0, "description": "arbitration id"},
        "extended": {"type": "boolean", "description": "29-bit identifier"},
        "dlc": {
            "type": "integer",
            "minimum": 0,
            "maximum": 64,
            "description": "python-can Message.dlc: the DLC code of a classic frame (0..15), the data length of an "
            "FD frame (up to 64)",
        },
        "data": {"type": "string", "contentEncoding": "base64", "description": "payload bytes"},
        "dir": {"type": "string", "enum": list(DIRECTIONS)},
        "remote": _flag("remote transmission request (RTR)"),
        "error": _flag("an error frame: a bus event, never a frame to transmit"),
        "fd": _flag("CAN FD frame"),
        "brs": _flag("CAN FD bit rate switch"),
        "esi": _flag("CAN FD error state indicator"),
        "channel": {"type": ["string", "integer"], "description": "python-can Message.channel, where known"},
    },
    "required": ["timestamp", "id", "extended", "dlc", "data", "dir"],
}

ILC_SAMPLE_SCHEMA: Final[dict[str, Any]] = {
    "$schema": JSON_SCHEMA_DIALECT,
    "title": "foilc_hil.IlcSample",
    "description": "One sample of one trial: what the learning law saw (output) and what it commanded (control).",
    "type": "object",
    "properties": {
        "trial": {"type": "integer", "minimum": 1, "description": "trial index k, from 1"},
        "t": {"type": "number", "description": "time within the trial, seconds: the instant of every signal"},
        "sample": {"type": "integer", "minimum": 0, "description": "sample index within the trial"},
        "axis": {"type": "integer", "minimum": 1, "maximum": 127, "description": "the axis's node id (axes: runs)"},
        "reference": {**_SIGNAL, "description": "y_r(t)"},
        "output": {**_SIGNAL, "description": "measured feedback y(t, k)"},
        "control": {**_SIGNAL, "description": "command u(t, k) the law produced, applied from t when its RPDO came "
                    "before the SYNC at t (see latched)"},
        "latched": {**_SIGNAL, "description": "the command the drive latched at the SYNC at t, as sent (clamped, "
                    "quantised, plant units): control when its RPDO came before that SYNC, else the last RPDO before "
                    "it (a missed deadline); known from the bus. Absent in logs written before it"},
        "error": {**_SIGNAL, "description": "e = y_r - y"},
        "E": {
            "oneOf": [*_SIGNAL["oneOf"], {"type": "null"}],
            "description": "fractional PD function E = e + kp D^r e (eq. 15); null if the law has none",
        },
    },
    "required": ["trial", "t", "reference", "output", "control", "error", "E"],
}

ILC_TRIAL_SCHEMA: Final[dict[str, Any]] = {
    "$schema": JSON_SCHEMA_DIALECT,
    "title": "foilc_hil.IlcTrial",
    "description": "Tracking metrics of one completed trial (extra fields allowed).",
    "type": "object",
    "properties": {
        "trial": {"type": "integer", "minimum": 1},
        "sse": {"type": "number", "description": "sum of squared errors"},
        "rmse": {"type": "number"},
        "max_abs_error": {"type": "number"},
        "lost_feedback": {
            "type": "integer",
            "minimum": 0,
            "description": "SYNCs of the trial without a complete TPDO set in time (the law held the last good one)",
        },
        "bad_frames": {"type": "integer", "minimum": 0, "description": "frames of the trial that did not decode"},
        "demand_mismatches": {
            "type": "integer",
            "minimum": 0,
            "description": "samples whose demand echo (0x606B / 0x6074, drive.demand_echo) is not latched; absent "
                           "without an echo",
        },
        "axis": {"type": "integer", "minimum": 1, "maximum": 127, "description": "the axis's node id (axes: runs)"},
    },
    "required": ["trial", "sse", "rmse", "max_abs_error"],
    "additionalProperties": True,
}

TIMING_SCHEMA: Final[dict[str, Any]] = {
    "$schema": JSON_SCHEMA_DIALECT,
    "title": "foilc_hil.CycleTiming",
    "description": "Timing of one real-time bench cycle.",
    "type": "object",
    "properties": {
        "cycle": {"type": "integer", "minimum": 0, "description": "cycle counter over the whole run"},
        "trial": {"type": "integer", "minimum": 0},
        "sample": {"type": "integer", "minimum": 0},
        "lateness_us": {"type": "number", "description": "SYNC sent this late after its absolute deadline"},
        "period_us": {"type": "number", "description": "time since the previous cycle's SYNC"},
        "feedback_latency_us": {
            "type": ["number", "null"],
            "description": "SYNC to TPDO feedback; null when no feedback arrived",
        },
        "missed": {"type": "boolean", "description": "the cycle missed its deadline"},
        "lost_feedback": {
            "type": "boolean",
            "description": "no TPDO set answered the SYNC within its bound; the law held the last good feedback",
        },
    },
    "required": ["cycle", "trial", "sample", "lateness_us", "period_us", "feedback_latency_us", "missed"],
}

#: the CiA 402 states ``/drive/state`` names (``drivers.cia402.State402``'s names, in its order)
DRIVE_STATES: Final = (
    "NOT_READY_TO_SWITCH_ON", "SWITCH_ON_DISABLED", "READY_TO_SWITCH_ON", "SWITCHED_ON", "OPERATION_ENABLED",
    "QUICK_STOP_ACTIVE", "FAULT_REACTION_ACTIVE", "FAULT",
)

DRIVE_STATE_SCHEMA: Final[dict[str, Any]] = {
    "$schema": JSON_SCHEMA_DIALECT,
    "title": "foilc_hil.DriveState",
    "description": "One axis's drive as the bench last saw it: the CiA 402 state of its statusword and its "
    "feedback (live view only: run --live polls the master, replay --live decodes the logged TPDOs).",
    "type": "object",
    "properties": {
        "node": {"type": "integer", "minimum": 1, "maximum": 127, "description": "the drive's node id"},
        "cycle": {"type": "integer", "minimum": 0, "description": "the SYNC this feedback answered (the master's "
                  "SYNC counter; replay: the count of logged SYNCs)"},
        "state": {"type": "string", "enum": list(DRIVE_STATES), "description": "decoded from the statusword"},
        "statusword": {"type": "integer", "minimum": 0, "maximum": 65535, "description": "0x6041"},
        "controlword": {"type": ["integer", "null"], "minimum": 0, "maximum": 65535,
                        "description": "0x6040 the master sends; null where not known (replay)"},
        "velocity": {"type": ["number", "null"], "description": "0x606C in plant units (velocity_unit); null where "
                     "not mapped"},
    },
    "required": ["node", "cycle", "state", "statusword", "controlword", "velocity"],
}

#: topic -> (schema name, schema): what every log registers (the MCAP layout)
TOPICS: Final[dict[str, tuple[str, dict[str, Any]]]] = {
    TOPIC_CAN: ("foilc_hil.CanFrame", CAN_FRAME_SCHEMA),
    TOPIC_SAMPLE: ("foilc_hil.IlcSample", ILC_SAMPLE_SCHEMA),
    TOPIC_TRIAL: ("foilc_hil.IlcTrial", ILC_TRIAL_SCHEMA),
    TOPIC_TIMING: ("foilc_hil.CycleTiming", TIMING_SCHEMA),
}

#: topic -> (schema name, schema): the live view's channels (``foilc_hil.io.live``): the log's, and ``/drive/state``
LIVE_TOPICS: Final[dict[str, tuple[str, dict[str, Any]]]] = {
    **TOPICS,
    TOPIC_DRIVE_STATE: ("foilc_hil.DriveState", DRIVE_STATE_SCHEMA),
}


#: units of the fields whose unit does not depend on the config (channel metadata ``units``)
_FIXED_UNITS: Final[dict[str, dict[str, str]]] = {
    TOPIC_CAN: {"timestamp": "s"},
    TOPIC_SAMPLE: {"t": "s"},
    TOPIC_TRIAL: {},
    TOPIC_TIMING: {"lateness_us": "us", "period_us": "us", "feedback_latency_us": "us"},
}


def _signal_units(config_yaml: str | None) -> tuple[str, str] | None:
    """(output unit, command unit) from the logged ``drive:`` section; ``None`` when the text does not load."""
    from drivers.config import DriveConfig
    from foilc_hil.errors import FoilcHilError
    from foilc_hil.schema import load_yaml_text

    if config_yaml is None:
        return None
    try:
        document = load_yaml_text(config_yaml) or {}
        drive = DriveConfig.model_validate(document.get("drive") or {})
    except (FoilcHilError, ValueError, AttributeError, yaml.YAMLError):  # units are a courtesy: never fail a log
        return None
    # the bench logs in plant units: velocities in velocity_unit; the command is a torque in cst mode
    return drive.velocity_unit, drive.torque_unit if drive.mode == "cst" else drive.velocity_unit


def channel_metadata(config_yaml: str | None) -> dict[str, dict[str, str]]:
    """Channel metadata per topic: ``{"units": <JSON object field -> unit>}``.

    Time fields always carry their unit; ``/ilc/sample`` signals and ``/ilc/trial`` errors carry the plant units of
    the logged ``drive:`` section (``velocity_unit``; ``control`` and ``latched`` in ``torque_unit`` in ``cst``
    mode) when ``config_yaml`` loads. Metadata only: the schemas and messages are unchanged.
    """
    units = {topic: dict(fixed) for topic, fixed in _FIXED_UNITS.items()}
    signal = _signal_units(config_yaml)
    if signal is not None:
        output, command = signal
        units[TOPIC_SAMPLE].update({"reference": output, "output": output, "error": output, "E": output,
                                    "control": command, "latched": command})
        units[TOPIC_TRIAL].update({"sse": f"{output}^2", "rmse": output, "max_abs_error": output})
    return {topic: {"units": json.dumps(fields, sort_keys=True)} for topic, fields in units.items()}


def schema_bytes(schema: dict[str, Any]) -> bytes:
    """The schema as the UTF-8 JSON text stored in the MCAP schema record."""
    return json.dumps(schema, sort_keys=True).encode("utf-8")
