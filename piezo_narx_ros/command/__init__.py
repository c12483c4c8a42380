"""command subpackage."""
