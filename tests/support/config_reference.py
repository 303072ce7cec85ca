"""Generates ``docs/config-reference.md`` from the typed config models (``foilc_hil.config.Config``).

Every key of every section, with its type, default, bounds and the comment beside its declaration. Run
``python -m tests.support.config_reference`` after changing a config model; ``tests/config/test_config_reference.py``
fails while the file is not current.
"""

from __future__ import annotations

import inspect
import re
import types
import typing
from pathlib import Path
from typing import Any

from pydantic import BaseModel
from pydantic.fields import FieldInfo

from foilc_hil.config import Config

DOC = Path(__file__).resolve().parents[2] / "docs" / "config-reference.md"

HEADER = """# Config reference

Generated from the typed config models (`foilc_hil/config.py` and the sections it includes) by
`python -m tests.support.config_reference`; `tests/config/test_config_reference.py` fails when this file is not current.
Every key is optional (the default applies); unknown keys are refused with a did-you-mean. Command-line options override
the file. Durations are in seconds unless a key says otherwise (`_ms` keys are CANopen objects in milliseconds).

For editors: `.venv/bin/foilc-hil config schema > foilc-hil.schema.json` writes the JSON Schema of the same models
(draft 2020-12); with the YAML language server, a first line `# yaml-language-server: $schema=foilc-hil.schema.json`
gives completion and checks. The schema cannot express the cross-field checks; `load_config` still reports those.

## The `piecewise` reference profile

`reference.profile: piecewise` builds the trial's set-point from `reference.segments`, in order. Segment `j` covers
`(t_j, t_j + duration]` (times multiplied by `reference.time_scale`, values by `reference.scale`): it holds `start`,
or ramps linearly from `start` to `end` when `end` is given. The trial lasts the sum of the durations, which must be a
whole number of `sample_time`s. Example (a ramp to 30, a hold, a ramp down to 10; 1 s):

```yaml
reference:
  profile: piecewise
  segments:
    - {duration: 0.3, start: 0.0, end: 30.0}
    - {duration: 0.4, start: 30.0}
    - {duration: 0.3, start: 30.0, end: 10.0}
```

`eq49` and `eq52` are the paper's profiles (6 s; `eq52` is printed in ms, `time_scale: 1.0` keeps 6 s).
"""


def _comments(model: type[BaseModel]) -> dict[str, str]:
    """``name -> comment`` of the field declarations in the model's source: the comment beside the field, else
    the comment lines right above it."""
    found: dict[str, str] = {}
    for klass in reversed(model.__mro__):
        if not (isinstance(klass, type) and issubclass(klass, BaseModel)) or klass is BaseModel:
            continue
        try:
            source = inspect.getsource(klass)
        except (OSError, TypeError):
            continue
        above: list[str] = []
        for line in source.splitlines():
            comment = re.fullmatch(r"    #\s*(.+)", line)
            field = re.match(r"    (\w+): [^#]*(?:#\s*(.+))?$", line)
            if comment is not None:
                above.append(comment.group(1).strip())
                continue
            if field is not None:
                text = field.group(2) or " ".join(above)
                if text:
                    found[field.group(1)] = text.strip()
            above = []
    return found


def _type_name(annotation: Any) -> str:
    origin = typing.get_origin(annotation)
    if origin is typing.Annotated:  # e.g. Matrix: a number, a list or a list of lists, validated
        return "matrix" if "matrix" in repr(annotation) else _type_name(typing.get_args(annotation)[0])
    if origin is typing.Literal:
        return " \\| ".join(f"`{value}`" for value in typing.get_args(annotation))
    if origin in (typing.Union, types.UnionType):
        return " or ".join(_type_name(arg) for arg in typing.get_args(annotation))
    if origin is list:
        return f"list of {_type_name(typing.get_args(annotation)[0])}"
    if annotation is type(None):
        return "null"
    if isinstance(annotation, type) and hasattr(annotation, "__members__"):  # an enum
        return " \\| ".join(f"`{member.value}`" for member in annotation.__members__.values())
    return getattr(annotation, "__name__", str(annotation))


def _bounds(info: FieldInfo) -> str:
    parts = []
    for item in info.metadata:
        for name, symbol in (("gt", ">"), ("ge", ">="), ("lt", "<"), ("le", "<="), ("min_length", "length >="),
                             ("max_length", "length <=")):
            value = getattr(item, name, None)
            if value is not None:
                parts.append(f"{symbol} {value}")
    return ", ".join(parts)


def _default(info: FieldInfo) -> str:
    if info.is_required():
        return "required"
    value = info.get_default(call_default_factory=True)
    if isinstance(value, BaseModel):
        return "(section)"
    if hasattr(value, "value") and not isinstance(value, (int, float)):
        value = value.value
    return f"`{value}`" if value is not None else "`null`"


def _section_model(annotation: Any) -> type[BaseModel] | None:
    for candidate in (annotation, *typing.get_args(annotation)):
        if typing.get_origin(candidate) is list:
            candidate = typing.get_args(candidate)[0]
        if isinstance(candidate, type) and issubclass(candidate, BaseModel):
            return candidate
    return None


def _render_model(model: type[BaseModel], path: str, out: list[str]) -> None:
    doc = inspect.cleandoc(model.__doc__ or "").split("\n\n")[0].replace("\n", " ")
    out += [f"## `{path}`" if path else "## top level", "", doc, "",
            "| key | type | default | bounds | notes |", "|---|---|---|---|---|"]
    comments = _comments(model)
    nested: list[tuple[type[BaseModel], str]] = []
    for name, info in model.model_fields.items():
        key = f"{path}.{name}" if path else name
        sub = _section_model(info.annotation)
        kind = f"section `{key}`" if sub is not None else _type_name(info.annotation)
        if sub is not None and "list of" in _type_name(info.annotation):
            kind = f"list of section `{key}[]`, or null"
            key_of_items = f"{key}[]"
        else:
            key_of_items = key
        note = comments.get(name, "").replace("|", "\\|")
        out.append(f"| `{key}` | {kind} | {_default(info)} | {_bounds(info)} | {note} |")
        if sub is not None:
            nested.append((sub, key_of_items))
    out.append("")
    for sub, key in nested:
        _render_model(sub, key, out)


def render() -> str:
    """The whole reference, as written to :data:`DOC`."""
    out = [HEADER]
    _render_model(Config, "", out)
    return "\n".join(out).rstrip("\n") + "\n"


if __name__ == "__main__":
    DOC.write_text(render(), encoding="utf-8")
    print(f"wrote {DOC}")
