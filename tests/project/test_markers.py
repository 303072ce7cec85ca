"""The test markers are applied: every test module that creates a private network namespace (``unshare --net``) is
marked ``netns``, and ``slow`` too (a namespace holds whole processes, never a quick check), so
``pytest -m "not slow"`` leaves them out of the inner loop and ``-m "not netns"`` where namespaces are not permitted.

Read from the sources (no test is run): a module is marked when its module-level ``pytestmark`` names the marker.
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

TESTS = Path(__file__).resolve().parents[1]
NETNS_CALL = '"unshare", "--net"'


def creates_netns(source: str) -> bool:
    """The module runs ``unshare --net`` itself."""
    return NETNS_CALL in source


def _mark_names(node: ast.AST) -> set[str]:
    return {sub.attr for sub in ast.walk(node)
            if isinstance(sub, ast.Attribute) and isinstance(sub.value, ast.Attribute) and sub.value.attr == "mark"}


def module_marks(source: str) -> set[str]:
    """The markers of a module's ``pytestmark`` (``pytest.mark.NAME`` or a list of them)."""
    marks: set[str] = set()
    for node in ast.parse(source).body:
        if isinstance(node, ast.Assign) and any(isinstance(t, ast.Name) and t.id == "pytestmark"
                                                for t in node.targets):
            marks |= _mark_names(node.value)
    return marks


def marks_of_tests(source: str) -> dict[str, set[str]]:
    """Each test function's own markers (its decorators), by name."""
    return {node.name: set().union(*(_mark_names(d) for d in node.decorator_list))
            for node in ast.parse(source).body
            if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef) and node.name.startswith("test_")}


def netns_modules() -> list[Path]:
    """The test modules that create a network namespace (this one only names the call)."""
    return sorted(path for path in TESTS.rglob("test_*.py")
                  if path != Path(__file__).resolve() and creates_netns(path.read_text(encoding="utf-8")))


def test_netns_modules_are_found() -> None:
    """The scan sees the namespace tests (it can fail: a renamed call would leave this list empty)."""
    assert TESTS / "crossprocess" / "test_crossprocess_emulator.py" in netns_modules()


def netns_marked(source: str) -> bool:
    """The whole module is marked ``netns`` and ``slow``, or its namespace tests are (a module that also holds
    quick tests marks those that create the namespace)."""
    if {"netns", "slow"} <= module_marks(source):
        return True
    per_test = marks_of_tests(source).values()
    return any("netns" in marks for marks in per_test) and all("slow" in marks for marks in per_test
                                                                if "netns" in marks)


@pytest.mark.parametrize("path", netns_modules(), ids=lambda path: path.name)
def test_every_module_creating_a_netns_is_marked_netns_and_slow(path: Path) -> None:
    assert netns_marked(path.read_text(encoding="utf-8")), (
        f"{path.name}: pytestmark = [pytest.mark.netns, pytest.mark.slow], or both on each test that creates one")


@pytest.mark.parametrize(("source", "marked"), [
    ("pytestmark = [pytest.mark.netns, pytest.mark.slow]\ndef test_a(): ...", True),
    ("pytestmark = pytest.mark.slow\ndef test_a(): ...", False),
    ("@pytest.mark.netns\n@pytest.mark.slow\ndef test_a(): ...\ndef test_b(): ...", True),
    ("@pytest.mark.netns\ndef test_a(): ...", False),
    ("def test_a(): ...", False),
])
def test_netns_marked_can_fail(source: str, marked: bool) -> None:
    assert netns_marked(source) is marked


@pytest.mark.parametrize(("source", "expected"), [
    ("pytestmark = [pytest.mark.netns, pytest.mark.slow]", {"netns", "slow"}),
    ("pytestmark = pytest.mark.slow", {"slow"}),
    ("pytestmark = pytest.mark.timeout(120)", {"timeout"}),
    ("marks = [pytest.mark.netns]", set()),
])
def test_module_marks_reads_pytestmark(source: str, expected: set[str]) -> None:
    assert module_marks(source) == expected
