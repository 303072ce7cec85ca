"""The writer comparison of issue 29 target 5 (``benchmarks/bench_foxglove_writer.py``) compares like with like:
both writers are given the same work and write the same documents at the same log times; what differs is reported
(``/can`` publish times, which foxglove-sdk's ``Channel.log`` cannot set). Never a timing assert."""

from __future__ import annotations

from pathlib import Path

from benchmarks.bench_foxglove_writer import layout_differences, workload, write_foxglove, write_ours
from foilc_hil.io.mcap_log import McapLogReader


def test_both_writers_write_the_same_documents(tmp_path: Path) -> None:
    load = workload(2, 50)
    assert (load.frame_count, load.sample_count) == (400, 100)
    ours, theirs = tmp_path / "ours.mcap", tmp_path / "theirs.mcap"
    write_ours(ours, load)
    write_foxglove(theirs, load)
    differences = layout_differences(ours, theirs)
    assert set(differences) == {"/can", "/ilc/sample"}
    assert differences["/can"]["messages"] == [400, 400] and differences["/ilc/sample"]["messages"] == [100, 100]
    for topic in differences.values():
        assert topic["documents_differ"] == 0 and topic["log_times_differ"] == 0
    assert differences["/ilc/sample"]["publish_times_differ"] == 0
    # /can: ours publishes a received frame at its bus timestamp; foxglove-sdk can only publish it at its log time
    assert differences["/can"]["publish_times_differ"] >= 200  # the 200 received frames' (their stamps are 30 us off)
    # the project's own reader reads foxglove-sdk's file: the same topics and documents
    with McapLogReader(theirs) as reader:
        documents = [message.data for message in reader.iter_messages(["/ilc/sample"])]
    assert [row["sample"] for row in documents] == [*range(50), *range(50)]
