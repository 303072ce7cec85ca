"""``foilc-hil export F.mcap --format asc|blf|csv --out FILE``: the log's CAN frames through python-can's writers.

JSON: ``{"log", "out", "format", "frames", "truncated", "damage"}``. A missing or non-MCAP log exits 2.
"""

from __future__ import annotations

import argparse
import sys

from foilc_hil.commands import CommandResult

HELP = "write a log's CAN frames as ASC, BLF or CSV"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("log", metavar="F.mcap", help="the log to export")
    parser.add_argument("--format", required=True, choices=("asc", "blf", "csv"), help="output format")
    parser.add_argument("--out", required=True, metavar="FILE", help="file to write")


def execute(args: argparse.Namespace) -> CommandResult:
    from foilc_hil.logtools.export import export_frames

    result = export_frames(args.log, args.out, args.format)
    if result.truncated:
        sys.stderr.write(f"foilc-hil export: {args.log}: {result.damage}; exported the frames read before it\n")
    document = {
        "log": str(args.log),
        "out": str(result.out),
        "format": result.format,
        "frames": result.frames,
        "truncated": result.truncated,
        "damage": result.damage or None,
    }
    text = f"wrote {result.frames} frames to {result.out} ({result.format})" + (
        " from a truncated log" if result.truncated else ""
    )
    return CommandResult(document, text)
