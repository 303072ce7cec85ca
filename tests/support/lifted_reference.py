"""Test helper: the dense truths the lifted laws (NOILC, gradient ILC) are checked against, written out here.

Random stable plants (delay-augmented as the design augments them), the lifted plant from its Markov parameters
``C A^(i - j + d) B`` (a loop of matrix products, not the code under test), and the design models and vertex plants
of a config.
"""

from __future__ import annotations

import numpy as np

from foilc_hil.config import Config
from foilc_hil.design.models import DiscreteModel, augment_input_delay, uncertainty_vertices
from foilc_hil.design.pipeline import design_model, model_delay_samples


def random_model(rng: np.random.Generator, states: int, channels: int, delay: int) -> DiscreteModel:
    """A stable plant of ``states`` states, ``channels`` inputs and outputs, augmented by ``delay`` samples."""
    A = rng.standard_normal((states, states))
    A *= rng.uniform(0.3, 0.97) / max(abs(np.linalg.eigvals(A)))
    plant = DiscreteModel(
        A, rng.standard_normal((states, channels)), rng.standard_normal((channels, states)), 0.01
    )
    return augment_input_delay(plant, delay)[0]


def lifted(A: np.ndarray, B: np.ndarray, C: np.ndarray, delay: int, length: int) -> np.ndarray:
    """``G``: block ``(i, j)`` is ``C A^(i - j + delay) B`` for ``i >= j`` (``length`` blocks a side)."""
    p, m = C.shape[0], B.shape[1]
    blocks = np.zeros((length + 1, p, m))  # the last one zero: the blocks above the diagonal
    state = np.linalg.matrix_power(A, delay) @ B
    for k in range(length):
        blocks[k] = C @ state
        state = A @ state
    lag = np.subtract.outer(np.arange(length), np.arange(length))
    tiles = blocks[np.where(lag >= 0, lag, length)]  # (L, L, p, m): block (i, j) by its lag i - j
    return np.asarray(tiles.transpose(0, 2, 1, 3).reshape(length * p, length * m))


def config_plants(
    config: Config, input_delay: int, n_samples: int, *, whole: bool = False
) -> tuple[DiscreteModel, list[np.ndarray]]:
    """The design model of ``config`` behind ``input_delay`` cycles (plus the plant's own delay) and its lifted
    plants on the ``n_samples - d`` learnable samples of a trial (``G``; ``whole``: all inputs to all outputs of the
    trial, ``G_y``, blocks ``C A^k B`` from ``k = 0``): nominal first, then the uncertainty vertices (as the design
    orders them)."""
    model, uncertainty = design_model(config, input_delay=input_delay + model_delay_samples(config))
    C, d = model.measured_output, model.input_delay
    length = n_samples - d
    if whole:
        d, length = 0, n_samples
    plants = [lifted(model.A, model.B, C, d, length)]
    plants += [lifted(model.A + dA, model.B + dB, C, d, length) for dA, dB in uncertainty_vertices(uncertainty)]
    return model, plants
