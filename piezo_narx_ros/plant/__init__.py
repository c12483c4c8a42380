"""plant subpackage."""
