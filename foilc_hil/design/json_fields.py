"""The JSON of the design records: plain JSON values out (:func:`jsonable`), typed fields read back with errors that
name the key (:func:`read_number`, :func:`read_typed`, :func:`read_matrix`, ...).

What :mod:`foilc_hil.design.certificate_record` and :mod:`foilc_hil.design.record` write, they read back with these:
non-finite floats go out as strings (``"inf"``, ``"nan"``) and come back as floats, matrices go out as lists of rows
and come back as finite, read-only float arrays.

Module order: after :mod:`foilc_hil.design.models`, before :mod:`foilc_hil.design.certificate_record`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from typing import Any, TypeVar

import numpy as np

from foilc_hil.design.models import ssmatrix
from foilc_hil.errors import InputError

__all__ = [
    "jsonable",
    "matrix_rows",
    "read_mapping",
    "read_matrix",
    "read_number",
    "read_optional",
    "read_typed",
]


_T = TypeVar("_T")


def read_matrix(value: Any, name: str) -> np.ndarray:
    """``value`` as a finite 2-D float array (a copy, read-only); the error names ``design.<name>``."""
    return ssmatrix(value, f"design.{name}", allow_scalar=False)


def matrix_rows(array: np.ndarray) -> list[list[float]]:
    """A matrix as JSON lists of rows (Python floats round-trip exactly through ``json``)."""
    return [[float(x) for x in row] for row in np.asarray(array, dtype=float)]


def jsonable(value: Any) -> Any:
    """Plain JSON values (numpy scalars/arrays converted, non-finite floats as strings, records via ``to_json``)."""
    if hasattr(value, "to_json"):
        return jsonable(value.to_json())
    if isinstance(value, Mapping):
        return {str(k): jsonable(v) for k, v in value.items()}
    if isinstance(value, np.ndarray):
        return jsonable(value.tolist())
    if isinstance(value, (list, tuple)):
        return [jsonable(v) for v in value]
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        number = float(value)
        return number if math.isfinite(number) else str(number)
    return value


# --- reading JSON back --------------------------------------------------------------------------------------------


def read_number(document: Mapping[str, Any], key: str, where: str) -> float:
    """A float written by :func:`jsonable` (non-finite values were written as strings such as ``"inf"``)."""
    if key not in document:
        raise InputError(f"{where}.{key}: is required")
    raw = document[key]
    if isinstance(raw, str) and raw in ("inf", "-inf", "nan"):
        return float(raw)
    if isinstance(raw, bool) or not isinstance(raw, (int, float)):
        raise InputError(f"{where}.{key}: must be a number")
    return float(raw)


def read_optional(document: Mapping[str, Any], key: str, read: Callable[[Any], _T]) -> _T | None:
    return read(document[key]) if key in document and document[key] is not None else None


def read_typed(document: Mapping[str, Any], key: str, kind: type[_T], where: str) -> _T:
    if key not in document:
        raise InputError(f"{where}.{key}: is required")
    value = document[key]
    if not isinstance(value, kind) or (kind is int and isinstance(value, bool)):
        raise InputError(f"{where}.{key}: must be a {kind.__name__}")
    return value


def read_mapping(value: Any, where: str) -> Mapping[str, Any]:
    if not isinstance(value, Mapping):
        raise InputError(f"{where}: must be an object")
    return value
