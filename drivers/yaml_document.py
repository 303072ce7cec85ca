"""The config document: safe YAML loading and dotted command-line overrides, with one-line errors.

Precedence is command-line options > config file > defaults: :func:`load_document` reads the YAML mapping,
:func:`apply_overrides` writes dotted-key CLI values into it, and :func:`drivers.schema.validate` builds the typed
object, so defaults fill only what neither gave. Loading refuses what a page of config never needs (a large file,
duplicate keys, deep nesting, alias expansion beyond bounds) with a :class:`~drivers.errors.ConfigError` naming the
file and line.

Below every package that reads the document (``plant-emulator``'s command line reads the bench's config file);
:mod:`foilc_hil.schema` re-exports it.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

import yaml

from drivers.errors import ConfigError

__all__ = ["MAX_DEPTH", "MAX_DOCUMENT_BYTES", "MAX_EXPANDED_NODES", "apply_overrides", "load_document",
           "load_yaml_text"]

#: a config is a page of YAML; anything larger is a mistake or an attack
MAX_DOCUMENT_BYTES = 1 << 20
#: nodes of the document with every alias expanded: YAML aliases can describe exponentially large documents
#: ("billion laughs") in a few lines; validation would expand them
MAX_EXPANDED_NODES = 100_000
#: how deep mappings and lists may nest (deeper input would exhaust the recursion of the validators)
MAX_DEPTH = 32


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


