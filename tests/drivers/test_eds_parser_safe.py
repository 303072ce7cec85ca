"""The shipped EDS reads the same in every INI-style reader: CiA 306 tools (canopen-monitor 4.1.0 among them) split
each ``key=value`` line at its ``=`` and crash on a second one, which the ``[Comments]`` lines once had.

Three readers must agree: a line splitter that refuses a second ``=`` (what those tools do), Python's
``configparser`` with its default ``=``/``:`` delimiters and ``%`` interpolation (strict: duplicate sections or keys
fail), and canopen's EDS loader, whose ``[Comments]`` lines must be exactly the file's.
"""

from __future__ import annotations

import configparser
from pathlib import Path

import pytest

EDS_FILES = sorted((Path(__file__).resolve().parents[2] / "configs").glob("*.eds"))


def _split_lines(path: Path) -> dict[str, dict[str, str]]:
    """``{section: {key: value}}`` by the naive reader: one ``=`` per entry line, else ValueError."""
    sections: dict[str, dict[str, str]] = {}
    current: dict[str, str] = {}
    for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        text = line.strip()
        if not text or text.startswith(";"):
            continue
        if text.startswith("["):
            current = sections.setdefault(text.strip("[]"), {})
            continue
        parts = text.split("=")
        if len(parts) != 2:  # a key and a value: what the naive readers unpack
            raise ValueError(f"{path.name}:{number}: {len(parts) - 1} '=' in {text!r}")
        current[parts[0].strip()] = parts[1].strip()
    return sections


@pytest.mark.parametrize("path", EDS_FILES, ids=lambda p: p.name)
def test_every_entry_line_has_one_equals_sign_and_configparser_agrees(path: Path) -> None:
    naive = _split_lines(path)
    parser = configparser.ConfigParser(strict=True)
    parser.optionxform = str  # type: ignore[assignment,method-assign]  # EDS keys are case-sensitive names
    parser.read(path, encoding="utf-8")
    parsed = {section: {key: parser.get(section, key) for key in parser[section]} for section in parser.sections()}
    assert parsed == naive
    assert int(parsed["Comments"]["Lines"]) == len(parsed["Comments"]) - 1


def test_the_naive_reader_refuses_a_second_equals_sign(tmp_path: Path) -> None:
    bad = tmp_path / "bad.eds"
    bad.write_text("[Comments]\nLines=1\nLine1=RPDO1 = 0x6040\n", encoding="utf-8")
    with pytest.raises(ValueError, match="2 '='"):
        _split_lines(bad)


@pytest.mark.parametrize("path", EDS_FILES, ids=lambda p: p.name)
def test_canopen_reads_the_comment_lines_as_written(path: Path) -> None:
    import canopen

    od = canopen.import_od(str(path))
    comments = _split_lines(path)["Comments"]
    expected = "\n".join(comments[f"Line{i}"] for i in range(1, int(comments["Lines"]) + 1))
    assert od.comments == expected
