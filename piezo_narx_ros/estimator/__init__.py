"""estimator subpackage."""
