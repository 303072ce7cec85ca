"""``foilc-hil robustness``: a designed law certified on plants drawn from the uncertainty set, on Dask.

The law is designed with the one pipeline (``build_design``), then certified on every uncertainty vertex and on
``--samples`` seeded random plants of the set (:mod:`foilc_hil.design.robustness`). The draws run on a Dask
local cluster by default (``--workers`` processes, no dashboard, bound to 127.0.0.1 only), on a running cluster
with ``--scheduler tcp://HOST:PORT``, or in this process with ``--scheduler synchronous`` / ``threads``.
JSON (``--json``): :meth:`~foilc_hil.design.robustness.RobustnessResult.to_json`. Exit 3 when the law cannot be
designed; the distribution is reported whatever it shows (exit 0).
"""

from __future__ import annotations

import argparse
import contextlib
from collections.abc import Iterator
from typing import TYPE_CHECKING, Any

from foilc_hil.commands import CommandResult
from foilc_hil.config import LawKind

if TYPE_CHECKING:
    from foilc_hil.design.robustness import RobustnessResult

HELP = "certify a designed law on plants drawn from the uncertainty set (Monte Carlo on Dask)"

#: ``--scheduler`` values that run in this process, without ``dask.distributed``.
LOCAL_SCHEDULERS = ("synchronous", "threads")
#: The only address a local cluster binds to (the network rules: no traffic beyond loopback).
LOOPBACK = "127.0.0.1"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``robustness``."""
    parser.add_argument("--config", required=True, help="YAML configuration file")
    parser.add_argument(
        "--law",
        choices=tuple(kind.value for kind in LawKind),
        default=None,
        help="law to design and certify (default: law.kind)",
    )
    parser.add_argument("--samples", type=int, default=100, help="random plants besides the vertices (default 100)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the draws (default 0)")
    parser.add_argument(
        "--scheduler",
        default=None,
        metavar="ADDRESS",
        help="a Dask scheduler address (tcp://host:port), or 'synchronous'/'threads' to run in this process "
        "(default: a local cluster of --workers processes on 127.0.0.1)",
    )
    parser.add_argument("--workers", type=int, default=2, help="local workers (default 2)")
    parser.add_argument(
        "--input-delay",
        type=int,
        default=1,
        metavar="CYCLES",
        help="cycles of input delay in the design model (default 1: the SYNC-driven CAN loop and simulate)",
    )
    parser.add_argument("--json", action="store_true", help="print one JSON document on stdout")


@contextlib.contextmanager
def _scheduler(address: str | None, workers: int) -> Iterator[Any]:
    """The scheduler :func:`~foilc_hil.design.robustness.robustness` computes with, closed on exit."""
    if address in LOCAL_SCHEDULERS:
        yield address
        return
    from distributed import Client, LocalCluster

    from foilc_hil.errors import InputError

    if address is None:
        with (
            LocalCluster(
                n_workers=workers, threads_per_worker=1, processes=True, host=LOOPBACK, dashboard_address=None
            ) as cluster,
            Client(cluster) as client,
        ):
            yield client
        return
    try:
        client = Client(address, timeout=10)
    except OSError as exc:
        raise InputError(f"--scheduler: cannot reach {address}: {exc}") from None
    with client:
        yield client


def _text(result: RobustnessResult) -> str:
    lines = [
        f"law {result.law}: {len(result.draws)} plants ({result.vertices} vertices, {result.samples} random, "
        f"seed {result.seed}), trials of {result.n_samples} samples",
        f"design's worst case (nominal and vertices): spectral radius {result.design_spectral_radius:.6g}, "
        f"induced 2-norm {result.design_norm_2:.6g}",
    ]
    for key, name in (("spectral_radius", "spectral radius"), ("norm_2", "induced 2-norm")):
        worst = result.worst(key)
        quantiles = ", ".join(f"q{q} {v:.6g}" for q, v in result.quantiles(key).items())
        where = "a vertex" if worst.vertex else "a random plant"
        lines.append(f"{name}: worst {getattr(worst, key):.6g} (draw {worst.index}, {where}); {quantiles}")
    lines.append(
        f"certified monotonic on {100 * result.fraction_monotonic:.1f} % of the plants, "
        f"asymptotic on {100 * result.fraction_asymptotic:.1f} %"
    )
    return "\n".join(lines)


def execute(args: argparse.Namespace) -> CommandResult:
    """Design the law with the one pipeline, then certify it on the drawn plants."""
    from foilc_hil.config import load_config
    from foilc_hil.design.pipeline import build_design
    from foilc_hil.design.robustness import robustness, running_law
    from foilc_hil.errors import InputError
    from foilc_hil.references import trial_samples

    for name, value in (("--samples", args.samples), ("--seed", args.seed), ("--input-delay", args.input_delay)):
        if value < 0:
            raise InputError(f"{name}: must be >= 0, got {value}")
    if args.workers < 1:
        raise InputError(f"--workers: must be >= 1, got {args.workers}")
    address = args.scheduler
    if not (address is None or address in LOCAL_SCHEDULERS or address.startswith(("tcp://", "tls://"))):
        raise InputError(f"--scheduler: {address!r} is not tcp://HOST:PORT, tls://HOST:PORT, synchronous or threads")
    config = load_config(args.config, {})
    n_samples = trial_samples(config.reference, config.sample_time)
    design = build_design(config, args.law or config.law.kind, n_samples, input_delay=args.input_delay)
    law = running_law(config, design, n_samples)
    with _scheduler(args.scheduler, args.workers) as scheduler:
        result = robustness(design, law, samples=args.samples, seed=args.seed, scheduler=scheduler,
                            workers=args.workers)
    return CommandResult(document=result.to_json(), text=_text(result))
