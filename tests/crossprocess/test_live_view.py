"""The live view (``run --live``, ``replay --live``) against a real client, and its parts on their own.

The end-to-end tests run ``foilc-hil`` and a WebSocket client speaking the Foxglove protocol
(``tests/support/live_client.py``, the ``websockets`` package) inside ONE private network namespace they create
(``unshare --net``): the server listens on that namespace's loopback, and nothing is sent in the host's. What the client
decoded is held against the MCAP log the same run wrote (or the log replayed): the advertised channels carry the log's
schemas, every ``/ilc/sample``, ``/ilc/trial`` and ``/timing`` message is the log's document, ``/can`` frames are the
log's frames (a rate-limited subsequence), and ``/drive/state`` says what the logged TPDO of that SYNC says (decoded
here from the logged PDO mapping, independently of the product's decoder).
"""

from __future__ import annotations

import base64
import json
import shlex
import shutil
import subprocess
import sys
import threading
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import pytest

from foilc_hil.errors import InputError
from foilc_hil.io.mcap_log import McapLogReader
from foilc_hil.io.schemas import DRIVE_STATES, LIVE_TOPICS, METADATA_PDO_MAPPING, TOPICS, schema_bytes
from foilc_hil.live.options import LiveAddress, LiveOptions, parse_address

ROOT = Path(__file__).resolve().parents[2]
PORT = 8765  # the namespace is the test's own: nothing else listens there
CONFIG = """\
sample_time: 0.005
plant: {model: first_order, a: -40.0, b: 40.0}  # settles in a few cycles: a short realtime run
reference:
  profile: piecewise
  segments:
  - {duration: 0.3, start: 0.0, end: 30.0}
tuning: {kp: 0.05, r: 0.5}
bench: {settle_time: 0.025, settle_tolerance: 0.05}
drive: {velocity_scale: 1000.0, velocity_limit: 10000.0, heartbeat_timeout_factor: 10.0, heartbeat_consumer_ms: 2000}
"""
SAMPLES = 60  # 0.3 s at 5 ms
STATUSWORD = 0x6041


def _unshare_reason() -> str | None:
    """None when ``unshare --net`` works here, else why not."""
    if shutil.which("unshare") is None or shutil.which("ip") is None:
        return "unshare or ip is not installed"
    probe = subprocess.run(["unshare", "--net", "--", "sh", "-c", "ip link set lo up"], capture_output=True,
                           text=True, timeout=30)
    if probe.returncode != 0:
        return f"unshare --net is not permitted here (needs root): {probe.stderr.strip() or probe.returncode}"
    return None


def _in_namespace(command: Sequence[str], client_out: Path, until_trial: int, tmp_path: Path) -> dict[str, Any]:
    """Run ``command`` and the client in one fresh network namespace; the command's JSON document."""
    reason = _unshare_reason()
    if reason is not None:
        pytest.skip(reason)
    python = shlex.quote(sys.executable)
    client = (f"{python} -m tests.support.live_client --url ws://127.0.0.1:{PORT} --until-trial {until_trial} "
              f"--out {shlex.quote(str(client_out))}")
    bench_out, bench_err = tmp_path / "bench.json", tmp_path / "bench.stderr"
    script = (f"ip link set lo up; {client} & CLIENT=$!; {shlex.join(command)} > {shlex.quote(str(bench_out))} "
              f"2> {shlex.quote(str(bench_err))}; RC=$?; wait $CLIENT; exit $RC")
    done = subprocess.run(["unshare", "--net", "--", "sh", "-c", script], cwd=ROOT, capture_output=True, text=True,
                          timeout=240)
    assert done.returncode == 0, (done.stderr + bench_err.read_text(encoding="utf-8"))[-2000:]
    document: dict[str, Any] = json.loads(bench_out.read_text(encoding="utf-8"))
    return document


