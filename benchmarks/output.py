"""The benchmarks' common command line: an ``--out`` option and one JSON document written there or to stdout."""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any


def json_parser(prog: str, description: str | None) -> argparse.ArgumentParser:
    """An argument parser with the ``--out`` option every benchmark takes."""
    parser = argparse.ArgumentParser(prog=prog, description=description)
    parser.add_argument("--out", help="JSON file to write (default: stdout)")
    return parser


def emit(document: dict[str, Any], out: str | None) -> None:
    """Write ``document`` as indented JSON to ``out`` (saying so on stderr), or to stdout."""
    text = json.dumps(document, indent=2) + "\n"
    if out:
        Path(out).write_text(text, encoding="utf-8")
        sys.stderr.write(f"wrote {out}\n")
    else:
        sys.stdout.write(text)
