"""``foilc-hil config schema``: the JSON Schema of the config file, for editors (YAML language servers) and CI.

The schema is pydantic's ``model_json_schema`` of :class:`foilc_hil.config.Config` (JSON Schema draft 2020-12,
``$schema`` set), so it never drifts from what ``load_config`` accepts; sections refuse unknown keys
(``additionalProperties: false``) as the loader does. It cannot express the loader's cross-field checks (e.g. a
``piecewise`` reference needs ``segments``): those stay one-line errors of ``load_config``. With or without
``--json`` the output is the schema itself.
"""

from __future__ import annotations

import argparse
import json

from foilc_hil.commands import CommandResult

HELP = "print the JSON Schema of the config file (for editors)"

def add_arguments(parser: argparse.ArgumentParser) -> None:
    actions = parser.add_subparsers(dest="action", required=True, metavar="ACTION")
    schema = actions.add_parser("schema", help="print the JSON Schema of the config (pydantic's model_json_schema)")
    # after the action too (`config schema --json`); SUPPRESS keeps a --json given before the action
    schema.add_argument("--json", action="store_true", default=argparse.SUPPRESS,
                        help="print one JSON document (the schema)")


def execute(args: argparse.Namespace) -> CommandResult:
    from foilc_hil.config import Config
    from foilc_hil.io.schemas import JSON_SCHEMA_DIALECT  # the dialect pydantic generates, as the log's schemas

    schema = {"$schema": JSON_SCHEMA_DIALECT, **Config.model_json_schema()}
    return CommandResult(schema, json.dumps(schema, indent=2))
