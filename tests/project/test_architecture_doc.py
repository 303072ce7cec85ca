"""docs/architecture.md is true to the code: every module, file and name it points at exists, every package and
module of the three packages is named, and its rank table is the one ``tests/project/test_layering.py`` enforces.

The doc names modules three ways: dotted (``foilc_hil.loop.rig.Rig``), as a path from the repository
(``drivers/inprocess.py``), or as a path inside the package of the section it stands in (``master/link.py`` under
"rank 0: `drivers/`"; before the module map, paths are inside ``foilc_hil``). A subpackage that is an entry of the
module map as a whole (``- `commission/` -- ...``) names its modules; the modules directly in a package's top
directory are named one by one.
"""

from __future__ import annotations

import ast
import functools
import re
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import pytest

from tests.project.test_layering import RANKS

ROOT = Path(__file__).resolve().parents[2]
DOC = ROOT / "docs" / "architecture.md"
PACKAGES = ("foilc_hil", "drivers", "plant_emulator")
#: top-level directories a path may start from
ROOT_DIRS = (*PACKAGES, "configs", "benchmarks", "tests", "docs", "examples")

_CODE_SPAN = re.compile(r"`([^`\n]+)`")
_PATH = re.compile(r"[A-Za-z_][\w./-]*")
_DOTTED = re.compile(r"(?:foilc_hil|drivers|plant_emulator)(?:\.(?:\w+|\*))*")
_SECTION = re.compile(r"^###\s.*?`(\w+)/`")


@dataclass(frozen=True)
class Mention:
    """One code span of the doc that points into the repository."""

    line: int
    text: str
    base: str  # the package a relative path is inside
    entry: bool  # a module map entry: a leading span of a bullet, before its " -- "


def _mentions(text: str) -> Iterator[Mention]:
    base, fenced = "foilc_hil", False
    for number, line in enumerate(text.splitlines(), start=1):
        if line.startswith("```"):
            fenced = not fenced
            continue
        if fenced:
            continue
        section = _SECTION.match(line)
        if section:
            base = section.group(1)
            continue
        head = line.split(" -- ", 1)[0] if line.startswith("- ") and " -- " in line else ""
        for span in _CODE_SPAN.finditer(line):
            yield Mention(number, span.group(1), base, span.end() <= len(head))


@functools.cache
def mentions() -> tuple[Mention, ...]:
    return tuple(_mentions(DOC.read_text(encoding="utf-8")))


def resolve_path(mention: Mention) -> tuple[Path, str] | None:
    """The file or directory a path-like span names, and the attribute after it (``loop/x.Name``); None: not a
    path. Dotted module names are :func:`resolve_dotted`'s."""
    text = mention.text
    if not _PATH.fullmatch(text) or not ("/" in text or text.endswith(".py")):
        return None
    attribute = ""
    head, _, tail = text.rpartition("/")
    if "." in tail and not tail.endswith(".py") and not re.search(r"\.[a-z]{2,5}$", tail):
        tail, _, attribute = tail.partition(".")
        text = f"{head}/{tail}.py" if head else f"{tail}.py"
    first = text.split("/", 1)[0]
    base = ROOT if first in ROOT_DIRS else ROOT / mention.base
    return base / text.rstrip("/"), attribute


def module_file(module: str) -> Path | None:
    path = ROOT.joinpath(*module.split("."))
    if (path / "__init__.py").is_file():
        return path / "__init__.py"
    return path.with_suffix(".py") if path.with_suffix(".py").is_file() else None


