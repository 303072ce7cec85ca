"""Test helper: emulated drives on a unique in-process channel that ``foilc-hil commission --bus inprocess:...``
joins in the same process (in-process channels are process-wide, see drivers.inprocess), so a test can run several
CLI commands against the same drives and check what each left behind."""

from __future__ import annotations

import json
import uuid
from collections.abc import Iterator, Sequence
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass
from typing import Any

import pytest

from foilc_hil.cli import main
from foilc_hil.config import Config, load_config
from plant_emulator.device import VirtualDrive
from plant_emulator.embedded import EmbeddedEmulator


@dataclass
class EmulatedBus:
    """Drives by node id on ``inprocess:<channel>``."""

    channel: str
    drives: dict[int, VirtualDrive]
    config: Config

    @property
    def spec(self) -> str:
        return f"inprocess:{self.channel}"


@contextmanager
def emulated_bus(nodes: Sequence[int], config: Config | None = None) -> Iterator[EmulatedBus]:
    """Start one emulated drive per node id (the default PMSM axis unless ``config`` names a plant)."""
    cfg = config if config is not None else load_config(None, {"plant.model": "pmsm"})
    channel = f"commission-test-{uuid.uuid4()}"
    with ExitStack() as stack:
        drives = {}
        for node in nodes:
            emulator = EmbeddedEmulator(cfg.plant, cfg.emulator, node_id=node, sample_time=cfg.sample_time,
                                        velocity_scale=cfg.drive.velocity_scale, torque_scale=cfg.drive.torque_scale,
                                        channel=channel)
            stack.enter_context(emulator)
            drives[node] = emulator.drive
        yield EmulatedBus(channel, drives, cfg)


def run_cli(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, str, str]:
    """``foilc-hil ARGV`` in-process: exit code, stdout, stderr."""
    code = main(list(argv))
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def run_json(capsys: pytest.CaptureFixture[str], *argv: str) -> tuple[int, Any, str]:
    """``foilc-hil ARGV --json``: exit code, the parsed document, stderr."""
    code, out, err = run_cli(capsys, *argv, "--json")
    return code, json.loads(out), err