def _received(path: Path) -> tuple[dict[str, Any], dict[str, list[tuple[int, dict[str, Any]]]]]:
    got = json.loads(path.read_text(encoding="utf-8"))
    by_topic: dict[str, list[tuple[int, dict[str, Any]]]] = {topic: [] for topic in LIVE_TOPICS}
    for topic, stamp, payload in got["messages"]:
        by_topic[topic].append((int(stamp), json.loads(payload)))
    return got, by_topic


def _logged(path: Path) -> tuple[dict[str, list[tuple[int, dict[str, Any]]]], dict[str, dict[str, str]]]:
    logged: dict[str, list[tuple[int, dict[str, Any]]]] = {topic: [] for topic in TOPICS}
    with McapLogReader(path) as reader:
        for message in reader.iter_messages():
            logged[message.topic].append((message.log_time_ns, message.data))
        assert not reader.damage
        return logged, reader.metadata


def _check_advertised(got: Mapping[str, Any], name: str) -> None:
    """serverInfo, and one advertised channel per live topic with the log's schema name and text."""
    assert got["subprotocol"] == "foxglove.sdk.v1"
    assert got["server_info"]["name"] == name
    channels = {channel["topic"]: channel for channel in got["channels"]}
    assert set(channels) == set(LIVE_TOPICS)
    for topic, (schema_name, schema) in LIVE_TOPICS.items():
        channel = channels[topic]
        assert (channel["encoding"], channel["schemaEncoding"], channel["schemaName"]) == ("json", "jsonschema",
                                                                                            schema_name)
        assert channel["schema"].encode() == schema_bytes(schema)


def _is_subsequence(items: Sequence[Any], of: Sequence[Any]) -> bool:
    position = iter(of)
    return all(any(item == candidate for candidate in position) for item in items)


def _frame_key(frame: Mapping[str, Any]) -> tuple[Any, ...]:
    """A frame's fields; its timestamp too where the bus stamped it (the bench's own frames are stamped with the time
    each writer took them, which differs between the log and the live view by microseconds)."""
    stamp = frame["timestamp"] if frame["dir"] == "rx" else None
    return (stamp, *(frame.get(key) for key in ("id", "extended", "dlc", "data", "dir", "channel")))


def _statuswords(frames: Sequence[Mapping[str, Any]], mapping: Mapping[str, str]) -> dict[int, int]:
    """SYNC count -> the statusword of the TPDO answering it, decoded from the logged mapping here."""
    tpdos = json.loads(mapping["tpdos"])
    where = {}
    for tpdo in tpdos:
        offset = 0
        for index, _sub, bits, _signed in tpdo["variables"]:
            if index == STATUSWORD:
                where[tpdo["cob_id"]] = (offset, bits)
            offset += bits
    words, syncs = {}, 0
    for frame in frames:
        if frame["dir"] == "tx" and frame["id"] == 0x80:
            syncs += 1
        elif frame["dir"] == "rx" and frame["id"] in where:
            offset, bits = where[frame["id"]]
            raw = int.from_bytes(base64.b64decode(frame["data"]), "little")
            words[syncs] = raw >> offset & ((1 << bits) - 1)
    return words


def _check_states(states: Sequence[Mapping[str, Any]], frames: Sequence[Mapping[str, Any]],
                  mapping: Mapping[str, str]) -> None:
    words = _statuswords(frames, mapping)
    assert states
    for state in states:
        assert state["node"] == 1 and state["state"] in DRIVE_STATES
        assert state["statusword"] == words[state["cycle"]], state
    assert "OPERATION_ENABLED" in {state["state"] for state in states}


def _write_config(tmp_path: Path) -> Path:
    path = tmp_path / "live.yaml"
    path.write_text(CONFIG, encoding="utf-8")
    return path


