# Everything a fresh machine needs: `make demo` and `make test` create .venv themselves.
PYTHON ?= python3
VENV   := .venv
PY     := $(VENV)/bin/python
STAMP  := $(VENV)/.installed-stamp
OUT    ?= out
PACKAGES := ground_sim flight_sw protocol hil_server studies reports
# type-checked along with PACKAGES: the bench scripts (where docs' measured figures come from) and the examples
SCRIPTS  := bench examples
SUDO   := $(shell [ "$$(id -u)" = 0 ] || echo sudo)

.PHONY: demo test lint chromium bench results install clean

# PYTHONWARNINGS: setuptools warns that an editable install is editable; nothing else is hidden
# (a failed install still fails the target).
$(STAMP): pyproject.toml setup.py flight_sw/_sgmc.c flight_sw/_treesc.c
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	PYTHONWARNINGS=ignore $(PY) -m pip install --quiet -e '.[test,fit]'
	@# the C kernels are optional extensions: a build without a compiler installs, slower, and is said here
	@$(PY) -c "import sys; from flight_sw.kernels import kernels_note, missing_kernels; m = missing_kernels(); \
	  m and print('warning: ' + kernels_note(m), file=sys.stderr)"
	touch $(STAMP)

install: $(STAMP)

demo: $(STAMP)
	$(VENV)/bin/hazard-hil demo --out $(OUT)/demo

MYPY := $(VENV)/bin/mypy $(PACKAGES) $(SCRIPTS)

lint: $(STAMP)
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	$(MYPY)

# The browser test opens every kind of report in Debian's headless Chromium.
chromium:
	@command -v chromium >/dev/null 2>&1 || command -v chromium-browser >/dev/null 2>&1 || \
	  { echo "installing Debian's chromium for the browser test"; \
	    $(SUDO) apt-get install -y -q chromium >/dev/null 2>&1 || \
	    { $(SUDO) apt-get update -q >/dev/null && $(SUDO) apt-get install -y -q chromium >/dev/null; }; }

# Two workers per core, each pinned to a core (tests/conftest.py), whole files apiece. The end-to-end tests mostly
# wait on lines and timers: two at once halved the suite (9.5 -> 4.5 min, stop 14); on this 2-core host three took
# it from 10.8 to 8.8 min (stop 77), and four from 8.9 to 7.1 min the same hour (stop 79; three had put two workers
# on one core and one on the other). Stop 78 kept three after one four-worker run saw the flight process peak at
# 51 MiB against its 41 MiB model: the memory watch had read the flight's ldconfig child as a second copy of it
# (flight_sw.warmup.settle_allocator no longer starts one).
TEST_WORKERS ?= $(shell echo $$(( 2 * $$(nproc) )))
# The tests write bytecode even where PYTHONDONTWRITEBYTECODE is set (it is on this VM): otherwise each worker
# rewrote the tests' asserts (12 s of CPU apiece) and every command a test started compiled the packages again.
# The caches go to __pycache__ beside the sources, which git ignores. tests/conftest.py hands out the longest files
# first (tests/file_seconds.json).
# mypy (25 s from a cold cache) runs beside the tests at the lowest priority, on the CPU they leave idle while
# they wait; its verdict is printed after theirs, and either failing fails the target. sh starts a background
# job with SIGINT ignored: the traps end it with the recipe, or a Ctrl-C left it running.
test: $(STAMP) chromium
	$(VENV)/bin/ruff check .
	$(VENV)/bin/ruff format --check .
	@nice -n 19 $(MYPY) > $(VENV)/mypy.log 2>&1 & types=$$!; \
	  trap 'kill $$types 2>/dev/null' EXIT; trap 'exit 130' INT TERM; \
	  env -u PYTHONDONTWRITEBYTECODE HAZARD_HIL_REQUIRE_BROWSER=1 $(PY) -m pytest -q -n $(TEST_WORKERS) --dist loadfile; tests=$$?; \
	  wait $$types; typed=$$?; trap - EXIT; echo "mypy:"; cat $(VENV)/mypy.log; \
	  [ $$tests -eq 0 ] && [ $$typed -eq 0 ]

bench: $(STAMP)
	$(PY) bench/run_all.py

# docs/RESULTS.md's measured blocks: both scenario tables on the thesis scene (held-out seeds) and the
# landing Monte Carlo over every library scene, then bench/results.py copies them into docs/.
RESULTS_SEEDS ?= 5
RESULTS_LANDINGS ?= 1008
# Scores and landings are recomputed (the flight software may have changed); rendered pairs are reused.
results: $(STAMP)
	rm -rf $(OUT)/eval_vertical/runs/evaluate.jsonl $(OUT)/eval_approach/runs/evaluate.jsonl
	rm -rf $(OUT)/eval_vertical/runs/multiframe.jsonl $(OUT)/eval_approach/runs/multiframe.jsonl
	rm -rf $(OUT)/landings $(OUT)/landings_perfect_nav
	$(VENV)/bin/hazard-hil evaluate --scenario vertical --seeds $(RESULTS_SEEDS) --multi-frame --out $(OUT)/eval_vertical
	$(VENV)/bin/hazard-hil evaluate --scenario approach --seeds $(RESULTS_SEEDS) --multi-frame --out $(OUT)/eval_approach
	$(VENV)/bin/hazard-hil landings --scenes all --n $(RESULTS_LANDINGS) --cache $(OUT)/landing_renders --out $(OUT)/landings
	$(VENV)/bin/hazard-hil landings --scenes all --n $(RESULTS_LANDINGS) --cache $(OUT)/landing_renders \
	  --pose-error none --out $(OUT)/landings_perfect_nav
	$(PY) bench/results.py $(OUT)

clean:
	rm -rf $(VENV) $(OUT) .pytest_cache .mypy_cache .ruff_cache
