# Two commands on a fresh machine: `make run` and `make test`.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
OUT ?= runs/latest
# pytest-xdist workers for `make test` (0: one process): on 2 cores two workers run the
# suite in ~240 s (46th session; tests marked e2e start first: tests/conftest.py)
TEST_WORKERS ?= 2

.PHONY: venv run test lint clean

venv: $(STAMP)

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test]'
	@echo "compiling the numba kernels once: a 20 s simulated flight (log: $(VENV)/warmup.log)"
	$(BIN)/collabslam run --world bshape --robots 3 --max-sim-time 20 \
		--set exploration.enabled=false --out $(VENV)/warmup > $(VENV)/warmup.log 2>&1 \
		|| echo "warm-up failed (see $(VENV)/warmup.log); the first run compiles them instead"
	$(BIN)/python -m collabslam.warmup >> $(VENV)/warmup.log 2>&1 \
		|| echo "kernel warm-up failed (see $(VENV)/warmup.log); the first run compiles them"
	touch $(STAMP)

run: venv
	$(BIN)/collabslam run --world bshape --robots 3 --out $(OUT)

test: venv
	$(BIN)/python -m pytest -n $(TEST_WORKERS) --dist worksteal

lint: venv
	$(BIN)/ruff check .

clean:
	rm -rf $(VENV) runs .pytest_cache