@pytest.mark.netns
@pytest.mark.slow
def test_run_live_serves_what_the_log_holds(tmp_path: Path) -> None:
    """A realtime run (its /timing too) with --live and a connected client: the client's messages are the log's."""
    trials = 2
    log = tmp_path / "run.mcap"
    command = [sys.executable, "-m", "foilc_hil.cli", "run", "--config", str(_write_config(tmp_path)), "--law",
               "p-type", "--mode", "realtime", "--trials", str(trials), "--out", str(log), "--json", "--quiet",
               "--live", f"127.0.0.1:{PORT}", "--live-wait", "60", "--live-linger", "60"]
    document = _in_namespace(command, tmp_path / "client.json", trials, tmp_path)
    got, received = _received(tmp_path / "client.json")
    logged, metadata = _logged(log)
    _check_advertised(got, "foilc-hil run")
    live = document["live"]
    assert (live["address"], live["trials"], live["trials_dropped"], live["error"]) == ("127.0.0.1:8765", trials, 0, "")
    # every row (60 < --live-rows) and every trial, in order, as the log holds them
    assert [doc for _, doc in received["/ilc/sample"]] == [doc for _, doc in logged["/ilc/sample"]]
    assert len(received["/ilc/sample"]) == trials * SAMPLES
    assert [doc for _, doc in received["/ilc/trial"]] == [doc for _, doc in logged["/ilc/trial"]]
    # the cycles' timing up to the client's leaving: the log's first records, field for field
    timing = [doc for _, doc in received["/timing"]]
    assert timing and timing == [doc for _, doc in logged["/timing"]][: len(timing)]
    frames = [doc for _, doc in received["/can"]]
    assert frames and _is_subsequence([_frame_key(f) for f in frames], [_frame_key(f) for _, f in logged["/can"]])
    _check_states([doc for _, doc in received["/drive/state"]], [doc for _, doc in logged["/can"]],
                  metadata[METADATA_PDO_MAPPING])


def _make_log(path: Path) -> None:
    """A short lockstep run on the embedded emulator, in this process (no network)."""
    from drivers.config import BusConfig
    from foilc_hil.config import load_config
    from foilc_hil.loop.rig import RunRequest, run_rig
    from plant_emulator.device import TimingMode

    config = load_config(_write_config(path.parent), {"trials": 3})
    run_rig(RunRequest(config=config, out=path, law="p-type", mode=TimingMode.LOCKSTEP,
                       bus=BusConfig(interface="embedded", channel="live-replay-test")))


@pytest.mark.netns
@pytest.mark.slow
def test_replay_live_streams_the_log(tmp_path: Path) -> None:
    """replay --live: every message on its topic with its logged log time; /can a subsequence of the log's."""
    log = tmp_path / "replayed.mcap"
    _make_log(log)
    command = [sys.executable, "-m", "foilc_hil.cli", "replay", str(log), "--rate", "20", "--json",
               "--live", f"127.0.0.1:{PORT}", "--live-wait", "60", "--live-linger", "60"]
    document = _in_namespace(command, tmp_path / "client.json", 3, tmp_path)
    got, received = _received(tmp_path / "client.json")
    logged, metadata = _logged(log)
    _check_advertised(got, f"foilc-hil replay {log}")
    for topic in ("/ilc/sample", "/ilc/trial"):
        assert received[topic] == logged[topic], topic  # payload and timestamp (the logged log time)
    assert received["/ilc/sample"] and len(received["/ilc/trial"]) == 3
    assert received["/can"] and _is_subsequence(received["/can"], logged["/can"])
    assert document["live"]["published"]["/can"] >= len(received["/can"])
    # frames after the client left are neither sent nor skipped: nobody watched them
    assert document["live"]["frames_skipped"] + document["live"]["published"]["/can"] <= len(logged["/can"])
    _check_states([doc for _, doc in received["/drive/state"]], [doc for _, doc in logged["/can"]],
                  metadata[METADATA_PDO_MAPPING])


# --- the parts, without a network --------------------------------------------------------------------------------


def test_addresses_parse_and_bad_ones_name_the_option() -> None:
    assert parse_address("8765") == LiveAddress("127.0.0.1", 8765)
    assert parse_address("0.0.0.0:9000") == LiveAddress("0.0.0.0", 9000)
    assert parse_address("[::1]:0") == LiveAddress("::1", 0)
    assert str(LiveAddress("::1", 1)) == "[::1]:1" and LiveAddress().loopback
    assert not LiveAddress("0.0.0.0", 1).loopback
    for bad in ("localhost:8765", "127.0.0.1:65536", "127.0.0.1:", "[::1]8765", "port"):
        with pytest.raises(InputError, match=r"^--live: "):
            parse_address(bad)


