"""Code-shape rules of the project, checked on the source: no function over 80 lines unless its docstring says why."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("foilc_hil", "drivers", "plant_emulator")
MAX_LINES = 80
#: a longer function must say why in its docstring, with these words
EXCUSE = "Longer than 80 lines because"


def long_functions(source: str, limit: int = MAX_LINES) -> list[tuple[str, int]]:
    """Functions of ``source`` longer than ``limit`` lines (def line to last line) without an excuse."""
    found = []
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            length = (node.end_lineno or node.lineno) - node.lineno + 1
            if length > limit and EXCUSE not in (ast.get_docstring(node) or ""):
                found.append((node.name, length))
    return found


SOURCES = sorted(path for package in PACKAGES for path in (ROOT / package).rglob("*.py"))


@pytest.mark.parametrize("path", SOURCES, ids=lambda path: str(path.relative_to(ROOT)))
def test_no_function_over_80_lines(path: Path) -> None:
    assert long_functions(path.read_text(encoding="utf-8")) == []


def test_the_rule_can_fail() -> None:
    body = "\n".join(f"    x{i} = {i}" for i in range(MAX_LINES))
    assert long_functions(f"def f():\n{body}\n") == [("f", MAX_LINES + 1)]
    excused = f'def f():\n    """{EXCUSE} it is a table."""\n{body}\n'
    assert long_functions(excused) == []
