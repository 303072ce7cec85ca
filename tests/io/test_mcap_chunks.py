"""The chunked MCAP writer behind :class:`~foilc_hil.io.mcap_log.McapLogWriter`, read back by ``mcap``'s own readers
(seeking, through the summary and message indexes, and non-seeking, record by record)."""

from __future__ import annotations

import io
import json
import math
from pathlib import Path

import pytest
from mcap.reader import NonSeekingReader, make_reader

from foilc_hil.io.mcap_chunks import ChunkedMcapWriter
from foilc_hil.io.mcap_log import McapLogWriter, read_log


@pytest.mark.parametrize("compression", ["zstd", "lz4", ""])
def test_indexes_statistics_and_sequences_are_what_mcap_reads(compression: str) -> None:
    stream = io.BytesIO()
    writer = ChunkedMcapWriter(stream, chunk_size=2000, compression=compression)  # small: many chunks
    writer.start("", "test")
    schema = writer.register_schema("s", "jsonschema", b"{}")
    channels = [writer.register_channel(topic, "json", schema) for topic in ("/a", "/b", "/unused")]
    writer.add_metadata("m", {"k": "v"})
    sent: list[tuple[int, int, bytes]] = []
    for i in range(500):
        channel = channels[i % 2]
        data = json.dumps({"i": i}).encode()
        # log times out of order within a chunk (the queued writer stamps on another thread): the chunk's time
        # range is a min/max, not first/last
        log_time = 1_000 + 10 * i + (5 if i % 7 == 0 else 0)
        writer.add_message(channel, log_time, data, log_time + 1)
        sent.append((channel, log_time, data))
    writer.flush()
    writer.finish()
    stream.seek(0)
    reader = make_reader(stream)
    summary = reader.get_summary()
    assert summary is not None and summary.statistics is not None
    statistics = summary.statistics
    assert statistics.message_count == 500
    assert dict(statistics.channel_message_counts) == {channels[0]: 250, channels[1]: 250}
    assert statistics.chunk_count == len(summary.chunk_indexes) > 5
    assert statistics.message_start_time == 1_000 + 0 + 5
    assert statistics.message_end_time == max(t for _, t, _ in sent)
    assert [record.name for record in reader.iter_metadata()] == ["m"]
    # the seeking reader goes through the chunk indexes and message indexes, in log-time order
    read = [(channel.id, message.log_time, message.data) for _, channel, message in reader.iter_messages()]
    assert read == sorted(sent, key=lambda item: item[1])
    stream.seek(0)
    plain = [
        (m.channel_id, m.sequence, m.publish_time - m.log_time) for _, _, m in NonSeekingReader(stream).iter_messages()
    ]
    assert [sequence for channel, sequence, _ in plain if channel == channels[1]] == list(range(250))
    assert {offset for *_, offset in plain} == {1}


def test_log_messages_decode_to_the_documents_json_would_have_written(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    with McapLogWriter(path, config_yaml=None) as writer:
        writer.log_sample(1, 0.001, 1.0, 0.1 + 0.2, 1e-5, [1e16, -0.0], None, sample=0)
        writer.log_sample(1, 0.002, 1.0, math.nan, math.inf, 0.5, None, sample=1)  # non-finite -> null
    samples = read_log(path).samples
    assert samples[0] == {
        "trial": 1,
        "t": 0.001,
        "reference": 1.0,
        "output": 0.1 + 0.2,
        "control": 1e-5,
        "error": [1e16, -0.0],
        "E": None,
        "sample": 0,
    }
    assert math.copysign(1.0, samples[0]["error"][1]) == -1.0
    assert (samples[1]["output"], samples[1]["control"]) == (None, None)
