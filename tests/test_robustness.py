"""Robustness Monte Carlo: reproducible whatever the workers, and its vertices agree with an independent lifted map."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from foilc_hil.cli import main
from foilc_hil.config import load_config
from foilc_hil.design.certificates import LawStructure
from foilc_hil.design.pipeline import build_design
from foilc_hil.design.record import Design
from foilc_hil.design.robustness import draw_perturbations, robustness, running_law

CONFIG = Path(__file__).resolve().parents[1] / "configs" / "paper_sim.yaml"
N_SAMPLES = 120


@pytest.fixture(scope="module")
def ioilc() -> tuple[Design, LawStructure]:
    config = load_config(CONFIG, {})
    design = build_design(config, "ioilc", N_SAMPLES, input_delay=1)
    return design, running_law(config, design, N_SAMPLES)


def _dense_error_map(
    A: np.ndarray, B: np.ndarray, C: np.ndarray, p1: np.ndarray, p2: np.ndarray, lead: int
) -> np.ndarray:
    """``T = I - H`` of a law with ``E = e`` (kp = 0), built sample by sample with numpy: ``H[i, j]`` is the error
    sample ``i + lead`` moved by the update ``p2 e[j + lead]`` applied at input ``j`` (state feedback ``p1``)."""
    length = N_SAMPLES - lead
    A_cl = A + B @ p1
    H = np.zeros((length, length))
    for j in range(length):
        z = B @ p2  # the update's effect on the state one sample after input j
        for _ in range(lead):
            z = A_cl @ z
        for i in range(j, length):
            H[i, j] = float((C @ z)[0, 0])
            z = A_cl @ z
    return np.eye(length) - H


def test_the_same_seed_gives_the_same_result_with_one_and_two_workers(ioilc: tuple[Design, LawStructure]) -> None:
    design, law = ioilc
    one = robustness(design, law, samples=12, seed=7, scheduler="synchronous", workers=1).to_json()
    two = robustness(design, law, samples=12, seed=7, scheduler="threads", workers=2).to_json()
    assert one == two
    assert one["draws"] == one["vertices"] + 12 == 16
    other = robustness(design, law, samples=12, seed=8, scheduler="synchronous", workers=1).to_json()
    assert other["per_draw"][4:] != one["per_draw"][4:]  # the seed matters for the random draws ...
    assert other["per_draw"][:4] == one["per_draw"][:4]  # ... not for the vertices


@pytest.fixture(scope="module")
def client() -> Iterator[Any]:
    """An in-process cluster (inproc transport: no socket), module-scoped and warmed up: dask.distributed starts
    its workers' executor threads and a process-wide offload thread lazily, on the first tasks, and the per-test
    leak guard would count those against the test that happened to start them."""
    from distributed import Client

    with Client(processes=False, n_workers=2, threads_per_worker=1, dashboard_address=None) as started:
        for address in started.scheduler_info()["workers"]:
            started.submit(abs, -1, workers=[address], pure=False).result()
        started.submit(bytes, 1 << 20, pure=False).result()  # a large result goes through the offload thread
        yield started


def test_an_in_process_distributed_client_agrees(ioilc: tuple[Design, LawStructure], client: Any) -> None:
    design, law = ioilc
    local = robustness(design, law, samples=6, seed=3, scheduler="synchronous").to_json()
    distributed = robustness(design, law, samples=6, seed=3, scheduler=client, workers=2).to_json()
    assert distributed == local


def test_the_worst_case_agrees_with_the_vertex_certificates(ioilc: tuple[Design, LawStructure]) -> None:
    design, law = ioilc
    model = design.model
    result = robustness(design, law, samples=8, seed=0)
    draws = draw_perturbations(design.uncertainty, 8, 0)
    for draw, certificate in zip(draws, result.draws, strict=True):
        A, B = model.A + draw.delta_a, model.B + draw.delta_b
        T = _dense_error_map(A, B, model.measured_output, design.p1, design.p2, 1)
        assert certificate.norm_2 == pytest.approx(np.linalg.norm(T, 2), rel=1e-6)
        assert certificate.spectral_radius == pytest.approx(max(abs(np.linalg.eigvals(T))), rel=1e-6)
    nominal = np.linalg.norm(_dense_error_map(model.A, model.B, model.measured_output, design.p1, design.p2, 1), 2)
    vertex_worst = max(c.norm_2 for c in result.draws if c.vertex)
    assert design.certificates is not None
    assert max(vertex_worst, nominal) == pytest.approx(design.certificates.norm_2, rel=1e-6)
    assert result.vertices == design.certificates.vertices == 4


def test_random_draws_stay_inside_the_uncertainty_set(ioilc: tuple[Design, LawStructure]) -> None:
    design, _ = ioilc
    unc = design.uncertainty
    bound_a = np.linalg.norm(unc.G1, 2) * np.linalg.norm(unc.H1, 2)
    bound_b = np.linalg.norm(unc.G2, 2) * np.linalg.norm(unc.H2, 2)
    draws = draw_perturbations(unc, 200, 5)
    random = [d for d in draws if not d.vertex]
    assert len(random) == 200 and all(d.vertex for d in draws[:4])
    sizes_a = np.array([np.linalg.norm(d.delta_a, 2) for d in random])
    assert np.all(sizes_a <= bound_a * (1 + 1e-12))
    assert all(np.linalg.norm(d.delta_b, 2) <= bound_b * (1 + 1e-12) for d in random)
    assert 0.3 * bound_a < float(np.median(sizes_a)) < 0.7 * bound_a  # uniform radius: median near half the bound


def test_cli_json_and_bad_input(capsys: pytest.CaptureFixture[str]) -> None:
    argv = ["robustness", "--config", str(CONFIG), "--law", "p-type", "--samples", "3", "--scheduler", "synchronous"]
    assert main([*argv, "--json"]) == 0
    document = json.loads(capsys.readouterr().out)
    assert document["law"] == "p-type" and document["draws"] == 7 and len(document["per_draw"]) == 7
    assert document["norm_2"]["worst"] >= document["norm_2"]["quantiles"]["0.5"]
    assert document["norm_2"]["worst"] == pytest.approx(document["design"]["norm_2"], rel=1e-6)
    for bad in (["--samples", "-1"], ["--workers", "0"], ["--scheduler", "udp://x"]):
        assert main([*argv[:5], *bad]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and bad[0] in err
