# The two set-up commands: `make demo` (closed-loop demo on built-in defaults) and `make test`.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
SHARED ?= $(abspath ../shared)
export CLOUDTRACK_SHARED ?= $(SHARED)

.PHONY: test lint types pytest demo install clean

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
	$(BIN)/python -m backend.verifiers.person_model install
	touch $@

install: $(BIN)/.installed

lint: install
	$(BIN)/ruff check .

types: install
	$(BIN)/mypy

# The supervisor page's browser test drives Debian's chromium (never a browser downloaded by playwright).
CHROMIUM ?= /usr/bin/chromium

$(CHROMIUM):
	@echo "installing Debian's chromium for the supervisor browser test"
	@SUDO=$$([ "$$(id -u)" = 0 ] || echo sudo); \
	$$SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null 2>&1 || \
	{ $$SUDO apt-get update -qq >/dev/null && $$SUDO env DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium >/dev/null; }

pytest: install $(CHROMIUM)
	$(BIN)/python -m pytest

test: lint types pytest

demo: $(BIN)/.installed-demo
	$(BIN)/cloudtrack-sim run follow --video out/demo.mp4 --plot out/demo.png --json out/demo.json

clean:
	rm -rf $(VENV) out .mypy_cache .ruff_cache .pytest_cache
