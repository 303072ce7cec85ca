"""Physics benchmarks: the compiled plants against scipy's ``solve_ivp`` and against the pre-kernel pure-Python
plants, all in one run.

- **PMSM axis**, 1 s of simulated time in 1 ms caller steps (20 internal steps of 50 us each): ``PmsmPlant.step``
  (numba kernel) against the same class at :data:`BEFORE_COMMIT` (the pure-Python sub-step, loaded from git so both
  run in this process) and against ``solve_ivp`` (RK45) of the reduced ODE the physics tests use as their truth
  (mechanics with Coulomb friction and cogging, the closed current loop as a first-order lag; no PI, no
  quantisation: less work than the plant does).
- **First-order plant (48)** with ``Delta a(t)``, ``Delta b(t)`` sines, 1 s in 1 ms steps: the plant against its
  pre-kernel version and against ``solve_ivp`` of the same ODE.
- **JIT cost**: importing ``plant_emulator.physics.kernels`` in a fresh process with an empty numba cache (compile)
  and again with the cache filled (load).

``python -m benchmarks.bench_physics [--out F.json]``
"""

from __future__ import annotations

import importlib.util
import math
import os
import subprocess
import sys
import tempfile
from collections.abc import Callable, Sequence
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np

from benchmarks.comparison import Comparison, alternate, comparisons_json, seconds
from benchmarks.output import emit, json_parser

#: the last commit with the pure-Python physics (the "before" column of the physics rows)
BEFORE_COMMIT = "a848700"
ROOT = Path(__file__).resolve().parents[1]
STEPS = 1000
DT = 1e-3
PMSM_TORQUE_MODE: dict[str, Any] = {"input_kind": "torque", "viscous": 2e-3, "coulomb": 0.05, "cogging_amplitude": 0.03}


def _before(module: str) -> ModuleType | None:
    """``plant_emulator/physics/<module>.py`` as it was at :data:`BEFORE_COMMIT` (``None`` without git history)."""
    try:
        source = subprocess.run(
            ["git", "show", f"{BEFORE_COMMIT}:plant_emulator/physics/{module}.py"],
            cwd=ROOT,
            capture_output=True,
            text=True,
            check=True,
            timeout=30,
        ).stdout
    except (OSError, subprocess.SubprocessError):
        return None
    spec = importlib.util.spec_from_loader(f"before_{module}", loader=None)
    assert spec is not None
    loaded = importlib.util.module_from_spec(spec)
    exec(compile(source, f"{BEFORE_COMMIT}:{module}.py", "exec"), loaded.__dict__)
    return loaded


def _step_us(plant: Any, command: float) -> Callable[[], float]:
    """A measurement: microseconds per 1 ms step of ``plant`` over the benchmark's 1 s, from its trial start."""
    u = np.array([command])

    def run() -> float:
        plant.reset(1)
        return seconds(lambda: [plant.step(u, DT) for _ in range(STEPS)]) / STEPS * 1e6

    return run


def _pmsm_ode_seconds() -> float:
    from plant_emulator.config import PmsmConfig

    c = PmsmConfig.model_validate(PMSM_TORQUE_MODE)
    torque, scale = 0.4, c.coulomb_velocity_scale * 2 * math.pi / 60

    def rhs(_t: float, z: np.ndarray) -> list[float]:
        theta, omega, iq = z
        losses = (
            c.viscous * omega
            + c.coulomb * math.tanh(omega / scale)
            + c.cogging_amplitude * math.sin(c.cogging_periods * theta)
        )
        return [
            omega,
            (c.torque_constant * iq - losses) / c.inertia,
            c.current_bandwidth * (torque / c.torque_constant - iq),
        ]

    return _solve_seconds(rhs, [0.0, 0.0, 0.0])


def _first_order_ode_seconds(a: float, b: float, variation: tuple[Any, Any]) -> float:
    delta_a, delta_b = variation

    def rhs(t: float, x: np.ndarray) -> list[float]:
        a_t = a + delta_a.amplitude * math.sin(delta_a.frequency * t)
        b_t = b + delta_b.amplitude * math.sin(delta_b.frequency * t)
        return [a_t * x[0] + b_t * 1.0]

    return _solve_seconds(rhs, [0.0])


def _solve_seconds(rhs: Callable[[float, np.ndarray], list[float]], x0: list[float]) -> float:
    """Seconds per simulated step of ``solve_ivp`` (RK45, rtol 1e-6) over the benchmark's 1 s, output every 1 ms."""
    from scipy.integrate import solve_ivp

    times = DT * np.arange(1, STEPS + 1)
    return seconds(lambda: solve_ivp(rhs, (0.0, times[-1]), x0, t_eval=times, rtol=1e-6, atol=1e-9)) / STEPS


