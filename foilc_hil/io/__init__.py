"""Log input/output: the MCAP log (:mod:`foilc_hil.io.mcap_log`), its layout (:mod:`foilc_hil.io.schemas`) and
python-can's ``can.io`` registration of ``.mcap`` (:mod:`foilc_hil.io.can_io`).

Imports nothing, so ``foilc-hil tune`` never pulls in mcap or python-can through this package.
"""