@functools.cache
def defined_names(path: Path) -> frozenset[str]:
    """Names a module defines or imports at its top level (and the names of its ``__all__``)."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    names: set[str] = set()
    for node in tree.body:
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef | ast.ClassDef):
            names.add(node.name)
        elif isinstance(node, ast.Import | ast.ImportFrom):
            names.update((alias.asname or alias.name).split(".")[0] for alias in node.names)
        elif isinstance(node, ast.Assign | ast.AnnAssign):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target]
            names.update(t.id for target in targets for t in ast.walk(target) if isinstance(t, ast.Name))
            if any(isinstance(t, ast.Name) and t.id == "__all__" for t in targets) and node.value is not None:
                names.update(c.value for c in ast.walk(node.value)
                             if isinstance(c, ast.Constant) and isinstance(c.value, str))
    return frozenset(names)


def resolve_dotted(text: str) -> tuple[str, str] | None:
    """``(module, attribute)`` of a dotted name of ours (the longest prefix that is a module; ``.*`` is the
    package); None: not a dotted name of ours. The module is ``""`` when no prefix is one."""
    match = _DOTTED.match(text)
    if match is None or (len(text) > match.end() and text[match.end()] not in "( "):
        return None
    parts = match.group(0).removesuffix(".*").split(".")
    for end in range(len(parts), 0, -1):
        module = ".".join(parts[:end])
        if module_file(module) is not None:
            return module, ".".join(parts[end:])
    return "", text


@functools.cache
def metadata_records() -> frozenset[str]:
    """The MCAP metadata records' names (``foilc_hil.closing``, ...): dotted, but not modules."""
    tree = ast.parse((ROOT / "foilc_hil" / "io" / "schemas.py").read_text(encoding="utf-8"))
    return frozenset(node.value for node in ast.walk(tree)
                     if isinstance(node, ast.Constant) and isinstance(node.value, str)
                     and node.value.startswith("foilc_hil."))


def _broken(mention: Mention) -> str | None:
    """Why a span points at nothing; None: it is not a pointer, or it holds."""
    if mention.text in metadata_records():
        return None
    dotted = resolve_dotted(mention.text)
    if dotted is not None:
        module, attribute = dotted
        if not module:
            return f"line {mention.line}: `{mention.text}`: no such module"
        name = attribute.split(".", 1)[0]
        file = module_file(module)
        if name and file is not None and module_file(f"{module}.{name}") is None and name not in defined_names(file):
            return f"line {mention.line}: `{mention.text}`: {module} has no {name}"
        return None
    resolved = resolve_path(mention)
    if resolved is None:
        return None
    path, attribute = resolved
    if not path.exists():
        return f"line {mention.line}: `{mention.text}`: no {path.relative_to(ROOT)}"
    if attribute and attribute.split(".")[0] not in defined_names(path):
        return f"line {mention.line}: `{mention.text}`: {path.relative_to(ROOT)} has no {attribute.split('.')[0]}"
    return None


def test_every_module_the_doc_names_exists() -> None:
    broken = [why for mention in mentions() if (why := _broken(mention)) is not None]
    assert not broken, "docs/architecture.md names what the tree does not have:\n" + "\n".join(broken)


def named_modules() -> tuple[set[Path], set[Path]]:
    """The module files the doc names, and the package directories that are module map entries as a whole."""
    files: set[Path] = set()
    whole: set[Path] = set()
    for mention in mentions():
        dotted = None if mention.text in metadata_records() else resolve_dotted(mention.text)
        if dotted is not None and dotted[0]:
            file = module_file(dotted[0])
            assert file is not None
            files.add(file.parent if file.name == "__init__.py" else file)
            continue
        resolved = resolve_path(mention)
        if resolved is not None and resolved[0].exists():
            files.add(resolved[0])
            if resolved[0].is_dir() and mention.entry:
                whole.add(resolved[0])
    return files, whole


def project_files() -> list[Path]:
    return sorted(path for package in PACKAGES for path in (ROOT / package).rglob("*.py"))


def unnamed(files: set[Path], whole: set[Path], tree: list[Path]) -> list[str]:
    """The packages and modules of ``tree`` the doc does not name (a package's ``__init__``/``__main__`` is the
    package)."""
    missing: list[str] = []
    packages = sorted({path.parent for path in tree})
    missing += [f"{package.relative_to(ROOT)}/" for package in packages if package not in files | whole]
    for path in tree:
        if path.name in ("__init__.py", "__main__.py") or path in files:
            continue
        if any(parent in whole for parent in path.parents):
            continue
        missing.append(str(path.relative_to(ROOT)))
    return missing


