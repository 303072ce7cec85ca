"""The dependency rule of docs/architecture.md: imports point down the ranks, and the import graph has no cycle.

Every import counts: module level, ``TYPE_CHECKING`` blocks and function-local imports alike (a cycle hidden behind
a function-local import is still a cycle in the design). Relative imports are resolved.
"""

from __future__ import annotations

import ast
import functools
from collections.abc import Iterable, Mapping
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("foilc_hil", "drivers", "plant_emulator")

# Rank of each part of the data path: drive side -> config -> design -> law -> loop -> log -> tools -> commands.
# A module may import modules of its own rank or lower. The longest matching prefix decides.
RANKS: dict[str, int] = {
    "drivers": 0,  # the CAN side, with the root of the error tree and the config sections' base: stands alone
    "plant_emulator": 1,  # physics and the virtual drive, on drivers only: stands alone too
    "foilc_hil": 2,  # the prefix of every foilc_hil module; the package's own __init__ is in PACKAGE_TOPS
    "foilc_hil.errors": 2,
    "foilc_hil.schema": 2,
    "foilc_hil.config": 4,
    "foilc_hil.metrics": 4,
    "foilc_hil.references": 5,
    "foilc_hil.progress": 5,
    "foilc_hil.design": 6,
    "foilc_hil.laws": 7,
    "foilc_hil.io": 8,
    "foilc_hil.loop": 9,
    "foilc_hil.logtools": 10,
    "foilc_hil.commission": 10,
    "foilc_hil.live": 10,  # the live view (run --live, replay --live): beside the log tools, over io and loop
    "foilc_hil.commands": 11,
    "foilc_hil.api": 11,
    "foilc_hil.cli": 12,
}

#: a package's own ``__init__`` where it is not its modules' prefix rank: ``foilc_hil``'s is the public API, which
#: re-exports (lazily) from every rank up to ``foilc_hil.api``; the CLI imports its ``__version__``
PACKAGE_TOPS: dict[str, int] = {"foilc_hil": 12}

#: the packages a script may import without the control stack: nothing of theirs imports ``foilc_hil``
STANDALONE = ("drivers", "plant_emulator")

def rank(module: str) -> int | None:
    """The rank of ``module`` (None: not ours)."""
    if module in PACKAGE_TOPS:
        return PACKAGE_TOPS[module]
    parts = module.split(".")
    for end in range(len(parts), 0, -1):
        prefix = ".".join(parts[:end])
        if prefix in RANKS:
            return RANKS[prefix]
    return None


def module_name(path: Path) -> str:
    parts = path.relative_to(ROOT).with_suffix("").parts
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def project_modules() -> dict[str, Path]:
    return {module_name(path): path for package in PACKAGES for path in sorted((ROOT / package).rglob("*.py"))}


def imports_of(module: str, source: str, known: Iterable[str], *, is_package: bool = False) -> set[str]:
    """Project modules ``module`` imports anywhere in ``source`` (``from a import b`` counts ``a.b`` if a module)."""
    known = set(known)
    found: set[str] = set()
    for node in ast.walk(ast.parse(source)):
        if isinstance(node, ast.Import):
            found.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = module.split(".")
                anchor = parts[: len(parts) - node.level + (1 if is_package else 0)]
                base = ".".join([*anchor, base] if base else anchor)
            found.add(base)
            found.update(f"{base}.{alias.name}" for alias in node.names if f"{base}.{alias.name}" in known)
    return {name for name in found if rank(name) is not None and name != module}


def import_graph(modules: Mapping[str, Path]) -> dict[str, set[str]]:
    graph: dict[str, set[str]] = {}
    for module, path in modules.items():
        targets = imports_of(module, path.read_text(encoding="utf-8"), modules, is_package=path.name == "__init__.py")
        # an import of a package means its __init__; a submodule import implies its parents' __init__ (empty here)
        graph[module] = {target for target in targets if target in modules}
    return graph


