"""Hostile configs: each is refused with exit 2 and one line naming the place, and one JSON document under --json.

An alias bomb, duplicate keys, absurd numbers, deep nesting, a recursive alias and an oversized file must never reach
numpy, the solver or the validators' recursion (no traceback, no hang, no memory blow-up).
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from foilc_hil.cli import main
from foilc_hil.config import load_config
from foilc_hil.errors import ConfigError
from foilc_hil.schema import MAX_DOCUMENT_BYTES, MAX_EXPANDED_NODES, MAX_MAGNITUDE

PLANT = "plant:\n  model: first_order\n  a: -1.23\n  b: 1.68\n"


def alias_bomb(levels: int = 9, width: int = 9) -> str:
    lines = ["l0: &l0 [" + ", ".join(['"lol"'] * width) + "]"]
    for level in range(1, levels):
        lines.append(f"l{level}: &l{level} [" + ", ".join([f"*l{level - 1}"] * width) + "]")
    return "\n".join(lines) + f"\n{PLANT}"


CASES: dict[str, tuple[str, str]] = {
    # name: (YAML text, what the one line must name)
    "alias bomb": (alias_bomb(), f"expands to more than {MAX_EXPANDED_NODES} nodes"),
    "duplicate key": (PLANT + "  b: 2.0\n", "plant.b: duplicate key (first at line 4)"),
    "duplicate section": (PLANT + "plant:\n  model: pmsm\n", "plant: duplicate key (first at line 1)"),
    "huge float": (PLANT + "sample_time: 1.0e300\n", "sample_time: must be finite and at most"),
    "infinity": (PLANT + "sample_time: .inf\n", "sample_time:"),
    "huge integer": (PLANT + "trials: 100000000000000000000000\n", "trials:"),
    "deep nesting": ("x: " + "[" * 200 + "]" * 200 + "\n", "nested deeper than"),
    "recursive alias": ("x: &x [*x]\n", "recursive alias"),
}


def write(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "hostile.yaml"
    path.write_text(text, encoding="utf-8")
    return path


@pytest.mark.parametrize("name", sorted(CASES))
def test_hostile_config_is_one_line_exit_2(
    name: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    text, expected = CASES[name]
    path = write(tmp_path, text)
    code = main(["simulate", "--config", str(path)])
    captured = capsys.readouterr()
    assert code == 2
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1, lines
    assert lines[0].startswith(f"foilc-hil simulate: {path}: ")
    assert expected in lines[0]
    assert "Traceback" not in captured.err


@pytest.mark.parametrize("name", ["alias bomb", "duplicate key", "huge float"])
def test_hostile_config_json_error_document(name: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = write(tmp_path, CASES[name][0])
    code = main(["tune", "--config", str(path), "--json"])
    captured = capsys.readouterr()
    assert code == 2
    document = json.loads(captured.out)  # exactly one document
    assert document["error"]["exit_code"] == 2
    assert document["error"]["type"] == "ConfigError"
    assert document["error"]["source"] == str(path)
    assert CASES[name][1] in document["error"]["message"]


def test_oversized_file_is_refused_before_parsing(tmp_path: Path) -> None:
    path = write(tmp_path, PLANT + "#" * (MAX_DOCUMENT_BYTES + 10) + "\n")
    with pytest.raises(ConfigError, match="larger than"):
        load_config(path)


def test_bounds_leave_legitimate_configs_alone(tmp_path: Path) -> None:
    """Anchors, aliases and merge keys used as people do, and the largest allowed magnitude, still load."""
    text = PLANT + (
        "reference:\n  profile: piecewise\n  segments:\n"
        "    - &ramp {duration: 0.1, start: 0.0, end: 1.0}\n"
        "    - <<: *ramp\n      start: 1.0\n"  # an explicit key overrides a merged one: not a duplicate
        "    - *ramp\n"
    )
    config = load_config(write(tmp_path, text))
    segments = config.reference.segments
    assert segments is not None and [s.start for s in segments] == [0.0, 1.0, 0.0]
    assert load_config(write(tmp_path, PLANT.replace("1.68", repr(MAX_MAGNITUDE)))).plant.b == [[MAX_MAGNITUDE]]
