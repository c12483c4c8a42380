# Two entry points for a fresh machine: `make demo` (main job) and `make test` (test suite).
# Both create the virtual environment at .venv on first use.
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: setup demo test bench clean

$(STAMP): requirements.txt setup.py package.xml
	python3 -m venv $(VENV)
	$(PY) -m pip install -q -r requirements.txt
	$(PY) -m pip install -q --no-deps -e .
	touch $(STAMP)

setup: $(STAMP)

demo: setup
	$(VENV)/bin/piezo-narx demo

test: setup
	$(PY) -m pytest -q test

clean:
	rm -rf $(VENV) reports
