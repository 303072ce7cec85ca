"""replay: frame selection, absolute-deadline playback, real-bus refusal, bit-exact verification, the CLI."""

from __future__ import annotations

import json
import math
import uuid
from pathlib import Path
from typing import Any

import can
import numpy as np
import pytest

from foilc_hil.cli import main
from foilc_hil.io.mcap_log import McapLogWriter, read_log
from foilc_hil.logtools.replay import _output_for_error, play_frames, select_frames, verify_log
from tests.support.designs import plain_design

N = 25


class FakeLaw:
    """A tiny deterministic ILC with state: u_k(t) = u_{k-1}(t) + 0.4 e_{k-1}(t) - 0.05 (y_k(t) - y_{k-1}(t))."""

    def __init__(self, n_samples: int = N) -> None:
        self.n_samples = n_samples
        self.feedforward = np.zeros(n_samples)
        self.learned = np.zeros(n_samples)
        self.y_prev = np.zeros(n_samples)
        self.y = np.zeros(n_samples)
        self.u = np.zeros(n_samples)

    def begin_trial(self) -> None:
        self.y[:] = 0.0

    def command(self, t: int, output: np.ndarray) -> np.ndarray:
        self.y[t] = float(np.asarray(output).ravel()[0])
        self.u[t] = self.feedforward[t] + 0.4 * self.learned[t] - 0.05 * (self.y[t] - self.y_prev[t])
        return self.u[t : t + 1]

    def end_trial(self, reference: np.ndarray, output: np.ndarray, applied: np.ndarray | None = None) -> Any:
        error = np.asarray(reference, dtype=float).ravel() - np.asarray(output, dtype=float).ravel()
        self.learned = error.copy()
        self.feedforward = self.u.copy()
        self.y_prev = self.y.copy()
        return error


def run_fake_bench(
    path: Path, trials: int = 3, *, final_output: bool = True, stop_mid_trial: int | None = None, **writer_kwargs: Any
) -> None:
    """Run FakeLaw against a first-order plant and log it the way the bench does (output = feedback seen)."""
    law = FakeLaw()
    reference = np.sin(np.linspace(0.1, 3.0, N)) + 1 / 3
    writer = McapLogWriter(path, config_yaml="trials: 3\n", **writer_kwargs)
    t_frame = 100.0
    for trial in range(1, trials + 1):
        law.begin_trial()
        x = 0.0
        seen = np.zeros(N + 1)
        control = np.zeros(N)
        for i in range(N):
            seen[i] = x
            control[i] = float(law.command(i, np.array([x]))[0])
            writer.log_frame(can.Message(timestamp=t_frame, arbitration_id=0x80, data=b"", is_extended_id=False), "tx")
            writer.log_frame(
                can.Message(timestamp=t_frame + 0.002, arbitration_id=0x181, data=bytes([i]), is_extended_id=False),
                "rx",
            )
            writer.log_frame(
                can.Message(
                    timestamp=t_frame + 0.003, arbitration_id=0x201, data=bytes([trial, i]), is_extended_id=False
                ),
                "tx",
            )
            t_frame += 0.01
            x = 0.8 * x + 0.3 * control[i] + 0.01 * math.sin(i)
            if stop_mid_trial == trial and i == N // 2:
                writer.close()
                return
        seen[N] = x
        output = seen[1:]
        error = law.end_trial(reference, output)
        for i in range(N):
            writer.log_sample(trial, (i + 1) * 0.01, reference[i], seen[i], control[i], error[i], None, sample=i)
        extra = {"final_output": float(seen[N])} if final_output else {}
        writer.log_trial({"trial": trial, "sse": float(error @ error), "rmse": 0.0, "max_abs_error": 0.0}, **extra)
        writer.end_trial()
    writer.close()


# --- verification -----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("final_output", [True, False])
def test_verify_accepts_a_faithful_log(tmp_path: Path, final_output: bool) -> None:
    path = tmp_path / "run.mcap"
    run_fake_bench(path, final_output=final_output)
    result = verify_log(read_log(path), law=FakeLaw())
    assert result.verified and result.first_divergence is None
    assert (result.samples_checked, result.trials_checked) == (3 * N, 3)


