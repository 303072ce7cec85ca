"""``docs/config-reference.md`` is current: regenerated from the config models it equals the file, and it names
every key a default ``Config`` dumps (an independent walk of the model's own serialisation)."""

from __future__ import annotations

from typing import Any

import pytest

from foilc_hil.config import Config
from tests.support.config_reference import DOC, render

pytestmark = pytest.mark.slow


def _keys(document: dict[str, Any], prefix: str = "") -> list[str]:
    keys = []
    for name, value in document.items():
        key = f"{prefix}{name}"
        keys.append(key)
        if isinstance(value, dict):
            keys += _keys(value, f"{key}.")
    return keys


def test_the_reference_is_generated_from_the_current_models() -> None:
    assert DOC.read_text(encoding="utf-8") == render(), "run `python -m tests.support.config_reference`"


def test_every_key_of_the_config_is_documented() -> None:
    text = DOC.read_text(encoding="utf-8")
    keys = _keys(Config().model_dump())
    assert len(keys) > 80
    missing = [key for key in keys if f"| `{key}` |" not in text]
    assert not missing
    assert "| `reference.segments[].duration` |" in text  # list sections too (no default instance to dump)
