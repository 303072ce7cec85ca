"""Tests of the repository as a whole: layering, the docs against the code, code shape, markers, the layout."""
