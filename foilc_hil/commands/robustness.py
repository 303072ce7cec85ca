"""``foilc-hil robustness``: every law over plants drawn from the uncertainty set, trials simulated per draw, on Dask.

The laws are ``--laws``, else the config's ``law.kind`` followed by the others of :data:`DEFAULT_LAWS` (the command
line overrides the file). Each law is designed once with the one pipeline (``build_design``), then certified and
run with ``simulate`` on the box corners and ``--samples`` seeded random plants (:mod:`foilc_hil.loop.robustness`:
frozen and time-varying ``Delta``, the disturbance, sensor noise). The draws run on ``dask.distributed`` only: a
``LocalCluster`` of ``--workers`` processes bound to 127.0.0.1 by default, the in-process cluster with
``--scheduler inprocess`` (threads, in-process transport: no socket), or a running cluster with ``--scheduler
tcp://HOST:PORT`` (``docs/robustness.md``). JSON (``--json``):
:meth:`~foilc_hil.loop.robustness.RobustnessReport.to_json`; with ``--out DIR`` the same document as
``robustness.json`` and the plots. Exit 3 when a law cannot be designed; the distributions are reported whatever
they show (exit 0).
"""

from __future__ import annotations

import argparse
import contextlib
from collections.abc import Iterator
from typing import TYPE_CHECKING, Any

from foilc_hil.commands import CommandResult
from foilc_hil.config import LawKind

if TYPE_CHECKING:
    from foilc_hil.loop.robustness import RobustnessReport

HELP = "run every law over plants drawn from the uncertainty set (Monte Carlo of simulated trials on Dask)"

#: ``--scheduler`` value for a cluster inside this process (threads; in-process transport, no socket).
IN_PROCESS = "inprocess"
#: The only address a local cluster binds to (the network rules: no traffic beyond loopback).
LOOPBACK = "127.0.0.1"
#: The scheduler's HTTP server (health and metrics routes) starts even without a dashboard, by default on
#: ``0.0.0.0:8787``: bound to loopback on an ephemeral port instead.
HTTP_ADDRESS = f"{LOOPBACK}:0"
#: Dask's default environment for a worker process it spawns, changed for the local cluster: ``None`` unsets the
#: variable. Dask sets ``MALLOC_TRIM_THRESHOLD_`` (64 KiB) to hand freed memory back at once; any such setting also
#: turns off glibc's dynamic mmap threshold, so every array of a NOILC draw (a few 32 MB ones) was mapped afresh and
#: faulted in page by page, which made a draw's certificate about twice as slow.

