# FreeScale: the two commands a new user types first are `make run` and `make test`.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV   ?= .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed
PRESET ?= fast
STORE  ?= data/sample-store
# pinned versions of every dependency (see the file's header); `make install CONSTRAINTS=` ignores it
CONSTRAINTS ?= constraints.txt
export PREFECT_SERVER_ANALYTICS_ENABLED ?= false
# no telemetry notice or reporting from Prefect (or any tool honouring DO_NOT_TRACK)
export DO_NOT_TRACK ?= 1

.PHONY: install run test serve bench clean

$(STAMP): pyproject.toml $(CONSTRAINTS)
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install -q $(if $(CONSTRAINTS),-c $(CONSTRAINTS)) -e '.[dev]'
	touch $(STAMP)

install: $(STAMP)

## make run: write the embedded sample scene, run generate-dataset on it (progress, then the
## manifest), write the store's HTML report
run: install
	$(BIN)/freescale sample-scene data/sample-scene
	$(BIN)/freescale run data/sample-scene --store $(STORE) --preset $(PRESET)
	$(BIN)/freescale report $(STORE)

## make test: the whole test suite (CPU only; real-scene tests skip when ../shared/datasets is absent)
test: install
	$(BIN)/python -m pytest -q

## make serve: local Prefect server on 127.0.0.1:$${PREFECT_PORT:-4200} + the served deployments
serve: install
	$(BIN)/freescale serve

## make bench: the benchmark tables (full-size runs; minutes)
bench: install
	$(BIN)/python -m benchmarks.selection
	$(BIN)/python -m benchmarks.rasterizer
	$(BIN)/python -m benchmarks.fidelity

clean:
	rm -rf data/sample-scene data/sample-store .pytest_cache
