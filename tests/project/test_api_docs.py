"""``docs/api.md`` documents the public API, and the API has numpydoc docstrings: every name the page heads exists
and every public name (each package top's ``__all__``) has its heading; each has a docstring with a summary line,
and the numpydoc sections its signature calls for (``Parameters`` for parameters, ``Returns`` or ``Yields`` for a
result, ``Attributes`` for a dataclass's fields)."""

from __future__ import annotations

import dataclasses
import importlib
import inspect
import re
from pathlib import Path
from typing import Any

import pytest

ROOT = Path(__file__).resolve().parents[2]
API_DOC = ROOT / "docs" / "api.md"
PACKAGES = ("foilc_hil", "drivers", "plant_emulator")
HEADING = re.compile(r"^#{3,4} `([\w.]+)`$", re.MULTILINE)


def documented(text: str) -> list[str]:
    """The dotted names of the page's level-3 and level-4 headings."""
    return HEADING.findall(text)


def resolve(dotted: str) -> Any:
    """``package.Name[.method]`` from the package's top, as a script reaches it."""
    package, *path = dotted.split(".")
    found: Any = importlib.import_module(package)
    for part in path:
        found = getattr(found, part)
    return found


def sections(doc: str) -> set[str]:
    """The numpydoc section titles of ``doc`` (a title underlined with dashes)."""
    return set(re.findall(r"^(\w[\w ]*)\n-{3,}$", doc, re.MULTILINE))


def missing_sections(obj: Any) -> list[str]:
    """What ``obj``'s docstring lacks (empty: a numpydoc docstring for its kind)."""
    doc = inspect.getdoc(obj) or ""
    if not doc.strip():
        return ["a docstring"]
    found = sections(doc)
    if inspect.ismodule(obj) or (isinstance(obj, type) and issubclass(obj, BaseException)):
        return []  # a summary: an exception's argument is its message
    if isinstance(obj, type):
        if dataclasses.is_dataclass(obj) and dataclasses.fields(obj):
            return [] if found & {"Attributes", "Parameters"} else ["Attributes"]
        return []  # enums and config sections (their fields: docs/config-reference.md); a class's __init__ is below
    function = obj.fget if isinstance(obj, property) else obj
    assert callable(function), f"{obj!r} is neither a module, a class, a property nor a function"
    signature = inspect.signature(function)
    wanted = []
    if [name for name in signature.parameters if name not in ("self", "cls")]:
        wanted.append("Parameters")
    returns = str(signature.return_annotation)
    if returns not in ("None", "inspect._empty", str(inspect.Signature.empty)) and not isinstance(obj, property):
        wanted.append("Returns|Yields")
    return [want for want in wanted if not set(want.split("|")) & found]


def test_every_documented_name_exists() -> None:
    names = documented(API_DOC.read_text(encoding="utf-8"))
    assert len(names) > 20
    for name in names:
        resolve(name)  # AttributeError names the one that does not


def test_every_public_name_is_documented() -> None:
    names = set(documented(API_DOC.read_text(encoding="utf-8")))
    public = {f"{package}.{name}" for package in PACKAGES for name in importlib.import_module(package).__all__
              if not name.startswith("__")}
    assert sorted(public - names) == []
    assert sorted(name for name in names if name.count(".") == 1 and name not in public) == []


@pytest.mark.parametrize("name", documented(API_DOC.read_text(encoding="utf-8")))
def test_documented_names_have_numpydoc_docstrings(name: str) -> None:
    obj = resolve(name)
    assert missing_sections(obj) == [], f"{name}'s docstring lacks {missing_sections(obj)}"
    if isinstance(obj, type) and not issubclass(obj, BaseException) and "__init__" in vars(obj):
        init = inspect.signature(obj)  # a class documents its constructor's parameters in its own docstring
        if [p for p in init.parameters if p != "self"] and not dataclasses.is_dataclass(obj):
            assert "Parameters" in sections(inspect.getdoc(obj) or ""), f"{name}: constructor parameters"


def test_the_check_sees_a_bare_function() -> None:
    """Not blind: a function with parameters and a result but no sections is caught."""

    def bare(x: int) -> int:
        """Double."""
        return 2 * x

    def undocumented() -> None:
        pass

    assert missing_sections(bare) == ["Parameters", "Returns|Yields"]
    assert missing_sections(undocumented) == ["a docstring"]
