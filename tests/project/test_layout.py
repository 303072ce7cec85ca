"""The test tree's layout (``docs/architecture.md``, "Tests"): every test module sits in a directory of the layout,
none directly in ``tests/`` and none among the helpers of ``tests/support/``; each directory is a package (test
module names stay unique by their dotted path) and the doc's table names each of them, no more.

Read from the tree (no test is run).
"""

from __future__ import annotations

import re
from pathlib import Path

TESTS = Path(__file__).resolve().parents[1]
DOC = TESTS.parent / "docs" / "architecture.md"

#: the directories of test modules (``tests/support/`` holds helpers, ``tests/data/`` data files)
TEST_DIRS = ("drivers", "plant_emulator", "design", "loop", "io", "config", "benchmarks", "project", "integration",
             "crossprocess")
HELPERS = "support"


def layout_modules() -> list[Path]:
    return sorted(TESTS.rglob("test_*.py"))


def misplaced(modules: list[Path]) -> list[str]:
    """The test modules outside the layout's directories (directly in ``tests/``, in ``support/``, nested deeper)."""
    return [str(path.relative_to(TESTS)) for path in modules
            if path.parent.parent != TESTS or path.parent.name not in TEST_DIRS]


def test_every_test_module_sits_in_a_directory_of_the_layout() -> None:
    modules = layout_modules()
    assert len(modules) > 100  # the scan sees the tree
    wrong = misplaced(modules)
    assert not wrong, f"test modules outside {TEST_DIRS}: {wrong}"


def test_the_rule_can_fail() -> None:
    assert misplaced([TESTS / "test_x.py", TESTS / HELPERS / "test_y.py", TESTS / "loop" / "deep" / "test_z.py",
                      TESTS / "loop" / "test_ok.py"]) == ["test_x.py", "support/test_y.py", "loop/deep/test_z.py"]


def test_every_directory_is_a_package_with_tests() -> None:
    for name in (*TEST_DIRS, HELPERS):
        assert (TESTS / name / "__init__.py").is_file(), f"tests/{name}/ has no __init__.py"
    for name in TEST_DIRS:
        assert list((TESTS / name).glob("test_*.py")), f"tests/{name}/ holds no test module"


def test_the_doc_names_the_layout() -> None:
    text = DOC.read_text(encoding="utf-8")
    section = text[text.index("## Tests"):]
    named = set(re.findall(r"^\| `tests/(\w+)/` \|", section, flags=re.MULTILINE))
    assert named == {*TEST_DIRS, HELPERS}, f"docs/architecture.md's test layout against TEST_DIRS: {named}"
    on_disk = {path.name for path in TESTS.iterdir() if path.is_dir() and (path / "__init__.py").is_file()}
    assert on_disk == {*TEST_DIRS, HELPERS}, f"packages of tests/ not in the layout: {on_disk - {*TEST_DIRS, HELPERS}}"
