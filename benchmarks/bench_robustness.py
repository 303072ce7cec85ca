"""The robustness Monte Carlo (``foilc-hil robustness``): 2 local Dask workers against 1 on the same draws, and the
issue's target (1,000 draws x 3 laws x 30 trials x 2000 samples on 2 cores in under 5 minutes) projected from two
measured 3-law runs (a measured 1,000-draw run takes minutes: too long for ``make bench``).

A local cluster of worker processes talks over loopback TCP, so every run happens in a private network namespace
(``unshare --net``, as root): no traffic in the host namespace. Each measurement is the command's own ``seconds``
(designs, draws, trials and the gathering of the results; not the cluster's start-up).

``python -m benchmarks.bench_robustness [--draws N] [--out F.json]``
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

from benchmarks.comparison import Comparison, Figure, comparisons_json
from benchmarks.output import emit, json_parser

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "configs" / "paper_sim.yaml"
#: The issue's target: draws x laws (30 trials of 2000 samples each) in at most this many seconds on 2 cores.
TARGET_DRAWS, TARGET_LAWS, TARGET_SECONDS = 1000, ("foilc", "ioilc", "noilc"), 300.0


def _robustness(draws: int, laws: tuple[str, ...], workers: int) -> dict[str, Any]:
    """One ``foilc-hil robustness`` run on paper_sim (its 4 box corners plus random draws) in a private namespace."""
    command = [
        sys.executable, "-m", "foilc_hil.cli", "robustness", "--config", str(CONFIG), "--samples", str(draws - 4),
        "--trials", "30", "--noise", "0.002", "--laws", ",".join(laws), "--workers", str(workers), "--json",
    ]
    script = "ip link set lo up; exec " + " ".join(command)
    done = subprocess.run(["unshare", "--net", "--", "sh", "-c", script], capture_output=True, text=True, cwd=ROOT,
                          check=False)
    if done.returncode != 0:
        raise RuntimeError(f"robustness failed ({done.returncode}): {done.stderr.strip()[-400:]}")
    document: dict[str, Any] = json.loads(done.stdout)
    return document


def robustness_comparisons(draws: int = 24, repeats: int = 1, small: int = 8, large: int = 48) -> list[Comparison]:
    """2 workers against 1 on ``draws`` IOILC draws (alternated), and the target projected from 3-law runs of
    ``small`` and ``large`` draws: the designs are a fixed cost, so the projection is the large run plus the
    per-draw slope between the two times the draws left (not the large run scaled, which would count the designs
    1000 / ``large`` times)."""
    one, two = [], []
    for _ in range(repeats):
        one.append(_robustness(draws, ("ioilc",), 1)["seconds"])
        two.append(_robustness(draws, ("ioilc",), 2)["seconds"])
    short, full = _robustness(small, TARGET_LAWS, 2), _robustness(large, TARGET_LAWS, 2)
    slope = max(0.0, (full["seconds"] - short["seconds"]) / max(1, full["draws"] - short["draws"]))
    projected = full["seconds"] + slope * (TARGET_DRAWS - full["draws"])
    return [
        Comparison(
            target=f"robustness Monte Carlo, {draws} draws x IOILC x 30 trials x 2000 samples: 2 local workers vs 1",
            unit="s",
            higher_is_better=False,
            project=Figure(tuple(two)),
            peer=Figure(tuple(one)),
            peer_name="the same run on 1 local worker",
            note="Dask LocalCluster of processes in a private network namespace; the same draws and results",
        ),
        Comparison(
            target=f"robustness target: {TARGET_DRAWS} draws x 3 laws x 30 trials x 2000 samples on 2 workers",
            unit="s",
            higher_is_better=False,
            project=Figure((projected,)),
            limit=TARGET_SECONDS,
            note=f"projected from measured runs of {short['draws']} and {full['draws']} draws x "
            f"{', '.join(TARGET_LAWS)} ({short['seconds']:.1f} s and {full['seconds']:.1f} s, the three designs "
            f"included): {slope:.3f} s per further draw",
        ),
    ]


def main(argv: list[str] | None = None) -> int:
    parser = json_parser("python -m benchmarks.bench_robustness", __doc__)
    parser.add_argument("--draws", type=int, default=24, help="draws per run (default 24: 4 corners + 20 random)")
    parser.add_argument("--repeats", type=int, default=1, help="alternated 1- and 2-worker runs (default 1)")
    parser.add_argument("--small", type=int, default=8, help="draws of the smaller 3-law run (default 8)")
    parser.add_argument("--large", type=int, default=48, help="draws of the larger 3-law run (default 48)")
    args = parser.parse_args(argv)
    comparisons = robustness_comparisons(args.draws, args.repeats, args.small, args.large)
    emit({"comparisons": comparisons_json(comparisons)}, args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
