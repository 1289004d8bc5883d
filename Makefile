# Two commands do all set-up: `make demo` (the main job on data/sample) and `make test`.
VENV ?= .venv
PY := $(VENV)/bin/python
OUT ?= out/sample

.PHONY: setup demo test lint bench clean

setup:
	@bash scripts/setup.sh

demo: setup
	$(VENV)/bin/turntable reconstruct data/sample/images --r-outer 80 --r-inner 50 --stroke 3 --out $(OUT)

test: setup lint
	$(PY) -m pytest -q

lint: setup
	$(VENV)/bin/ruff check .
	$(VENV)/bin/mypy calib recon

bench: setup
	for b in benchmarks/*.py; do $(PY) $$b || exit 1; done

clean:
	rm -rf out .pytest_cache
