# The two entry points of the README. Both create .venv and install femcal into it first.
VENV ?= .venv
export PATH := $(abspath $(VENV))/bin:$(PATH)

.PHONY: repro test test-slow lint install lock remote docs
install: $(VENV)/.installed  ## also installs CalculiX (ccx, the open FE solver) when missing
	command -v ccx >/dev/null || { sudo=$$([ "$$(id -u)" -eq 0 ] || echo sudo); \
	  $$sudo apt-get update -qq && $$sudo apt-get install -y -qq calculix-ccx; }

$(VENV)/.installed: pyproject.toml constraints.txt  ## the versions pinned in constraints.txt
	python3 -m venv $(VENV)
	$(VENV)/bin/pip install --quiet --upgrade pip
	$(VENV)/bin/pip install --quiet -c constraints.txt -e ".[dev]"
	touch $@

repro: install  ## fetch the data, train, evaluate: the whole pipeline
	dvc repro

# `make test` shares the tests over one process per core (pytest-xdist), each test file on one
# process (--dist loadfile: a file's fixtures are built once), each process on one thread.
test: install  ## the test suite without the slow tests (pyproject.toml's addopts: -m 'not slow')
	OMP_NUM_THREADS=1 pytest -n auto --dist loadfile $(PYTEST_ARGS)

test-slow: install  ## only the slow tests: the whole pipelines (dvc repro) and the FE runs
	pytest -m slow $(PYTEST_ARGS)

lint: install
	ruff check src tests experiments
	ruff format --check src tests experiments

# The docs site (mkdocs.yml, docs/): the tutorial's figures from the pipeline's outputs (absent
# on a fresh clone: the script says so and the pages build without them; FIGURES_ARGS=--require
# makes their absence an error), then the strict build into site/. `mkdocs serve` previews it at
# http://127.0.0.1:8000.
docs: install
	python docs/scripts/tutorial_figures.py $(FIGURES_ARGS)
	NO_MKDOCS_2_WARNING=1 mkdocs build --strict

# constraints.txt: every package of the working venv at its exact version (femcal itself left
# out), which `make install` installs. To move to newer versions: `.venv/bin/pip install
# --upgrade -e ".[dev]"`, run the tests, then `make lock` and commit constraints.txt. torch
# stays the CPU build of pyproject.toml's version (torch==X, never a +cpu local label or CUDA).
lock:
	@test -x $(VENV)/bin/pip || { echo "make lock: no $(VENV); run make install first" >&2; exit 1; }
	@{ echo "# femcal's pinned dependencies: make install uses them (pip install -c constraints.txt)."; \
	  echo "# Regenerated from the working venv by 'make lock'; see the Makefile."; \
	  $(VENV)/bin/pip freeze --exclude-editable | grep -v -i -E '^(femcal|-e |#)' \
	    | sed -E 's/^(torch==[^+]*)\+cpu$$/\1/'; } > constraints.txt.tmp
	@if grep -i -q -E '^(nvidia-|triton|cuda)' constraints.txt.tmp; then \
	  rm -f constraints.txt.tmp; \
	  echo "make lock: the venv holds CUDA packages (nvidia-*, triton): reinstall the CPU torch" \
	    "of pyproject.toml, then make lock again" >&2; exit 1; fi
	@mv constraints.txt.tmp constraints.txt
	@echo "constraints.txt: $$(grep -c -v '^#' constraints.txt) packages pinned"

# A local-folder DVC remote as the project's default (a shared disk, a mounted drive):
# `make remote DIR=/shared/femcal-dvc`, then `dvc push`; commit .dvc/config so that a
# teammate's clone pulls from it (`dvc pull`). Running it again points the remote elsewhere.
remote:
	@test -n "$(DIR)" || { echo "make remote: give the folder: make remote DIR=/shared/femcal-dvc" >&2; exit 1; }
	@command -v dvc >/dev/null || { echo "make remote: dvc not found; run make install first" >&2; exit 1; }
	mkdir -p "$(abspath $(DIR))"
	dvc remote add --default --force team "$(abspath $(DIR))"
	@echo "DVC remote 'team' (default): $(abspath $(DIR)); commit .dvc/config, then dvc push"
