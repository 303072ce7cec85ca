"""Fuzzed EDS files: a mutated ``configs/foilc_servo.eds`` either loads or is one ``EdsError`` naming the file
(the exit-2 class), never another exception out of canopen's parser."""

from __future__ import annotations

from pathlib import Path

import pytest
from hypothesis import event, example, given
from hypothesis import strategies as st

from drivers.od import REQUIRED_OBJECTS, load_od
from foilc_hil.errors import EdsError, ExitCode
from tests.support.fuzz_settings import fuzz_settings

EDS = Path(__file__).resolve().parents[2] / "configs" / "foilc_servo.eds"
LINES = EDS.read_text(encoding="utf-8").splitlines(keepends=True)
SECTIONS = [i for i, line in enumerate(LINES) if line.startswith("[")]
VALUE_LINES = [i for i, line in enumerate(LINES) if "=" in line]
NODE_ID = 2

CORRUPT_VALUES = st.one_of(
    st.sampled_from(["", "0x", "$NODEID+", "$NODEID+0x", "-1", "0x1FFFFFFFFFFFFFFFF", "1e9", "nan", "0b101",
                     "0x7", "abc", "$NODEID*2", "0x0007", "99999999999999999999"]),
    st.text(alphabet=st.characters(min_codepoint=32, max_codepoint=126), max_size=12),
)


@st.composite
def mutated_eds(draw: st.DrawFn) -> bytes:
    """The shipped EDS with a few line edits (drop, corrupt a value, duplicate a section), then maybe a cut or
    inserted bytes."""
    lines = list(LINES)
    for _ in range(draw(st.integers(1, 3))):
        action = draw(st.sampled_from(["drop", "corrupt", "duplicate"]))
        if action == "drop":
            del lines[draw(st.integers(0, len(lines) - 1))]
        elif action == "corrupt":
            at = draw(st.sampled_from(VALUE_LINES))
            if at < len(lines) and "=" in lines[at]:
                key = lines[at].split("=", 1)[0]
                lines[at] = f"{key}={draw(CORRUPT_VALUES)}\n"
        else:
            start = draw(st.sampled_from(SECTIONS))
            end = next((i for i in SECTIONS if i > start), len(LINES))
            lines.extend(LINES[start:end])
    data = "".join(lines).encode("utf-8")
    raw = draw(st.sampled_from(["none", "cut", "garbage"]))
    if raw == "cut":
        data = data[: draw(st.integers(0, len(data)))]
    elif raw == "garbage":
        at = draw(st.integers(0, len(data)))
        data = data[:at] + draw(st.binary(min_size=1, max_size=32)) + data[at:]
    return data


@pytest.mark.slow
@example(data=b"")
@example(data=b"\xff\xfe[1000]\n")
@given(data=mutated_eds())
@fuzz_settings(examples=40)
def test_mutated_eds_loads_or_is_one_eds_error(data: bytes, tmp_path: Path) -> None:
    path = tmp_path / "fuzzed.eds"
    path.write_bytes(data)
    try:
        od = load_od(path, NODE_ID)
    except EdsError as exc:
        event("EdsError")
        assert exc.exit_code == ExitCode.USAGE
        assert str(path) in str(exc)
        return
    event("loads")
    assert all(index in od for index in REQUIRED_OBJECTS)  # it loaded: what the check requires is there
