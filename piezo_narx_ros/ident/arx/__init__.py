"""ARX baseline family: the linear model (model.py) and its C emitter (export.py)."""
