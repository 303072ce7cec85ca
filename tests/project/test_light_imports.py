"""``synthesize`` imports what its design uses: no numba, python-control, scipy.signal, matplotlib, Dask or CAN stack.

The design path runs in a child process (a fresh ``sys.modules``) through the command's parser, the config load,
the tuner, a long fractional filter and a whole design with its certificates, and reports which modules it loaded.
Beside it, the numpy replacements of the scipy.signal calls that the design used to import are checked against
scipy.signal itself, bit for bit: the designs and replayed laws stay what they were.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from foilc_hil.design.convolution import fft_convolve
from foilc_hil.design.fractional import NEAR_FIELD, gl_derivative, gl_weights
from foilc_hil.errors import InputError
from plant_emulator.linear import ContinuousModel

ROOT = Path(__file__).resolve().parents[2]

#: what the design path of ``synthesize`` must not load (each costs a process 0.1-1.5 s to import)
HEAVY = ("numba", "control", "matplotlib", "dask", "distributed", "can", "canopen", "mcap")

#: the child: the command's parser and module, the config, the tuner (kp, r), a long 1-D fractional filter (the
#: FFT far field), and the whole design of a law with its lifted certificates; then the modules it loaded
_PROBE = """
import json, sys
import numpy as np
from foilc_hil.cli import build_parser
build_parser("synthesize")
from foilc_hil.config import load_config
from foilc_hil.design.fractional import FractionalPD
from foilc_hil.design.pipeline import build_design
from foilc_hil.design.tuning import tune
from foilc_hil.references import trial_samples
config = load_config(sys.argv[1], {})
n = trial_samples(config.reference, config.sample_time)
tuned = tune(config, python_control=False)
FractionalPD(tuned.kp, tuned.r, config.sample_time, history="zero").apply(np.ones(4 * n))
design = build_design(config, "p-type", n, input_delay=1)
print(json.dumps({"modules": sorted(sys.modules), "norm_2": design.certificates.norm_2}))
"""


@pytest.fixture(scope="module")
def loaded(tmp_path_factory: pytest.TempPathFactory) -> set[str]:
    """The modules the design path loaded in a fresh process (paper_sim at Ts = 0.2 s: 100 samples, quick)."""
    document = yaml.safe_load((ROOT / "configs" / "paper_sim.yaml").read_text(encoding="utf-8"))
    document["sample_time"] = 0.2
    path = tmp_path_factory.mktemp("imports") / "config.yaml"
    path.write_text(yaml.safe_dump(document), encoding="utf-8")
    child = subprocess.run(
        [sys.executable, "-c", _PROBE, str(path)], capture_output=True, text=True, cwd=ROOT, timeout=300, check=False
    )
    assert child.returncode == 0, child.stderr
    result = json.loads(child.stdout.splitlines()[-1])
    assert result["norm_2"] > 0  # the design really ran to its certificates
    return set(result["modules"])


@pytest.mark.slow
def test_the_probe_sees_what_the_design_loads(loaded: set[str]) -> None:
    """The probe is not blind: the modules the design does use are in its list."""
    assert {"numpy", "scipy.linalg", "foilc_hil.design.certificates", "foilc_hil.commands.synthesize"} <= loaded


@pytest.mark.slow
@pytest.mark.parametrize("module", HEAVY)
def test_the_design_path_does_not_load(loaded: set[str], module: str) -> None:
    assert module not in loaded, f"{module} was imported by the design path of synthesize"


@pytest.mark.slow
def test_the_design_path_does_not_load_scipy_signal(loaded: set[str]) -> None:
    assert "scipy.signal" not in loaded


@pytest.mark.slow
def test_the_command_module_alone_loads_no_design(tmp_path: Path) -> None:
    """Importing the command (as ``foilc-hil --help`` and the parser do) loads neither cvxpy nor scipy."""
    code = "import sys, foilc_hil.commands.synthesize; print(sorted(m for m in ('cvxpy', 'scipy') if m in sys.modules))"
    child = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert child.returncode == 0, child.stderr
    assert child.stdout.strip() == "[]"


@pytest.mark.parametrize("states", [1, 2, 3, 5])
def test_transfer_function_is_scipys_ss2tf_bit_for_bit(states: int) -> None:
    from scipy import signal

    rng = np.random.default_rng(states)
    for _ in range(20):
        a = rng.standard_normal((states, states))
        b = rng.standard_normal((states, 1))
        c = rng.standard_normal((1, states))
        num, den = signal.ss2tf(a, b, c, np.zeros((1, 1)))
        row = np.trim_zeros(np.asarray(num[0], dtype=float), "f")
        expected = ([float(x) for x in row] if row.size else [0.0]), [float(x) for x in den]
        assert ContinuousModel(a, b, c).transfer_function() == expected


@pytest.mark.parametrize(
    ("first", "second"),
    [((700,), (1300,)), ((1, 1), (900, 3)), ((513, 1), (2000, 2)), ((300, 2, 1), (41, 1, 4)), ((1,), (600,))],
)
def test_fft_convolve_is_scipys_fftconvolve_bit_for_bit(first: tuple[int, ...], second: tuple[int, ...]) -> None:
    from scipy import signal

    rng = np.random.default_rng(sum(first) + sum(second))
    a = rng.standard_normal(first)
    b = rng.standard_normal(second) * 10.0 ** rng.integers(-6, 6, size=second)
    got = fft_convolve(a, b)
    expected = signal.fftconvolve(a, b, mode="full", axes=0)
    assert got.shape == expected.shape
    assert got.tobytes() == expected.tobytes()


def test_fft_convolve_is_the_linear_convolution() -> None:
    """Independent of scipy: the direct sum (numpy.convolve per column) to rounding, with no wrap-around."""
    rng = np.random.default_rng(7)
    a = rng.standard_normal(1000)
    b = rng.standard_normal((777, 2))
    got = fft_convolve(a[:, None], b)
    for column in range(2):
        assert np.allclose(got[:, column], np.convolve(a, b[:, column]), rtol=0, atol=1e-10)


def test_fft_convolve_refuses_what_does_not_broadcast() -> None:
    with pytest.raises(InputError, match="do not broadcast"):
        fft_convolve(np.ones((5, 2)), np.ones((5, 3)))
    with pytest.raises(InputError, match="number of dimensions"):
        fft_convolve(np.ones(5), np.ones((5, 1)))
    with pytest.raises(InputError, match="real"):
        fft_convolve(np.ones(5, dtype=complex), np.ones(5))


@pytest.mark.parametrize("n", [1, 7, NEAR_FIELD + 5])
def test_one_dimensional_direct_sum_is_scipys_direct_convolve_bit_for_bit(n: int) -> None:
    """The 1-D direct path is numpy.convolve now; scipy.signal.convolve(method='direct') gave the same bits."""
    from scipy import signal

    rng = np.random.default_rng(n)
    g = rng.standard_normal(n) * 10.0 ** rng.integers(-8, 8, size=n)
    expected = signal.convolve(gl_weights(0.7, n), g, mode="full", method="direct")[:n] * 1e-3**-0.7
    assert gl_derivative(g, 0.7, 1e-3, method="direct").tobytes() == expected.tobytes()
