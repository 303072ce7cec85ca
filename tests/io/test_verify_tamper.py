"""``replay --verify`` proves what a log claims: a tamper suite.

One real run (the embedded emulator, four trials) is written; each case rewrites it as a VALID MCAP file -- the
``mcap`` library's own writer, good CRCs, every record but the tampered one as it was -- and ``replay --verify``
must exit 1 naming the topic (or metadata record), the trial and the sample. On the previous tree each of these
files was reported "bit-identical" with exit 0 (the issue's list), except the changed reference, whose place was
wrong.
"""

from __future__ import annotations

import base64
import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from mcap.reader import make_reader
from mcap.writer import Writer

from foilc_hil.cli import main
from foilc_hil.config import load_config
from foilc_hil.loop.rig import RunRequest, run_rig
from tests.support.bench import NODE, bench_config

pytestmark = pytest.mark.slow

TRIALS = 4
Edit = Callable[[str, dict[str, Any]], dict[str, Any] | None]
MetaEdit = Callable[[str, dict[str, str]], dict[str, str]]


@pytest.fixture(scope="module")
def logged_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    directory = tmp_path_factory.mktemp("tamper")
    out = directory / "run.mcap"
    run_rig(RunRequest(config=load_config(bench_config(directory)), out=out, trials=TRIALS))
    return out


def rewrite(source: Path, target: Path, edit: Edit | None = None, meta: MetaEdit | None = None) -> None:
    """``source`` rewritten by the mcap library as a valid file: each message through ``edit`` (``None``: drop it),
    each metadata record through ``meta``."""
    with source.open("rb") as stream, target.open("wb") as out:
        reader = make_reader(stream)
        writer = Writer(out)
        writer.start(profile="", library="tamper")
        schemas: dict[int, int] = {}
        channels: dict[int, int] = {}
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            if schema is not None and schema.id not in schemas:
                schemas[schema.id] = writer.register_schema(schema.name, schema.encoding, schema.data)
            if channel.id not in channels:
                channels[channel.id] = writer.register_channel(channel.topic, channel.message_encoding,
                                                               schemas.get(channel.schema_id, 0), channel.metadata)
            document = json.loads(message.data)
            edited = edit(channel.topic, document) if edit is not None else document
            if edited is not None:
                writer.add_message(channels[channel.id], message.log_time, json.dumps(edited).encode(),
                                   message.publish_time, message.sequence)
        stream.seek(0)
        for record in make_reader(stream).iter_metadata():
            data = dict(record.metadata)
            writer.add_metadata(record.name, meta(record.name, data) if meta is not None else data)
        writer.finish()


def verify(path: Path, capsys: pytest.CaptureFixture[str]) -> tuple[int, dict[str, Any]]:
    code = main(["replay", str(path), "--verify", "--json"])
    return code, json.loads(capsys.readouterr().out)


def _trial_record(topic: str, doc: dict[str, Any], trial: int) -> bool:
    return topic == "/ilc/trial" and doc["trial"] == trial


def _nth_frame(cob: int, n: int) -> Edit:
    """Flip the low byte of the target or velocity of the ``n``-th frame with COB-ID ``cob``."""
    seen = [0]

    def edit(topic: str, doc: dict[str, Any]) -> dict[str, Any]:
        if topic == "/can" and doc["id"] == cob:
            seen[0] += 1
            if seen[0] == n:
                data = bytearray(base64.b64decode(doc["data"]))
                data[2] ^= 0x01
                doc = {**doc, "data": base64.b64encode(bytes(data)).decode()}
        return doc

    return edit


def _first_sync(path: Path, trial: int) -> int:
    from foilc_hil.io.mcap_log import read_log

    return int(next(r for r in read_log(path).trials if r["trial"] == trial)["first_sync"])


def _sample(trial: int, sample: int, key: str, change: Callable[[Any], Any]) -> Edit:
    def edit(topic: str, doc: dict[str, Any]) -> dict[str, Any]:
        if topic == "/ilc/sample" and doc["trial"] == trial and doc["sample"] == sample:
            doc = {**doc, key: change(doc[key])}
        return doc

    return edit


