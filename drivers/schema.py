"""Config sections: the strict pydantic base :class:`Section` and :func:`validate`, with one-line errors.

Every section of the configuration is a :class:`Section` (extra keys forbidden, immutable, finite numbers of bounded
magnitude). :func:`validate` turns the first validation failure into a :class:`~drivers.errors.ConfigError` naming
the dotted key path, e.g. ``configs/x.yaml: drive.node_id: ...``; an unknown key gets a did-you-mean.

It lives at the bottom of the ranks so that ``drivers`` and ``plant_emulator`` define and validate their own sections
(``drive:``, ``bus:``, ``plant:``, ``emulator:``) without importing ``foilc_hil``; :mod:`foilc_hil.schema` re-exports
it with the YAML loading (:mod:`drivers.yaml_document`) and the plant's matrices.
"""

from __future__ import annotations

import difflib
from collections.abc import Mapping
from typing import Any, TypeVar

from pydantic import BaseModel, ConfigDict, ValidationError, field_validator

from drivers.errors import ConfigError

__all__ = ["MAX_MAGNITUDE", "Section", "validate"]

SectionT = TypeVar("SectionT", bound="Section")

#: no physical quantity of a servo axis, a design or a bench setting is larger: a finite but absurd value (1e308)
#: would overflow numpy or stall the LMI solver rather than fail cleanly
MAX_MAGNITUDE = 1e12


class Section(BaseModel):
    """Base of every config section: strict keys, frozen values, finite numbers of bounded magnitude."""

    model_config = ConfigDict(extra="forbid", frozen=True, populate_by_name=True, allow_inf_nan=False)

    @field_validator("*", mode="after")
    @classmethod
    def _bounded_numbers(cls, value: Any) -> Any:
        _check_magnitude(value)
        return value


def _check_magnitude(value: Any) -> None:
    """Every number inside ``value`` (nested lists included) is finite and at most :data:`MAX_MAGNITUDE`."""
    if isinstance(value, bool):
        return
    if isinstance(value, (int, float)):
        if not abs(value) <= MAX_MAGNITUDE:  # also catches nan
            raise ValueError(f"must be finite and at most {MAX_MAGNITUDE:g} in magnitude, got {value!r}")
    elif isinstance(value, (list, tuple)):
        for item in value:
            _check_magnitude(item)


def validate(model: type[SectionT], document: Mapping[str, Any], source: str = "") -> SectionT:
    """Build ``model`` from ``document``; raise :class:`ConfigError` for the first problem, naming its key."""
    try:
        return model.model_validate(document)
    except ValidationError as exc:
        raise _first_error(model, exc, source) from None


def _first_error(model: type[BaseModel], exc: ValidationError, source: str) -> ConfigError:
    error = exc.errors(include_url=False)[0]
    location = [str(part) for part in error["loc"]]
    key = ".".join(location)
    kind = error["type"]
    if kind == "extra_forbidden":
        message = "unknown key" + _did_you_mean(model, location)
    elif kind == "missing":
        message = "is required"
    else:
        message = str(error["msg"])
        # pydantic prefixes messages of custom validators; the key path already says where.
        for prefix in ("Value error, ", "Assertion failed, "):
            message = message.removeprefix(prefix)
    return ConfigError(message, key=key, source=source)


def _did_you_mean(model: type[BaseModel], location: list[str]) -> str:
    """Suggest the closest known key for an unknown key at ``location``."""
    current: Any = model
    for part in location[:-1]:
        fields = getattr(current, "model_fields", None)
        if fields is None or part not in fields:
            # A list index or a union: fall back to no suggestion rather than guess.
            if part.isdigit():
                continue
            return ""
        annotation = fields[part].annotation
        current = _section_type(annotation)
        if current is None:
            return ""
    fields = getattr(current, "model_fields", {})
    known = list(fields) + [f.alias for f in fields.values() if f.alias]
    matches = difflib.get_close_matches(location[-1], known, n=1, cutoff=0.6)
    if matches:
        return f" (did you mean '{matches[0]}'?)"
    return f"; known keys: {', '.join(sorted(known))}" if known else ""


def _section_type(annotation: Any) -> Any:
    """The Section subclass inside ``annotation`` (plain, Optional or list), or None."""
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    for arg in getattr(annotation, "__args__", ()):
        found = _section_type(arg)
        if found is not None:
            return found
    return None
