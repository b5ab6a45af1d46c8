# Each target sets itself up on a fresh machine that has only Python 3.11 and pip.
PYTHON ?= python3.11
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: run test venv data bench gallery wheel clean

$(STAMP): pyproject.toml setup.py
	@command -v $(PYTHON) >/dev/null 2>&1 || { echo "error: $(PYTHON) not found; install Python 3.11 or run 'make PYTHON=python3 ...'" >&2; exit 2; }
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e '.[test]'
	@# compile the simulator's kernels into numba's on-disk cache now, not in a user's first run (~1 min)
	$(BIN)/python -m ptrack warmup --quiet
	@touch $(STAMP)

venv: $(STAMP)

# The main job: the shipped synthetic data in data/synthetic/ analysed end to end.
run: $(STAMP)
	$(BIN)/python -m ptrack.mainjob

test: $(STAMP)
	$(BIN)/python -m pytest -q tests

# Regenerate data/synthetic/ (deterministic: fixed seeds).
data: $(STAMP)
	$(BIN)/python -m sim.render.datasets --out data/synthetic

bench: $(STAMP)
	@for f in bench/bench_*.py; do echo "== $$f"; $(BIN)/python $$f || exit $$?; done

# Every analysis and deposition figure in out/gallery/, to judge them by eye.
gallery: $(STAMP)
	$(BIN)/python bench/plots_gallery.py out/gallery

# A non-editable wheel (ships scenes/ and data/synthetic/ as package data) in dist/.
wheel: $(STAMP)
	$(BIN)/pip wheel --quiet --no-deps -w dist .

clean:
	rm -rf $(VENV) build dist *.egg-info
