"""
The model families the package knows, by their model-file `kind`.

Each family registers its own class (`base.register_family`) when its module is imported; this
module imports the package's family modules, so that model_io and the C export can look a kind up
without naming any family. A new family: a module with a registered DynamicModel subclass (its
math, file document, Stepper and C emitter) and its import below.
"""
from . import narx, arx, hysteresis, hysteresis_chains, ensemble  # noqa: F401 - registration
from .base import registered_families

__all__ = ['family', 'kinds', 'registered_families']


def family(kind):
    """Return the model class registered for `kind`, or None."""
    return registered_families().get(kind)


def kinds() -> tuple:
    """Return every registered kind, in registration order."""
    return tuple(registered_families())
