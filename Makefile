# The two set-up commands: `make demo` (closed-loop demo on built-in defaults) and `make test`.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
SHARED ?= $(abspath ../shared)
export CLOUDTRACK_SHARED ?= $(SHARED)

.PHONY: test check lint format-check types pytest trials demo install clean install-services backend-redis

$(BIN)/python:
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip

# The demo needs the back-end and plotting extras only; the tests add the test tools and CPU torch.
# The local verifier's pose model is copied out of the mediapipe 0.10.14 wheel that pip fetches from PyPI.
$(BIN)/.installed-demo: pyproject.toml | $(BIN)/python
	$(BIN)/pip install -q -e '.[backend,eval,person]'
	$(BIN)/python -m backend.verifiers.person_model install
	touch $@

$(BIN)/.installed: pyproject.toml | $(BIN)/python
	# CPU-only torch first (for the open-vocabulary detector tests): the PyPI build pulls several GB of CUDA.
	# The +cpu build comes from pip's configured sources where they have it, else from PyTorch's CPU index.
	$(BIN)/pip install -q "torch==2.13.0+cpu" || \
	  $(BIN)/pip install -q "torch==2.13.0+cpu" --extra-index-url https://download.pytorch.org/whl/cpu
	$(BIN)/pip install -q -e '.[test]'
	# MAVProxy for the `module load cloudtrack` test, without its declared dependencies: its opencv-python
	# would shadow the contrib OpenCV the trackers need, and vtk & co. serve only its GUI modules.
	$(BIN)/pip install -q --no-deps "MAVProxy==1.8.75"
	$(BIN)/python -m backend.verifiers.person_model install
	touch $@

install: $(BIN)/.installed

lint: install
	$(BIN)/ruff check .

types: install
	$(BIN)/mypy

format-check: install
	$(BIN)/ruff format --check .

# The supervisor page's browser test drives Debian's chromium (never a browser downloaded by playwright).
CHROMIUM ?= /usr/bin/chromium

$(CHROMIUM):
	@echo "installing Debian's chromium for the supervisor browser test"
	@SUDO=$$([ "$$(id -u)" = 0 ] || echo sudo); \
	$$SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null 2>&1 || \
	{ $$SUDO apt-get update -qq >/dev/null && $$SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null; }

# The back-end's replicated-state tests and `cloudtrack-backend bench` start Debian's redis-server and nginx.
REDIS_SERVER ?= /usr/bin/redis-server
NGINX ?= /usr/sbin/nginx

$(REDIS_SERVER) $(NGINX):
	@echo "installing Debian's redis-server and nginx for the back-end's replica tests and bench"
	@SUDO=$$([ "$$(id -u)" = 0 ] || echo sudo); \
	$$SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq redis-server nginx >/dev/null 2>&1 || \
	{ $$SUDO apt-get update -qq >/dev/null && $$SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq redis-server nginx >/dev/null; }

install-services: $(REDIS_SERVER) $(NGINX)

# A redis-server for back-end replicas (sessions.store = "redis"): loopback only, every write fsync'd.
backend-redis: $(REDIS_SERVER)
	mkdir -p out/redis
	$(REDIS_SERVER) --bind 127.0.0.1 --port 6379 --dir out/redis --save "" --appendonly yes --appendfsync always

# The COCO word table's test rebuilds it from Debian's WordNet 3.0 (wordnet-base) and compares.
WORDNET ?= /usr/share/wordnet/data.noun

$(WORDNET):
	@echo "installing Debian's wordnet-base for the COCO vocabulary test"
	@SUDO=$$([ "$$(id -u)" = 0 ] || echo sudo); \
	$$SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq wordnet-base >/dev/null 2>&1 || \
	{ $$SUDO apt-get update -qq >/dev/null && $$SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq wordnet-base >/dev/null; }

# The fast tests run in CHECK_WORKERS processes as in `make check`; the slow ones (real-time flights,
# SITL, browser) one at a time, as their timings were measured.
pytest: install $(CHROMIUM) $(REDIS_SERVER) $(NGINX) $(WORDNET)
	$(BIN)/python -m pytest -m "not slow" -n $(CHECK_WORKERS)
	$(BIN)/python -m pytest -m "slow and not trial" --durations=40

# Every test without the slow mark with mypy beside them (its output printed after theirs); fails if either
# does. $(1): extra pytest options.
define fast_tests_beside_mypy
@mkdir -p .mypy_cache; $(BIN)/mypy > .mypy_cache/check.out 2>&1 & types=$$!; \
$(BIN)/python -m pytest $(1) -m "not slow" -n $(CHECK_WORKERS); tests=$$?; \
wait $$types; typed=$$?; echo "mypy:"; cat .mypy_cache/check.out; \
test $$tests -eq 0 && test $$typed -eq 0
endef

# CI: as `pytest`, with mypy (cold in a fresh clone: ~40 s of CPU) beside the fast tests as in `check`,
# never beside the slow ones, whose real-time flights were timed without it.
test: lint format-check $(CHROMIUM) $(REDIS_SERVER) $(NGINX) $(WORDNET)
	$(call fast_tests_beside_mypy,)
	$(BIN)/python -m pytest -m "slow and not trial" --durations=40

# The developer's inner loop: lint, types and every test without the slow mark (closed-loop scenarios,
# browser, real-time MAVLink and SITL flights); under 2 minutes on a 2-core machine. `make test` runs all.
# The fast tests mostly wait on sockets and timers, so pytest-xdist runs them in CHECK_WORKERS processes
# (2, 4 and 6 compared in docs/benchmarks.md; 0: one process); mypy runs beside them (about a second with
# its cache; a cold cache, 40 s of CPU, then overlaps the tests) and its output is printed after theirs.
CHECK_WORKERS ?= 4

check: install
	$(BIN)/ruff check .
	$(call fast_tests_beside_mypy,-q)

# Slow flights marked `trial`: they run end to end but fail a known open check today (named in the test and
# docs/sitl.md). Not in `make test` until they hold. None at present (exit 5 from pytest: nothing selected).
trials: install $(CHROMIUM) $(REDIS_SERVER) $(NGINX) $(WORDNET)
	$(BIN)/python -m pytest -m trial --durations=10 || [ $$? -eq 5 ]

demo: $(BIN)/.installed-demo
	$(BIN)/cloudtrack-sim run follow --video out/demo.mp4 --plot out/demo.png --json out/demo.json
	@echo "the console scripts are in $(BIN)/: 'source $(BIN)/activate' puts them on PATH (README, Set-up)"

clean:
	rm -rf $(VENV) out .mypy_cache .ruff_cache .pytest_cache
