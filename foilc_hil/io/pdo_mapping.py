"""The ``foilc_hil.pdo_mapping`` metadata record of a log (:data:`foilc_hil.io.schemas.METADATA_PDO_MAPPING`): the
PDO mapping ``run`` installed, as JSON texts.

Apart from :mod:`foilc_hil.io.schemas` because it needs :mod:`drivers.pdo`, and so python-can: the schemas are
imported by the log's writer process, which must start fast (:mod:`foilc_hil.io.log_child`).
"""

from __future__ import annotations

import json

from drivers.pdo import MappedVariable, PdoDirection, PdoLayout, TransmissionType

__all__ = ["decode_pdo_mapping", "encode_pdo_mapping"]


def encode_pdo_mapping(rpdos: tuple[PdoLayout, ...], tpdos: tuple[PdoLayout, ...]) -> dict[str, str]:
    """The ``foilc_hil.pdo_mapping`` metadata record of a mapping (MCAP metadata is str -> str)."""

    def layouts(group: tuple[PdoLayout, ...]) -> str:
        return json.dumps([
            {"number": layout.number, "cob_id": layout.cob_id, "transmission_type": int(layout.transmission_type),
             "variables": [[v.index, v.subindex, v.bits, v.signed] for v in layout.variables]}
            for layout in group
        ])

    return {"rpdos": layouts(rpdos), "tpdos": layouts(tpdos)}


def decode_pdo_mapping(record: dict[str, str]) -> tuple[tuple[PdoLayout, ...], tuple[PdoLayout, ...]]:
    """Inverse of :func:`encode_pdo_mapping`; ``ValueError`` (or ``KeyError``/``TypeError``) when malformed."""

    def layouts(direction: PdoDirection) -> tuple[PdoLayout, ...]:
        return tuple(
            PdoLayout(direction, int(item["number"]), int(item["cob_id"]),
                      tuple(MappedVariable(int(index), int(sub), int(bits), bool(signed))
                            for index, sub, bits, signed in item["variables"]),
                      TransmissionType(int(item["transmission_type"])))
            for item in json.loads(record[direction.name.lower() + "s"])
        )

    return layouts(PdoDirection.RPDO), layouts(PdoDirection.TPDO)
