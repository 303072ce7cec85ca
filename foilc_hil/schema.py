"""Config validation toolkit: strict pydantic models, YAML loading, CLI overrides, one-line errors.

Every section of the configuration is a :class:`Section` (extra keys forbidden, immutable). Loading turns the
first validation failure into a :class:`~foilc_hil.errors.ConfigError` naming the file and the dotted key path,
e.g. ``configs/x.yaml: plant.b: must be non-zero``; an unknown key gets a did-you-mean.

Precedence is command-line options > config file > defaults: :func:`load_document` reads the YAML mapping,
:func:`apply_overrides` writes dotted-key CLI values into it, and :func:`validate` builds the typed object, so
defaults fill only what neither gave.
"""

from __future__ import annotations

import difflib
from collections.abc import Mapping
from pathlib import Path
from typing import Annotated, Any, TypeVar

import numpy as np
import yaml
from pydantic import BaseModel, BeforeValidator, ConfigDict, ValidationError, WithJsonSchema, field_validator

from foilc_hil.errors import ConfigError

__all__ = [
    "MAX_DOCUMENT_BYTES",
    "MAX_EXPANDED_NODES",
    "MAX_MAGNITUDE",
    "Matrix",
    "Section",
    "apply_overrides",
    "as_array",
    "load_document",
    "load_yaml_text",
    "validate",
]

SectionT = TypeVar("SectionT", bound="Section")

#: a config is a page of YAML; anything larger is a mistake or an attack
MAX_DOCUMENT_BYTES = 1 << 20
#: nodes of the document with every alias expanded: YAML aliases can describe exponentially large documents
#: ("billion laughs") in a few lines; validation would expand them
MAX_EXPANDED_NODES = 100_000
#: how deep mappings and lists may nest (deeper input would exhaust the recursion of the validators)
MAX_DEPTH = 32
#: no physical quantity of a servo axis, a design or a bench setting is larger: a finite but absurd value (1e308)
#: would overflow numpy or stall the LMI solver rather than fail cleanly
MAX_MAGNITUDE = 1e12


class Section(BaseModel):
    """Base of every config section: strict keys, frozen values, finite numbers of bounded magnitude."""

    model_config = ConfigDict(extra="forbid", frozen=True, populate_by_name=True, allow_inf_nan=False)

    @field_validator("*", mode="after")
    @classmethod
    def _bounded_numbers(cls, value: Any) -> Any:
        _check_magnitude(value)
        return value


def _check_magnitude(value: Any) -> None:
    """Every number inside ``value`` (nested lists included) is finite and at most :data:`MAX_MAGNITUDE`."""
    if isinstance(value, bool):
        return
    if isinstance(value, (int, float)):
        if not abs(value) <= MAX_MAGNITUDE:  # also catches nan
            raise ValueError(f"must be finite and at most {MAX_MAGNITUDE:g} in magnitude, got {value!r}")
    elif isinstance(value, (list, tuple)):
        for item in value:
            _check_magnitude(item)


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


