"""Design: models, fractional calculus, tuning, the LMI, certificates, and the one pipeline config -> Design.

Module order (each module imports only modules to its left; no cycles, function-local imports included)::

    models < fractional, qfilter, ptype < record < certificates < lmi < tuning < pipeline

``models`` (discrete models, ZOH, delay augmentation, uncertainty and its vertices); ``fractional``, ``qfilter``
(the operators the law applies); ``ptype`` (the Arimoto gain); ``record`` (the :class:`Design` and its typed
certificates); ``certificates`` (the lifted trial map of the law as it runs); ``lmi`` (Theorem 1, then
certified); ``tuning`` (``kp``, ``r`` from a loop specification; uses ``models``' layer only); ``pipeline``
(:func:`~foilc_hil.design.pipeline.build_design`, the one config -> Design seam every command uses).
"""
