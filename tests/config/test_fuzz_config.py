"""Fuzzed configs: a mutated shipped config either loads or is one ``ConfigError`` -- exit 2, one stderr line
naming the file, one JSON document under ``--json`` -- never another exception and never a traceback."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
import yaml
from hypothesis import event, example, given
from hypothesis import strategies as st

from foilc_hil.cli import main
from foilc_hil.config import load_config
from foilc_hil.errors import ConfigError
from tests.support.fuzz_settings import fuzz_settings

pytestmark = pytest.mark.slow

CONFIGS = Path(__file__).resolve().parents[2] / "configs"
SHIPPED = {name: yaml.safe_load((CONFIGS / name).read_text(encoding="utf-8")) for name in ("demo.yaml",
                                                                                         "paper_sim.yaml")}


def _paths(node: Any, prefix: tuple[str, ...] = ()) -> list[tuple[str, ...]]:
    """Every key path of a mapping tree, sections included."""
    if not isinstance(node, dict):
        return []
    found = []
    for key, value in node.items():
        found.append((*prefix, str(key)))
        found.extend(_paths(value, (*prefix, str(key))))
    return found


SCALARS = st.one_of(
    st.none(), st.booleans(), st.integers(), st.floats(), st.text(max_size=12),
    st.sampled_from([10**30, -(10**30), 1e308, -1e308, 0, -1, 1e-320, "nan", ".inf", "", "yes", "0x10"]),
)
VALUES = st.recursive(SCALARS, lambda inner: st.lists(inner, max_size=3) | st.dictionaries(
    st.text(max_size=6), inner, max_size=3), max_leaves=6)


@st.composite
def mutated_config(draw: st.DrawFn) -> bytes:
    """A shipped config with one structured mutation, then maybe a raw one (cut, garbage bytes)."""
    document = json.loads(json.dumps(SHIPPED[draw(st.sampled_from(sorted(SHIPPED)))]))  # a deep copy
    path = draw(st.sampled_from(_paths(document)))
    parent = document
    for key in path[:-1]:
        parent = parent[key]
    action = draw(st.sampled_from(["replace", "delete", "insert"]))
    if action == "replace":
        parent[path[-1]] = draw(VALUES)
    elif action == "delete":
        del parent[path[-1]]
    else:
        parent[draw(st.text(min_size=1, max_size=10))] = draw(VALUES)
    text = yaml.safe_dump(document, sort_keys=False).encode()
    raw = draw(st.sampled_from(["none", "cut", "garbage"]))
    if raw == "cut":
        text = text[: draw(st.integers(0, len(text)))]
    elif raw == "garbage":
        at = draw(st.integers(0, len(text)))
        text = text[:at] + draw(st.binary(min_size=1, max_size=16)) + text[at:]
    return text


def _check_one_error(code: int, out: str, err: str, path: Path) -> None:
    """The exit-2 contract: one stderr line naming the file, one JSON error document."""
    assert code == 2, (code, err)
    lines = err.strip().splitlines()
    assert len(lines) == 1, lines
    assert str(path) in lines[0]
    document = json.loads(out)  # exactly one document, or this raises
    assert document["error"]["exit_code"] == 2
    assert document["error"]["type"] == "ConfigError"


# a section replaced by a list of mappings
@example(text=b"plant:\n- {}\n")
@example(text=b"\xff\xfe\x00plant: {model: first_order}\n")  # not UTF-8
@given(text=mutated_config())
@fuzz_settings(examples=40)
def test_mutated_config_loads_or_is_one_config_error(
    text: bytes, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "fuzzed.yaml"
    path.write_bytes(text)
    try:
        load_config(path)
    except ConfigError as exc:
        event("ConfigError")
        assert exc.source == str(path) or str(path) in str(exc)
        capsys.readouterr()
        code = main(["simulate", "--config", str(path), "--json"])
        captured = capsys.readouterr()
        _check_one_error(code, captured.out, captured.err, path)
        assert "Traceback" not in captured.err
    else:
        event("loads")


@given(text=mutated_config())
@fuzz_settings(examples=15)
def test_tune_on_a_mutated_config_exits_cleanly(
    text: bytes, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """``tune`` validates, then tunes a loop in well under a second: a loaded mutant runs to its end."""
    path = tmp_path / "fuzzed.yaml"
    path.write_bytes(text)
    capsys.readouterr()
    code = main(["tune", "--config", str(path), "--json"])
    captured = capsys.readouterr()
    assert "Traceback" not in captured.err
    document = json.loads(captured.out)  # exactly one document, whatever happened
    assert code in (0, 2, 3), (code, captured.err)
    event(f"tune exit {code}")
    if code == 0:
        assert "error" not in document and captured.err == ""
        return
    assert len(captured.err.strip().splitlines()) == 1, captured.err
    assert document["error"]["exit_code"] == code
    if document["error"]["type"] == "ConfigError":
        assert str(path) in captured.err
