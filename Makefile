# ManiEval: `make demo` runs the service on embedded defaults, `make test` runs every check.
# Both install what is missing first and are fast the second time.
SHELL := /bin/bash
VENV := .venv
BIN := $(VENV)/bin
INSTALLED := $(VENV)/.installed

.PHONY: demo test lint system base-image install install-evaluator bench clean

system:
	@scripts/system-deps.sh

$(INSTALLED): pyproject.toml evaluator/sdk/pyproject.toml constraints.txt scripts/install-python.sh
	@echo "Installing Python packages into $(VENV) (first time: a few minutes)"
	@scripts/install-python.sh $(VENV)
	@touch $@

# The base image participants' policies build on, localhost/manieval-base:bookworm: the demo's
# `manieval push` path and the container tests use it. docker/policy-base/build.sh needs root
# and about a minute the first time, then does nothing while the image exists.
base-image: system
	@if [ "$$(id -u)" = 0 ]; then \
	  CONTAINERS_CONF=$(CURDIR)/docker/containers.conf docker/policy-base/build.sh; \
	else \
	  echo "The policy base image needs root: sudo docker/policy-base/build.sh (once)"; \
	fi

install: system $(INSTALLED) base-image

# What `manieval evaluate` needs and no more: a participant scoring a policy locally (the
# getting-started page's step 5). The simulator's system packages and ManiEval without the
# service's and the tests' tools; `make install` later adds those.
EVALUATOR_INSTALLED := $(VENV)/.evaluator-installed

$(EVALUATOR_INSTALLED): pyproject.toml evaluator/sdk/pyproject.toml constraints.txt scripts/install-python.sh
	@echo "Installing ManiEval's evaluator into $(VENV) (first time: a few minutes)"
	@scripts/install-python.sh $(VENV) ''
	@touch $@

install-evaluator:
	@scripts/system-deps.sh --evaluator
	@$(MAKE) --no-print-directory $(if $(wildcard $(INSTALLED)),$(INSTALLED),$(EVALUATOR_INSTALLED))

lint: install
	$(BIN)/ruff format --check .
	$(BIN)/ruff check .
	$(BIN)/mypy
	$(BIN)/lint-imports --no-cache

# The suite in parallel workers: most of its slow tests wait (on a server, a container, a database
# coming back) rather than compute, so more workers than cores pay. Each worker has its own
# databases, ports and data directories, and takes whole modules (their fixtures built once),
# the `long` ones first. `make test TEST_WORKERS=0` runs it in one process.
TEST_WORKERS ?= 4

test: lint
	$(BIN)/pytest -n $(TEST_WORKERS) --dist loadscope --no-loadscope-reorder --durations=30

demo: install
	$(BIN)/manieval demo

bench: install
	$(BIN)/python bench/protocol_overhead.py

clean:
	rm -rf $(VENV) .pytest_cache .mypy_cache .ruff_cache
