"""Robustness Monte Carlo: draws inside the set, reproducible whatever the workers, per-draw certificates against an
independent numpy lifted map, per-draw trial figures against a direct simulation, and the CLI on 20 draws.

Every cluster here runs in this process (``processes=False``: threads and the in-process transport, no socket)."""

from __future__ import annotations

import json
import math
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from foilc_hil.cli import main
from foilc_hil.commands.robustness import HTTP_ADDRESS
from foilc_hil.config import Config, LawKind, load_config
from foilc_hil.design.pipeline import build_design
from foilc_hil.loop.robustness import MonteCarloSettings, draw_plants, drawn_config, run_robustness
from foilc_hil.loop.simulation import simulate

A_C, B_C, TS = -1.23, 1.68, 0.01
BOX_A, BOX_B = 0.1, 0.15
N_SAMPLES = 40


def _write(tmp_path: Path, noise: float = 0.001) -> Path:
    """paper_sim's plant, variation box and disturbance on a 0.4 s trial (40 samples)."""
    path = tmp_path / "robust.yaml"
    path.write_text(
        f"""
plant:
  a: {A_C}
  b: {B_C}
  c: 1.0
  variation:
    a: {{kind: sine, amplitude: {BOX_A}, frequency: 1.0}}
    b: {{kind: sine, amplitude: {BOX_B}, frequency: 2.3}}
  uncertainty: {{G1: 0.001, H1: 1.0, G2: 0.0016, H2: 1.0}}
  disturbance: {{kind: sine, amplitude: 0.1, frequency: 3.14159, start_trial: 3}}
  output_noise: {noise}
reference:
  profile: piecewise
  segments:
    - {{duration: 0.2, start: 0.0, end: 1.0}}
    - {{duration: 0.2, start: 1.0}}
sample_time: {TS}
trials: 4
synthesis: {{tau: 0.868, theta: 0.868}}
law: {{kind: ioilc}}
bench: {{divergence_factor: 10000.0}}
""",
        encoding="utf-8",
    )
    return path


@pytest.fixture(scope="module")
def config(tmp_path_factory: pytest.TempPathFactory) -> Config:
    return load_config(_write(tmp_path_factory.mktemp("robust")))


@pytest.fixture(scope="module")
def client() -> Iterator[Any]:
    """An in-process cluster, module-scoped and warmed up: dask.distributed starts its workers' executor threads and a
    process-wide offload thread lazily, on the first tasks, and the per-test leak guard would count those against
    the test that happened to start them."""
    from distributed import Client

    with Client(
        processes=False, n_workers=2, threads_per_worker=1, dashboard_address=None,
        scheduler_kwargs={"dashboard_address": HTTP_ADDRESS},  # the scheduler's HTTP routes: loopback, not 0.0.0.0
    ) as started:
        for address in started.scheduler_info()["workers"]:
            started.submit(abs, -1, workers=[address], pure=False).result()
        started.submit(bytes, 1 << 20, pure=False).result()  # a large result goes through the offload thread
        yield started


def test_draws_stay_inside_the_box_and_reproduce(config: Config) -> None:
    draws = draw_plants(config, 300, 5)
    corners = {(d.delta_a, d.delta_b) for d in draws[:4]}
    assert corners == {(a, b) for a in (-BOX_A, BOX_A) for b in (-BOX_B, BOX_B)} and all(d.vertex for d in draws[:4])
    random = draws[4:]
    assert len(random) == 300 and not any(d.vertex for d in random)
    for d in random:  # frozen offset plus the walk's bound never leaves the box
        assert abs(d.delta_a) + d.walk_a == pytest.approx(BOX_A) and abs(d.delta_b) + d.walk_b == pytest.approx(BOX_B)
        assert -1.0 <= d.disturbance_scale <= 1.0
    offsets = np.array([d.delta_a for d in random])
    assert offsets.min() < -0.8 * BOX_A and offsets.max() > 0.8 * BOX_A  # uniform on the whole box
    assert len({d.seed for d in random}) == 300
    assert draws == draw_plants(config, 300, 5) and draws[4:] != draw_plants(config, 300, 6)[4:]
    plant = drawn_config(config, random[0], 0.02).plant
    assert np.asarray(plant.a) == pytest.approx(A_C + random[0].delta_a) and plant.output_noise == 0.02
    assert plant.variation.a.kind == "random_walk" and plant.variation.a.amplitude == pytest.approx(random[0].walk_a)
    assert plant.disturbance.amplitude == pytest.approx(0.1 * random[0].disturbance_scale)
    assert plant.seed == random[0].seed


