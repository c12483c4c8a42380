"""
Exceptions that carry a one-line, user-facing message.

The command line prints `piezo-narx: error: <message>` for any of these and exits non-zero, so the
message must name the problem (file, field, value) on its own.
"""


class PiezoNarxError(Exception):
    """Base class of every error the project reports to a user in one line."""


class DataError(PiezoNarxError):
    """Input data missing, malformed, or unusable (NaN, too short, wrong columns, fs mismatch)."""


class ModelFileError(PiezoNarxError):
    """A model file is missing, malformed, truncated or of an incompatible format version."""


class BagError(PiezoNarxError):
    """A bag is missing, truncated, empty, or lacks the expected topics or message types."""


class ConfigError(PiezoNarxError):
    """A parameter or configuration value is invalid."""
