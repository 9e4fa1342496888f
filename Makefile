# The two commands of the README: `make run` and `make test`. Both set up .venv first.
PYTHON ?= python3.11
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: setup run test bench demo clean constraints

# every dependency at the version in constraints.txt (the tested set; `make constraints`)
$(STAMP): pyproject.toml clients/python/pyproject.toml constraints.txt
	@command -v $(PYTHON) >/dev/null 2>&1 || { echo "need $(PYTHON) on PATH (Python 3.11+)"; exit 1; }
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -c constraints.txt -e '.[dev]'
	$(BIN)/python -m pip install --quiet -c constraints.txt -e './clients/python[grpc]'
	touch $(STAMP)

setup: $(STAMP)

## run: set up and run the service with embedded defaults (SQLite, local blobs, an embedded
## worker) on 127.0.0.1:8000 (HTTP) and :50051 (gRPC), data in ./facesynth-data
run: $(STAMP)
	$(BIN)/facesynth serve

## test: set up and run the whole test suite (what .ci/run calls)
test: $(STAMP)
	$(BIN)/python -m pytest -q

## demo: set up and run the whole story against an embedded server (README quickstart):
## sample actor, upload, train a PDM, synthesize a held-out performance; results in
## ./facesynth-demo (meshes, EXR maps, side_by_side.png)
demo: $(STAMP)
	$(BIN)/facesynth demo --out facesynth-demo

## bench: speed and accuracy benchmarks (slow; not part of CI)
bench: $(STAMP)
	$(BIN)/python benchmarks/thin_shell.py
	$(BIN)/python benchmarks/pdm_report.py
	$(BIN)/python benchmarks/shape_space_report.py
	$(BIN)/python benchmarks/pose_space_report.py benchmarks/out/actor-l1
	$(BIN)/python benchmarks/game_outputs_report.py
	$(BIN)/python benchmarks/correspondence_report.py
	$(BIN)/python benchmarks/generalization_report.py
	$(BIN)/python benchmarks/tracking_report.py
	$(BIN)/python benchmarks/tracking_job.py
	$(BIN)/python benchmarks/load.py
	$(BIN)/python benchmarks/upload_memory.py
	$(BIN)/python benchmarks/realtime.py --profile
	$(BIN)/python benchmarks/cold_start.py
	$(BIN)/python benchmarks/enhance_speed.py

## constraints: rewrite constraints.txt from the versions installed in .venv (after
## changing a dependency in pyproject.toml: install it, then run this)
constraints: $(STAMP)
	$(BIN)/python docker/freeze_constraints.py

clean:
	rm -rf $(VENV) .pytest_cache build *.egg-info
