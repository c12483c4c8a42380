"""
Stepper of the envelope family (HysteresisNARX.stepper).

One compiled call per sample on a preallocated state, for estimator_node and controller_node.
"""
from collections import deque

import numpy as np

from . import kernels as hk
from ..narx.kernels import _finite_input, _history, finite_inputs


class HysteresisStepper:
    """
    Stepper of a HysteresisNARX: step(u_k V) -> y_k m, reset(u_past, y_past).

    One compiled call per step on a preallocated state.
    """

    def __init__(self, model, u_past=None, y_past=None):
        self._model = model
        self.nu, self.ny = model.nu, model.ny
        self._args = model._kernel_args
        self._u_scale, self._y_scale = model.u_scale_, model.y_scale_
        self.reset(u_past, y_past)
        self._scratch = np.zeros(self._st.size)

    #: Added to every output (m): the sensor offset of a ModelState (estimate_state).
    offset = 0.0

    def set_state(self, state):
        """Continue from a ModelState (estimate_state): its state vector and offset (m)."""
        values = self._model._check_state(state)
        self._st = values
        self.offset = float(state.offset)
        m = self._model
        lh = max(m.n_lags, 1)
        v = values[:lh][::-1] * self._u_scale                   # drive, oldest first
        yl = values[values.size - m.na:][::-1] if m.na else np.zeros(0)
        y = (yl + self._args[-1]) * self._y_scale + self.offset
        self._u_hist = deque(v[v.size - self.nu:], maxlen=self.nu)   # nu = n_lags <= lh
        self._y_hist = deque(y[-self.ny:] if self.ny else [], maxlen=self.ny)

    @property
    def state(self):
        """Return the current ModelState (the kernel state vector, normalised; the offset)."""
        from ..state.estimate import ModelState
        return ModelState(self._st.copy(), self.offset)

    def reset(self, u_past=None, y_past=None):
        """Restart from rest, then u_past (V, nu samples); y_past (m) as in stepper()."""
        up = _history(u_past, self.nu, 'u_past') if u_past is not None else None
        yp = _history(y_past, self.ny, 'y_past') if y_past is not None else None
        self._st = self._model._initial_state(up, yp)
        self._u_hist = deque(np.zeros(self.nu) if up is None else up, maxlen=self.nu)
        self._y_hist = deque(np.zeros(self.ny) if yp is None else yp, maxlen=self.ny)

    def step(self, u_k):
        """
        Feed one input sample u_k (V); returns the free-run output y(k) (m).

        A non-finite u_k raises DataError and leaves the state untouched.
        """
        u = _finite_input(u_k)
        y = hk.step(u / self._u_scale, self._st, *self._args) * self._y_scale + self.offset
        self._u_hist.append(u)
        self._y_hist.append(y)
        return y

    def step_many(self, u):
        """
        Feed the inputs u (n,) V in order; returns the free-run outputs y (n,) m.

        The same numbers as n step() calls, in one compiled call. A non-finite input raises
        DataError before any step: the state stays untouched.
        """
        return self.step_many_checked(finite_inputs(u))

    def step_many_checked(self, u: np.ndarray) -> np.ndarray:
        """step_many of inputs already checked: u a contiguous finite (n,) float64 array, V."""
        yn = np.empty(u.size)
        hk.step_many(u / self._u_scale, yn, self._st, *self._args)
        y = yn * self._y_scale + self.offset
        self._u_hist.extend(u[u.size - self.nu:].tolist() if self.nu else ())
        self._y_hist.extend(y[y.size - self.ny:].tolist() if self.ny else ())
        return y

    def peek(self, u_k):
        """Return the output step(u_k) would return (m), without changing the state."""
        return hk.peek(_finite_input(u_k) / self._u_scale, self._st, self._scratch,
                       *self._args) * self._y_scale + self.offset

    @property
    def kernel_state(self):
        """
        Return the live state array the compiled step advances and the kernel parameters.

        Normalised units, layout in hysteresis.kernels; for compiled code that evaluates candidate
        inputs without committing them (control/kernels.py). Read, never write.
        """
        return (self._st,), self._args

    @property
    def u_past(self):
        """Copy of the last nu inputs [u(k-nu) ... u(k-1)], V."""
        return np.array(self._u_hist, dtype=np.float64)

    @property
    def y_past(self):
        """Copy of the last ny outputs [y(k-ny) ... y(k-1)], m."""
        return np.array(self._y_hist, dtype=np.float64)
