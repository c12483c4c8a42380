"""`piezo-narx demo`: record, identify, and run the free-run estimator live (see docs/demo.md)."""
