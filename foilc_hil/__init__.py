"""foilc-hil: two-dimensional fractional-order iterative learning control on a CAN hardware-in-the-loop bench.

Layering (imports point downwards only; ``tests/test_layering.py`` enforces it):

0. ``foilc_hil.errors``, ``foilc_hil.schema`` -- the error hierarchy and config validation toolkit (no project
   imports).
1. ``drivers`` -- the CAN side of a drive: CiA 301/402 protocol, object dictionary, PDO codecs, the master.
2. ``plant_emulator`` -- plant physics (the one physics code path) and the virtual CiA 402 drive.
3. the rest of ``foilc_hil`` -- control science, bench loop, logging, CLI.

This module imports nothing so that layers 1 and 2 can use layer 0 without pulling in layer 3.
"""

__version__ = "0.1.0"
