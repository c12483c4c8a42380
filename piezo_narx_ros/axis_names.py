"""
Axis names: every list of them names each axis once.

Node parameters, plant files, model files and messages alike. Two axes of one name cannot be
told apart anywhere downstream: a message is read by name, so one of them is silently dropped
(issue 45: `axes:=['x','x']` sent two signals named x; the simulator applied one and the
estimator estimated the other).
"""
from __future__ import annotations

from typing import Iterable


def repeated(names: Iterable) -> str | None:
    """Return the first name that appears more than once, else None."""
    seen = set()
    for name in names:
        if name in seen:
            return name
        seen.add(name)
    return None


def distinct_names(names) -> bool:
    """Return True for a non-empty list of non-empty, distinct strings."""
    return (len(names) > 0 and all(isinstance(a, str) and a.strip() for a in names)
            and repeated(names) is None)


# A ParamSpec check for an `axes` parameter (nodes.params).
AXES_CHECK = (distinct_names, 'must be a non-empty list of distinct non-empty names')
