# `make demo` sets up a fresh Debian machine and runs the agent on its bundled example; `make test` runs the checks
# and the tests. Both install from the lock (requirements.lock, requirements-test.lock; `make lock` remakes them).
VENV := .venv
PY := $(VENV)/bin/python
PIP := $(VENV)/bin/pip
# torch's CPU build: pip prefers its 2.13.0+cpu to PyPI's 2.13.0 (a CUDA build on Linux). For CUDA, e.g.
# `make setup TORCH_INDEX=https://download.pytorch.org/whl/cu128` (docs/install.md). Only torch is looked up there
# (its own requirements come from the lock); an index pip cannot reach is skipped with a warning, and PyPI's (or a
# local wheel's) torch of the locked version is installed.
TORCH_INDEX ?= https://download.pytorch.org/whl/cpu
# Python writes each module's bytecode the first time it imports it, once for all later processes (the tests start
# about a hundred): where the environment sets PYTHONDONTWRITEBYTECODE, every process would compile torch again
# (9 s to import it instead of 4 on the 2-core EPYC), and compiling all of .venv up front takes 37 s
unexport PYTHONDONTWRITEBYTECODE
PIP_INSTALL := $(PIP) install -q --no-compile
STAMP := $(VENV)/.installed
# moshi for the moshi backend's tests, beside the environment rather than in it: moshi 0.2.13 requires torch<2.10
# and numpy<2.3, which the lock does not meet (docs/install.md, "Moshi"); only `make test` puts it on the path
MOSHI_OVERLAY := $(VENV)/moshi-overlay
# two workers, one per core; a module's tests stay on one worker, so its module fixtures run once
PYTEST_ARGS ?= -m "not slow" -n 2 --dist loadfile

.PHONY: setup demo test test-all bench lock clean

setup: $(STAMP)

$(STAMP): pyproject.toml requirements.lock requirements-test.lock requirements-nodeps.txt scripts/install_system.sh
	bash scripts/install_system.sh
	test -x $(PY) || python3 -m venv $(VENV)
	$(PIP_INSTALL) --no-deps --retries 2 --extra-index-url $(TORCH_INDEX) $$(grep '^torch==' requirements.lock)
	$(PIP_INSTALL) -r requirements.lock -r requirements-test.lock
	$(PIP_INSTALL) --no-deps --no-build-isolation -e .
	$(PIP) check
	$(PIP_INSTALL) --no-deps --upgrade --target $(MOSHI_OVERLAY) -r requirements-nodeps.txt
	touch $@

demo: setup
	mkdir -p out
	OPENBLAS_NUM_THREADS=1 $(VENV)/bin/ecas --headless --mp4 out/demo.mp4 --report out/demo-report

test: setup
	$(VENV)/bin/ruff format --check .
	$(VENV)/bin/ruff check .
	OPENBLAS_NUM_THREADS=1 PYTHONPATH=$(MOSHI_OVERLAY) $(PY) -m pytest $(PYTEST_ARGS); \
		echo $$? > .pytest-exit; exit $$(cat .pytest-exit)

test-all: PYTEST_ARGS =
test-all: test

bench: setup
	$(VENV)/bin/ecas bench bus --json

# Resolve pyproject.toml afresh in a clean environment and pin what it installs (torch as its public version, so
# TORCH_INDEX still chooses the build). Run it after changing the dependencies; commit both lock files.
LOCK_VENV := .venv-lock
lock:
	rm -rf $(LOCK_VENV)
	python3 -m venv $(LOCK_VENV)
	$(LOCK_VENV)/bin/pip install -q --extra-index-url $(TORCH_INDEX) "torch==$$(sed -n 's/^torch==//p' requirements.lock)"
	$(LOCK_VENV)/bin/pip install -q --extra-index-url $(TORCH_INDEX) .
	(echo "# make lock: the runtime requirements of pyproject.toml, resolved in a clean environment"; \
	 $(LOCK_VENV)/bin/pip freeze --all --exclude embodied-agent --exclude pip | sed 's/+[a-z0-9.]*$$//') > requirements.lock
	$(LOCK_VENV)/bin/pip install -q --extra-index-url $(TORCH_INDEX) -c requirements.lock ".[test]"
	(echo "# make lock: what the test extra adds to requirements.lock"; \
	 $(LOCK_VENV)/bin/pip freeze --all --exclude embodied-agent --exclude pip | grep -vxFf requirements.lock) \
	 > requirements-test.lock
	$(LOCK_VENV)/bin/pip check
	rm -rf $(LOCK_VENV) build

clean:
	rm -rf $(VENV) runs out .pytest-exit build
	find . -path ./$(VENV) -prune -o -name __pycache__ -type d -exec rm -rf {} +
