"""``make soak``: a long lockstep run on the PMSM emulator with parameter spread and a load disturbance, watched for
leaks.

A sampler thread reads the process's resident memory (``VmRSS``), thread count and open file descriptors every
``--every`` seconds while ``foilc-hil run`` logic runs in this process (the embedded emulator, logging to MCAP). The
report gives RSS after warm-up and at the end, the growth per 1000 cycles after warm-up, thread and fd ranges, the
log size and whether learning stayed bounded (no divergence stop, final SSE against the best).

``python -m benchmarks.soak --trials 200 --out benchmarks/soak.json``
"""

from __future__ import annotations

import os
import tempfile
import threading
import time
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from pathlib import Path

from benchmarks.output import emit, json_parser

#: trials run before the memory baseline is taken (caches, the design, the first chunks are allocated by then)
WARM_UP_FRACTION = 0.1


@dataclass(frozen=True)
class Sample:
    seconds: float
    rss_mib: float
    threads: int
    fds: int


def _rss_mib() -> float:
    for line in Path("/proc/self/status").read_text(encoding="utf-8").splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024.0
    raise RuntimeError("no VmRSS in /proc/self/status (Linux only)")


class Sampler:
    """Samples RSS, threads and fds on a thread of its own until :meth:`stop`."""

    def __init__(self, every: float) -> None:
        self.every = every
        self.samples: list[Sample] = []
        self._stop = threading.Event()
        self._started = time.monotonic()
        self._thread = threading.Thread(target=self._run, name="soak-sampler", daemon=True)

    def start(self) -> None:
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()

    def _run(self) -> None:
        while not self._stop.is_set():
            self.samples.append(Sample(time.monotonic() - self._started, _rss_mib(), threading.active_count(),
                                       len(os.listdir("/proc/self/fd"))))
            self._stop.wait(self.every)


def soak(config_path: str, trials: int, every: float) -> dict[str, object]:
    from foilc_hil.config import load_config
    from foilc_hil.loop.rig import RunRequest, run_rig

    config = load_config(config_path)
    sampler = Sampler(every)
    with tempfile.TemporaryDirectory() as directory:
        log = Path(directory) / "soak.mcap"
        sampler.start()
        began = time.monotonic()
        try:
            report = run_rig(RunRequest(config=config, out=log, trials=trials, quiet=True))
        finally:
            sampler.stop()
        seconds = time.monotonic() - began
        log_bytes = log.stat().st_size
    samples = sampler.samples
    cycles = report.cycles
    warm = [s for s in samples if s.seconds >= WARM_UP_FRACTION * seconds] or samples
    sse = [metrics.sse for metrics in report.outcome.trials]
    growth = warm[-1].rss_mib - warm[0].rss_mib
    warm_cycles = cycles * (1.0 - WARM_UP_FRACTION)
    return {
        "config": config_path,
        "trials": len(sse),
        "cycles": cycles,
        "seconds": round(seconds, 1),
        "rss_start_mib": round(samples[0].rss_mib, 1),
        "rss_after_warm_up_mib": round(warm[0].rss_mib, 1),
        "rss_end_mib": round(warm[-1].rss_mib, 1),
        "rss_growth_after_warm_up_mib": round(growth, 2),
        "rss_growth_bytes_per_1000_cycles": round(growth * 2**20 / warm_cycles * 1000, 1) if warm_cycles else None,
        "threads": [min(s.threads for s in samples), max(s.threads for s in samples)],
        "fds": [min(s.fds for s in samples), max(s.fds for s in samples)],
        "log_bytes": log_bytes,
        "stopped": report.outcome.stopped,
        "sse_first": sse[0] if sse else None,
        "sse_best": min(sse) if sse else None,
        "sse_last": sse[-1] if sse else None,
        "drive_stop": report.drive_stop.to_json(),
        "samples": [asdict(s) for s in samples],
    }


def main(argv: Sequence[str] | None = None) -> None:
    parser = json_parser("python -m benchmarks.soak", (__doc__ or "").splitlines()[0])
    parser.add_argument("--config", default="configs/demo.yaml")
    parser.add_argument("--trials", type=int, default=200)
    parser.add_argument("--every", type=float, default=1.0, help="seconds between samples")
    args = parser.parse_args(argv)
    emit(soak(args.config, args.trials, args.every), args.out)


if __name__ == "__main__":
    main()
