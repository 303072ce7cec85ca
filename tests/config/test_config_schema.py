"""``foilc-hil config schema``: the JSON Schema of the config accepts every shipped config and refuses what the
loader refuses.

``jsonschema`` is not a dependency of the product, so when it is not installed the documents are checked by
:func:`_check`, a small validator of the keywords pydantic emits (``$ref``, ``anyOf``, ``type``, ``enum``,
``properties``/``additionalProperties``, ``items``/``prefixItems``, numeric bounds); it is itself checked to refuse
planted errors (unknown keys, wrong types, an out-of-range value), so a schema that accepted anything would fail.
"""

from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path
from typing import Any

import pytest
import yaml

from foilc_hil.cli import main
from foilc_hil.config import load_config
from foilc_hil.errors import ConfigError

# every shipped config file but the parameter set of `commission params` (not a config)
CONFIGS = sorted(p for p in (Path(__file__).resolve().parents[2] / "configs").glob("*.yaml")
                 if p.name != "params_example.yaml")
_TYPES: dict[str, tuple[type, ...]] = {
    "object": (dict,), "array": (list,), "string": (str,), "boolean": (bool,), "null": (type(None),),
    "integer": (int,), "number": (int, float),
}


def _schema() -> dict[str, Any]:
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert main(["config", "schema", "--json"]) == 0
    document: dict[str, Any] = json.loads(out.getvalue())
    return document


def _check(value: Any, node: dict[str, Any], root: dict[str, Any], path: str) -> list[str]:
    """Where ``value`` breaks ``node`` (empty: it validates)."""
    if "$ref" in node:
        return _check(value, root["$defs"][node["$ref"].rsplit("/", 1)[-1]], root, path)
    if "anyOf" in node:
        failures = [_check(value, option, root, path) for option in node["anyOf"]]
        return [] if any(not f for f in failures) else [f"{path}: matches no anyOf branch ({failures})"]
    kinds = node.get("type")
    if kinds is not None:
        allowed = tuple(t for kind in ([kinds] if isinstance(kinds, str) else kinds) for t in _TYPES[kind])
        if not isinstance(value, allowed) or (isinstance(value, bool) and bool not in allowed):
            return [f"{path}: {value!r} is not {kinds}"]
    if "enum" in node and value not in node["enum"]:
        return [f"{path}: {value!r} not in {node['enum']}"]
    if "const" in node and value != node["const"]:
        return [f"{path}: {value!r} is not {node['const']!r}"]
    for key, broken in (("minimum", lambda v, b: v < b), ("maximum", lambda v, b: v > b),
                        ("exclusiveMinimum", lambda v, b: v <= b), ("exclusiveMaximum", lambda v, b: v >= b)):
        if key in node and isinstance(value, (int, float)) and broken(value, node[key]):
            return [f"{path}: {value!r} breaks {key} {node[key]}"]
    if isinstance(value, dict):
        return _check_object(value, node, root, path)
    if isinstance(value, list):
        prefix = node.get("prefixItems", [])
        rest = node.get("items", {})
        return [problem for i, item in enumerate(value)
                for problem in _check(item, prefix[i] if i < len(prefix) else rest, root, f"{path}[{i}]")]
    return []


def _check_object(value: dict[str, Any], node: dict[str, Any], root: dict[str, Any], path: str) -> list[str]:
    properties = node.get("properties", {})
    problems = [f"{path}.{key}: not allowed" for key in value
                if key not in properties and node.get("additionalProperties") is False]
    extra = node.get("additionalProperties")
    for key, item in value.items():
        if key in properties:
            problems += _check(item, properties[key], root, f"{path}.{key}")
        elif isinstance(extra, dict):
            problems += _check(item, extra, root, f"{path}.{key}")
    problems += [f"{path}.{key}: required" for key in node.get("required", []) if key not in value]
    return problems


def _validate(document: Any, schema: dict[str, Any]) -> list[str]:
    try:
        import jsonschema
    except ImportError:
        return _check(document, schema, schema, "$")
    return [error.message for error in jsonschema.Draft202012Validator(schema).iter_errors(document)]


def test_the_schema_names_its_dialect_and_refuses_unknown_keys() -> None:
    schema = _schema()
    assert schema["$schema"] == "https://json-schema.org/draft/2020-12/schema"
    assert schema["additionalProperties"] is False
    assert {"plant", "law", "drive", "bus", "bench"} <= set(schema["properties"])


@pytest.mark.parametrize("path", CONFIGS, ids=lambda p: p.name)
def test_every_shipped_config_validates(path: Path) -> None:
    load_config(path)  # the loader accepts it: the schema must too
    assert _validate(yaml.safe_load(path.read_text(encoding="utf-8")), _schema()) == []


@pytest.mark.parametrize(("change", "where"), [
    ({"plant": {"colour": "red"}}, "$.plant.colour"),
    ({"trials": "many"}, "$.trials"),
    ({"drive": {"node_id": 200}}, "$.drive.node_id"),
    ({"law": {"kind": "pid"}}, "$.law.kind"),
    ({"sampletime": 0.001}, "$.sampletime"),
])
def test_what_the_loader_refuses_the_schema_refuses(change: dict[str, Any], where: str, tmp_path: Path) -> None:
    document = {**yaml.safe_load(CONFIGS[0].read_text(encoding="utf-8")), **change}
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump(document), encoding="utf-8")
    with pytest.raises(ConfigError, match=r"bad\.yaml"):
        load_config(bad)
    problems = _validate(document, _schema())
    assert problems
    assert any(where.rsplit(".", 1)[-1] in problem for problem in problems)