def _dense_error_map(ad: float, bd: float, p1: np.ndarray, p2: np.ndarray) -> np.ndarray:
    """``T = I - H`` of the 2D law (kp = 0) on the scalar ZOH plant with one cycle of input delay, state
    ``[x, u_prev]``, built sample by sample with numpy: ``H[i, j]`` is the error sample ``i + 1`` moved by the
    update ``p2 e[j + 1]`` applied at input ``j`` (state feedback ``p1``)."""
    A = np.array([[ad, bd], [0.0, 0.0]])
    B, C = np.array([[0.0], [1.0]]), np.array([[1.0, 0.0]])
    A_cl = A + B @ p1
    length = N_SAMPLES - 1
    H = np.zeros((length, length))
    for j in range(length):
        z = A_cl @ (B @ p2)  # one cycle of input delay: the update reaches the output two samples later
        for i in range(j, length):
            H[i, j] = float((C @ z)[0, 0])
            z = A_cl @ z
    return np.eye(length) - H


@pytest.mark.slow
def test_per_draw_certificates_match_a_numpy_lifted_map_of_the_drawn_plant(config: Config, client: Any) -> None:
    settings = MonteCarloSettings(samples=2, seed=1, trials=2, noise=0.0, tolerance=0.01)
    report = run_robustness(config, [LawKind.IOILC], settings, client=client, workers=2)
    design = build_design(config, "ioilc", N_SAMPLES, input_delay=1)
    (law,) = report.laws
    assert law.design_norm_2 == design.certificates.norm_2  # type: ignore[union-attr]
    for outcome in law.outcomes:
        a, b = A_C + outcome.draw.delta_a, B_C + outcome.draw.delta_b
        ad = math.exp(a * TS)
        T = _dense_error_map(ad, b * (ad - 1.0) / a, design.p1, design.p2)
        assert outcome.norm_2 == pytest.approx(np.linalg.norm(T, 2), rel=1e-6)
        assert outcome.spectral_radius == pytest.approx(max(abs(np.linalg.eigvals(T))), rel=1e-6)


@pytest.mark.slow
def test_one_and_two_workers_agree_and_figures_match_a_direct_simulation(config: Config, client: Any) -> None:
    settings = MonteCarloSettings(samples=5, seed=3, trials=4, noise=0.002, tolerance=0.01)
    one = run_robustness(config, [LawKind.IOILC], settings, client=client, workers=1).to_json()
    two = run_robustness(config, [LawKind.IOILC], settings, client=client, workers=2).to_json()
    for document in (one, two):
        document.pop("seconds"), document.pop("workers")
    assert one == two
    assert one["draws"] == one["vertices"] + 5 == 9
    outcome = one["laws"][0]["per_draw"][6]
    draw = draw_plants(config, 5, 3)[6]
    design = build_design(config, "ioilc", N_SAMPLES, input_delay=1)
    direct = simulate(drawn_config(config, draw, 0.002), law="ioilc", trials=4, design=design, input_delay=1)
    rmse = [m.rmse_learnable for m in direct.metrics]
    assert outcome["final_rmse"] == rmse[-1]
    assert outcome["trials_to_tolerance"] == next((k for k, v in enumerate(rmse, 1) if v < 0.01), None)
    assert outcome["noise_floor"] == pytest.approx(direct.metrics[-1].noise_floor)  # the last third of 4: 1 trial
    assert outcome["noise_floor"] > 0.002 * 0.5 and not outcome["diverged"]


