# codedvideo: thin make targets over the CLI.  `make run` and `make test` do all set-up.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
CLI    := $(BIN)/codedvideo
STAMP  := $(VENV)/.installed
CONFIG ?= pipeline.yaml
# processes the test suite is shared among (pytest-xdist; 0: the tests run in this one)
TEST_WORKERS ?= 2

.PHONY: help setup run test wheel-check lower-bounds docs bench report train train-config simulate reconstruct submit clean

help:  ## list the targets
	@grep -E '^[a-z-]+:.*## ' $(MAKEFILE_LIST) | sed 's/:.*## /\t/'

CONSTRAINTS := constraints.txt

$(STAMP): pyproject.toml $(CONSTRAINTS)
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -c $(CONSTRAINTS) -e '.[test]'
	touch $(STAMP)

setup: $(STAMP)  ## create .venv and install the project (the versions in constraints.txt)

run: $(STAMP)  ## run the whole pipeline on the embedded default scene
	$(CLI) run "$(CONFIG)"

test: $(STAMP)  ## run the test suite (TEST_WORKERS=2 processes; TEST_WORKERS=0: one)
	$(BIN)/python -m pytest -q -n $(TEST_WORKERS)

DOCS_STAMP := $(VENV)/.docs-installed
$(DOCS_STAMP): $(STAMP) pyproject.toml $(CONSTRAINTS)
	$(BIN)/python -m pip install --quiet -c $(CONSTRAINTS) -e '.[test,docs]'
	touch $(DOCS_STAMP)

docs: $(DOCS_STAMP)  ## the documentation with its API reference, from the docstrings: build/docs/index.html
	sed -e 's#](docs/#](#g' -e 's#\[examples/\](examples/)#`examples/`#' README.md > docs/index.md
	$(BIN)/python -m codedvideo.app.reference > docs/reference.md
	$(BIN)/mkdocs build --strict

wheel-check:  ## build the wheel, install it into a fresh venv, run the CLI and the API from an empty folder
	tasks/check_wheel.sh $(PYTHON)

lower-bounds:  ## install every dependency at its lower bound in pyproject.toml (a fresh venv) and run the core tests
	tasks/check_lower_bounds.sh $(PYTHON)

bench: $(STAMP)  ## time reconstruction against GAP-TV and a matrix multiply (CASES=sequence,footage: some cases)
	$(BIN)/python tasks/bench.py $(if $(CASES),--cases $(CASES))

report: $(STAMP)  ## the paper's experiments and error against run time: out/report/report.html (+ .csv)
	$(CLI) report "$(CONFIG)"

train: $(STAMP)  ## regenerate the shipped dictionaries (src/codedvideo/data) and their data_manifest rows
	$(BIN)/python tasks/train.py --shipped

train-config: $(STAMP)  ## train (or reuse) the dictionary pipeline.yaml describes
	$(BIN)/python tasks/train.py "$(CONFIG)"

simulate: $(STAMP)  ## simulate the coded capture pipeline.yaml describes
	$(BIN)/python tasks/simulate.py "$(CONFIG)"

reconstruct: $(STAMP)  ## reconstruct (trains/simulates first if needed)
	$(BIN)/python tasks/reconstruct.py "$(CONFIG)"

submit: $(STAMP)  ## run pipeline.yaml on a dask.distributed scheduler: make submit SCHEDULER=tcp://host:8786
	$(BIN)/python tasks/submit.py "$(CONFIG)" $(SCHEDULER)

clean:  ## remove the outputs and the default cache (the user's cache folder, where runs keep it; not .venv)
	rm -rf out
	test ! -x $(BIN)/codedvideo || $(BIN)/codedvideo cache clean
