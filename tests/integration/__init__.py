"""Whole commands in one process: the CLI (``foilc_hil.cli.main``) and the API on the embedded emulator or an in-
process bus.
"""
