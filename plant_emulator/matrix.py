"""Matrices in a config: :data:`Matrix`, how a section gives one, and :func:`as_array`, the array it becomes.

The ``plant:`` section (:mod:`plant_emulator.config`) and the control stack's sections give their matrices this way;
it lives in the emulator package, below ``foilc_hil``, so the plant's section validates without the control stack
(:mod:`foilc_hil.schema` re-exports both names).
"""

from __future__ import annotations

from typing import Annotated, Any

import numpy as np
from pydantic import BeforeValidator, WithJsonSchema

from drivers.errors import ConfigError

__all__ = ["Matrix", "as_array"]


def _to_matrix(value: Any) -> Any:
    """Accept a scalar, a flat list (one row) or a list of rows; return a list of rows of floats."""
    if isinstance(value, bool):
        raise ValueError("must be a number or a matrix (list of rows)")
    if isinstance(value, (int, float)):
        return [[float(value)]]
    if isinstance(value, list):
        if not value:
            raise ValueError("must not be empty")
        rows = value if all(isinstance(row, list) for row in value) else [value]
        width = len(rows[0])
        for i, row in enumerate(rows):
            if len(row) != width:
                raise ValueError(f"row {i} has {len(row)} entries, row 0 has {width}")
            for entry in row:
                if isinstance(entry, bool) or not isinstance(entry, (int, float)):
                    raise ValueError(f"entry {entry!r} is not a number")
        return [[float(x) for x in row] for row in rows]
    raise ValueError("must be a number or a matrix (list of rows)")


_NUMBER_ROW: dict[str, Any] = {"type": "array", "items": {"type": "number"}, "minItems": 1}
#: what _to_matrix accepts, for `foilc-hil config schema` (pydantic would describe only the list of rows it returns)
_MATRIX_JSON_SCHEMA: dict[str, Any] = {"anyOf": [
    {"type": "number"}, _NUMBER_ROW, {"type": "array", "items": _NUMBER_ROW, "minItems": 1},
]}

Matrix = Annotated[list[list[float]], BeforeValidator(_to_matrix), WithJsonSchema(_MATRIX_JSON_SCHEMA)]
"""A real matrix given as a scalar, a single row or a list of rows (interface: matrices are lists of rows)."""


def as_array(matrix: list[list[float]], name: str) -> np.ndarray:
    """Return ``matrix`` as a finite 2-D float array, naming it in the error otherwise."""
    array = np.asarray(matrix, dtype=float)
    if array.ndim != 2:
        raise ConfigError("must be a 2-D matrix", key=name)
    if not np.all(np.isfinite(array)):
        raise ConfigError("must be finite", key=name)
    return array


