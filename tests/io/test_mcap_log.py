"""The MCAP log: layout as the standard mcap reader sees it, exact floats, truncation, damage, the queued writer."""

from __future__ import annotations

import json
import os
import struct
import subprocess
import sys
import textwrap
import threading
from pathlib import Path

import can
import numpy as np
import pytest
import zstandard
from mcap.exceptions import McapError
from mcap.reader import NonSeekingReader, make_reader

from foilc_hil.errors import LogFormatError
from foilc_hil.io.log_process import ProcessLogWriter
from foilc_hil.io.mcap_log import LogWriteError, McapLogReader, McapLogWriter, read_log
from foilc_hil.io.schemas import TOPICS

CONFIG_YAML = "sample_time: 0.01\ntrials: 3\n"
DESIGN = {"P": [[0.5, -0.25]], "kp": 0.1, "certificates": {"spectral_radius": 0.42, "induced_norm": 0.9}}
N_SAMPLES = 40


def _write_trial(writer: McapLogWriter | ProcessLogWriter, trial: int, rng: np.random.Generator) -> list[dict]:
    """Log one synthetic trial; return the sample documents expected back."""
    expected = []
    for i in range(N_SAMPLES):
        reference, output, control = (float(x) for x in rng.normal(size=3))
        writer.log_frame(can.Message(arbitration_id=0x201, data=struct.pack("<d", control), is_extended_id=False), "tx")
        writer.log_frame(
            can.Message(
                timestamp=1000.0 + trial + i * 1e-3, arbitration_id=0x181, data=b"\x01\x02", is_extended_id=False
            ),
            "rx",
        )
        writer.log_sample(trial, i * 0.01, reference, output, control, reference - output, None, sample=i)
        writer.log_timing(trial * N_SAMPLES + i, trial, i, 12.5, 10000.0, 300.0 if i % 2 else None, i == 3)
        expected.append(
            {
                "trial": trial,
                "t": i * 0.01,
                "reference": reference,
                "output": output,
                "control": control,
                "error": reference - output,
                "E": None,
                "sample": i,
            }
        )
    writer.log_trial({"trial": trial, "sse": float(trial), "rmse": 0.5, "max_abs_error": 2.0}, law="foilc")
    return expected


def _write_log(path: Path, trials: int = 3, compression: str = "zstd") -> tuple[list[dict], list[int]]:
    """A log of ``trials`` trials; returns the expected samples and the file size after each end_trial."""
    rng = np.random.default_rng(7)
    samples: list[dict] = []
    sizes: list[int] = []
    with McapLogWriter(path, compression=compression, config_yaml=CONFIG_YAML, design=DESIGN) as writer:  # type: ignore[arg-type]
        for trial in range(1, trials + 1):
            samples += _write_trial(writer, trial, rng)
            writer.end_trial()
            sizes.append(path.stat().st_size)
    return samples, sizes


@pytest.mark.parametrize("compression", ["zstd", "lz4", "none"])
def test_standard_mcap_reader_sees_the_layout(tmp_path: Path, compression: str) -> None:
    path = tmp_path / "run.mcap"
    _write_log(path, compression=compression)
    with path.open("rb") as stream:
        reader = make_reader(stream)
        summary = reader.get_summary()
        assert summary is not None
        topics = {channel.topic: channel for channel in summary.channels.values()}
        assert set(topics) == {"/can", "/ilc/sample", "/ilc/trial", "/timing"}
        for channel in topics.values():
            assert channel.message_encoding == "json"
            schema = summary.schemas[channel.schema_id]
            assert schema.encoding == "jsonschema"
            assert json.loads(schema.data) == TOPICS[channel.topic][1]
        can_schema = json.loads(summary.schemas[topics["/can"].schema_id].data)
        assert can_schema["properties"]["data"]["contentEncoding"] == "base64"
        counts = {topic: 0 for topic in topics}
        for _, channel, message in reader.iter_messages():
            counts[channel.topic] += 1
            json.loads(message.data)  # every message is JSON
        assert counts == {
            "/can": 3 * 2 * N_SAMPLES,
            "/ilc/sample": 3 * N_SAMPLES,
            "/ilc/trial": 3,
            "/timing": 3 * N_SAMPLES,
        }
        assert summary.statistics is not None and summary.statistics.chunk_count == 3  # one chunk per trial
        metadata = {record.name: record.metadata for record in reader.iter_metadata()}
    assert metadata["foilc_hil.config"] == {"yaml": CONFIG_YAML}
    assert {key: json.loads(value) for key, value in metadata["foilc_hil.design"].items()} == DESIGN


