# Two commands do all the set-up: `make demo` and `make test` (README.md).
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: venv test lint demo bench clean

venv: $(STAMP)

# torch is pinned first: 2.13.0 is the CPU build on this disk; a bare `torch` would pull CUDA.
$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q torch==2.13.0
	$(BIN)/pip install -q -e '.[datagen,train,ray,dev]'
	touch $(STAMP)

lint: venv
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

test: lint
	$(BIN)/pytest

demo: venv
	$(BIN)/datagen build --towns 2 --frames 200 --workers 2 --out data --force
	$(BIN)/datagen inspect data --frame 10 --out data/_frame.png
	$(BIN)/train fit --shards data --config tiny --epochs 1 --out runs/demo
	$(BIN)/train show --ckpt runs/demo/last.pt --shards data --frame 10 --out runs/demo/show.png

bench: venv
	$(BIN)/python bench/frame.py
	$(BIN)/python bench/sim.py
	$(BIN)/python bench/build.py
	$(BIN)/python bench/train.py
	$(BIN)/python bench/drive.py

clean:
	rm -rf $(VENV) runs
