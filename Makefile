# `make demo` sets up a fresh Debian machine and runs the agent on its bundled example; `make test` runs the tests.
VENV := .venv
PY := $(VENV)/bin/python
PIP := $(VENV)/bin/pip
# pip byte-compiles on one core; compileall does the same on all of them (processes here do not write .pyc files
# when PYTHONDONTWRITEBYTECODE is set, and torch imports in 9 s instead of 4 without them); as with pip, a file that
# does not compile (torch's Python 3.12-only test helpers) is left alone
PIP_INSTALL := $(PIP) install -q --no-compile
STAMP := $(VENV)/.installed
PYTEST_ARGS ?= -m "not slow"

.PHONY: setup bytecode demo test test-all bench clean

setup: $(STAMP)

$(STAMP): requirements.txt requirements-nodeps.txt constraints.txt scripts/install_system.sh
	bash scripts/install_system.sh
	test -x $(PY) || python3 -m venv $(VENV)
	$(PIP_INSTALL) torch==2.13.0
	$(PIP_INSTALL) -c constraints.txt -r requirements.txt
	$(PIP_INSTALL) --no-deps -r requirements-nodeps.txt
	$(PY) -m compileall -q -j 0 $(VENV)/lib > /dev/null || true
	touch $@

# the project's own modules, compiled once: the tests start about a hundred Python processes, and where
# PYTHONDONTWRITEBYTECODE is set each would compile them again (about 1 s for a stage's imports)
bytecode:
	$(PY) -m compileall -q -j 0 launch.py $(dir $(wildcard */__init__.py)) > /dev/null

demo: setup bytecode
	mkdir -p out
	OPENBLAS_NUM_THREADS=1 $(PY) launch.py --headless --mp4 out/demo.mp4 --report out/demo-report

test: setup bytecode
	OPENBLAS_NUM_THREADS=1 $(PY) -m pytest $(PYTEST_ARGS); echo $$? > .pytest-exit; exit $$(cat .pytest-exit)

test-all: PYTEST_ARGS =
test-all: test

bench: setup
	$(PY) -m bench.bus --json

clean:
	rm -rf $(VENV) runs out .pytest-exit
	find . -path ./$(VENV) -prune -o -name __pycache__ -type d -exec rm -rf {} +
