"""
Compiled free-run kernels and the per-sample Stepper (numpy + numba only, never torch).

The models hand these kernels their weights "folded" into raw units (V in, m out) and ordered in
time, so one evaluation reads a contiguous window of the input and output histories:

    NARX: y(k) = b2 + sum_h w2[h] * sigmoid(b1[h] + Wu[h] . u[k-nu .. k] + Wy[h] . y[k-ny .. k-1])
    ARX:  y(k) = c  + bu . u[k-nu .. k] + ay . y[k-ny .. k-1]

``simulate`` and ``Stepper.step`` call the same evaluation function on the same window layout, so
the two agree to rounding (in practice bit for bit).
"""
import math

import numpy as np
from numba import njit

from ..errors import DataError


@njit(cache=True)
def _narx_eval(u, iu, y, iy, Wu, Wy, b1, w2, b2):
    """One NARX output from u[iu : iu+nu+1] and y[iy : iy+ny] (time order)."""
    H = Wu.shape[0]
    nu1 = Wu.shape[1]
    ny = Wy.shape[1]
    out = b2
    for h in range(H):
        z = b1[h]
        for i in range(nu1):
            z += Wu[h, i] * u[iu + i]
        for j in range(ny):
            z += Wy[h, j] * y[iy + j]
        out += w2[h] / (1.0 + np.exp(-z))
    return out


@njit(cache=True)
def narx_simulate(u, y, start, Wu, Wy, b1, w2, b2):
    """Free-run in place: fill y[start:] from u and y's own past (y[:start] given). u, y: (N,)."""
    nu1 = Wu.shape[1]
    ny = Wy.shape[1]
    for k in range(start, u.size):
        y[k] = _narx_eval(u, k - nu1 + 1, y, k - ny, Wu, Wy, b1, w2, b2)


@njit(cache=True)
def narx_predict(u, y, start, Wu, Wy, b1, w2, b2):
    """One-step-ahead outputs (N,) for k >= start from measured u, y (N,); [:start] = y[:start]."""
    nu1 = Wu.shape[1]
    ny = Wy.shape[1]
    out = y.copy()
    for k in range(start, u.size):
        out[k] = _narx_eval(u, k - nu1 + 1, y, k - ny, Wu, Wy, b1, w2, b2)
    return out


@njit(cache=True)
def narx_step(u_k, ubuf, ybuf, Wu, Wy, b1, w2, b2):
    """Shift u_k into ubuf (nu+1,), evaluate y(k), shift it into ybuf (ny,); returns y(k) in m."""
    for i in range(ubuf.size - 1):
        ubuf[i] = ubuf[i + 1]
    ubuf[ubuf.size - 1] = u_k
    y_k = _narx_eval(ubuf, 0, ybuf, 0, Wu, Wy, b1, w2, b2)
    for j in range(ybuf.size - 1):
        ybuf[j] = ybuf[j + 1]
    ybuf[ybuf.size - 1] = y_k
    return y_k


@njit(cache=True)
def narx_peek(u_k, ubuf, ybuf, scratch, Wu, Wy, b1, w2, b2):
    """
    Return y(k) (m) that narx_step would return for u_k (V), leaving ubuf and ybuf untouched.

    Scratch: (nu+1,) work array. For solvers that try candidate inputs (control/).
    """
    for i in range(ubuf.size - 1):
        scratch[i] = ubuf[i + 1]
    scratch[ubuf.size - 1] = u_k
    return _narx_eval(scratch, 0, ybuf, 0, Wu, Wy, b1, w2, b2)


@njit(cache=True)
def _arx_eval(u, iu, y, iy, bu, ay, c):
    """One ARX output from u[iu : iu+nu+1] and y[iy : iy+ny] (time order)."""
    out = c
    for i in range(bu.size):
        out += bu[i] * u[iu + i]
    for j in range(ay.size):
        out += ay[j] * y[iy + j]
    return out


@njit(cache=True)
def arx_simulate(u, y, start, bu, ay, c):
    """Free-run in place: fill y[start:] from u and y's own past (y[:start] given)."""
    nu1 = bu.size
    ny = ay.size
    for k in range(start, u.size):
        y[k] = _arx_eval(u, k - nu1 + 1, y, k - ny, bu, ay, c)


@njit(cache=True)
def arx_predict(u, y, start, bu, ay, c):
    """One-step-ahead outputs (N,) for k >= start from measured u, y (N,); [:start] = y[:start]."""
    out = y.copy()
    for k in range(start, u.size):
        out[k] = _arx_eval(u, k - bu.size + 1, y, k - ay.size, bu, ay, c)
    return out


@njit(cache=True)
def arx_step(u_k, ubuf, ybuf, bu, ay, c):
    """Shift u_k into ubuf, evaluate y(k), shift it into ybuf; returns y(k)."""
    for i in range(ubuf.size - 1):
        ubuf[i] = ubuf[i + 1]
    ubuf[ubuf.size - 1] = u_k
    y_k = _arx_eval(ubuf, 0, ybuf, 0, bu, ay, c)
    for j in range(ybuf.size - 1):
        ybuf[j] = ybuf[j + 1]
    ybuf[ybuf.size - 1] = y_k
    return y_k


