# codedvideo: thin make targets over the CLI.  `make run` and `make test` do all set-up.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
CLI    := $(BIN)/codedvideo
STAMP  := $(VENV)/.installed
CONFIG ?= pipeline.yaml

.PHONY: help setup run test wheel-check bench report train train-config simulate reconstruct submit clean

help:  ## list the targets
	@grep -E '^[a-z-]+:.*## ' $(MAKEFILE_LIST) | sed 's/:.*## /\t/'

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test]'
	touch $(STAMP)

setup: $(STAMP)  ## create .venv and install the project

run: $(STAMP)  ## run the whole pipeline on the embedded default scene
	$(CLI) run "$(CONFIG)"

test: $(STAMP)  ## run the test suite
	$(BIN)/python -m pytest -q

wheel-check:  ## build the wheel, install it into a fresh venv, run the CLI and the API from an empty folder
	tasks/check_wheel.sh $(PYTHON)

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

clean:  ## remove outputs and caches (not .venv)
	rm -rf out cache
