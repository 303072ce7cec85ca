"""Config validation toolkit: strict pydantic models, YAML loading, CLI overrides, one-line errors.

Every section of the configuration is a :class:`Section` (extra keys forbidden, immutable). Loading turns the
first validation failure into a :class:`~foilc_hil.errors.ConfigError` naming the file and the dotted key path,
e.g. ``configs/x.yaml: plant.b: must be non-zero``; an unknown key gets a did-you-mean.

Precedence is command-line options > config file > defaults: :func:`load_document` reads the YAML mapping,
:func:`apply_overrides` writes dotted-key CLI values into it, and :func:`validate` builds the typed object, so
defaults fill only what neither gave.

The toolkit is defined below ``foilc_hil``, where the sections of ``drivers`` and ``plant_emulator`` need it without
importing the control stack: :mod:`drivers.schema` (``Section``, ``validate``), :mod:`drivers.yaml_document` (the
document and its overrides) and :mod:`plant_emulator.matrix` (``Matrix``, ``as_array``). This module is their one
name for the rest of ``foilc_hil``: the same objects.
"""

from __future__ import annotations

from drivers.schema import MAX_MAGNITUDE, Section, validate
from drivers.yaml_document import (
    MAX_DEPTH,
    MAX_DOCUMENT_BYTES,
    MAX_EXPANDED_NODES,
    apply_overrides,
    load_document,
    load_yaml_text,
)
from plant_emulator.matrix import Matrix, as_array

__all__ = [
    "MAX_DEPTH",
    "MAX_DOCUMENT_BYTES",
    "MAX_EXPANDED_NODES",
    "MAX_MAGNITUDE",
    "Matrix",
    "Section",
    "apply_overrides",
    "as_array",
    "load_document",
    "load_yaml_text",
    "validate",
]
