# The two entry points of the README. Both create .venv and install femcal into it first.
VENV ?= .venv
export PATH := $(abspath $(VENV))/bin:$(PATH)

.PHONY: repro test lint install
install: $(VENV)/.installed  ## also installs CalculiX (ccx, the open FE solver) when missing
	command -v ccx >/dev/null || { sudo=$$([ "$$(id -u)" -eq 0 ] || echo sudo); \
	  $$sudo apt-get update -qq && $$sudo apt-get install -y -qq calculix-ccx; }

$(VENV)/.installed: pyproject.toml
	python3 -m venv $(VENV)
	$(VENV)/bin/pip install --quiet --upgrade pip
	$(VENV)/bin/pip install --quiet -e ".[dev]"
	touch $@

repro: install  ## fetch the data, train, evaluate: the whole pipeline
	dvc repro

test: install  ## the test suite (slow tests excluded; `make test PYTEST_ARGS="-m slow"` for them)
	pytest $(PYTEST_ARGS)

lint: install
	ruff check src tests
