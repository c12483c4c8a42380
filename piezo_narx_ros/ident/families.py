"""
The model families the package knows, by their model-file `kind`.

Each family registers its own class (`base.register_family`) when its module is imported; this
module imports the package's family modules, so that model_io and the C export can look a kind up
without naming any family. A new family: a module with a registered DynamicModel subclass (its
math, file document, Stepper and C emitter) and its import below.
"""
# Importing a family's module registers it; the order here is the registration order.
from .narx import model as _narx  # noqa: F401
from .arx import model as _arx  # noqa: F401
from .hysteresis import model as _hysteresis, chains as _chains  # noqa: F401
from .ensemble import model as _ensemble  # noqa: F401
from .base import registered_families

__all__ = ['family', 'kinds', 'registered_families']


def family(kind):
    """Return the model class registered for `kind`, or None."""
    return registered_families().get(kind)


def kinds() -> tuple:
    """Return every registered kind, in registration order."""
    return tuple(registered_families())
