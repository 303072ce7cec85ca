"""foilc-hil: two-dimensional fractional-order iterative learning control on a CAN hardware-in-the-loop bench.

Layering (imports point downwards only; ``tests/test_layering.py`` enforces it):

0. ``drivers`` -- the CAN side of a drive: CiA 301/402 protocol, object dictionary, PDO codecs, the master; the
   root of the error tree (``drivers.errors``) and the config sections' base (``drivers.schema``).
1. ``plant_emulator`` -- plant physics (the one physics code path) and the virtual CiA 402 drive.
2. ``foilc_hil.errors``, ``foilc_hil.schema`` -- the error hierarchy and config toolkit under one name (re-exported
   from layers 0 and 1, plus the control stack's errors).
3. the rest of ``foilc_hil`` -- control science, bench loop, logging, CLI.

Layers 0 and 1 import nothing of ``foilc_hil``: a script uses the master or the emulator without the control stack.
This module imports nothing.
"""

__version__ = "0.1.0"
