"""Standard CiA 402 drives that lack optional objects (issue 12): the shipped EDS without some objects, a config whose
drive and emulator load such EDS files, and ``foilc-hil`` run in this process with ``--json``. Used by
``tests/integration/test_standard_drives.py``, the commissioning tests and the DBC tests.
"""

from __future__ import annotations

import contextlib
import io
import json
import re
from pathlib import Path
from typing import Any

import yaml

from drivers.od import DEFAULT_EDS
from foilc_hil.cli import main

NODE = 3


def mutated_eds(tmp_path: Path, *removed: int) -> Path:
    """The shipped EDS without the objects ``removed`` (their sections, sub-index sections and list entries)."""
    text = DEFAULT_EDS.read_text(encoding="utf-8")
    gone = {f"{index:04X}" for index in removed}
    kept: list[str] = []
    skipping = False
    for line in text.splitlines():
        header = re.fullmatch(r"\[([0-9A-Fa-f]{4})(sub[0-9A-Fa-f]+)?\]", line.strip())
        if header is not None or line.startswith("["):
            skipping = header is not None and header.group(1).upper() in gone
        entry = re.fullmatch(r"\d+=0x([0-9A-Fa-f]{4})", line.strip())
        if skipping or (entry is not None and entry.group(1).upper() in gone):
            continue
        kept.append(line)
    # renumber the object lists so they stay a valid CiA 306 list (1..n, SupportedObjects=n)
    out: list[str] = []
    counter = 0
    for line in kept:
        if line.startswith("["):
            counter = 0
        if re.fullmatch(r"\d+=0x[0-9A-Fa-f]{4}", line.strip()):
            counter += 1
            line = f"{counter}={line.split('=', 1)[1]}"
        out.append(line)
    text = "\n".join(out) + "\n"
    for section in ("MandatoryObjects", "OptionalObjects"):
        body = text.split(f"[{section}]\n", 1)[1].split("\n[", 1)[0]
        count = len(re.findall(r"^\d+=0x", body, flags=re.MULTILINE))
        text = re.sub(rf"(\[{section}\]\nSupportedObjects=)\d+", rf"\g<1>{count}", text)
    path = tmp_path / f"without_{'_'.join(sorted(gone))}.eds"
    path.write_text(text, encoding="utf-8")
    return path


def config_file(tmp_path: Path, drive_eds: Path, emulator_eds: Path) -> Path:
    document: dict[str, Any] = {
        "plant": {"model": "first_order", "a": -1.23, "b": 1.68, "c": 1.0},
        "reference": {"profile": "piecewise", "segments": [{"duration": 0.1, "start": 0.0, "end": 20.0}]},
        "sample_time": 0.005,
        "trials": 2,
        "law": {"kind": "p-type"},
        "drive": {"node_id": NODE, "eds": str(drive_eds), "velocity_limit": 500.0,
                  "heartbeat_timeout_factor": 10.0, "heartbeat_consumer_ms": 2000},
        "emulator": {"eds": str(emulator_eds)},
        "bench": {"settle_time": 0.01, "settle_tolerance": 0.5},
    }
    path = tmp_path / "standard.yaml"
    path.write_text(yaml.safe_dump(document), encoding="utf-8")
    return path


def cli(*argv: str) -> tuple[int, dict[str, Any]]:
    stdout = io.StringIO()
    with contextlib.redirect_stdout(stdout):
        code = main([*argv, "--json"])
    return code, json.loads(stdout.getvalue())