WORKER_ENVIRONMENT: dict[str, str | None] = {"MALLOC_TRIM_THRESHOLD_": None}
#: The laws compared beside the config's ``law.kind`` when ``--laws`` is not given.
DEFAULT_LAWS = (LawKind.FOILC, LawKind.IOILC, LawKind.NOILC)


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of ``robustness``."""
    parser.add_argument("--config", required=True, help="YAML configuration file")
    parser.add_argument(
        "--laws",
        default=None,
        help=f"comma-separated laws among {', '.join(LawKind)} (default: the config's law.kind, then the others of "
        f"{','.join(DEFAULT_LAWS)})",
    )
    parser.add_argument("--samples", type=int, default=100, help="random plants besides the box corners (default 100)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the draws (default 0)")
    parser.add_argument("--trials", type=int, default=None, help="trials per draw (default: the config's trials)")
    parser.add_argument(
        "--noise", type=float, default=None, help="sensor noise std on the output (default plant.output_noise)"
    )
    parser.add_argument(
        "--tolerance",
        type=float,
        default=0.01,
        metavar="FRACTION",
        help="tolerance on the learnable RMSE as a fraction of the reference range (default 0.01)",
    )
    parser.add_argument(
        "--scheduler",
        default=None,
        metavar="ADDRESS",
        help="a Dask scheduler address (tcp://host:port or tls://host:port), or 'inprocess' for a cluster of "
        "threads in this process (default: a local cluster of --workers processes on 127.0.0.1)",
    )
    parser.add_argument("--workers", type=int, default=2, help="local workers (default 2)")
    parser.add_argument(
        "--input-delay",
        type=int,
        default=1,
        metavar="CYCLES",
        help="cycles of input delay in the design and the simulated loop (default 1: the SYNC-driven CAN loop)",
    )
    parser.add_argument("--out", default=None, metavar="DIR", help="write robustness.json and the plots here")
    parser.add_argument("--json", action="store_true", help="print one JSON document on stdout")


@contextlib.contextmanager
def _client(address: str | None, workers: int) -> Iterator[Any]:
    """The ``dask.distributed`` client the draws run on, closed (with its local cluster) on exit."""
    from distributed import Client, LocalCluster

    from foilc_hil.errors import InputError

    if address is None or address == IN_PROCESS:
        import dask

        local = address is None
        options: dict[str, Any] = {"host": LOOPBACK} if local else {}
        environment = {f"distributed.nanny.pre-spawn-environ.{key}": value for key, value in WORKER_ENVIRONMENT.items()}
        with (
            dask.config.set(environment),
            LocalCluster(
                n_workers=workers,
                threads_per_worker=1,
                processes=local,
                dashboard_address=None,
                scheduler_kwargs={"dashboard_address": HTTP_ADDRESS},
                **options,
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


def _default_laws(configured: LawKind) -> list[LawKind]:
    """The laws run without ``--laws``: the config's ``law.kind`` first (the command line names none, so the file's
    law is the one under test), then the others of :data:`DEFAULT_LAWS` to compare it with."""
    return [configured, *(law for law in DEFAULT_LAWS if law is not configured)]


def _laws(text: str) -> list[LawKind]:
    from foilc_hil.errors import InputError

    names = [name.strip() for name in text.split(",") if name.strip()]
    try:
        laws = [LawKind(name) for name in names]
    except ValueError:
        raise InputError(f"--laws: {text!r} is not a comma-separated list of {', '.join(LawKind)}") from None
    if not laws or len(set(laws)) != len(laws):
        raise InputError(f"--laws: {text!r} must name each law once")
    return laws


def _text(report: RobustnessReport) -> str:
    s = report.settings
    lines = [
        f"{report.draws} plants ({report.vertices} box corners, {s.samples} random, seed {s.seed}), {s.trials} trials "
        f"of {report.n_samples} samples, noise {s.noise:g}, tolerance {s.tolerance:g}, {report.workers} workers, "
        f"{report.seconds:.1f} s",
    ]
    for law in report.laws:
        document = law.to_json()
        rates = ", ".join(f"{name} {100 * law.rate(name):.1f} %" for name in ("diverged", "reached", "monotonic"))
        lines.append(f"{law.law}: design 2-norm {law.design_norm_2:.4g}; {rates}")
        for figure in ("norm_2", "trials_to_tolerance", "final_rmse", "noise_floor"):
            points = document[figure].items()
            cells = ", ".join(f"{key} {'-' if value is None else f'{value:.4g}'}" for key, value in points)
            lines.append(f"  {figure}: {cells}")
    return "\n".join(lines)


def execute(args: argparse.Namespace) -> CommandResult:
    """Design every law with the one pipeline, then run it on the drawn plants."""
    from pathlib import Path

    from foilc_hil.config import load_config
    from foilc_hil.design.json_fields import jsonable
    from foilc_hil.errors import InputError
    from foilc_hil.loop.robustness import MonteCarloSettings, plot_robustness, run_robustness
    from foilc_hil.references import reference_profile

    laws = None if args.laws is None else _laws(args.laws)  # checked before the config is read
    if args.workers < 1:
        raise InputError(f"--workers: must be >= 1, got {args.workers}")
    address = args.scheduler
    if not (address is None or address == IN_PROCESS or address.startswith(("tcp://", "tls://"))):
        raise InputError(f"--scheduler: {address!r} is not tcp://HOST:PORT, tls://HOST:PORT or {IN_PROCESS}")
    config = load_config(args.config, {})
    if laws is None:
        laws = _default_laws(config.law.kind)
    reference = reference_profile(config.reference, config.sample_time)
    span = float(reference.max() - reference.min()) or float(abs(reference).max()) or 1.0  # as the paper table's
    settings = MonteCarloSettings(
        samples=args.samples,
        seed=args.seed,
        trials=config.trials if args.trials is None else args.trials,
        noise=config.plant.output_noise if args.noise is None else args.noise,
        tolerance=args.tolerance * span,
        input_delay=args.input_delay,
    )
    with _client(address, args.workers) as client:
        report = run_robustness(config, laws, settings, client=client, workers=args.workers)
    document = report.to_json()
    if args.out is not None:
        import orjson

        out = Path(args.out)
        written = plot_robustness(report, out)
        (out / "robustness.json").write_bytes(orjson.dumps(jsonable(document)))
        document["files"] = [str(path) for path in [*written, out / "robustness.json"]]
    return CommandResult(document=document, text=_text(report))
