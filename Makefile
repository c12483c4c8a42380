# Two entry points for a fresh machine: `make demo` (main job) and `make test` (test suite).
# Both create the virtual environment at .venv on first use.
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: setup demo test bench soak mutate clean

$(STAMP): requirements.txt setup.py package.xml
	python3 -m venv $(VENV)
	$(PY) -m pip install -q -r requirements.txt
	$(PY) -m pip install -q --no-deps -e .
	touch $(STAMP)

setup: $(STAMP)

demo: setup
	$(VENV)/bin/piezo-narx demo

# The tests that need the machine to themselves (live DDS, timing: conftest.SERIAL_FILES) run
# alone after the others, which share both cores.
test: setup
	$(PY) -m pytest -q -n 2 -m 'not serial' test
	$(PY) -m pytest -q -m serial test

# Benchmarks print figures (speed targets are checked here, not in unit tests).
bench: setup
	$(PY) -m pip install -q -r bench/requirements.txt
	mkdir -p bench/out && rm -f bench/out/results.jsonl
	export PNR_RESULTS=$(CURDIR)/bench/out/results.jsonl; \
	$(PY) bench/bench_simulate.py && \
	$(PY) bench/bench_plant.py && \
	$(PY) bench/bench_grid.py && \
	$(PY) bench/bench_scale.py && \
	$(PY) bench/bench_sysidentpy.py && \
	$(PY) bench/bench_live.py && \
	$(PY) bench/bench_recorder.py && \
	$(PY) bench/bench_control.py && \
	$(PY) bench/bench_export.py && \
	$(PY) bench/bench_envelope.py --presets paper envelope search --reference
	$(PY) bench/write_results.py bench/out/results.jsonl

# 10 minutes of command -> simulator -> estimator -> recorder at 2 kHz with scheduled faults.
soak: setup
	$(PY) bench/bench_soak.py

# Mutation testing of the core modules with their fast tests, one module at a time (CPU-heavy:
# about an hour on the shared 2-core box); the tool comes from requirements-dev.txt, not from
# requirements.txt, so neither `make test` nor CI installs it. Settings: [mutmut] in setup.cfg;
# results in mutants/ (a second run only retests what changed); figures: docs/testing.md.
MUTATE := ident.narx.regressors ident.data.checks ident.validation.correlation \
	ident.validation.metrics ident.validation.noise_model ident.narx.model ident.model_io \
	estimator.free_run bag.pairing nodes.wire.joint_state.x_decode_joint_state \
	nodes.wire.joint_state.x_encode_joint_state

mutate: setup
	$(PY) -m pip install -q -r requirements-dev.txt
	for m in $(MUTATE); do echo "mutating $$m"; $(VENV)/bin/mutmut run "piezo_narx_ros.$$m*" \
		> .mutmut.log 2>&1 || { tail -c 2000 .mutmut.log; exit 1; }; done
	$(PY) bench/mutation_summary.py

clean:
	rm -rf $(VENV) reports mutants .mutmut.log
