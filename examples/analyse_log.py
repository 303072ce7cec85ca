"""Analyse a run's log: its config and design, each trial's figures, how fast the error fell, and the samples as a
pandas DataFrame where pandas is installed (``pip install 'foilc-hil[pandas]'``).

Uses only the documented API (docs/api.md)::

    foilc-hil run --config configs/demo.yaml --trials 5 --out run.mcap
    python examples/analyse_log.py run.mcap
"""

from __future__ import annotations

import argparse
import itertools
from collections.abc import Sequence

import numpy as np

import foilc_hil as fh


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("log", help="an MCAP log of foilc-hil run or simulate, fh.Bench or fh.simulate")
    args = parser.parse_args(argv)
    log = fh.open_log(args.log)
    if log.damage:
        print(f"note: the log {log.damage}; reading what precedes")
    config = log.config
    print(f"law {config.law.kind}, Ts {config.sample_time:g} s, plant {config.plant.model}")
    design = log.design
    if design is not None:
        print(f"design: P = {np.array2string(design.P, precision=4)}, kp {design.kp:g}, r {design.r:g}")
    trials = log.trials()
    print(f"{'trial':>5} {'SSE':>14} {'RMSE':>10} {'peak |e|':>10} {'peak |u|':>10}")
    for trial in trials:
        print(f"{trial.index:>5} {trial.sse:14.6g} {trial.rmse:10.4g} {np.max(np.abs(trial.error)):10.4g} "
              f"{np.max(np.abs(trial.control)):10.4g}")
    if len(trials) >= 2:
        ratios = [later.sse / earlier.sse for earlier, later in itertools.pairwise(trials) if earlier.sse]
        print(f"SSE ratio trial to trial: median {np.median(ratios):.3g}")
    frames = sum(1 for _ in log.frames())
    print(f"{frames} CAN frames in the log")
    try:
        samples = log.to_pandas()
    except ImportError as exc:
        print(f"no DataFrame: {exc}")
    else:
        print(samples.groupby("trial")["error"].agg(["mean", "std"]).to_string())
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
