"""Unit tests of ``foilc_hil.io`` and ``foilc_hil.logtools``: the MCAP log, its writer process, replay, report,
export.
"""
