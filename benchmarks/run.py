"""``make bench``: run the bench-loop benchmarks and write one JSON document (``--out``, default stdout).

``python -m benchmarks.run --out benchmarks/results.json``
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import sys
from collections.abc import Sequence
from typing import Any


def collect() -> dict[str, Any]:
    from benchmarks import bench_loop

    no_log = bench_loop.can_lockstep(logged=False)
    logged = bench_loop.can_lockstep(logged=True)
    return {
        "machine": {
            "python": platform.python_version(),
            "platform": platform.platform(),
            "cpus": os.cpu_count(),
        },
        "loop_only": bench_loop.loop_only(),
        "can_lockstep_virtual": {
            "without_logging": no_log,
            "with_logging": logged,
            "logging_overhead_compute_p50_us": (
                logged["compute_p50_us"] - no_log["compute_p50_us"]
                if logged["compute_p50_us"] is not None and no_log["compute_p50_us"] is not None
                else None
            ),
        },
    }


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.run", description=__doc__)
    parser.add_argument("--out", help="JSON file to write (default: stdout)")
    args = parser.parse_args(argv)
    document = json.dumps(collect(), indent=2)
    if args.out:
        with open(args.out, "w", encoding="utf-8") as handle:
            handle.write(document + "\n")
        sys.stderr.write(f"wrote {args.out}\n")
    else:
        sys.stdout.write(document + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
