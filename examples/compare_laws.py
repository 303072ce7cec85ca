"""Compare two learning laws on your own reference: a piecewise velocity profile of your machine's motion cycle.

Each law is designed (certified) for the reference's trial length and run for the same trials, offline on the
plant's physics (``fh.simulate``) or, with ``--bench``, over CAN on the embedded emulator (``fh.Bench``); then the
SSE of every trial side by side. Uses only the documented API (docs/api.md)::

    python examples/compare_laws.py
    python examples/compare_laws.py --laws foilc,p-type --trials 10 --bench
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence

import foilc_hil as fh

#: your motion cycle: (duration s, start rpm, end rpm) -- a ramp up, a dwell, a ramp down to rest
SEGMENTS = [(0.3, 0.0, 300.0), (0.4, 300.0, 300.0), (0.3, 300.0, 0.0)]


def run_law(config: fh.Config, law: str, trials: int, on_bench: bool) -> list[fh.TrialResult]:
    """``trials`` trials of ``law``, designed for the config's reference."""
    design = fh.design(config, law=law)
    print(f"{law}: kp {design.kp:g}, r {design.r:g}, gain scale {design.gain_scale:g}")
    if not on_bench:
        return fh.simulate(config, design=design, trials=trials)
    with fh.Bench(config, design=design) as bench:
        return list(bench.trials(trials))


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", default="configs/demo.yaml", help="the plant, drive and design settings")
    parser.add_argument("--laws", default="foilc,ioilc", help="two laws, comma-separated")
    parser.add_argument("--trials", type=int, default=5)
    parser.add_argument("--bench", action="store_true", help="over CAN on the embedded emulator (fh.Bench)")
    args = parser.parse_args(argv)
    reference = {"profile": "piecewise",
                 "segments": [{"duration": d, "start": a, "end": b} for d, a, b in SEGMENTS]}
    # the disturbance of the demo config starts at trial 5: keep it, it is part of the comparison
    config = fh.load_config(args.config, overrides={"reference": reference, "trials": args.trials})
    laws = [law.strip() for law in args.laws.split(",")]
    results = {law: run_law(config, law, args.trials, args.bench) for law in laws}
    print(f"{'trial':>5}  " + "  ".join(f"{law + ' SSE':>14}" for law in laws))
    for k in range(max(len(trials) for trials in results.values())):
        row = [f"{results[law][k].sse:14.6g}" if k < len(results[law]) else f"{'-':>14}" for law in laws]
        print(f"{k + 1:>5}  " + "  ".join(row))
    last = {law: trials[-1].rmse for law, trials in results.items()}
    best = min(last, key=lambda law: last[law])
    print(f"lowest RMSE in the last trial: {best} ({last[best]:.4g})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
