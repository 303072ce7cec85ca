"""``foilc-hil tune``: tune the fractional PD function's ``kp``, ``r`` (and ``K``) from a loop specification.

The open loop is ``L(s) = K (1 + kp s^r) G(s)``; see :mod:`foilc_hil.design.tuning` for the method and its checks.
JSON (``--json``): ``{"K", "kp", "r", "crossover", "phase_margin_deg", "plant": {"num", "den", "delay"},
"achieved": {"crossover", "phase_margin_deg"}, "mode", "flat_phase", "solutions", "checks"}``.
Exit 3 when no ``kp > 0``, ``0 < r < 2`` meets the specification; the message says why.
"""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

from foilc_hil.commands import CommandResult

if TYPE_CHECKING:
    from foilc_hil.design.tuning import TuningResult

HELP = "tune the fractional PD function's kp and r from loop specifications"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``tune``."""
    parser.add_argument("--config", required=True, help="YAML configuration file (plant: and tuning: sections)")
    parser.add_argument(
        "--crossover", type=float, default=None, metavar="W", help="gain crossover, rad/s (default: tuning.crossover)"
    )
    parser.add_argument(
        "--phase-margin",
        type=float,
        default=None,
        metavar="DEG",
        help="phase margin, degrees (default: tuning.phase_margin_deg)",
    )
    parser.add_argument(
        "--flat-phase",
        action="store_true",
        default=None,
        help="also require d arg L/dw = 0 at the crossover and solve the loop gain K (default: tuning.flat_phase)",
    )
    parser.add_argument("--json", action="store_true", help="print one JSON document on stdout")


def execute(args: argparse.Namespace) -> CommandResult:
    """Load the config with the command-line overrides, tune (or evaluate kp/r), and report."""
    from foilc_hil.config import load_config
    from foilc_hil.design.tuning import tune

    overrides = {
        "tuning.crossover": args.crossover,
        "tuning.phase_margin_deg": args.phase_margin,
        "tuning.flat_phase": True if args.flat_phase else None,
    }
    config = load_config(args.config, overrides)
    result = tune(config)
    return CommandResult(document=result.to_json(), text=render(result))


def _number(value: float | None, digits: int = 6) -> str:
    return "-" if value is None else f"{value:.{digits}g}"


def render(result: TuningResult) -> str:
    """A short human summary: the gains, the spec against what the dense sweep achieved, the checks."""
    num = ", ".join(f"{x:.6g}" for x in result.plant_num)
    den = ", ".join(f"{x:.6g}" for x in result.plant_den)
    plant = f"G(s) = [{num}] / [{den}]"
    if result.plant_delay:
        plant += f" * exp(-{result.plant_delay:g} s)"
    title = "solved from the loop specification" if result.mode == "spec" else "given kp and r, evaluated"
    lines = [
        f"L(s) = K (1 + kp s^r) G(s), {plant}  [{title}{', flat phase' if result.flat_phase else ''}]",
        f"  K  = {_number(result.K, 8)}",
        f"  kp = {_number(result.kp, 8)}",
        f"  r  = {_number(result.r, 8)}",
        f"{'':18}{'spec':>12}{'achieved':>12}",
    ]
    spec_crossover = result.crossover if result.mode == "spec" else None
    spec_margin = result.phase_margin_deg if result.mode == "spec" else None
    lines.append(f"{'crossover rad/s':18}{_number(spec_crossover):>12}{_number(result.achieved_crossover):>12}")
    lines.append(f"{'phase margin deg':18}{_number(spec_margin):>12}{_number(result.achieved_phase_margin_deg):>12}")
    sweep = result.checks.sweep
    if sweep.gain_margin_db is not None:
        lines.append(f"gain margin {sweep.gain_margin_db:.3g} dB at {sweep.phase_crossover:.4g} rad/s (sweep)")
    check = result.checks.python_control
    if check is not None and check.crossover is not None:
        lines.append(
            f"python-control (Oustaloup/Pade model): crossover {check.crossover:.6g} rad/s, phase margin "
            f"{check.phase_margin_deg:.4g} deg -> {'agrees' if check.agrees_with_sweep else 'DISAGREES'} with the "
            "sweep"
            + (
                f"; closed loop {'stable' if check.closed_loop_stable else 'UNSTABLE'}"
                if check.closed_loop_stable is not None
                else ""
            )
        )
    if len(result.solutions) > 1:
        lines.append(f"{len(result.solutions)} solutions found; chosen by: {result.checks.selection}")
    for warning in result.checks.warnings:
        lines.append(f"warning: {warning}")
    return "\n".join(lines)
