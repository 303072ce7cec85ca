"""export: frames through python-can's ASC/BLF/CSV writers, read back with python-can's readers."""

from __future__ import annotations

import json
from pathlib import Path

import can
import pytest

from foilc_hil.cli import main
from foilc_hil.io.mcap_log import McapLogWriter

T0 = 1_763_700_000.0  # a Unix time, as python-can buses stamp frames


def _frames() -> list[can.Message]:
    frames = []
    for i in range(40):
        frames.append(
            can.Message(
                timestamp=T0 + 0.01 * i + 1e-5 * (i % 7),
                arbitration_id=(0x181, 0x201, 0x80, 0x701)[i % 4],
                data=bytes((i * 7 + k) & 0xFF for k in range(i % 9)),
                is_extended_id=False,
                is_rx=i % 4 in (0, 3),
            )
        )
    frames.append(can.Message(timestamp=T0 + 0.5, arbitration_id=0x18FF50E5, data=b"\x01", is_extended_id=True))
    return frames


def _write(path: Path) -> list[can.Message]:
    frames = _frames()
    with McapLogWriter(path, config_yaml=None) as writer:
        for msg in frames:
            writer.log_frame(msg, "rx" if msg.is_rx else "tx")
            writer.log_sample(1, 0.0, 0.0, 0.0, 0.0, 0.0)  # other topics are not exported
    return frames


READERS = {"asc": can.ASCReader, "blf": can.BLFReader, "csv": can.CSVReader}


@pytest.mark.parametrize("fmt", ["asc", "blf", "csv"])
def test_export_round_trips_through_python_can_readers(
    tmp_path: Path, fmt: str, capsys: pytest.CaptureFixture[str]
) -> None:
    log = tmp_path / "run.mcap"
    frames = _write(log)
    out = tmp_path / f"frames.{fmt}"
    assert main(["export", str(log), "--format", fmt, "--out", str(out), "--json"]) == 0
    document = json.loads(capsys.readouterr().out)
    assert document == {
        "log": str(log),
        "out": str(out),
        "format": fmt,
        "frames": len(frames),
        "truncated": False,
        "damage": None,
    }
    back = list(READERS[fmt](out))
    assert len(back) == len(frames)
    for original, read in zip(frames, back, strict=True):
        assert read.arbitration_id == original.arbitration_id
        assert read.is_extended_id == original.is_extended_id
        assert bytes(read.data) == bytes(original.data) and read.dlc == original.dlc
        # Relative timing: ASC keeps microseconds, BLF nanoseconds, CSV the full float.
        tolerance = {"asc": 1.5e-6, "blf": 1e-8, "csv": 0.0}[fmt]
        assert (read.timestamp - back[0].timestamp) == pytest.approx(
            original.timestamp - frames[0].timestamp, abs=tolerance
        )
        if fmt != "csv":  # python-can's CSV format has no direction column
            assert read.is_rx == original.is_rx
    if fmt == "csv":
        assert [m.timestamp for m in back] == [m.timestamp for m in frames]
    if fmt == "blf":
        assert back[0].timestamp == pytest.approx(frames[0].timestamp, abs=1e-3)  # BLF start: millisecond


def test_export_of_a_truncated_log_exports_what_was_read(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    log = tmp_path / "run.mcap"
    with McapLogWriter(log, config_yaml=None) as writer:
        for msg in _frames()[:20]:
            writer.log_frame(msg, "tx")
        writer.end_trial()
        for msg in _frames()[20:]:
            writer.log_frame(msg, "tx")
    data = log.read_bytes()
    log.write_bytes(data[: len(data) - 200])
    out = tmp_path / "x.csv"
    assert main(["export", str(log), "--format", "csv", "--out", str(out), "--json"]) == 0
    captured = capsys.readouterr()
    document = json.loads(captured.out)
    assert document["truncated"] is True and document["frames"] >= 20
    assert len(list(can.CSVReader(out))) == document["frames"]
    assert "before its footer" in captured.err


def test_export_errors_are_one_line_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "bad.mcap"
    bad.write_text("nope")
    assert main(["export", str(bad), "--format", "asc", "--out", str(tmp_path / "x.asc")]) == 2
    assert "bad.mcap: not an MCAP file" in capsys.readouterr().err
    assert main(["export", str(bad), "--format", "mf4", "--out", str(tmp_path / "x.mf4")]) == 2
    assert "--format" in capsys.readouterr().err
    log = tmp_path / "ok.mcap"
    _write(log)
    assert main(["export", str(log), "--format", "csv", "--out", str(tmp_path / "no" / "dir" / "x.csv")]) == 2
    assert "cannot write" in capsys.readouterr().err
