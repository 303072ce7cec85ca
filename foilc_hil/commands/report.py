"""``foilc-hil report F.mcap --out DIR``: plots (PNG) and a summary (JSON and Markdown) of a log.

JSON: the summary document (``{"log", "truncated", "damage", "trials", "completed_trials", "incomplete_trials",
"samples", "frames", "design", "timing", "plots", ...}``) plus ``"out"``, the directory written. A truncated log
is reported as far as it goes (``truncated`` and ``partial`` true) and exits 1 with one line saying what was
reported; a missing or non-MCAP file exits 2.
"""

from __future__ import annotations

import argparse

from foilc_hil.commands import CommandResult
from foilc_hil.errors import ExitCode

HELP = "plots and a summary of a log"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("log", metavar="F.mcap", help="the log to report on")
    parser.add_argument("--out", required=True, metavar="DIR", help="directory for the PNG plots and summaries")


def execute(args: argparse.Namespace) -> CommandResult:
    from foilc_hil.logtools.report import write_report

    files = write_report(args.log, args.out)
    summary = files.summary
    document = {**summary, "out": str(files.directory)}
    lines = [
        f"{args.log}: {summary['completed_trials']} completed trials, {summary['samples']} samples"
        + (" (truncated log)" if summary["truncated"] else ""),
        f"wrote {', '.join(summary['plots']) or 'no plots'}, {files.summary_json.name}, {files.summary_markdown.name} "
        f"to {files.directory}",
    ]
    if summary["truncated"]:
        # Why exit 1: a report of part of a log must not pass for a report of the whole run in a script
        return CommandResult(
            document,
            "\n".join(lines),
            exit_code=ExitCode.RUNTIME_FAILURE,
            message=f"partial: {args.log}: {summary['damage']}; reported the {summary['completed_trials']} trials "
            "read before it, the rest of the log is not in the report",
        )
    return CommandResult(document, "\n".join(lines))
