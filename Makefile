# Two entry points for a fresh machine: `make demo` (main job) and `make test` (test suite).
# Both create the virtual environment at .venv on first use.
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: setup demo test bench soak clean

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

# Benchmarks print figures (speed targets are checked here, not in unit tests).
bench: setup
	$(PY) -m pip install -q -r bench/requirements.txt
	$(PY) bench/bench_simulate.py
	$(PY) bench/bench_plant.py
	$(PY) bench/bench_grid.py
	$(PY) bench/bench_sysidentpy.py
	$(PY) bench/bench_live.py
	$(PY) bench/bench_recorder.py
	$(PY) bench/bench_control.py
	$(PY) bench/bench_envelope.py --reference

# 10 minutes of command -> simulator -> estimator -> recorder at 2 kHz with scheduled faults.
soak: setup
	$(PY) bench/bench_soak.py

clean:
	rm -rf $(VENV) reports