def find_cycle(graph: Mapping[str, set[str]]) -> list[str] | None:
    """One cycle of ``graph`` as a path ``[a, b, ..., a]``, or None (iterative DFS, three colours)."""
    white, grey, black = 0, 1, 2
    colour = dict.fromkeys(graph, white)
    for start in sorted(graph):
        if colour[start] != white:
            continue
        stack: list[tuple[str, list[str]]] = [(start, sorted(graph[start]))]
        colour[start] = grey
        while stack:
            node, todo = stack[-1]
            if not todo:
                colour[node] = black
                stack.pop()
                continue
            nxt = todo.pop()
            if colour.get(nxt, black) == grey:
                path = [entry for entry, _ in stack]
                return [*path[path.index(nxt):], nxt]
            if colour.get(nxt) == white:
                colour[nxt] = grey
                stack.append((nxt, sorted(graph.get(nxt, ()))))
    return None


MODULES = project_modules()


@functools.cache
def project_graph() -> dict[str, set[str]]:
    """The project's import graph, parsed once per process and only where a test needs it: at module level every
    pytest worker parsed all the sources while collecting (2 s of CPU each)."""
    return import_graph(MODULES)


def test_every_module_has_a_rank() -> None:
    unranked = sorted(module for module in MODULES if rank(module) is None)
    assert not unranked, f"give these a rank in RANKS (and docs/architecture.md): {unranked}"


@pytest.mark.slow
@pytest.mark.parametrize("module", sorted(MODULES))
def test_imports_point_down(module: str) -> None:
    own = rank(module)
    assert own is not None
    graph = project_graph()
    upward = sorted(f"{target} (rank {rank(target)})" for target in graph[module] if (rank(target) or 0) > own)
    assert not upward, f"{module} (rank {own}) imports up: {upward}"


@pytest.mark.slow
@pytest.mark.parametrize("module", sorted(m for m in MODULES if m.split(".")[0] in STANDALONE))
def test_stand_alone_packages_import_nothing_of_foilc_hil(module: str) -> None:
    """``drivers`` and ``plant_emulator`` stand alone: no import of theirs, function-local ones included, reaches
    ``foilc_hil`` (the ranks alone would allow a same-rank one)."""
    reached = sorted(target for target in project_graph()[module] if target.split(".")[0] == "foilc_hil")
    assert not reached, f"{module} imports {reached}"


def test_a_planted_import_of_foilc_hil_is_seen() -> None:
    """The stand-alone rule sees a function-local import of foilc_hil inside drivers."""
    source = "def late():\n    from foilc_hil.errors import ConfigError\n"
    found = imports_of("drivers.bus", source, MODULES)
    assert any(target.split(".")[0] == "foilc_hil" for target in found)


@pytest.mark.slow
def test_the_import_graph_has_no_cycle() -> None:
    cycle = find_cycle(project_graph())
    assert cycle is None, "import cycle: " + " -> ".join(cycle or [])


def test_function_local_imports_are_seen() -> None:
    source = "def f():\n    from foilc_hil.loop import bench\n    import drivers.cia402\n"
    assert imports_of("foilc_hil.design.x", source, MODULES) >= {"foilc_hil.loop", "drivers.cia402"}


@pytest.mark.slow
def test_a_planted_cycle_is_found() -> None:
    """The checker fails on a cycle planted through a function-local import (the shape that hid one before)."""
    planted = {module: set(targets) for module, targets in project_graph().items()}
    low, high = "foilc_hil.design.certificates", "foilc_hil.design.lmi"
    assert low in planted and high in planted
    planted[low] |= imports_of(low, "def late():\n    from foilc_hil.design.lmi import synthesize\n", MODULES)
    planted[high].add(low)
    cycle = find_cycle(planted)
    assert cycle is not None and cycle[0] == cycle[-1] and {low, high} <= set(cycle)


def test_a_planted_upward_import_is_flagged() -> None:
    assert (rank("foilc_hil.loop.bench") or 0) > (rank("foilc_hil.design.lmi") or 0)
    assert (rank("drivers.cia402") or 0) < (rank("plant_emulator.device") or 0) < (rank("foilc_hil.errors") or 0)
    assert rank("numpy") is None
