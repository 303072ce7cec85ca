"""``foilc-hil export F.mcap --format asc|blf|csv|dbc --out FILE``: the log's CAN frames through python-can's writers,
or the DBC of the PDO mapping the run installed.

JSON: ``{"log", "out", "format", "frames", "truncated", "damage"}``; for ``dbc``: ``{"log", "out", "format",
"dbc": {"file", "frames": [{"name", "arbitration_id", "signals"}]}}``. A missing or non-MCAP log exits 2.
"""

from __future__ import annotations

import argparse
import sys

from foilc_hil.commands import CommandResult

HELP = "write a log's CAN frames as ASC, BLF or CSV, or the DBC of its PDO mapping"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("log", metavar="F.mcap", help="the log to export")
    parser.add_argument("--format", required=True, choices=("asc", "blf", "csv", "dbc"),
                        help="output format (dbc: the mapping the run installed, to decode the frames with)")
    parser.add_argument("--out", required=True, metavar="FILE", help="file to write")


def execute(args: argparse.Namespace) -> CommandResult:
    from foilc_hil.logtools.export import ExportFormat, export_dbc, export_frames

    if args.format == ExportFormat.DBC:
        dbc = export_dbc(args.log, args.out)
        document = {"log": str(args.log), "out": dbc.file, "format": args.format, "dbc": dbc.to_json()}
        return CommandResult(document, f"wrote the DBC of the logged PDO mapping to {dbc.file} "
                                       f"({len(dbc.frames)} frames)")
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
