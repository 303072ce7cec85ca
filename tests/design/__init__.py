"""Unit tests of ``foilc_hil.design`` and ``foilc_hil.laws``: models, certificates, LMIs, filters, the design
pipeline.
"""
