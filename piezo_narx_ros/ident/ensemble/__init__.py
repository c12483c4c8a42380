"""Ensembles of fitted models (the mean of their free runs) and their C emitter."""
