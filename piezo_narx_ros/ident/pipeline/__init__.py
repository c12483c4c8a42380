"""
The fit pipeline: load -> check and warn -> fit -> select -> save -> report.

`fit.run_fit` is the one entry point `piezo-narx fit` (and through it the demo and the
benchmarks) calls; `settings` merges a preset, a settings file and overrides into an
ExperimentConfig; `fleet` fits each recording on its own. The command line only parses its
arguments into a `FitJob` and prints the outcome.
"""
