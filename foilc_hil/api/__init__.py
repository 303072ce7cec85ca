"""The public Python API's own modules (``docs/api.md``): :class:`~foilc_hil.api.bench.Bench`, ``design``,
``simulate`` (:mod:`foilc_hil.api.bench`), ``open_log`` and ``Log`` (:mod:`foilc_hil.api.log`),
``TrialResult`` (:mod:`foilc_hil.api.results`). Scripts use them from :mod:`foilc_hil`'s top."""
