"""Unit tests of the config (``foilc_hil.config``, ``schema``, ``references``) and of the shipped configs."""
