"""
Is the free run's state determined yet? Two brackets that differ only in their unknown past.

A sensorless estimator started from rest does not know the actuator's hysteresis memory: the
actuator may have come to its first command from above or from below, and a model with operator
memory (or slow creep) carries that difference as an offset until the input has swept the range
(which wipes the memory). `MemoryBracket` runs two extra free runs beside the estimate, started
from the two extreme pasts the model admits (family hook `_bracket_states`: for the hysteresis
family, the input having come down from the top of its trained range or up from the bottom; for
the lagged families, rest and the input held at the first command), and reports their spread: an
upper bound on what the unknown past can still change in the estimate. Once the spread falls
below `tolerance` the state is determined and the brackets stop (their cost is two Stepper steps
per sample while they run).
"""
from __future__ import annotations

import math


class MemoryBracket:
    """
    Spread (m) between free runs from the model's extreme pasts, sample by sample.

    tolerance: spread (m) below which the state is taken as determined (default: 0.2 % of the
    trained output span, or 1 nm); confirm: commands the spread must stay below it (two runs
    can cross without having met).
    """

    def __init__(self, model, u0: float, tolerance: float | None = None, confirm: int = 20):
        span = None
        rng = getattr(model, 'output_range', None)
        if rng is not None:
            span = float(rng[1] - rng[0])
        self.tolerance = float(tolerance) if tolerance is not None else \
            max(2e-3 * span if span else 0.0, 1e-9)
        self._steppers = [model.stepper(state=s) for s in model._bracket_states(float(u0))]
        self.spread = math.inf
        self.determined = False
        self._confirm, self._below = max(int(confirm), 1), 0

    def step(self, u: float) -> float:
        """Advance both brackets by one command (V); returns the spread now (m)."""
        if self.determined:
            return self.spread
        a, b = (s.step(u) for s in self._steppers)
        self.spread = abs(a - b)
        self._below = self._below + 1 if self.spread <= self.tolerance else 0
        if self._below >= self._confirm:
            self.determined = True
            self._steppers = []
        return self.spread


def memory_bracket(model, u0: float) -> MemoryBracket | None:
    """
    Return the MemoryBracket of `model` from the first command u0 (V).

    None for a family without brackets (`_bracket_states` missing or not implemented).
    """
    try:
        return MemoryBracket(model, u0)
    except (AttributeError, NotImplementedError):
        return None
