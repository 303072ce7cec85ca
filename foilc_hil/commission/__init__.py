"""Drive commissioning behind ``foilc-hil commission`` (see ``docs/commissioning.md``).

- :mod:`~foilc_hil.commission.target` -- the bus to talk on: ``--bus`` or the embedded emulator (one or more
  emulated drives on a private ``virtual`` channel).
- node discovery (heartbeat, boot-up, SDO probe) with identity and NMT state is :mod:`drivers.scan` (below the
  control stack: a commissioning script scans without it).
- :mod:`~foilc_hil.commission.info` -- identity, modes, 402 state, errors, PDO mapping, DBC export.
- :mod:`~foilc_hil.commission.power` -- enable / disable / fault reset over SDO, every transition reported.
- :mod:`~foilc_hil.commission.params` -- transactional parameter sets over SDO.
- :mod:`~foilc_hil.commission.identify` -- step-test campaign, exact sampled-model fit, uncertainty bounds, plant
  fragment for ``tune`` / ``synthesize`` / ``run``.

Each module imports what it needs; importing this package imports nothing heavy.
"""