def test_every_package_and_module_is_named() -> None:
    files, whole = named_modules()
    missing = unnamed(files, whole, project_files())
    assert not missing, "docs/architecture.md does not name:\n" + "\n".join(missing)


def test_the_coverage_check_finds_a_module_left_out() -> None:
    """The check can fail: from a doc that names every module and package, leave one out and it is reported."""
    tree = project_files()
    everything = set(tree) | {path.parent for path in tree}
    target = ROOT / "foilc_hil" / "loop" / "rig.py"
    assert unnamed(everything, set(), tree) == []
    assert unnamed(everything - {target}, set(), tree) == ["foilc_hil/loop/rig.py"]
    assert unnamed(everything - {target.parent}, set(), tree) == ["foilc_hil/loop/"]
    assert unnamed(everything - {target}, {target.parent}, tree) == []  # the package named as a whole


@pytest.mark.parametrize(("text", "why"), [
    ("foilc_hil.loop.no_such_module", "foilc_hil.loop has no no_such_module"),
    ("foilc_hil.loop.rig.NoSuchName", "foilc_hil.loop.rig has no NoSuchName"),
    ("loop/no_such.py", "no foilc_hil/loop/no_such.py"),
    ("loop/rig.NoSuchName", "foilc_hil/loop/rig.py has no NoSuchName"),
    ("nowhere/rig.py", "no foilc_hil/nowhere/rig.py"),
])
def test_the_existence_check_finds_a_stale_name(text: str, why: str) -> None:
    found = _broken(Mention(1, text, "foilc_hil", entry=False))
    assert found is not None and why in found


def rank_table() -> dict[str, int]:
    """The doc's rank table: each backticked module prefix of a row, with the row's rank."""
    table: dict[str, int] = {}
    for line in DOC.read_text(encoding="utf-8").splitlines():
        row = re.match(r"\|\s*(\d+)\s*\|([^|]*)\|", line)
        if row:
            for span in _CODE_SPAN.findall(row.group(2)):
                table[span.removesuffix(".*").removesuffix(" (its `__init__`)")] = int(row.group(1))
    return table


def test_the_rank_table_is_the_enforced_one() -> None:
    table = rank_table()
    wrong = {prefix: (table.get(prefix), rank) for prefix, rank in RANKS.items()
             if prefix != "foilc_hil" and table.get(prefix) != rank}
    assert not wrong, (f"docs/architecture.md's rank table against tests/project/test_layering.RANKS "
                       f"(doc, enforced): {wrong}")


def design_order() -> list[set[str]]:
    """The rank table's order of the design modules (``a < b, c < d``): groups, lowest first."""
    row = next(line for line in DOC.read_text(encoding="utf-8").splitlines() if "`foilc_hil.design.*`" in line)
    order = row.split("|")[3].strip()
    return [{name.strip() for name in group.split(",")} for group in order.split("<")]


def test_the_design_modules_import_down_the_documented_order() -> None:
    """Every design module is in the documented order, and imports only design modules before its own group."""
    from tests.project.test_layering import imports_of, project_modules

    groups = design_order()
    position = {name: index for index, group in enumerate(groups) for name in group}
    modules = {name: path for name, path in project_modules().items()
               if name.startswith("foilc_hil.design.") and path.name != "__init__.py"}
    assert set(position) == {name.rsplit(".", 1)[1] for name in modules}
    upward = [f"{name} imports {target}" for name, path in modules.items()
              for target in imports_of(name, path.read_text(encoding="utf-8"), modules)
              if target in modules
              and position[target.rsplit(".", 1)[1]] >= position[name.rsplit(".", 1)[1]]]
    assert not upward, "docs/architecture.md's design order against the imports:\n" + "\n".join(upward)