def load_document(path: str | Path) -> dict[str, Any]:
    """Read a YAML config file into a mapping, with errors naming the file."""
    source = str(path)
    try:
        with Path(path).open("rb") as stream:
            raw = stream.read(MAX_DOCUMENT_BYTES + 1)
        if len(raw) > MAX_DOCUMENT_BYTES:
            raise ConfigError(f"larger than {MAX_DOCUMENT_BYTES} bytes; a config is a page of YAML", source=source)
        text = raw.decode("utf-8")
    except FileNotFoundError:
        raise ConfigError("no such file", source=source) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise ConfigError(f"cannot read: {exc}", source=source) from None
    try:
        document = load_yaml_text(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f"line {mark.line + 1}: " if mark is not None else ""
        problem = getattr(exc, "problem", None) or "invalid YAML"
        raise ConfigError(f"{where}{problem}", source=source) from None
    if document is None:
        return {}
    if not isinstance(document, dict):
        raise ConfigError("the top level must be a mapping of sections", source=source)
    return document


def load_yaml_text(text: str) -> Any:
    """``yaml.safe_load`` that refuses duplicate keys, deep nesting and alias expansion beyond the bounds.

    The node graph is composed first (aliases stay shared nodes, so composing is linear in the text) and checked
    before anything is constructed.
    """
    loader = yaml.SafeLoader(text)
    try:
        node = loader.get_single_node()
        if node is None:
            return None
        _check_nodes(node)
        return loader.construct_document(node)
    finally:
        loader.dispose()


def _check_nodes(root: yaml.Node) -> None:
    """Duplicate keys, depth and the expanded size of the graph below ``root`` (memoised per node)."""
    sizes: dict[int, int] = {}

    def size(node: yaml.Node, path: str, depth: int) -> int:
        if id(node) in sizes:
            if sizes[id(node)] < 0:
                raise _problem(node, f"{path or 'document'}: a recursive alias")
            return sizes[id(node)]
        if depth > MAX_DEPTH:
            raise _problem(node, f"{path or 'document'}: nested deeper than {MAX_DEPTH} levels")
        sizes[id(node)] = -1  # in progress: meeting it again is a cycle
        total = 1
        if isinstance(node, yaml.MappingNode):
            seen: dict[Any, int] = {}
            for key_node, value_node in node.value:
                key = key_node.value if isinstance(key_node, yaml.ScalarNode) else None
                if key is not None and key != "<<":
                    if key in seen:
                        raise _problem(key_node, f"{_join(path, key)}: duplicate key (first at line {seen[key]})")
                    seen[key] = key_node.start_mark.line + 1
                total += size(key_node, path, depth + 1) + size(value_node, _join(path, key), depth + 1)
        elif isinstance(node, yaml.SequenceNode):
            total += sum(size(item, f"{path}[{i}]", depth + 1) for i, item in enumerate(node.value))
        if total > MAX_EXPANDED_NODES:
            raise _problem(node, f"{path or 'document'}: expands to more than {MAX_EXPANDED_NODES} nodes "
                                 "(aliases refer to aliases)")
        sizes[id(node)] = total
        return total

    size(root, "", 0)


def _join(path: str, key: Any) -> str:
    return f"{path}.{key}" if path else str(key)


def _problem(node: yaml.Node, message: str) -> yaml.YAMLError:
    return yaml.constructor.ConstructorError(None, None, message, node.start_mark)


def apply_overrides(document: Mapping[str, Any], overrides: Mapping[str, Any]) -> dict[str, Any]:
    """Return a copy of ``document`` with dotted-key ``overrides`` written in (``None`` values are skipped)."""
    result: dict[str, Any] = _deep_copy(document)
    for dotted, value in overrides.items():
        if value is None:
            continue
        node = result
        *parents, leaf = dotted.split(".")
        for part in parents:
            child = node.get(part)
            if not isinstance(child, dict):
                child = {}
                node[part] = child
            node = child
        node[leaf] = value
    return result


def _deep_copy(value: Any) -> Any:
    if isinstance(value, Mapping):
        return {key: _deep_copy(item) for key, item in value.items()}
    if isinstance(value, list):
        return [_deep_copy(item) for item in value]
    return value


def validate(model: type[SectionT], document: Mapping[str, Any], source: str = "") -> SectionT:
    """Build ``model`` from ``document``; raise :class:`ConfigError` for the first problem, naming its key."""
    try:
        return model.model_validate(document)
    except ValidationError as exc:
        raise _first_error(model, exc, source) from None


def _first_error(model: type[BaseModel], exc: ValidationError, source: str) -> ConfigError:
    error = exc.errors(include_url=False)[0]
    location = [str(part) for part in error["loc"]]
    key = ".".join(location)
    kind = error["type"]
    if kind == "extra_forbidden":
        message = "unknown key" + _did_you_mean(model, location)
    elif kind == "missing":
        message = "is required"
    else:
        message = str(error["msg"])
        # pydantic prefixes messages of custom validators; the key path already says where.
        for prefix in ("Value error, ", "Assertion failed, "):
            message = message.removeprefix(prefix)
    return ConfigError(message, key=key, source=source)


def _did_you_mean(model: type[BaseModel], location: list[str]) -> str:
    """Suggest the closest known key for an unknown key at ``location``."""
    current: Any = model
    for part in location[:-1]:
        fields = getattr(current, "model_fields", None)
        if fields is None or part not in fields:
            # A list index or a union: fall back to no suggestion rather than guess.
            if part.isdigit():
                continue
            return ""
        annotation = fields[part].annotation
        current = _section_type(annotation)
        if current is None:
            return ""
    fields = getattr(current, "model_fields", {})
    known = list(fields) + [f.alias for f in fields.values() if f.alias]
    matches = difflib.get_close_matches(location[-1], known, n=1, cutoff=0.6)
    if matches:
        return f" (did you mean '{matches[0]}'?)"
    return f"; known keys: {', '.join(sorted(known))}" if known else ""


def _section_type(annotation: Any) -> Any:
    """The Section subclass inside ``annotation`` (plain, Optional or list), or None."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    for arg in getattr(annotation, "__args__", ()):
        found = _section_type(arg)
        if found is not None:
            return found
    return None