def test_verify_finds_a_one_ulp_change_where_it_is(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    run_fake_bench(path)
    contents = read_log(path)
    target = next(s for s in contents.samples if s["trial"] == 2 and s["sample"] == 7)
    original = target["control"]
    target["control"] = math.nextafter(original, math.inf)
    result = verify_log(contents, law=FakeLaw())
    assert not result.verified
    divergence = result.first_divergence
    assert divergence is not None
    assert (divergence.trial, divergence.sample, divergence.reason) == (2, 7, "command differs")
    assert divergence.recomputed[0] == original and divergence.logged[0] == target["control"]
    assert result.samples_checked == N + 7
    document = divergence.to_json()
    assert document["recomputed_hex"] == original.hex()
    json.dumps(document, allow_nan=False)


def test_verify_sees_a_changed_feedback_in_a_later_trial(tmp_path: Path) -> None:
    """Changing what the law saw in trial 1 changes what it commands in trial 2 (learning carries it)."""
    path = tmp_path / "run.mcap"
    run_fake_bench(path)
    contents = read_log(path)
    last = [s for s in contents.samples if s["trial"] == 1][-1]
    trial = next(t for t in contents.trials if t["trial"] == 1)
    trial["final_output"] += 1e-9
    last["error"] = last["reference"] - trial["final_output"]
    result = verify_log(contents, law=FakeLaw())
    assert not result.verified and result.first_divergence is not None
    assert result.first_divergence.trial == 2


def test_verify_notices_an_error_field_that_disagrees_with_the_output(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    run_fake_bench(path)
    contents = read_log(path)
    contents.samples[3]["error"] += 1.0
    result = verify_log(contents, law=FakeLaw())
    assert not result.verified and result.first_divergence is not None
    assert "sample 3" in result.first_divergence.reason


def test_verify_a_log_cut_mid_trial_checks_what_it_has(tmp_path: Path) -> None:
    path = tmp_path / "run.mcap"
    run_fake_bench(path, trials=3, stop_mid_trial=3)
    contents = read_log(path)
    result = verify_log(contents, law=FakeLaw())
    assert result.verified and result.trials_checked == 2 and result.samples_checked == 2 * N


def test_output_for_error_reproduces_the_error_exactly() -> None:
    rng = np.random.default_rng(3)
    for _ in range(2000):
        reference, y = (float(v) for v in rng.normal(size=2) * 10.0 ** rng.integers(-8, 8, size=2))
        error = reference - y
        found = _output_for_error(reference, error)
        assert found is not None and reference - found == error


def test_verify_with_the_real_foilc_law_rebuilt_from_metadata(tmp_path: Path,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    """make_law + Design.from_json + config from the log's metadata reproduce a FOILC run bit for bit."""
    from foilc_hil.config import Config, dump_config
    from foilc_hil.laws.learning import make_law

    design = plain_design([[0.9]], [[0.1]], [[1.0]], [[-0.4, 3.0]], kp=0.05, r=0.6, sample_time=0.01)
    law = make_law(design, Config().law, N)
    reference = np.linspace(0.0, 1.0, N) ** 2
    path = tmp_path / "foilc.mcap"
    with McapLogWriter(path, config_yaml=dump_config(Config()), design=design.to_json()) as writer:
        for trial in range(1, 4):
            law.begin_trial()
            x, seen, control = 0.0, np.zeros(N + 1), np.zeros(N)
            for i in range(N):
                seen[i] = x
                control[i] = float(law.command(i, np.array([x]))[0])
                x = 0.9 * x + 0.1 * control[i] + 0.001 * trial
            seen[N] = x
            update = law.end_trial(reference, seen[1:])
            error = np.asarray(update.error).ravel()
            for i in range(N):
                writer.log_sample(
                    trial,
                    i * 0.01,
                    reference[i],
                    seen[i],
                    control[i],
                    error[i],
                    float(np.asarray(update.E).ravel()[i]),
                    sample=i,
                )
            writer.log_trial(update.metrics, final_output=float(seen[N]))
            writer.end_trial()
    assert main(["replay", str(path), "--verify", "--json"]) == 0
    capsys.readouterr()
    assert main(["replay", str(path), "--verify"]) == 0
    # the text is the verdict alone: no "N frames selected, 0 sent" line, which read like a failed replay
    assert capsys.readouterr().out.strip() == f"verified: {3 * N} commands in 3 trials are bit-identical to the log"
    contents = read_log(path)
    contents.samples[N + 4]["control"] = math.nextafter(contents.samples[N + 4]["control"], 0.0)
    result = verify_log(contents)
    assert result.first_divergence is not None and (result.first_divergence.trial, result.first_divergence.sample) == (
        2,
        4,
    )


def test_verify_without_design_metadata_is_a_usage_error(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "run.mcap"
    run_fake_bench(path)
    assert main(["replay", str(path), "--verify", "--json"]) == 2
    err = capsys.readouterr().err
    assert "foilc_hil.design" in err and err.count("\n") == 1


# --- frames -----------------------------------------------------------------------------------------------------


def _frames() -> list[dict[str, Any]]:
    return [
        {
            "timestamp": 10.0 + i / 64,
            "id": 0x200 + i % 2,
            "extended": False,
            "dlc": 1,
            "data": "AA==",
            "dir": "tx" if i % 3 else "rx",
        }
        for i in range(30)
    ]


def test_select_frames_filters_direction_window_and_ids() -> None:
    frames = _frames()
    assert all(f["dir"] == "tx" for f in select_frames(frames))
    assert len(select_frames(frames, directions=("tx", "rx"))) == 30
    window = select_frames(frames, directions=("tx", "rx"), start=8 / 64, duration=4 / 64)  # exact binary times
    assert [(f["timestamp"] - 10.0) * 64 for f in window] == [8, 9, 10, 11]
    assert {f["id"] for f in select_frames(frames, ids=[0x201])} == {0x201}
    from foilc_hil.errors import InputError

    with pytest.raises(InputError, match="--duration"):
        select_frames(frames, duration=0.0)


class _FakeTime:
    """A clock that every sleep overshoots by ``overshoot`` seconds."""

    def __init__(self, overshoot: float) -> None:
        self.now = 1000.0
        self.overshoot = overshoot

    def clock(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        self.now += seconds + self.overshoot


class _RecordingBus:
    def __init__(self, time_source: _FakeTime) -> None:
        self.time_source = time_source
        self.sent: list[tuple[float, can.Message]] = []

    def send(self, msg: can.Message) -> None:
        self.sent.append((self.time_source.now, msg))
        self.time_source.now += 0.0005  # sending takes time too


@pytest.mark.parametrize("rate", [1.0, 4.0])
def test_play_frames_keeps_absolute_deadlines_without_drift(rate: float) -> None:
    fake = _FakeTime(overshoot=0.003)
    bus = _RecordingBus(fake)
    frames = [dict(f, dir="tx") for f in _frames()]
    result = play_frames(bus, frames, rate=rate, clock=fake.clock, sleep=fake.sleep)  # type: ignore[arg-type]
    assert result.frames_sent == 30
    start = bus.sent[0][0]
    for k, (sent_at, msg) in enumerate(bus.sent):
        due = (frames[k]["timestamp"] - frames[0]["timestamp"]) / rate
        # Lateness is bounded by one overshoot plus one send: it does not grow with k.
        assert -1e-9 <= (sent_at - start) - due <= 0.003 + 0.0005 + 1e-9, k
        assert msg.arbitration_id == frames[k]["id"] and msg.timestamp == 0.0


@pytest.mark.slow
def test_replay_cli_emits_the_tx_frames_on_a_virtual_bus(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / "run.mcap"
    run_fake_bench(path, trials=1)
    channel = f"replay-{uuid.uuid4()}"
    with can.Bus(interface="virtual", channel=channel) as listener:
        code = main(["replay", str(path), "--bus", f"virtual:{channel}", "--rate", "20", "--json"])
        received = []
        while (msg := listener.recv(timeout=0.5)) is not None:
            received.append(msg)
    assert code == 0
    document = json.loads(capsys.readouterr().out)
    tx = [f for f in read_log(path).frames if f["dir"] == "tx"]
    assert document["frames_sent"] == len(tx) == 2 * N and document["verified"] is None
    assert not document["truncated"]
    assert [(m.arbitration_id, bytes(m.data)) for m in received] == [
        (f["id"], bytes([1, i])) if f["id"] == 0x201 else (f["id"], b"")
        for i, f in zip([k // 2 for k in range(2 * N)], tx, strict=True)
    ]


def test_replay_refuses_a_real_bus_before_opening_it(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    import drivers.bus

    opened: list[Any] = []
    monkeypatch.setattr(drivers.bus, "open_bus", lambda cfg: opened.append(cfg))
    path = tmp_path / "run.mcap"
    run_fake_bench(path, trials=1)
    assert main(["replay", str(path), "--bus", "socketcan:vcan0"]) == 2
    err = capsys.readouterr().err
    assert "--allow-real-bus" in err and "real hardware" in err and err.count("\n") == 1
    assert opened == []


def test_replay_rejects_bad_files_and_options(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    text = tmp_path / "notes.mcap"
    text.write_text("not a log")
    assert main(["replay", str(text)]) == 2
    assert "notes.mcap: not an MCAP file" in capsys.readouterr().err
    assert main(["replay", str(tmp_path / "gone.mcap")]) == 2
    assert "gone.mcap: no such file" in capsys.readouterr().err
    run_fake_bench(tmp_path / "ok.mcap", trials=1)
    assert main(["replay", str(tmp_path / "ok.mcap"), "--rate", "0"]) == 2
    assert "--rate" in capsys.readouterr().err


def test_replay_of_a_truncated_log_says_so_and_uses_what_it_has(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path = tmp_path / "run.mcap"
    run_fake_bench(path, trials=3)
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * 0.8)])
    channel = f"replay-{uuid.uuid4()}"
    code = main(["replay", str(path), "--bus", f"virtual:{channel}", "--rate", "50", "--json"])
    captured = capsys.readouterr()
    assert code == 0
    document = json.loads(captured.out)
    assert document["truncated"] is True and "footer" in document["damage"]
    assert 0 < document["frames_sent"] <= 3 * 2 * N
    assert "before its footer" in captured.err


def test_verify_rebuilds_a_clamping_law_with_the_logged_command_limits(tmp_path: Path) -> None:
    """A run whose law clamped to limits verifies bit for bit only with the logged limits (saturation-aware law)."""
    from foilc_hil.config import Config, dump_config
    from foilc_hil.laws.learning import make_law

    design = plain_design([[0.9]], [[0.1]], [[1.0]], [[-0.4, 5.0]], kp=0.0, r=1.0, sample_time=0.01, law="ioilc")
    limits = (-0.8, 0.8)
    law = make_law(design, Config().law, N, limits=limits)
    reference = np.full(N, 5.0)  # out of reach with |u| <= 0.8 (DC gain 1): the law saturates
    path = tmp_path / "clamped.mcap"
    clamped_any = False
    with McapLogWriter(path, config_yaml=dump_config(Config()), design=design.to_json()) as writer:
        for trial in range(1, 4):
            law.begin_trial()
            x, seen, control = 0.0, np.zeros(N + 1), np.zeros(N)
            for i in range(N):
                seen[i] = x
                control[i] = float(law.command(i, np.array([x]))[0])
                x = 0.9 * x + 0.1 * control[i]
            seen[N] = x
            clamped_any = clamped_any or bool(np.any(np.abs(control) == 0.8))
            update = law.end_trial(reference, seen[1:])
            error, learned = np.asarray(update.error).ravel(), np.asarray(update.E).ravel()
            for i in range(N):
                writer.log_sample(
                    trial, i * 0.01, reference[i], seen[i], control[i], error[i], learned[i], sample=i
                )
            writer.log_trial(update.metrics, final_output=float(seen[N]), command_limits=list(limits))
            writer.end_trial()
    assert clamped_any  # the limits were active, so the check below can fail
    contents = read_log(path)
    assert verify_log(contents).first_divergence is None
    for record in contents.trials:  # without the logged limits the rebuilt law does not clamp: it diverges
        del record["command_limits"]
    assert verify_log(contents).first_divergence is not None


@pytest.mark.slow
def test_verify_of_a_damaged_log_is_partial_and_exits_1(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A checksum error mid-file: --verify checks what precedes it and says so; it never passes for the whole log."""
    from tests.support.bench import bench_config

    config = bench_config(tmp_path)
    log = tmp_path / "sim.mcap"
    assert main(["simulate", "--config", str(config), "--trials", "4", "--input-delay", "1", "--out", str(log)]) == 0
    capsys.readouterr()
    assert main(["replay", str(log), "--verify", "--json"]) == 0  # intact: the whole log verifies
    intact = json.loads(capsys.readouterr().out)
    assert intact["verified"] is True and intact["partial"] is False and intact["trials_checked"] == 4
    data = bytearray(log.read_bytes())
    middle = len(data) // 2
    data[middle : middle + 8] = bytes(b ^ 0xFF for b in data[middle : middle + 8])  # inside a compressed chunk
    log.write_bytes(bytes(data))
    code = main(["replay", str(log), "--verify", "--json"])
    captured = capsys.readouterr()
    document = json.loads(captured.out)
    assert code == 1
    assert document["partial"] is True and document["truncated"] is True and document["damage"]
    assert document["trials_checked"] < 4
    lines = captured.err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("foilc-hil replay: partial: ")
    assert f"checked {document['samples_checked']} commands in {document['trials_checked']} trials" in lines[0]