def test_the_untouched_log_verifies_and_so_does_a_faithful_rewrite(
    logged_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert verify(logged_run, capsys)[0] == 0
    copy = tmp_path / "copy.mcap"
    rewrite(logged_run, copy)  # the rewrite itself changes nothing verify checks
    code, document = verify(copy, capsys)
    assert code == 0 and document["verified"] is True and document["trials_checked"] == TRIALS


def _wire_case(kind: str, logged_run: Path) -> tuple[Edit, int, int]:
    """A frame of trial 2's sample 10: its RPDO (0x200 + node), or the TPDO answering its SYNC (0x180 + node)."""
    sync = _first_sync(logged_run, 2)
    # one RPDO and one TPDO1 in each SYNC's window from the drive's first cycle on: the k-th is cycle k's
    cob = 0x200 + NODE if kind == "rpdo" else 0x180 + NODE
    from foilc_hil.io.mcap_log import read_log

    frames = read_log(logged_run).frames
    syncs = [i for i, f in enumerate(frames) if f["id"] == 0x80 and f["dir"] == "tx"]
    target_index = next(i for i in range(syncs[sync - 1 + 10], len(frames)) if frames[i]["id"] == cob)
    n = sum(1 for f in frames[: target_index + 1] if f["id"] == cob)
    return _nth_frame(cob, n), 2, 10


@pytest.mark.parametrize("kind", ["rpdo", "tpdo"])
def test_a_changed_can_frame_is_found_on_the_wire(
    kind: str, logged_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    edit, trial, sample = _wire_case(kind, logged_run)
    tampered = tmp_path / f"{kind}.mcap"
    rewrite(logged_run, tampered, edit)
    code, document = verify(tampered, capsys)
    divergence = document["first_divergence"]
    assert code == 1 and divergence["topic"] == "/can", divergence
    assert (divergence["trial"], divergence["sample"]) == (trial, sample)
    assert ("RPDO" if kind == "rpdo" else "TPDO") in divergence["reason"]


CASES: dict[str, tuple[Edit | None, MetaEdit | None, str, int, int]] = {
    "E of one sample": (_sample(2, 37, "E", lambda e: e * 1.5 + 1.0), None, "/ilc/sample", 2, 37),
    "a trial's sse": (lambda topic, doc: {**doc, "sse": doc["sse"] * 1.01} if _trial_record(topic, doc, 3) else doc,
                      None, "/ilc/trial", 3, 199),
    "the reference of one sample": (_sample(3, 120, "reference", lambda r: r + 1.0), None, "/ilc/sample", 3, 120),
    "trial 3 deleted": (lambda topic, doc: None if doc.get("trial") == 3 and topic.startswith("/ilc") else doc,
                        None, "/ilc/sample", 3, 0),
    "the last trial deleted": (lambda topic, doc: None if doc.get("trial") == TRIALS and topic.startswith("/ilc")
                               else doc, None, "foilc_hil.closing", TRIALS, 0),
    "the design's gain_scale": (None, lambda name, data: {**data, "gain_scale": json.dumps(
        json.loads(data["gain_scale"]) * 1.5)} if name == "foilc_hil.design" else data, "foilc_hil.design", 0, 0),
    "a certified spectral radius": (None, lambda name, data: {**data, "certificates": json.dumps(
        {**json.loads(data["certificates"]), "spectral_radius": 1.5})} if name == "foilc_hil.design" else data,
        "foilc_hil.design", 0, 0),
    "the config's law": (None, lambda name, data: {"yaml": data["yaml"].replace("kind: foilc", "kind: ioilc")}
                         if name == "foilc_hil.config" else data, "foilc_hil.config", 0, 0),
}


@pytest.mark.parametrize("case", list(CASES))
def test_each_tamper_is_caught_at_its_place(
    case: str, logged_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    edit, meta, topic, trial, sample = CASES[case]
    tampered = tmp_path / "tampered.mcap"
    rewrite(logged_run, tampered, edit, meta)
    code, document = verify(tampered, capsys)
    divergence = document["first_divergence"]
    assert code == 1 and document["verified"] is False, document
    assert (divergence["topic"], divergence["trial"], divergence["sample"]) == (topic, trial, sample), divergence


def test_a_log_damaged_before_its_first_trial_names_the_damage(
    logged_run: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(logged_run.read_bytes()[:2000])  # the header and part of the metadata: no trial
    assert main(["replay", str(cut), "--verify"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no /ilc/sample messages to verify (" in err[0], err


def test_a_plant_with_its_own_delay_verifies(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The design's input delay is the CAN loop's plus the plant's own (``plant.delay``): the rebuilt design gets the
    loop's alone, as the run's did (the demo's log failed --verify on a design rebuilt with both twice)."""
    import yaml

    config = bench_config(tmp_path)
    document = yaml.safe_load(config.read_text(encoding="utf-8"))
    document["plant"]["delay"] = document["sample_time"]  # one sample of the plant's own
    config.write_text(yaml.safe_dump(document), encoding="utf-8")
    out = tmp_path / "delayed.mcap"
    run_rig(RunRequest(config=load_config(config), out=out, trials=2))
    code, report = verify(out, capsys)
    assert code == 0 and report["verified"] is True, report.get("first_divergence")
