"""docs/interface.md is one versioned document: "Version 1 (the contract)" is the contract word for word (its
headings one level down), and "Version 2 additions" holds what foilc-hil adds. Editing version 1 is a breaking
change (the contract says so): this test fails on any change to it, so the change has to be deliberate.
"""

from __future__ import annotations

import hashlib
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
DOC = ROOT / "docs" / "interface.md"
V1 = "## Version 1 (the contract)\n"
V2 = "## Version 2 additions\n"
#: sha256 of the contract as it was given (its text after the title line, without the final newline)
CONTRACT_SHA256 = "8d7a0e93dd77a997aa8f58dbc668ee97f13837e5fab7b03706e6c6ef5f04d859"


def version_1(text: str) -> str:
    """The version 1 section with its headings back at their own level: the contract's text."""
    section = text[text.index(V1) + len(V1):text.index(V2)].rstrip("\n")
    return "\n".join(re.sub(r"^#(#+ )", r"\1", line) for line in section.split("\n"))


def digest(text: str) -> str:
    return hashlib.sha256(text.encode("utf-8")).hexdigest()


def test_version_1_is_the_contract_word_for_word() -> None:
    assert digest(version_1(DOC.read_text(encoding="utf-8"))) == CONTRACT_SHA256, (
        "docs/interface.md's Version 1 changed: the contract is not edited; add to 'Version 2 additions'")


def test_the_check_sees_a_one_character_change() -> None:
    text = DOC.read_text(encoding="utf-8")
    changed = text.replace("| 3 | the design is infeasible", "| 3 | the design is unfeasible", 1)
    assert changed != text
    assert digest(version_1(changed)) != CONTRACT_SHA256


def test_the_additions_are_one_document() -> None:
    """Version 2 follows version 1 in the same file; the old additions page only points to it."""
    text = DOC.read_text(encoding="utf-8")
    assert text.index(V1) < text.index(V2)
    pointer = (ROOT / "docs" / "interface-additions.md").read_text(encoding="utf-8")
    assert len(pointer.strip().splitlines()) == 1 and "interface.md" in pointer
