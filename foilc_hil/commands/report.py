"""``foilc-hil report F.mcap --out DIR``: plots (PNG) and a summary (JSON and Markdown) of a log.

JSON: the summary document (``{"log", "truncated", "damage", "trials", "completed_trials", "incomplete_trials",
"samples", "frames", "design", "timing", "plots", ...}``) plus ``"out"``, the directory written. A truncated log
is reported as far as it goes (a warning on stderr, ``truncated: true``); a missing or non-MCAP file exits 2.
"""

from __future__ import annotations

import argparse
import sys

from foilc_hil.commands import CommandResult

HELP = "plots and a summary of a log"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("log", metavar="F.mcap", help="the log to report on")
    parser.add_argument("--out", required=True, metavar="DIR", help="directory for the PNG plots and summaries")


def execute(args: argparse.Namespace) -> CommandResult:
    from foilc_hil.logtools.report import write_report

    files = write_report(args.log, args.out)
    summary = files.summary
    if summary["truncated"]:
        sys.stderr.write(f"foilc-hil report: {args.log}: {summary['damage']}; reporting what was read before it\n")
    document = {**summary, "out": str(files.directory)}
    lines = [
        f"{args.log}: {summary['completed_trials']} completed trials, {summary['samples']} samples"
        + (" (truncated log)" if summary["truncated"] else ""),
        f"wrote {', '.join(summary['plots']) or 'no plots'}, {files.summary_json.name}, {files.summary_markdown.name} "
        f"to {files.directory}",
    ]
    return CommandResult(document, "\n".join(lines))
