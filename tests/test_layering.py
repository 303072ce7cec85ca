"""The dependency rule: imports point down the layers of docs/architecture.md, never up."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LAYER0 = {"foilc_hil.errors", "foilc_hil.schema", "foilc_hil"}


def _layer(module: str) -> int:
    if module in LAYER0:
        return 0
    top = module.split(".")[0]
    return {"drivers": 1, "plant_emulator": 2, "foilc_hil": 3}.get(top, -1)


def _imports(path: Path) -> list[str]:
    tree = ast.parse(path.read_text(encoding="utf-8"))
    found: list[str] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            found.extend(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            found.append(node.module)
    return found


def _project_modules() -> list[tuple[str, Path]]:
    modules = []
    for package in ("foilc_hil", "drivers", "plant_emulator"):
        for path in sorted((ROOT / package).rglob("*.py")):
            parts = path.relative_to(ROOT).with_suffix("").parts
            name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
            modules.append((name, path))
    return modules


@pytest.mark.parametrize(("module", "path"), _project_modules(), ids=lambda v: str(v))
def test_imports_point_down(module: str, path: Path) -> None:
    own = _layer(module)
    for imported in _imports(path):
        other = _layer(imported)
        if other < 0:
            continue  # third party or stdlib
        assert other <= own, f"{module} (layer {own}) imports {imported} (layer {other})"


def test_the_rule_can_fail() -> None:
    """The checker itself flags an upward import."""
    assert _layer("foilc_hil.bench") > _layer("drivers.cia402")
    assert _layer("foilc_hil.errors") < _layer("drivers.cia402")
