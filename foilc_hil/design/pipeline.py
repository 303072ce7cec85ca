"""The one design pipeline: config -> :class:`~foilc_hil.design.record.Design`, for every law.

The bench (``run``), ``simulate``, ``synthesize`` and the demo all call :func:`build_design`, so the design a log
records is the design of the law that ran: tuned when the law needs it (FOILC without ``tuning.kp``/``tuning.r``),
synthesised, and certified exactly as it will run (Q-filter, fractional memory, input delay).
"""

from __future__ import annotations

from foilc_hil.config import Config
from foilc_hil.design.lmi import synthesize_from_config
from foilc_hil.design.qfilter import QFilter
from foilc_hil.design.record import Design
from foilc_hil.design.tuning import tune
from foilc_hil.errors import ConfigError

__all__ = ["build_design"]


def build_design(config: Config, law: str, n_samples: int, *, input_delay: int) -> Design:
    """The design of ``law`` for ``config``'s plant, certified as the law will run.

    Parameters
    ----------
    config
        The whole configuration.
    law
        ``foilc``, ``ioilc`` or ``p-type``.
    n_samples
        Samples per trial (the certificates are for this trial length).
    input_delay
        Cycles between computing a command and the plant applying it: 1 for the SYNC-driven CAN loop, and for
        ``simulate`` that stands in for it; 0 for an ideal offline loop.
    """
    q_matrix = None
    if config.law.q_filter is not None:
        q_filter = QFilter(config.law.q_filter.cutoff, config.law.q_filter.order, config.sample_time)
        q_matrix = q_filter.matrix(n_samples)
    kp, r = config.tuning.kp, config.tuning.r
    if law == "ioilc":  # the integer-order law needs no tuning: kp = 0 (r is recorded, unused)
        return synthesize_from_config(config, law="ioilc", kp=0.0, r=1.0 if r is None else r,
                                      input_delay=input_delay, n_samples=n_samples, q_filter=q_matrix)
    if law == "foilc":
        if kp is None or r is None:
            tuned = tune(config)
            kp, r = tuned.kp, tuned.r
        return synthesize_from_config(config, law="foilc", kp=kp, r=r, input_delay=input_delay,
                                      n_samples=n_samples, q_filter=q_matrix)
    raise ConfigError(f"no design pipeline for law {law!r} yet", key="law.kind")
