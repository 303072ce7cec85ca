# Every target bootstraps its own .venv, so `make demo` and `make test` work on a fresh machine.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed-stamp
# pytest workers: two per core (see the pytest target), at most 16 (a worker holds the project's imports, a few
# hundred MB: 2 per core on a 64-core host would be 128 of them)
WORKERS ?= $(shell n=$$((2 * $$(getconf _NPROCESSORS_ONLN 2>/dev/null || echo 1))); echo $$((n > 16 ? 16 : n)))

.PHONY: demo test lint typecheck pytest docs bench bench-realtime soak clean

# Bytecode caching on, whatever the shell says: a run starts many Python processes (the log writer, emulators, the
# CLI in tests) and with PYTHONDONTWRITEBYTECODE set each one compiled every module it imports from source again,
# and every pytest worker re-rewrote every test module (the cost: docs/benchmarks.md)
unexport PYTHONDONTWRITEBYTECODE

# The .venv by uv (from PyPI, into the .venv by the system's pip): much faster than pip, which spends most of its
# time byte-compiling every module of every package (here a module is compiled when it is first imported, and most
# never are; the times: docs/benchmarks.md). Where uv cannot be had (an old pip without --python, no PyPI), pip
# installs it all as before.
$(STAMP): pyproject.toml
	$(PYTHON) -m venv --without-pip $(VENV)
	if $(PYTHON) -m pip --python $(BIN)/python install --quiet 'uv>=0.4' \
	    && $(BIN)/uv pip install --quiet --python $(BIN)/python pip -e '.[dev]'; then :; else \
	    $(BIN)/python -m ensurepip --upgrade && $(BIN)/python -m pip install --quiet --upgrade pip \
	    && $(BIN)/python -m pip install --quiet -e '.[dev]'; fi
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/foilc-hil demo

# the four at once: mypy's cold run (half a minute on a fresh clone) fills the time pytest's workers spend waiting
# on subprocesses and timeouts; each target's output is printed whole when it ends, and any failure fails the test
# (docs: a pdoc warning too)
test: $(STAMP)
	$(MAKE) --no-print-directory -j3 --output-sync=target lint typecheck pytest docs

lint: $(STAMP)
	$(BIN)/ruff check .

typecheck: $(STAMP)
	$(BIN)/mypy

# two workers per core (pytest-xdist; worksteal evens out the long tests): a quarter of the suite's test time is
# spent waiting, not computing (timeouts that are the point of a test, emulator and CLI processes, a drive's
# heartbeat), so more workers than cores finish sooner (the measured counts: docs/benchmarks.md). Each test stays
# independent of the others and of wall-clock speed. `pytest -m "not slow"` is the inner loop (README). One BLAS thread
# per worker: the workers already fill the cores, and OpenBLAS threads that spin-wait for a core a loaded host does
# not give them made a 3x3 expm hundreds of times slower
# The shared caches first, once (tests/support/warm_caches.py): numba's compiled kernels, the packages' byte code and the
# rewritten test modules; on a fresh clone each worker and each emulator process a test starts would otherwise
# fill them again, at the same time (several seconds of CPU each)
pytest: $(STAMP)
	$(BIN)/python -m tests.support.warm_caches
	OPENBLAS_NUM_THREADS=1 OMP_NUM_THREADS=1 $(BIN)/pytest -n $(WORKERS) --dist worksteal --durations=15

# The API reference (docs/api.md) from the docstrings: the public package tops only (every other module is
# internal), into build/api/ (git-ignored). -W error: any warning of pdoc's (a name of __all__ that does not resolve,
# a docstring it cannot parse) fails the build
docs: $(STAMP)
	rm -rf build/api
	$(BIN)/python -W error -m pdoc --docformat numpy --output-directory build/api \
	    foilc_hil drivers plant_emulator '!foilc_hil\..*' '!drivers\..*' '!plant_emulator\..*'

bench: $(STAMP)
	$(BIN)/python -m benchmarks.run --out benchmarks/results.json --doc docs/benchmarks.md

# 1 kHz realtime across processes in a private network namespace (root; its duration: docs/benchmarks.md), vs canopen
# and python-can; then four axes (configs/scara_4axis.yaml) at 2.5 ms, 5 runs each with one and four emulator processes
bench-realtime: $(STAMP)
	$(BIN)/python -m benchmarks.realtime --out benchmarks/realtime.json
	$(BIN)/python -m benchmarks.realtime_axes --runs 5 --out benchmarks/realtime_axes.json

# 200 lockstep trials on the PMSM emulator (uncertainty, load disturbance), watched for leaks (docs/reliability.md)
soak: $(STAMP)
	$(BIN)/python -m benchmarks.soak --trials 200 --out benchmarks/soak.json

clean:
	rm -rf $(VENV) build *.egg-info .mypy_cache .pytest_cache .ruff_cache
