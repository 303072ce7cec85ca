"""Control-science benchmarks, peers side by side in one run, JSON out.

- Caputo derivative of one trial: our direct convolution, our zero-padded FFT convolution, and scipy's
  ``lfilter`` running the same Grünwald–Letnikov weights as an FIR filter (an independent implementation); the
  largest difference between them is reported next to the times.
- LMI (31) synthesis: CLARABEL and SCS on the same problem (time, gamma, the margin relative to the solved matrix,
  cond(Q), and whether the numpy re-check passed).

``python -m benchmarks.bench_science [--out F.json]``
"""

from __future__ import annotations

import statistics
import time
from collections.abc import Callable, Sequence
from typing import Any

import numpy as np

from benchmarks.output import emit, json_parser


def _median_seconds(call: Callable[[], object], repeats: int = 5) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        call()
        times.append(time.perf_counter() - start)
    return float(statistics.median(times))


def fractional(lengths: Sequence[int] = (256, 2000, 6000), r: float = 0.7, h: float = 1e-3) -> list[dict[str, Any]]:
    """Direct vs FFT vs scipy.lfilter for the Caputo derivative of a smooth signal of each length."""
    from scipy.signal import lfilter

    from foilc_hil.design.fractional import caputo_derivative, gl_weights

    rows = []
    for n in lengths:
        t = np.arange(n) * h
        f = np.sin(3 * t) + t**2
        direct = caputo_derivative(f, r, h, method="direct")
        fft = caputo_derivative(f, r, h, method="fft")
        # independent: the GL weights as an FIR filter on f - f(0) (0 < r < 1: Caputo = GL of f - f(0))
        reference = lfilter(gl_weights(r, n), [1.0], f - f[0]) * h**-r
        weights = gl_weights(r, n)

        def run_direct(f: np.ndarray = f) -> object:
            return caputo_derivative(f, r, h, method="direct")

        def run_fft(f: np.ndarray = f) -> object:
            return caputo_derivative(f, r, h, method="fft")

        def run_lfilter(f: np.ndarray = f, weights: np.ndarray = weights) -> object:
            return lfilter(weights, [1.0], f - f[0]) * h**-r

        rows.append(
            {
                "samples": n,
                "direct_s": _median_seconds(run_direct),
                "fft_s": _median_seconds(run_fft),
                "scipy_lfilter_s": _median_seconds(run_lfilter),
                "max_abs_difference_direct_fft": float(np.max(np.abs(direct - fft))),
                "max_abs_difference_direct_lfilter": float(np.max(np.abs(direct - reference))),
            }
        )
    return rows


def lmi(sample_time: float = 0.01) -> list[dict[str, Any]]:
    """LMI (31) on the paper's plant (48), once with each solver asked first. ``solve_lmi`` falls back to the other
    solver when a solution fails the numpy re-check; ``solved_by`` and ``fallbacks`` show when that happened."""
    from foilc_hil.design.lmi import solve_lmi
    from foilc_hil.design.models import Uncertainty, discretize
    from plant_emulator.config import PlantConfig
    from plant_emulator.linear import continuous_model

    model = discretize(continuous_model(PlantConfig(a=-1.23, b=1.68, c=1.0)), sample_time, "zoh")
    uncertainty = Uncertainty(
        G1=np.array([[0.01]]), H1=np.array([[1.0]]), G2=np.array([[0.002]]), H2=np.array([[1.0]])
    )
    rows = []
    for solver in ("CLARABEL", "SCS"):
        start = time.perf_counter()
        solution = solve_lmi(model, uncertainty, tau=0.868, theta=0.868, solver=solver)
        elapsed = time.perf_counter() - start
        rows.append(
            {
                "requested_solver": solver,
                "solved_by": solution.solver,
                "seconds": elapsed,
                "gamma": solution.gamma,
                "relative_margin": solution.checks.relative_margin,
                "Q_condition": solution.checks.Q_condition,
                "P": solution.P.tolist(),
                "fallbacks": list(solution.checks.solver_failures),
            }
        )
    return rows


def collect() -> dict[str, Any]:
    return {"fractional_derivative": fractional(), "lmi_synthesis": lmi()}


def main(argv: Sequence[str] | None = None) -> int:
    args = json_parser("python -m benchmarks.bench_science", __doc__).parse_args(argv)
    emit(collect(), args.out)
    return 0

if __name__ == "__main__":
    raise SystemExit(main())
