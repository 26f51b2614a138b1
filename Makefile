# `make demo` sets up everything and runs the built-in demo; `make test` runs the test suite.
VENV ?= .venv
OUT ?= out/demo
# Real data for the tests that use it (they skip without it).
OCTOLOG_DATA ?= $(abspath $(firstword $(wildcard ../shared/data)))

.PHONY: setup demo test test-quick bench bench-transport
setup: $(VENV)/.installed

$(VENV)/.installed: pyproject.toml requirements.lock .ci/setup.sh
	VENV=$(VENV) bash .ci/setup.sh

demo: setup
	$(VENV)/bin/octolog demo --out $(OUT) --overwrite  # a demo folder is disposable: re-running replaces it

# Three pytest-xdist workers on two cores, a test module each at a time (module fixtures made once;
# the shared end-to-end runs once across workers): much of the suite waits on processes, links and
# timeouts, and a third worker fills those waits (13.5 against 14.5 min). TEST_WORKERS=0: one process.
TEST_WORKERS ?= 3
PYTEST = OCTOLOG_DATA=$(OCTOLOG_DATA) $(VENV)/bin/python -m pytest -q -n $(TEST_WORKERS) --dist loadfile

# Each test starts hundreds of stage processes: with the project's bytecode compiled first, none of
# them compiles octolog's modules again (PYTHONDONTWRITEBYTECODE=1 keeps Python from saving it).
COMPILE = $(VENV)/bin/python -m compileall -q -j 0 kit schemas recorder replay tracker mapper shell

test: setup
	$(COMPILE)
	$(PYTEST)

# The quick tier while working: everything but the `slow` and `root` tests (tests/conftest.py).
test-quick: setup
	$(COMPILE)
	$(PYTEST) -m "not slow and not root"

bench: setup
	OCTOLOG_DATA=$(OCTOLOG_DATA) $(VENV)/bin/python bench/pipeline.py

# Bus throughput/latency (shared memory, TCP loopback, TCP between network namespaces) next to a raw
# memory copy, and the wire-compression table; the namespace rows need root (skipped otherwise).
bench-transport: setup
	OCTOLOG_DATA=$(OCTOLOG_DATA) $(VENV)/bin/python bench/transport.py --wire

# Native tracker vs the ORB-SLAM3 backend on TUM fr1/xyz first 300, as recorded and every 3rd frame
# (fast motion) (builds and caches a vocabulary in /tmp/octolog-bench/vocab unless VOCABULARY=FILE).
.PHONY: bench-tracker
bench-tracker: setup
	OCTOLOG_DATA=$(OCTOLOG_DATA) $(VENV)/bin/python bench/tracker.py $(if $(VOCABULARY),--vocabulary $(VOCABULARY))

# The tracker over a 10-minute session (the synthetic room looped at 30 fps; ~12 min on 2 cores).
.PHONY: bench-long
bench-long: setup
	$(VENV)/bin/python bench/long_session.py --minutes 10

# Screenshots of the Rerun viewer on the demo and on TUM first300 into docs/img (Xvfb + software Vulkan).
.PHONY: screenshots
screenshots: setup
	command -v Xvfb >/dev/null && command -v import >/dev/null && command -v xdotool >/dev/null || \
		{ apt-get update -qq && apt-get install -y -qq xvfb mesa-vulkan-drivers imagemagick xdotool >/dev/null; }
	OCTOLOG_DATA=$(OCTOLOG_DATA) $(VENV)/bin/python bench/screenshots.py