def test_samples_round_trip_bit_for_bit(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    expected, _ = _write_log(path, trials=2)
    contents = read_log(path)
    assert not contents.truncated
    assert contents.samples == expected
    awkward = [5e-324, -0.0, 1 / 3, np.nextafter(1.0, 2.0), -1.7976931348623157e308, 0.1 + 0.2]
    with McapLogWriter(tmp_path / "f.mcap", config_yaml=None) as writer:
        for i, value in enumerate(awkward):
            writer.log_sample(1, float(i), np.float64(value), np.array(value), value, [value, -value], None)
    back = read_log(tmp_path / "f.mcap").samples
    for value, sample in zip(awkward, back, strict=True):
        for key in ("reference", "output", "control"):
            assert struct.pack("<d", sample[key]) == struct.pack("<d", value), key
        assert sample["error"] == [value, -value]


def test_non_finite_values_become_null(tmp_path: Path) -> None:
    with McapLogWriter(tmp_path / "n.mcap", config_yaml=None) as writer:
        writer.log_sample(1, 0.0, 1.0, float("nan"), float("inf"), np.array([1.0, np.nan]), None)
    (sample,) = read_log(tmp_path / "n.mcap").samples
    assert sample["output"] is None and sample["control"] is None and sample["error"] == [1.0, None]


def test_frames_keep_id_payload_direction_and_timestamp(tmp_path: Path) -> None:
    path = tmp_path / "f.mcap"
    with McapLogWriter(path, config_yaml=None) as writer:
        extended = can.Message(timestamp=12.25, arbitration_id=0x1ABCDE, data=b"\x00\xff", is_extended_id=True)
        writer.log_frame(extended, "tx")
        heartbeat = can.Message(timestamp=13.5, arbitration_id=0x701, data=b"\x05", is_extended_id=False)
        writer.on_message_received(heartbeat)
    frames = read_log(path).frames
    assert frames[0] == {"timestamp": 12.25, "id": 0x1ABCDE, "extended": True, "dlc": 2, "data": "AP8=", "dir": "tx"}
    assert frames[1]["dir"] == "rx" and frames[1]["id"] == 0x701 and frames[1]["timestamp"] == 13.5


@pytest.mark.parametrize("fraction", [0.05, 0.3, 0.5, 0.7, 0.95, 1.0])
def test_truncated_file_keeps_every_trial_completed_before_the_cut(tmp_path: Path, fraction: float) -> None:
    path = tmp_path / "run.mcap"
    expected, sizes = _write_log(path, trials=4)
    data = path.read_bytes()
    cuts = {int(len(data) * fraction) - (1 if fraction == 1.0 else 0)}  # 1.0: one byte short of the magic
    cuts |= {size for size in sizes if size <= len(data) * fraction}  # exactly at a trial boundary
    for cut in sorted(cuts):
        cut_path = tmp_path / f"cut{cut}.mcap"
        cut_path.write_bytes(data[:cut])
        contents = read_log(cut_path)
        assert contents.truncated and contents.damage
        safe = [trial for trial, size in enumerate(sizes, start=1) if size <= cut]
        assert set(safe) <= set(contents.completed_trials), (cut, sizes)
        got = [sample for sample in contents.samples if sample["trial"] in safe]
        assert got == [sample for sample in expected if sample["trial"] in safe]
        if sizes[0] <= cut:
            assert contents.config_yaml == CONFIG_YAML and contents.design == DESIGN


def test_standard_non_seeking_reader_reads_a_cut_file_up_to_the_cut(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    _, sizes = _write_log(path, trials=3)
    cut = (sizes[1] + sizes[2]) // 2  # in the middle of trial 3's chunk
    path.write_bytes(path.read_bytes()[:cut])
    trials = []
    with path.open("rb") as stream:
        messages = NonSeekingReader(stream, validate_crcs=True).iter_messages(log_time_order=False)
        with pytest.raises((McapError, zstandard.ZstdError)):  # EndOfFile, or the cut chunk fails to decompress
            for _, channel, message in messages:
                if channel.topic == "/ilc/trial":
                    trials.append(json.loads(message.data)["trial"])
    assert trials == [1, 2]


def test_a_flipped_byte_stops_reading_at_the_damage(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    expected, sizes = _write_log(path, trials=3)
    data = bytearray(path.read_bytes())
    data[(sizes[1] + sizes[2]) // 2] ^= 0xFF  # inside trial 3's compressed chunk
    path.write_bytes(bytes(data))
    contents = read_log(path)
    assert contents.truncated and "damaged" in contents.damage
    assert contents.completed_trials == [1, 2]
    assert contents.samples == [sample for sample in expected if sample["trial"] <= 2]


def test_an_exception_inside_the_with_block_still_leaves_a_complete_file(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    rng = np.random.default_rng(1)
    with pytest.raises(RuntimeError), McapLogWriter(path, config_yaml=CONFIG_YAML) as writer:
        _write_trial(writer, 1, rng)
        writer.end_trial()
        writer.log_sample(2, 0.0, 1.0, 0.0, 0.5, 1.0)
        raise RuntimeError("drive fault")
    with path.open("rb") as stream:
        reader = make_reader(stream)
        trials = [json.loads(m.data)["trial"] for _, _, m in reader.iter_messages(topics=["/ilc/trial"])]
    assert trials == [1]
    contents = read_log(path)
    assert not contents.truncated
    assert [s["trial"] for s in contents.samples].count(2) == 1  # the trial in progress is kept too


def test_a_killed_process_loses_only_the_trial_in_progress(tmp_path: Path) -> None:
    path = tmp_path / "crash.mcap"
    script = textwrap.dedent(
        f"""
        import os
        from foilc_hil.io.mcap_log import McapLogWriter
        log = McapLogWriter({str(path)!r}, config_yaml="x: 1\\n")
        for trial in (1, 2, 3):
            for i in range(200):
                log.log_sample(trial, i * 0.01, 1.0, 0.5, 0.25, 0.5)
            if trial < 3:
                log.log_trial({{"trial": trial, "sse": 1.0, "rmse": 1.0, "max_abs_error": 1.0}})
                log.end_trial()
        os._exit(9)  # die mid-trial 3: no close, no footer
        """
    )
    result = subprocess.run([sys.executable, "-c", script], timeout=60, capture_output=True, text=True)
    assert result.returncode == 9, result.stderr
    contents = read_log(path)
    assert contents.truncated
    assert contents.completed_trials == [1, 2]
    assert [s["trial"] for s in contents.samples] == [1] * 200 + [2] * 200
    assert contents.config_yaml == "x: 1\n"


def test_not_mcap_and_missing_files_are_named(tmp_path: Path) -> None:
    bogus = tmp_path / "notes.mcap"
    bogus.write_text("hello, this is not a log\n")
    with pytest.raises(LogFormatError, match=r"notes\.mcap: not an MCAP file"):
        McapLogReader(bogus)
    (tmp_path / "empty.mcap").write_bytes(b"")
    with pytest.raises(LogFormatError, match=r"empty\.mcap"):
        McapLogReader(tmp_path / "empty.mcap")
    with pytest.raises(LogFormatError, match=r"absent\.mcap: no such file"):
        McapLogReader(tmp_path / "absent.mcap")


def test_header_only_file_is_truncated_but_readable(tmp_path: Path) -> None:
    path = tmp_path / "h.mcap"
    writer = McapLogWriter(path, config_yaml=CONFIG_YAML)
    writer._stream.flush()  # as if the process died right after opening the log
    size = path.stat().st_size
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(path.read_bytes()[:size])
    writer.close()
    contents = read_log(cut)
    assert contents.truncated and contents.samples == [] and contents.config_yaml == CONFIG_YAML


def test_bad_compression_and_unwritable_path_are_input_errors(tmp_path: Path) -> None:
    with pytest.raises(LogFormatError, match="compression"):
        McapLogWriter(tmp_path / "x.mcap", compression="brotli", config_yaml=None)  # type: ignore[arg-type]
    with pytest.raises(LogFormatError, match="cannot create"):
        McapLogWriter(tmp_path / "no" / "such" / "dir.mcap", config_yaml=None)


def test_the_process_writer_accepts_frames_from_a_notifier_thread(tmp_path: Path) -> None:
    path = tmp_path / "threads.mcap"
    log = ProcessLogWriter(path, config_yaml=None, fsync=False)

    def rx() -> None:
        for i in range(500):
            log.on_message_received(can.Message(timestamp=1.0 + i, arbitration_id=0x181, data=[i & 0xFF]))

    thread = threading.Thread(target=rx)
    thread.start()
    for i in range(500):
        log.log_sample(1, i * 0.01, 0.0, 0.0, float(i), 0.0)
    thread.join()
    log.close()
    contents = read_log(path)
    assert [s["control"] for s in contents.samples] == [float(i) for i in range(500)]
    assert [f["timestamp"] for f in contents.frames] == [1.0 + i for i in range(500)]


def test_writer_rejects_use_after_close(tmp_path: Path) -> None:
    writer = McapLogWriter(tmp_path / "c.mcap", config_yaml=None)
    writer.close()
    writer.close()  # idempotent
    with pytest.raises(LogWriteError):
        writer.log_trial({"trial": 1, "sse": 0.0, "rmse": 0.0, "max_abs_error": 0.0})
    with McapLogWriter(tmp_path / "d.mcap", config_yaml=None) as other, pytest.raises(LogFormatError, match="lacks"):
        other.log_trial({"trial": 1})
    assert os.path.getsize(tmp_path / "c.mcap") > 0


@pytest.mark.slow
@pytest.mark.parametrize("compression", ["zstd", "none"])
def test_every_cut_offset_reads_without_error_and_keeps_completed_trials(tmp_path: Path, compression: str) -> None:
    """Cut a small log at ~800 offsets: reading never raises, never invents data, keeps finished trials."""
    path = tmp_path / "small.mcap"
    sizes = []
    expected = []
    with McapLogWriter(path, compression=compression, config_yaml="x: 1\n", fsync=False) as writer:  # type: ignore[arg-type]
        for trial in (1, 2, 3):
            for i in range(5):
                writer.log_sample(trial, i * 0.5, 1.0, i / 3, -i / 7, 1.0 - i / 3, None, sample=i)
                expected.append((trial, i, -i / 7))
            writer.log_trial({"trial": trial, "sse": 1.0, "rmse": 1.0, "max_abs_error": 1.0})
            writer.end_trial()
            sizes.append(path.stat().st_size)
    data = path.read_bytes()
    cut_path = tmp_path / "cut.mcap"
    for cut in sorted(set(range(8, len(data), 13)) | set(sizes)):  # every 13th byte: ~800 cuts, a few seconds
        cut_path.write_bytes(data[:cut])
        contents = read_log(cut_path)
        assert contents.truncated
        got = [(s["trial"], s["sample"], s["control"]) for s in contents.samples]
        assert got == expected[: len(got)], cut  # a prefix of what was written, never altered data
        finished = sum(1 for size in sizes if size <= cut)
        assert contents.completed_trials[:finished] == list(range(1, finished + 1)), cut


def _channel_units(path: Path) -> dict[str, dict[str, str]]:
    with path.open("rb") as stream:
        summary = make_reader(stream).get_summary()
    assert summary is not None
    return {channel.topic: json.loads(channel.metadata["units"]) for channel in summary.channels.values()}


def test_schemas_name_their_dialect_and_channels_carry_units(tmp_path: Path) -> None:
    for _, schema in TOPICS.values():
        assert schema["$schema"] == "https://json-schema.org/draft/2020-12/schema"
    path = tmp_path / "cst.mcap"
    drive = "drive:\n  mode: cst\n  velocity_unit: rad/s\n  torque_unit: Nm\n"
    McapLogWriter(path, config_yaml=CONFIG_YAML + drive).close()
    units = _channel_units(path)
    assert units["/ilc/sample"] == {"t": "s", "reference": "rad/s", "output": "rad/s", "error": "rad/s",
                                    "E": "rad/s", "control": "Nm", "latched": "Nm"}
    assert units["/ilc/trial"] == {"sse": "rad/s^2", "rmse": "rad/s", "max_abs_error": "rad/s"}
    assert units["/timing"]["lateness_us"] == "us" and units["/can"] == {"timestamp": "s"}
    # the defaults of the drive section when the config names none (rpm: drive.velocity_unit's default)
    McapLogWriter(tmp_path / "default.mcap", config_yaml=CONFIG_YAML).close()
    assert _channel_units(tmp_path / "default.mcap")["/ilc/sample"]["control"] == "rpm"
    # a config that does not load gives the time units only, and the log is still written
    McapLogWriter(tmp_path / "odd.mcap", config_yaml="drive: [1, 2]\n").close()
    assert _channel_units(tmp_path / "odd.mcap")["/ilc/sample"] == {"t": "s"}


def test_a_topic_filtered_read_gives_the_records_of_a_full_read(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    _write_log(path)
    full = read_log(path)
    filtered = read_log(path, ["/ilc/sample", "/ilc/trial"])
    assert filtered.samples == full.samples and len(full.samples) == 3 * N_SAMPLES
    assert filtered.trials == full.trials and len(full.trials) == 3
    assert filtered.frames == [] and filtered.timing == [] and len(full.frames) == 2 * 3 * N_SAMPLES
    assert filtered.metadata == full.metadata and not filtered.truncated


@pytest.mark.parametrize("compression", ["ZSTD", "LZ4", "NONE"])
def test_the_reader_reads_what_mcaps_own_writer_puts_in_its_chunks(tmp_path: Path, compression: str) -> None:
    # mcap's writer puts the schema and channel records inside its chunks (the bench's writer does not): the
    # reader's own chunk split must hand those chunks to mcap's and decode the same messages
    from mcap.writer import CompressionType, Writer

    path = tmp_path / "other.mcap"
    documents = [{"trial": 1, "t": i * 0.5, "reference": float(i), "sample": i} for i in range(5)]
    with path.open("wb") as stream:
        writer = Writer(stream, compression=CompressionType[compression])
        writer.start()
        schema = writer.register_schema(name="s", encoding="jsonschema", data=b"{}")
        channel = writer.register_channel(topic="/ilc/sample", message_encoding="json", schema_id=schema)
        for i, document in enumerate(documents):
            writer.add_message(channel, log_time=10 + i, data=json.dumps(document).encode(), publish_time=20 + i)
        writer.finish()
    with McapLogReader(path) as reader:
        messages = list(reader.iter_messages())
    assert [m.data for m in messages] == documents
    assert [(m.log_time_ns, m.publish_time_ns) for m in messages] == [(10 + i, 20 + i) for i in range(5)]
    assert not reader.truncated


def test_a_message_overrunning_its_chunk_is_damage(tmp_path: Path) -> None:
    # an uncompressed chunk without a CRC: a message length pointing past the chunk's end is caught by the split
    # itself (no CRC to catch it first), and reading stops there with the damage named
    path = tmp_path / "run.mcap"
    _write_log(path, trials=1, compression="none")
    data = _first_chunk_without_crc_and_a_long_message(bytearray(path.read_bytes()))
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    contents = read_log(bad)
    assert contents.truncated and "overruns its chunk" in contents.damage
    assert contents.samples == []


def _first_chunk_without_crc_and_a_long_message(data: bytearray) -> bytearray:
    """``data`` with its first chunk's uncompressed CRC zeroed and its first message's length grown past the
    chunk (record layouts: MCAP specification, Chunk op 0x06 and Message op 0x05)."""
    offset = 8  # magic
    while data[offset] != 0x06:
        offset += 9 + struct.unpack_from("<Q", data, offset + 1)[0]
    body = offset + 9
    # chunk: start time, end time (8 + 8), uncompressed size (8), uncompressed crc (4), compression (4 + len), ...
    struct.pack_into("<I", data, body + 24, 0)
    compression_length = struct.unpack_from("<I", data, body + 28)[0]
    records = body + 32 + compression_length + 8  # after the records' length field
    assert data[records] == 0x05
    struct.pack_into("<Q", data, records + 1, 1 << 20)
    return data
