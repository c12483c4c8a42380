"""Choosing a model: the identification experiment (grid, scoring, rules) and its executors."""
