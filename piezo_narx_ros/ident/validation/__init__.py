"""Judging a model: metrics, correlation tests, the noise model and the fit report."""
