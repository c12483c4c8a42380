"""ident subpackage."""
