"""Fuzzed MCAP logs: a real ``simulate`` log with flipped bytes, a cut or inserted garbage is read as far as it goes
(``truncated``) or refused with ``LogFormatError``; ``replay --verify``, ``report`` and ``export`` exit 0, 1 (a
partial result of a damaged log) or 2, with one stderr line and, under ``--json``, one JSON document."""

from __future__ import annotations

import json
import struct
from pathlib import Path

import pytest
from hypothesis import event, example, given
from hypothesis import strategies as st
from mcap.opcode import Opcode
from mcap.stream_reader import MAGIC_SIZE

from foilc_hil.cli import main
from foilc_hil.errors import LogFormatError
from foilc_hil.io.mcap_log import read_log
from tests.support.bench import bench_config
from tests.support.fuzz_settings import fuzz_settings

TRIALS = 2
ZSTD_MAGIC = b"\x28\xb5\x2f\xfd"
#: a zstd frame header descriptor byte: single segment, 8-byte frame content size
ZSTD_SINGLE_SEGMENT_8_BYTE_SIZE = 0xE0


@pytest.fixture(scope="module")
def intact_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One small real log per module: a first-order axis, a 100-sample reference, two trials."""
    directory = tmp_path_factory.mktemp("fuzz_mcap")
    log = directory / "intact.mcap"
    code = main(["simulate", "--config", str(bench_config(directory)), "--trials", str(TRIALS),
                 "--input-delay", "1", "--out", str(log)])
    assert code == 0
    return log  # a path, not the bytes: hypothesis prints the arguments of a failing example


def damaged(data: bytes, kind: str, offset: int, payload: bytes) -> bytes:
    if kind == "cut":
        return data[:offset]
    if kind == "insert":
        return data[:offset] + payload + data[offset:]
    flipped = bytearray(data)
    for i, mask in enumerate(payload):
        if offset + i < len(flipped):
            flipped[offset + i] ^= mask or 0xFF  # a zero mask would change nothing
    return bytes(flipped)


DAMAGE = st.tuples(st.sampled_from(["flip", "cut", "insert"]), st.floats(0.0, 1.0), st.binary(min_size=1,
                                                                                               max_size=16))


def _place(data: bytes, spec: tuple[str, float, bytes]) -> bytes:
    kind, where, payload = spec
    return damaged(data, kind, min(int(where * len(data)), len(data) - 1), payload)


@example(spec=("cut", 0.0, b"\x00"))  # an empty file
@example(spec=("cut", 0.999, b"\x00"))  # the footer's last bytes gone
@example(spec=("flip", 0.0, b"\x01"))  # the magic
@given(spec=DAMAGE)
@fuzz_settings(examples=30)
def test_read_log_of_a_damaged_log_returns_or_raises_log_format_error(
    spec: tuple[str, float, bytes], intact_log: Path, tmp_path: Path
) -> None:
    path = tmp_path / "damaged.mcap"
    path.write_bytes(_place(intact_log.read_bytes(), spec))
    try:
        contents = read_log(path)
    except LogFormatError as exc:
        event("LogFormatError")
        assert str(path) in str(exc) or "/can" in str(exc) or "/ilc" in str(exc)
        return
    event("read, truncated" if contents.truncated else "read, intact")
    assert len(contents.trials) <= TRIALS
    if not contents.truncated:
        assert contents.damage == ""


def _first_chunk_data_length_offset(data: bytes) -> int:
    """Where the first chunk's ``data_length`` field is (MCAP: magic, then records of opcode, u64 length, content;
    a chunk's content starts with start, end, uncompressed size (u64 each), crc, compression length (u32 each),
    then the compression name and the u64 data length)."""
    offset = MAGIC_SIZE
    while True:
        opcode = data[offset]
        (length,) = struct.unpack_from("<Q", data, offset + 1)
        content = offset + 9
        if opcode == Opcode.CHUNK:
            (name_length,) = struct.unpack_from("<I", data, content + 28)
            return content + 32 + name_length
        offset = content + length


# regression, found by the long run of docs/fuzzing.md (a flip at 14 % of the file): mcap checks a record's own length
# against the file but reads the length fields inside it unchecked, and asked the file for that many bytes at once --
# MemoryError, or OverflowError past sys.maxsize. Reads now go piecewise: the cut-short chunk is damage.
@pytest.mark.parametrize("length", [2**40, 2**62, 2**63, 2**64 - 1])
def test_a_huge_length_inside_a_record_is_damage(length: int, intact_log: Path, tmp_path: Path) -> None:
    data = bytearray(intact_log.read_bytes())
    struct.pack_into("<Q", data, _first_chunk_data_length_offset(bytes(data)), length)
    path = tmp_path / "huge.mcap"
    path.write_bytes(bytes(data))
    contents = read_log(path)
    assert contents.truncated
    assert contents.damage



def test_a_huge_zstd_content_size_is_damage(intact_log: Path, tmp_path: Path) -> None:
    """A zstd frame header claiming an 8-byte content size of ~9 EB: zstandard's allocation fails, the log is damaged
    there (found while fixing the case above; the writer compresses chunks with zstd by default)."""
    data = bytearray(intact_log.read_bytes())
    length_at = _first_chunk_data_length_offset(bytes(data))
    frame = length_at + 8
    assert data[frame : frame + 4] == ZSTD_MAGIC
    data[frame + 4] = ZSTD_SINGLE_SEGMENT_8_BYTE_SIZE
    data[frame + 5 : frame + 13] = b"\x7f" * 8
    path = tmp_path / "zstd.mcap"
    path.write_bytes(bytes(data))
    contents = read_log(path)
    assert contents.truncated
    assert "MemoryError" in contents.damage


COMMANDS = {
    "replay": lambda log, out: ["replay", str(log), "--verify", "--json"],
    "report": lambda log, out: ["report", str(log), "--out", str(out / "report"), "--json"],
    "export": lambda log, out: ["export", str(log), "--format", "csv", "--out", str(out / "frames.csv"), "--json"],
}


@pytest.mark.slow
@example(command="replay", spec=("cut", 0.6, b"\x00"))
@example(command="report", spec=("flip", 0.5, b"\xff" * 8))
@example(command="export", spec=("flip", 1.0, b"\x00"))  # the footer damaged: exit 0 and one line
@given(command=st.sampled_from(sorted(COMMANDS)), spec=DAMAGE)
@fuzz_settings(examples=12)
def test_cli_on_a_damaged_log_exits_0_1_or_2_with_one_line(
    command: str, spec: tuple[str, float, bytes], intact_log: Path, tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    path = tmp_path / "damaged.mcap"
    path.write_bytes(_place(intact_log.read_bytes(), spec))
    capsys.readouterr()
    code = main(COMMANDS[command](path, tmp_path))
    captured = capsys.readouterr()
    assert "Traceback" not in captured.err
    document = json.loads(captured.out)  # exactly one document
    assert code in (0, 1, 2), (code, captured.err)
    event(f"{command} exit {code}")
    lines = captured.err.strip().splitlines()
    if code == 0:  # export writes what it could read and says so in one line: its documented exit 0
        assert "error" not in document
        assert lines == [] or (command == "export" and document["truncated"] is True and len(lines) == 1), lines
        return
    assert len(lines) == 1, lines
    if code == 2:
        assert document["error"]["exit_code"] == 2
    elif "error" not in document:  # exit 1 with a result: a partial one, or a verification that failed
        assert document.get("truncated") is True or document.get("verified") is False, document
        if document.get("truncated"):
            assert lines[0].startswith(f"foilc-hil {command}: partial: ")
    else:
        assert document["error"]["exit_code"] == 1
