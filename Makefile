# `make demo` sets up a fresh Debian machine and runs the agent on its bundled example; `make test` runs the tests.
VENV := .venv
PY := $(VENV)/bin/python
PIP := $(VENV)/bin/pip
# Python writes each module's bytecode the first time it imports it, once for all later processes (the tests start
# about a hundred): where the environment sets PYTHONDONTWRITEBYTECODE, every process would compile torch again
# (9 s to import it instead of 4 on the 2-core EPYC), and compiling all of .venv up front takes 37 s
unexport PYTHONDONTWRITEBYTECODE
PIP_INSTALL := $(PIP) install -q --no-compile
STAMP := $(VENV)/.installed
# two workers, one per core; a module's tests stay on one worker, so its module fixtures run once
PYTEST_ARGS ?= -m "not slow" -n 2 --dist loadfile

.PHONY: setup demo test test-all bench clean

setup: $(STAMP)

$(STAMP): requirements.txt requirements-nodeps.txt constraints.txt scripts/install_system.sh
	bash scripts/install_system.sh
	test -x $(PY) || python3 -m venv $(VENV)
	$(PIP_INSTALL) torch==2.13.0
	$(PIP_INSTALL) -c constraints.txt -r requirements.txt
	$(PIP_INSTALL) --no-deps -r requirements-nodeps.txt
	touch $@

demo: setup
	mkdir -p out
	OPENBLAS_NUM_THREADS=1 $(PY) launch.py --headless --mp4 out/demo.mp4 --report out/demo-report

test: setup
	OPENBLAS_NUM_THREADS=1 $(PY) -m pytest $(PYTEST_ARGS); echo $$? > .pytest-exit; exit $$(cat .pytest-exit)

test-all: PYTEST_ARGS =
test-all: test

bench: setup
	$(PY) -m bench.bus --json

clean:
	rm -rf $(VENV) runs out .pytest-exit
	find . -path ./$(VENV) -prune -o -name __pycache__ -type d -exec rm -rf {} +