def _row(
    target: str, project: Callable[[], float], peer: Callable[[], float], repeats: int, **fields: Any
) -> Comparison:
    """A us/step row, the project's and the peer's repetitions alternated."""
    mine, theirs = alternate(project, peer, repeats)
    return Comparison(target=target, unit="us/step", higher_is_better=False, project=mine, peer=theirs, **fields)


def physics_comparisons(repeats: int = 5) -> list[Comparison]:
    """The PMSM and first-order rows: kernel vs pre-kernel Python vs solve_ivp."""
    from foilc_hil.config import load_config
    from plant_emulator.config import PlantConfig
    from plant_emulator.physics import build_plant

    demo = load_config(ROOT / "configs" / "demo.yaml").plant
    paper = load_config(ROOT / "configs" / "paper_sim.yaml").plant
    rows: list[Comparison] = []
    before_pmsm, before_first = _before("pmsm"), _before("first_order")
    before = f"the same plant in pure Python ({BEFORE_COMMIT})"
    if before_pmsm is not None:
        old = _step_us(before_pmsm.PmsmPlant(demo, seed=demo.seed), 400.0)
        target = "PMSM axis (demo config, velocity loop), one 1 ms step"
        rows.append(
            _row(
                target,
                _step_us(build_plant(demo), 400.0),
                old,
                repeats,
                peer_name=before,
                min_ratio=20.0,
                note="a step is 20 internal steps of 50 us in the kernel (each a serial chain of about 7 sin/tanh/exp "
                "calls and 8 divisions: 100-200 ns) plus the Python around the call (input check, call, output array); "
                "done so far: the state in locals during the loop, per-call constants hoisted, the single input read "
                "directly, sub-steps and filter weight kept per dt, the kernel's machine code called without numba's "
                "dispatcher (which typed all nine arguments every call)",
            )
        )
    torque_plant = build_plant(PlantConfig.model_validate({"model": "pmsm", "pmsm": PMSM_TORQUE_MODE}))
    rows.append(
        _row(
            "PMSM axis (torque mode), 1 ms of simulated time",
            _step_us(torque_plant, 0.4),
            lambda: _pmsm_ode_seconds() * 1e6,
            repeats,
            peer_name="scipy solve_ivp RK45 of the reduced ODE",
            note="the peer integrates 3 states without the current PI or the resolver: less work than the plant",
        )
    )
    first_now = _step_us(build_plant(paper), 1.0)
    if before_first is not None:
        old = _step_us(before_first.FirstOrderPlant(paper, seed=paper.seed), 1.0)
        target = "first-order plant (48), time-varying, one 1 ms step"
        rows.append(_row(target, first_now, old, repeats, peer_name=before))
    variation = (paper.variation.a, paper.variation.b)
    a, b = continuous_scalars(paper)
    rows.append(
        _row(
            "first-order plant (48), 1 ms of simulated time",
            first_now,
            lambda: _first_order_ode_seconds(a, b, variation) * 1e6,
            repeats,
            peer_name="scipy solve_ivp RK45 of the same ODE",
            note="the peer integrates 1 s with a constant input in one call, taking large adaptive steps; the plant "
            "answers every 1 ms step with the input of that step (ZOH), as the bench needs",
        )
    )
    return rows


def continuous_scalars(plant: Any) -> tuple[float, float]:
    """``(a, b)`` of a scalar first-order plant section."""
    from plant_emulator.linear import continuous_model

    model = continuous_model(plant)
    return float(model.a[0, 0]), float(model.b[0, 0])


def jit_cost() -> dict[str, float]:
    """Seconds to import the kernels in a fresh process: with an empty numba cache (compiles), then cached."""
    code = "import time; t = time.perf_counter(); import plant_emulator.physics.kernels; print(time.perf_counter() - t)"
    with tempfile.TemporaryDirectory(prefix="foilc-numba-") as cache:
        env = {**os.environ, "NUMBA_CACHE_DIR": cache, "PYTHONPATH": str(ROOT)}
        runs = [
            float(
                subprocess.run(
                    [sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True, timeout=300
                ).stdout
            )
            for _ in range(2)
        ]
    return {"first_import_compiles_s": runs[0], "cached_import_s": runs[1]}


def collect(repeats: int = 5) -> dict[str, Any]:
    return {"comparisons": comparisons_json(physics_comparisons(repeats)), "jit": jit_cost()}


def main(argv: Sequence[str] | None = None) -> int:
    args = json_parser("python -m benchmarks.bench_physics", __doc__).parse_args(argv)
    emit(collect(), args.out)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
