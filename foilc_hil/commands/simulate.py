"""``foilc-hil simulate``: learning trials offline on the physics model, with no bus.

JSON (``--json``): ``{"law", "trials": [{"trial", "sse", "rmse", "max_abs_error"}, ...], "certificates",
"design"?, "stopped"?, "log"?, "plots"?}``. Exit 1 (with the document still printed) when learning diverged and
the run was stopped.
"""

from __future__ import annotations

import argparse

from foilc_hil.commands import CommandResult

HELP = "run learning trials offline, with no bus"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``simulate``."""
    parser.add_argument("--config", required=True, help="YAML configuration file")
    parser.add_argument(
        "--law",
        choices=("foilc", "ioilc", "p-type", "noilc", "gradient"),
        default=None,
        help="learning law (default: law.kind)",
    )
    parser.add_argument(
        "--design",
        choices=("paper", "codesign"),
        default=None,
        help="FOILC: the paper's method (tuner + LMI) or the co-design (default: synthesis.design)",
    )
    parser.add_argument("--trials", type=int, default=None, help="number of trials (default: trials)")
    parser.add_argument(
        "--input-delay",
        type=int,
        default=0,
        help="samples of input delay between command and plant (1 emulates the SYNC-driven CAN loop)",
    )
    parser.add_argument("--out", default=None, help="write an MCAP log of the run to this file")
    parser.add_argument("--plots", default=None, metavar="DIR", help="write PNG plots into DIR")
    parser.add_argument("--json", action="store_true", help="print one JSON document on stdout")


def execute(args: argparse.Namespace) -> CommandResult:
    """Load the config, design (tune + synthesize) unless P-type, run the trials, report per-trial metrics."""
    from foilc_hil.config import load_config
    from foilc_hil.errors import ConfigError, ExitCode, InputError
    from foilc_hil.loop.simulation import plot_simulation, simulate

    config = load_config(args.config, {"law.kind": args.law, "trials": args.trials, "synthesis.design": args.design})
    if args.trials is not None and args.trials < 1:
        raise ConfigError(f"must be >= 1, got {args.trials}", key="--trials")
    if args.input_delay < 0:
        raise InputError(f"--input-delay: must be >= 0, got {args.input_delay}")
    if args.out is not None:
        from foilc_hil.io.mcap_writer import check_log_path

        check_log_path(args.out)  # before the (possibly slow) design
    result = simulate(config, law=config.law.kind, trials=config.trials, input_delay=args.input_delay, out=args.out)
    document = result.to_json()
    if args.out is not None:
        document["log"] = str(args.out)
    if args.plots is not None:
        document["plots"] = [str(path) for path in plot_simulation(result, args.plots)]
    lines = [f"{result.law}: {len(result.metrics)} trial(s) in {result.seconds:.2f} s"]
    lines.append(f"{'trial':>5} {'SSE':>12} {'RMSE':>12} {'max|e|':>12}")
    for metric in result.metrics:
        lines.append(f"{metric.trial:>5} {metric.sse:>12.6g} {metric.rmse:>12.6g} {metric.max_abs_error:>12.6g}")
    if result.stopped:
        return CommandResult(
            document=document,
            text="\n".join(lines),
            exit_code=ExitCode.RUNTIME_FAILURE,
            message=result.stopped,
        )
    return CommandResult(document=document, text="\n".join(lines))