@pytest.mark.slow
def test_cli_twenty_draws_three_laws_json_plots_and_bad_input(
    tmp_path: Path, client: Any, capsys: pytest.CaptureFixture[str]
) -> None:
    argv = ["robustness", "--config", str(_write(tmp_path)), "--samples", "16", "--trials", "3",
            "--laws", "ioilc,p-type,noilc", "--scheduler", "inprocess", "--workers", "2"]
    assert main([*argv, "--json", "--out", str(tmp_path / "out")]) == 0
    document = json.loads(capsys.readouterr().out)
    assert document["draws"] == 20 and document["vertices"] == 4 and document["trials"] == 3
    assert [law["law"] for law in document["laws"]] == ["ioilc", "p-type", "noilc"]
    for law in document["laws"]:
        assert len(law["per_draw"]) == 20
        norms = [d["norm_2"] for d in law["per_draw"]]
        assert law["norm_2"]["worst"] == max(norms) >= law["norm_2"]["0.5"]
        assert law["divergence_rate"] == sum(d["diverged"] for d in law["per_draw"]) / 20
    names = {Path(f).name for f in document["files"]}
    assert names == {"ecdf_norm_2.png", "ecdf_final_rmse.png", "ecdf_noise_floor.png", "hist_trials_to_tolerance.png",
                     "robustness.json"}
    assert json.loads((tmp_path / "out" / "robustness.json").read_text())["laws"][0]["law"] == "ioilc"
    for bad in (["--samples", "-1"], ["--workers", "0"], ["--scheduler", "udp://x"], ["--laws", "foilc,pid"],
                ["--trials", "1"]):
        assert main([*argv[:3], *bad]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and bad[0] in err


def test_a_tolerance_never_reached_is_never_in_the_quantiles() -> None:
    from foilc_hil.loop.robustness import DrawOutcome, LawRobustness, PlantDraw

    def outcome(index: int, reached: int | None) -> DrawOutcome:
        draw = PlantDraw(index, False, 0.0, 0.0, 0.0, 0.0, 1.0, index)
        return DrawOutcome(draw, 0.5, 0.6, reached, 0.01, 0.002, False, 5)

    law = LawRobustness(LawKind.IOILC, 0.5, 0.6, tuple(outcome(i, 3 if i < 6 else None) for i in range(10)))
    figure = law.to_json()["trials_to_tolerance"]
    assert figure == {"worst": None, "0.5": 3.0, "0.9": None, "0.99": None}
    assert law.rate("reached") == 0.6 and law.rate("diverged") == 0.0 and law.rate("monotonic") == 1.0


@pytest.mark.parametrize("path", ["rational", "fft"])
def test_noilc_per_draw_certificates_bound_a_numpy_lifted_map_of_the_drawn_plant(
    config: Config, path: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """NOILC's per-draw certificate (``T T^T`` through the plant's transfer function, Cholesky bound; ``fft``: that
    bound made inconclusive, so the map is formed by FFT, the gain transformed once for the chunk) against
    ``T = I - G_v L`` built with numpy from the drawn plant's Markov parameters and the design's weights: a rigorous
    bound, within 1e-7 of the exact norm."""
    from foilc_hil.design import robustness
    from foilc_hil.design.map_norms import CHOLESKY_METHOD
    from foilc_hil.design.rational_map import RATIONAL_METHOD
    from foilc_hil.design.robustness import certify_draws, running_law
    from foilc_hil.loop.robustness import _frozen_perturbations

    if path == "fft":
        monkeypatch.setattr(robustness, "rational_norm_bound", lambda *args: None)

    design = build_design(config, "noilc", N_SAMPLES, input_delay=1)
    assert design.certificates is not None and design.certificates.noilc is not None
    weights = design.certificates.noilc
    draws = draw_plants(config, 3, 4)
    certificates = certify_draws(
        design, running_law(config, design, N_SAMPLES), _frozen_perturbations(config, design, draws)
    )

    def lifted(a: float, b: float) -> np.ndarray:  # y[i + 2] moved by u[i] (one cycle of delay): c ad^k bd
        ad = math.exp(a * TS)
        bd = b * (ad - 1.0) / a
        taps = bd * ad ** np.arange(N_SAMPLES - 1)
        return np.array([[taps[i - j] if i >= j else 0.0 for j in range(N_SAMPLES - 1)] for i in range(N_SAMPLES - 1)])

    G = lifted(A_C, B_C)
    L = np.linalg.solve(weights.q * G.T @ G + weights.r * np.eye(N_SAMPLES - 1), weights.q * G.T)
    for draw, certificate in zip(draws, certificates, strict=True):
        T = np.eye(N_SAMPLES - 1) - lifted(A_C + draw.delta_a, B_C + draw.delta_b) @ L
        exact = float(np.linalg.norm(T, 2))
        assert certificate.norm_2_method == (RATIONAL_METHOD if path == "rational" else CHOLESKY_METHOD)
        assert exact <= certificate.norm_2 <= exact * (1 + 1e-7)
        assert certificate.spectral_radius >= float(np.max(np.abs(np.linalg.eigvals(T))))
