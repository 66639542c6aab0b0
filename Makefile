# Two-command quick start: `make demo` and `make test`. Both bootstrap everything they need
# (virtualenv, pinned packages, a usable libLLVM) and skip what is already done.
SHELL := /bin/bash
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.ngp-mi-installed

.PHONY: setup demo test test-slow bench doctor clean

setup: $(STAMP)
	@scripts/ensure-libllvm.sh $(PY)

# Re-install only when the dependency list changes (the package itself is installed editable).
$(STAMP): pyproject.toml
	@test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --disable-pip-version-check -e '.[test]'
	@touch $@

demo: setup
	$(VENV)/bin/ngp-mi demo

test: setup
	@scripts/ensure-chromium.sh
	$(PY) -m pytest -q

test-slow: setup
	@scripts/ensure-chromium.sh
	$(PY) -m pytest -q -m slow

bench: setup
	@# experiments that need runs or data as arguments say "make bench: skip" on their first line
	@for script in bench/bench_*.py; do head -1 $$script | grep -q "make bench: skip" && continue; \
		echo "== $$script"; $(PY) $$script || exit 1; done

doctor: setup
	$(VENV)/bin/ngp-mi doctor

clean:
	rm -rf $(VENV) outputs .pytest_cache
