# The two commands of the README: `make run` and `make test`. Both set up .venv first.
PYTHON ?= python3.11
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: setup run test bench clean

$(STAMP): pyproject.toml
	@command -v $(PYTHON) >/dev/null 2>&1 || { echo "need $(PYTHON) on PATH (Python 3.11+)"; exit 1; }
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

setup: $(STAMP)

## run: set up and run the service with embedded defaults (SQLite, local blobs, an embedded
## worker) on 127.0.0.1:8000 (HTTP) and :50051 (gRPC), data in ./facesynth-data
run: $(STAMP)
	$(BIN)/facesynth serve

## test: set up and run the whole test suite (what .ci/run calls)
test: $(STAMP)
	$(BIN)/python -m pytest -q

## bench: speed and accuracy benchmarks (slow; not part of CI)
bench: $(STAMP)
	$(BIN)/python benchmarks/thin_shell.py
	$(BIN)/python benchmarks/pdm_report.py

clean:
	rm -rf $(VENV) .pytest_cache build *.egg-info