def test_cli_refuses_bad_live_options_before_running(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Exit 2, one line naming the option, before anything is designed, opened or served."""
    from foilc_hil.cli import main

    config, out = _write_config(tmp_path), tmp_path / "x.mcap"
    cases = [
        (["run", "--config", str(config), "--out", str(out), "--live", "1.2.3.4.5:1"], "--live: "),
        (["run", "--config", str(config), "--out", str(out), "--live", "--live-rows", "-1"], "--live-rows: "),
        (["run", "--config", str(config), "--out", str(out), "--live", "--live-can-rate", "inf"], "--live-can-rate: "),
        (["replay", str(tmp_path / "none.mcap"), "--live", "--live-wait", "nan"], "--live-wait: "),
        (["replay", str(tmp_path / "none.mcap"), "--live", "--bus", "virtual:x"], "--live: "),
    ]
    for argv, field in cases:
        code = main(argv)
        err = capsys.readouterr().err
        assert code == 2, err
        assert field in err and len(err.strip().splitlines()) == 1, err
        assert not out.exists()


class _StuckServer:
    """A server whose every send blocks until released: the slowest viewer there is."""

    def __init__(self) -> None:
        self.release = threading.Event()
        self.entered = threading.Event()
        self.sent: list[tuple[str, bytes]] = []

    def wanted(self, topic: str) -> bool:
        return True

    def log(self, topic: str, payload: bytes, log_time_ns: int) -> None:
        self.entered.set()
        self.release.wait()
        self.sent.append((topic, payload))

    def log_all(self, topic: str, payloads: Any, log_time_ns: int) -> int:
        count = 0
        for payload in payloads:
            self.log(topic, payload, log_time_ns)
            count += 1
        return count


def _record(trial: int) -> Any:
    import numpy as np

    from foilc_hil.loop.interfaces import TrialRecord
    from foilc_hil.metrics import trial_metrics

    n = 4
    reference, seen = np.arange(n, dtype=float), np.linspace(0.0, 1.0, n + 1)
    error = reference - seen[1:]
    return TrialRecord(trial=trial, sample_time=0.01, reference=reference, seen=seen, control=np.ones(n),
                       applied=np.ones(n), output=seen[1:], error=error, E=error,
                       metrics=trial_metrics(trial, error), sync_times=np.zeros(n + 1))


def test_a_stuck_viewer_never_holds_the_loop_side() -> None:
    """With the publisher thread blocked inside a send, what the loop's side calls (a trial, frames) returns at once;
    what does not fit the queue is dropped and counted, and is published once the viewer moves again."""
    from foilc_hil.live.publisher import QUEUE_ITEMS, LivePublisher, LiveSink

    server = _StuckServer()
    publisher = LivePublisher(server, LiveOptions(rows=0, row_rate=0.0))  # type: ignore[arg-type]
    sink = LiveSink(publisher, (-1.0, 1.0))
    with publisher:
        sink.trial_finished(_record(1))
        assert server.entered.wait(30)  # the thread is stuck in the first send
        for trial in range(2, QUEUE_ITEMS + 6):  # one more than fits, and three more
            sink.trial_finished(_record(trial))
        assert publisher.stats.trials_dropped == 4
        server.release.set()
    trials = [json.loads(payload)["trial"] for topic, payload in server.sent if topic == "/ilc/trial"]
    assert trials == list(range(1, QUEUE_ITEMS + 2))  # the first, and the QUEUE_ITEMS that waited
    assert publisher.stats.trials == QUEUE_ITEMS + 1 and publisher.stats.samples == 4 * (QUEUE_ITEMS + 1)


def test_frames_pass_only_within_the_can_budget() -> None:
    """The tap takes nothing while nobody watches /can (no budget), and at most the budget of a tick after."""
    import can

    from foilc_hil.live.publisher import LivePublisher

    class Watched(_StuckServer):
        def __init__(self, watched: bool) -> None:
            super().__init__()
            self.watched = watched
            self.release.set()

        def wanted(self, topic: str) -> bool:
            return self.watched

    message = can.Message(arbitration_id=0x181, data=b"\x37\x12", is_extended_id=False)
    unwatched = LivePublisher(Watched(False), LiveOptions(can_rate=1000.0))  # type: ignore[arg-type]
    unwatched._refill(1.0)
    for _ in range(50):
        unwatched.log_frame(message, "rx")
    unwatched._publish_frames()
    assert unwatched.stats.frames == 0
    server = Watched(True)
    watched = LivePublisher(server, LiveOptions(can_rate=1000.0))  # type: ignore[arg-type]
    watched._refill(0.005)  # 5 frames' worth
    for _ in range(50):
        watched.log_frame(message, "rx")
    watched._publish_frames()
    assert watched.stats.frames == 5
    assert {json.loads(payload)["data"] for _, payload in server.sent} == {base64.b64encode(b"\x37\x12").decode()}


def test_decimated_rows_are_the_logs_rows() -> None:
    """More rows than --live-rows: every k-th from row 0, each the log's document of that row."""
    import numpy as np

    from foilc_hil.io.mcap_writer import trial_samples_documents
    from foilc_hil.io.records import TrialSamples
    from foilc_hil.live.messages import decimation, sample_documents

    n = 1001
    columns = [np.random.default_rng(k).standard_normal(n) for k in range(5)]
    reference, output, control, error, big_e = columns
    samples = TrialSamples(3, 0.001, reference, output, control, error, big_e)
    documents = sample_documents(samples, 100)
    assert decimation(n, 100) == 11 and len(documents) == 91  # rows 0, 11, ..., 990
    full = trial_samples_documents(samples)
    assert full is not None and documents == full[::11]
    assert [json.loads(document)["sample"] for document in documents] == list(range(0, n, 11))
    assert sample_documents(samples, 0) == full


# --- the Foxglove layout of docs/ ---------------------------------------------------------------------------------

_PATH = r"(/[\w/]+)(?:\{(\w+)==(\$\w+|\d+)\})?\.(\w+)"


def _panel_ids(node: Any) -> list[str]:
    """The panels of a layout's mosaic tree (a panel id, or a split of two subtrees)."""
    if isinstance(node, str):
        return [node]
    return [*_panel_ids(node["first"]), *_panel_ids(node["second"])]


def test_the_shipped_layout_plots_the_ilc_view_from_live_channels() -> None:
    """docs/foxglove-ilc-layout.json: every panel placed and configured, every message path a live topic's schema
    field (its filter too), the trial variable set by a slider; reference and output, the learned input, SSE by
    trial."""
    import re

    layout = json.loads((ROOT / "docs" / "foxglove-ilc-layout.json").read_text(encoding="utf-8"))
    panels = layout["configById"]
    placed = _panel_ids(layout["layout"])
    assert sorted(placed) == sorted(panels) and len(set(placed)) == len(placed)
    assert {panel.split("!")[0] for panel in panels} == {"Plot", "VariableSlider", "StateTransitions"}
    sliders = {config["globalVariableName"] for panel, config in panels.items() if panel.startswith("VariableSlider!")}
    plotted: dict[str, set[str]] = {}
    for panel, config in panels.items():
        paths = [path["value"] for path in config.get("paths", [])]
        if "xAxisPath" in config:
            paths.append(config["xAxisPath"]["value"])
        for path in paths:
            match = re.fullmatch(_PATH, path)
            assert match is not None, path
            topic, key, value, name = match.groups()
            properties = LIVE_TOPICS[topic][1]["properties"]
            assert name in properties, path
            if key is not None:
                assert key in properties, path
                if value.startswith("$"):
                    assert value[1:] in layout["globalVariables"] and value[1:] in sliders, path
            plotted.setdefault(panel, set()).add(f"{topic}.{name}")
    assert {"/ilc/sample.reference", "/ilc/sample.output", "/ilc/sample.t"} <= plotted["Plot!ilc-reference-output"]
    assert "/ilc/sample.control" in plotted["Plot!ilc-learned-input"]
    assert {"/ilc/trial.sse", "/ilc/trial.trial"} <= plotted["Plot!ilc-sse-by-trial"]
    assert "/drive/state.state" in plotted["StateTransitions!drive-state"]


def test_rows_keep_to_the_row_rate_budget() -> None:
    """--live-row-rate: a trial gets the rows the budget saved (every k-th), none when it saved none; the budget
    refills at the rate, up to its cap. A fake clock: no wall time."""
    from foilc_hil.live.publisher import ROW_SAVE, LivePublisher

    class Watched(_StuckServer):
        def __init__(self) -> None:
            super().__init__()
            self.release.set()

    now = [0.0]
    server = Watched()
    publisher = LivePublisher(server, LiveOptions(rows=0, row_rate=100.0), clock=lambda: now[0])  # type: ignore[arg-type]
    record = _record(1)

    def rows_of(n: int, at: float) -> int:
        from dataclasses import replace

        import numpy as np

        now[0] = at
        trial = replace(record, reference=np.zeros(n), seen=np.zeros(n + 1), control=np.zeros(n),
                        applied=np.zeros(n), output=np.zeros(n), error=np.zeros(n), E=np.zeros(n))
        before = publisher.stats.samples
        publisher._publish_rows(trial, 0)
        return publisher.stats.samples - before

    cap = int(ROW_SAVE * 100)
    assert rows_of(600, 5.0) == 300  # empty at the start, 5 s of rate: 500 rows saved, so every 2nd row
    assert rows_of(600, 20.0) == 600  # 200 left + 15 s of rate, saved up to the cap of 1000
    assert rows_of(600, 20.0) == 300  # 400 left: every 2nd row
    assert rows_of(600, 20.0) == 100  # 100 left: every 6th
    assert rows_of(600, 20.005) == 0  # half a row saved: none
    assert rows_of(2 * cap, 120.0) == cap  # refilled to the cap, not beyond
    assert publisher.stats.trials_thinned == 5


def test_a_run_of_several_axes_is_served_axis_by_axis(tmp_path: Path) -> None:
    """axes: every axis's rows and /ilc/trial, as the log's AxesSink splits them (no network: a recording server in
    place of foxglove-sdk's), and a /drive/state of each node."""
    from drivers.config import BusConfig
    from foilc_hil.config import load_config
    from foilc_hil.live.publisher import LivePublisher
    from foilc_hil.loop.rig import RunRequest, run_rig
    from plant_emulator.device import TimingMode

    config_path = tmp_path / "axes.yaml"
    config_path.write_text(CONFIG + "axes:\n  - node_id: 1\n  - node_id: 2\n    plant: {model: first_order, a: -30.0, "
                           "b: 30.0}\n", encoding="utf-8")
    server = _StuckServer()
    server.release.set()  # records, never blocks
    log = tmp_path / "axes.mcap"
    with LivePublisher(server, LiveOptions(rows=0, row_rate=0.0)) as publisher:  # type: ignore[arg-type]
        run_rig(RunRequest(config=load_config(config_path, {"trials": 2}), out=log, law="p-type",
                           mode=TimingMode.LOCKSTEP, bus=BusConfig(interface="embedded", channel="live-axes-test"),
                           live=publisher))
    logged, _ = _logged(log)
    sent: dict[str, list[dict[str, Any]]] = {}
    for topic, payload in server.sent:
        sent.setdefault(topic, []).append(json.loads(payload))
    for topic in ("/ilc/sample", "/ilc/trial"):
        assert sent[topic] == [doc for _, doc in logged[topic]], topic
    assert {doc["axis"] for doc in sent["/ilc/trial"]} == {1, 2} and len(sent["/ilc/sample"]) == 2 * 2 * SAMPLES
    assert {state["node"] for state in sent["/drive/state"]} == {1, 2}
    assert publisher.stats.trials == 4 and publisher.stats.trials_dropped == 0
