# Two commands do all the set-up: `make demo` and `make test` (README.md).
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: venv test lint demo figure bench clean

venv: $(STAMP)

# torch is pinned first: 2.13.0 is the CPU build on this disk; a bare `torch` would pull CUDA.
$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q torch==2.13.0
	$(BIN)/pip install -q -e '.[datagen,train,ray,viz,dev]'
	touch $(STAMP)

lint: venv
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

test: lint
	$(BIN)/pytest

# The dataset goes to data/shards/ (datagen build's default; data/README.md explains why).
demo: venv
	$(BIN)/datagen build --towns 2 --frames 200 --workers 2 --force
	$(BIN)/datagen inspect data --frame 10 --out runs/demo/frame.png
	$(BIN)/datagen inspect data --video runs/demo/episode.mp4 --speed 4
	$(BIN)/train fit --shards data --config tiny --epochs 1 --out runs/demo --force
	$(BIN)/train show --ckpt runs/demo/last.pt --shards data --frame 10 --out runs/demo/show.png

# The README's picture (docs/inspect.png) and the video it links to: one 360-frame episode
# (about a minute to build), its frame 312 and the whole episode at 4x (8 fps).
FIGURE := runs/figure
FIGURE_EPISODE := downtown-5-0000
figure: venv
	$(BIN)/datagen build --town downtown --frames 360 --weather-mix sunny=1 --seed 5 --workers 1 --out $(FIGURE)/data --force
	$(BIN)/datagen inspect $(FIGURE)/data --episode $(FIGURE_EPISODE) --frame 312 --out docs/inspect.png
	$(BIN)/datagen inspect $(FIGURE)/data --episode $(FIGURE_EPISODE) --video $(FIGURE)/episode.mp4 --speed 4
	$(BIN)/datagen inspect $(FIGURE)/data --episode $(FIGURE_EPISODE) --rerun $(FIGURE)/episode.rrd

bench: venv
	$(BIN)/python bench/frame.py
	$(BIN)/python bench/sim.py
	$(BIN)/python bench/build.py
	$(BIN)/python bench/train.py
	$(BIN)/python bench/drive.py

clean:
	rm -rf $(VENV) runs