@njit(cache=True)
def arx_peek(u_k, ubuf, ybuf, scratch, bu, ay, c):
    """y(k) that arx_step would return for u_k, leaving ubuf and ybuf untouched."""
    for i in range(ubuf.size - 1):
        scratch[i] = ubuf[i + 1]
    scratch[ubuf.size - 1] = u_k
    return _arx_eval(scratch, 0, ybuf, 0, bu, ay, c)


def _history(x, n, name):
    """Validate an (n,) float64 history; None means rest (zeros)."""
    if x is None:
        return np.zeros(n)
    try:
        a = np.array(x, dtype=np.float64).ravel()
    except (TypeError, ValueError):
        raise DataError(f'{name} must be an array of numbers') from None
    if a.size != n:
        raise DataError(f'{name} must hold {n} samples, got {a.size}')
    if not np.all(np.isfinite(a)):
        raise DataError(f'{name} contains NaN or infinite values')
    return a


class Stepper:
    """
    Free-run a model one sample at a time (the estimator's inner loop).

    ``u_past`` holds ``[u(k-nu) ... u(k-1)]`` and ``y_past`` ``[y(k-ny) ... y(k-1)]`` in time order
    (None = rest, zeros). ``step(u_k)`` returns the model output y(k) in m for the new input u_k
    in V and shifts both histories. No array is allocated per step.
    """

    #: Added to every output (m): the sensor offset of a ModelState (estimate_state).
    offset = 0.0

    def __init__(self, params, nu, ny, u_past=None, y_past=None):
        self._params = tuple(params)
        self.nu = nu
        self.ny = ny
        self._ubuf = np.zeros(nu + 1)
        self._ybuf = np.zeros(ny)
        self._scratch = np.zeros(nu + 1)
        self.reset(u_past, y_past)

    def reset(self, u_past=None, y_past=None):
        """Restart from the given histories (None = rest; y_past as output, offset included)."""
        self._ubuf[1:] = _history(u_past, self.nu, 'u_past')
        self._ybuf[:] = _history(y_past, self.ny, 'y_past')
        if y_past is not None:
            self._ybuf -= self.offset

    @property
    def y_past(self):
        """Copy of the output history ``[y(k-ny) ... y(k-1)]``, m (as output: offset included)."""
        return self._ybuf + self.offset

    @property
    def state(self):
        """Return the current ModelState (past inputs V and outputs m, and the offset)."""
        from .state import ModelState
        return ModelState(np.r_[self._ubuf[1:], self._ybuf], self.offset)

    @property
    def u_past(self):
        """Copy of the input history ``[u(k-nu) ... u(k-1)]``, V."""
        return self._ubuf[1:].copy()

    @property
    def kernel_state(self):
        """
        Return the live arrays the compiled step advances and the kernel parameters.

        (ubuf (nu+1,) V, ybuf (ny,) m): for compiled code that evaluates candidate inputs without
        committing them (control/kernels.py). Read them, never write them.
        """
        return (self._ubuf, self._ybuf), self._params


def _finite_input(u_k) -> float:
    """u_k as a float (V); DataError when it is NaN or infinite (the histories stay untouched)."""
    u = float(u_k)
    if not math.isfinite(u):
        raise DataError(f'stepper input must be a finite voltage, got {u_k!r}')
    return u


class NARXStepper(Stepper):
    """Stepper of a NARXNetwork (see Stepper)."""

    def step(self, u_k):
        """
        Feed one input sample u_k (V); returns the free-run output y(k) (m).

        A non-finite u_k raises DataError and leaves the histories untouched.
        """
        u = _finite_input(u_k)
        Wu, Wy, b1, w2, b2 = self._params
        return narx_step(u, self._ubuf, self._ybuf, Wu, Wy, b1, w2, b2) + self.offset

    def peek(self, u_k):
        """Return the output step(u_k) would return (m), without changing the histories."""
        Wu, Wy, b1, w2, b2 = self._params
        return narx_peek(_finite_input(u_k), self._ubuf, self._ybuf, self._scratch, Wu, Wy,
                         b1, w2, b2) + self.offset


class ARXStepper(Stepper):
    """Stepper of an ARXModel (see Stepper)."""

    def step(self, u_k):
        """
        Feed one input sample u_k (V); returns the free-run output y(k) (m).

        A non-finite u_k raises DataError and leaves the histories untouched.
        """
        u = _finite_input(u_k)
        bu, ay, c = self._params
        return arx_step(u, self._ubuf, self._ybuf, bu, ay, c) + self.offset

    def peek(self, u_k):
        """Return the output step(u_k) would return (m), without changing the histories."""
        bu, ay, c = self._params
        return arx_peek(_finite_input(u_k), self._ubuf, self._ybuf, self._scratch, bu, ay,
                        c) + self.offset
