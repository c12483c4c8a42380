"""
Compiled free-run kernels and the per-sample Stepper (numpy + numba only, never torch).

The models hand these kernels their weights "folded" into raw units (V in, m out) and ordered in
time, so one evaluation reads a contiguous window of the input and output histories:

    NARX: y(k) = b2 + sum_h w2[h] * sigmoid(b1[h] + Wu[h] . u[k-nu .. k] + Wy[h] . y[k-ny .. k-1])
    ARX:  y(k) = c  + bu . u[k-nu .. k] + ay . y[k-ny .. k-1]

``simulate`` and ``Stepper.step`` call the same evaluation function on the same window layout, so
the two agree to rounding (in practice bit for bit). A NARX Stepper's batches (``narx_run``) sum
input by input across the hidden units, each unit's terms added in the same order: the same bits.
"""
import math

import numpy as np
from numba import njit

from ...errors import DataError
from ..data.checks import input_vector


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
def narx_run(u, y, state, rows, nu1, b2, offset):
    """
    Run narx_step for each u[k] (V) in order; y[k] = its output + offset (m). One call a batch.

    state (nu+1+ny,): ubuf then ybuf (NARXStepper's histories, views of it), advanced in place;
    rows (nu+1+ny+2, H): Wu.T, Wy.T, b1, w2, one row per input of the hidden units. Input by
    input across the units, as the C export: each unit's sum keeps _narx_eval's order (the same
    bits) while the units' independent sums overlap (2x faster for 10 units); and two arrays
    instead of six (numba checks every argument on each call).
    """
    n_x = state.size
    H = rows.shape[1]
    z = np.empty(H)
    for k in range(u.size):
        for i in range(nu1 - 1):
            state[i] = state[i + 1]
        state[nu1 - 1] = u[k]
        for h in range(H):
            z[h] = rows[n_x, h]
        for i in range(n_x):         # u(k-nu) .. u(k), then y(k-ny) .. y(k-1)
            x = state[i]
            for h in range(H):
                z[h] += rows[i, h] * x
        out = b2
        for h in range(H):
            out += rows[n_x + 1, h] / (1.0 + np.exp(-z[h]))
        if n_x > nu1:
            for j in range(nu1, n_x - 1):
                state[j] = state[j + 1]
            state[n_x - 1] = out
        y[k] = out + offset


@njit(cache=True)
def narx_next(u_k, state, rows, nu1, b2):
    """
    narx_run for one input u_k (V): returns y(k) (m, without offset), state advanced in place.

    Each unit's sum in _narx_eval's order: the same bits as narx_step, in five arguments
    instead of eight (numba checks each on every call: 0.8 against 1.35 us a step).
    """
    n_x = state.size
    for i in range(nu1 - 1):
        state[i] = state[i + 1]
    state[nu1 - 1] = u_k
    out = b2
    for h in range(rows.shape[1]):
        z = rows[n_x, h]
        for i in range(n_x):         # u(k-nu) .. u(k), then y(k-ny) .. y(k-1)
            z += rows[i, h] * state[i]
        out += rows[n_x + 1, h] / (1.0 + np.exp(-z))
    if n_x > nu1:
        for j in range(nu1, n_x - 1):
            state[j] = state[j + 1]
        state[n_x - 1] = out
    return out


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
def arx_step_many(u, y, ubuf, ybuf, bu, ay, c):
    """Run arx_step for each u[k] (V) in order, y[k] (m) filled: one compiled call per batch."""
    for k in range(u.size):
        y[k] = arx_step(u[k], ubuf, ybuf, bu, ay, c)


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
    _step_many = None   # the family's compiled loop (u, y, ubuf, ybuf, *params), see step_many

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

    def step_many(self, u):
        """
        Feed the inputs u (n,) V in order; returns the free-run outputs y (n,) m.

        The same numbers as n step() calls, in one compiled call (a batch of the estimator's
        stream). A non-finite input raises DataError before any step: the histories stay
        untouched.
        """
        return self.step_many_checked(finite_inputs(u))

    def step_many_checked(self, u: np.ndarray) -> np.ndarray:
        """step_many of inputs already checked: u a contiguous finite (n,) float64 array, V."""
        y = np.empty(u.size)
        type(self)._step_many(u, y, self._ubuf, self._ybuf, *self._params)
        y += self.offset
        return y

    @property
    def y_past(self):
        """Copy of the output history ``[y(k-ny) ... y(k-1)]``, m (as output: offset included)."""
        return self._ybuf + self.offset

    @property
    def state(self):
        """Return the current ModelState (past inputs V and outputs m, and the offset)."""
        from ..state.estimate import ModelState
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


def finite_inputs(u) -> np.ndarray:
    """Return u as a contiguous (n,) float64 array (V); DataError if not 1-D or not all finite."""
    try:
        a = np.ascontiguousarray(u, dtype=np.float64)
    except (TypeError, ValueError):
        raise DataError('stepper inputs must be an array of voltages') from None
    if a.ndim != 1:
        raise DataError(f'stepper inputs must be 1-D (n,), got shape {a.shape}')
    # A finite sum holds no NaN or inf (one that overflows is looked at closely); for a batch of
    # a few samples a Python sum costs a third of isfinite().all() in a node's cold caches.
    total = sum(a.tolist()) if a.size <= 64 else float(a.sum())
    if not math.isfinite(total) and not np.isfinite(a).all():
        k = int(np.flatnonzero(~np.isfinite(a))[0])
        raise DataError(f'stepper input must be a finite voltage, got {float(a[k])!r} at '
                        f'index {k}')
    return a


class NARXStepper(Stepper):
    """Stepper of a NARXNetwork (see Stepper; its batches run narx_run, not _step_many)."""

    def __init__(self, params, nu, ny, u_past=None, y_past=None):
        super().__init__(params, nu, ny, u_past, y_past)
        # narx_run's layout: both histories views of one array, the weights one row per input.
        self._state = np.concatenate((self._ubuf, self._ybuf))
        self._ubuf, self._ybuf = self._state[:nu + 1], self._state[nu + 1:]
        Wu, Wy, b1, w2, b2 = self._params
        self._rows = np.ascontiguousarray(np.vstack((Wu.T, Wy.T, b1, w2)), dtype=np.float64)
        self._b2 = float(b2)

    def step_many_checked(self, u: np.ndarray) -> np.ndarray:
        """step_many of inputs already checked: u a contiguous finite (n,) float64 array, V."""
        y = np.empty(u.size)
        narx_run(u, y, self._state, self._rows, self.nu + 1, self._b2, float(self.offset))
        return y

    def step(self, u_k):
        """
        Feed one input sample u_k (V); returns the free-run output y(k) (m).

        A non-finite u_k raises DataError and leaves the histories untouched.
        """
        return narx_next(_finite_input(u_k), self._state, self._rows, self.nu + 1,
                         self._b2) + self.offset

    def peek(self, u_k):
        """Return the output step(u_k) would return (m), without changing the histories."""
        Wu, Wy, b1, w2, b2 = self._params
        return narx_peek(_finite_input(u_k), self._ubuf, self._ybuf, self._scratch, Wu, Wy,
                         b1, w2, b2) + self.offset


class ARXStepper(Stepper):
    """Stepper of an ARXModel (see Stepper)."""

    _step_many = staticmethod(arx_step_many)

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


# ------------------------------------------------------------------ several inputs and outputs
# The same models with channels: u (N, n_in) V, y (N, n_out) m, windows of rows in time order.
#   NARX: y(k) = b2 + W2 sigmoid(b1 + sum_l Wu[:, l, :] u(k-nu+l) + sum_l Wy[:, l, :] y(k-ny+l))
#   ARX:  y_j(k) = c_j + sum_l Bu[j, l, :] . u(k-nu+l) + sum_l Ay[j, l, :] . y(k-ny+l)
# with Wu (H, nu+1, n_in), Wy (H, ny, n_out), W2 (n_out, H), b2 (n_out,); Bu (n_out, nu+1, n_in),
# Ay (n_out, ny, n_out), c (n_out,). One-axis models keep the kernels above (bit for bit).

@njit(cache=True)
def _narx_eval_mimo(u, iu, y, iy, Wu, Wy, b1, W2, b2, out):
    """Write y(k) (n_out,) into out from rows u[iu : iu+nu+1] and y[iy : iy+ny]."""
    H, nu1, n_in = Wu.shape
    ny, n_out = Wy.shape[1], Wy.shape[2]
    for j in range(n_out):
        out[j] = b2[j]
    for h in range(H):
        z = b1[h]
        for lag in range(nu1):
            for i in range(n_in):
                z += Wu[h, lag, i] * u[iu + lag, i]
        for lag in range(ny):
            for i in range(n_out):
                z += Wy[h, lag, i] * y[iy + lag, i]
        s = 1.0 / (1.0 + np.exp(-z))
        for j in range(n_out):
            out[j] += W2[j, h] * s


@njit(cache=True)
def narx_simulate_mimo(u, y, start, Wu, Wy, b1, W2, b2):
    """Free-run in place: fill y[start:] (N, n_out) from u (N, n_in) and y's own past."""
    nu1, ny = Wu.shape[1], Wy.shape[1]
    for k in range(start, u.shape[0]):
        _narx_eval_mimo(u, k - nu1 + 1, y, k - ny, Wu, Wy, b1, W2, b2, y[k])


@njit(cache=True)
def narx_predict_mimo(u, y, start, Wu, Wy, b1, W2, b2):
    """One-step-ahead outputs (N, n_out) for k >= start from measured u, y; [:start] = y."""
    nu1, ny = Wu.shape[1], Wy.shape[1]
    out = y.copy()
    for k in range(start, u.shape[0]):
        _narx_eval_mimo(u, k - nu1 + 1, y, k - ny, Wu, Wy, b1, W2, b2, out[k])
    return out


@njit(cache=True)
def _arx_eval_mimo(u, iu, y, iy, Bu, Ay, c, out):
    """Write y(k) (n_out,) into out from rows u[iu : iu+nu+1] and y[iy : iy+ny]."""
    n_out, nu1, n_in = Bu.shape
    ny = Ay.shape[1]
    for j in range(n_out):
        acc = c[j]
        for lag in range(nu1):
            for i in range(n_in):
                acc += Bu[j, lag, i] * u[iu + lag, i]
        for lag in range(ny):
            for i in range(n_out):
                acc += Ay[j, lag, i] * y[iy + lag, i]
        out[j] = acc


@njit(cache=True)
def arx_simulate_mimo(u, y, start, Bu, Ay, c):
    """Free-run in place: fill y[start:] (N, n_out) from u (N, n_in) and y's own past."""
    nu1, ny = Bu.shape[1], Ay.shape[1]
    for k in range(start, u.shape[0]):
        _arx_eval_mimo(u, k - nu1 + 1, y, k - ny, Bu, Ay, c, y[k])


@njit(cache=True)
def arx_predict_mimo(u, y, start, Bu, Ay, c):
    """One-step-ahead outputs (N, n_out) for k >= start from measured u, y; [:start] = y."""
    nu1, ny = Bu.shape[1], Ay.shape[1]
    out = y.copy()
    for k in range(start, u.shape[0]):
        _arx_eval_mimo(u, k - nu1 + 1, y, k - ny, Bu, Ay, c, out[k])
    return out


@njit(cache=True)
def _shift_in(buf, row):
    """Shift the rows of buf up by one and put `row` last."""
    for r in range(buf.shape[0] - 1):
        for i in range(buf.shape[1]):
            buf[r, i] = buf[r + 1, i]
    for i in range(buf.shape[1]):
        buf[buf.shape[0] - 1, i] = row[i]


@njit(cache=True)
def _finite(x):
    for v in x:
        if not np.isfinite(v):
            return False
    return True


@njit(cache=True)
def narx_step_mimo(u_k, ubuf, ybuf, out, Wu, Wy, b1, W2, b2):
    """
    Step with u_k (n_in,) V: y(k) into out (n_out,) m, both histories shifted; True.

    False (nothing changed) when u_k is not finite.
    """
    if not _finite(u_k):
        return False
    _shift_in(ubuf, u_k)
    _narx_eval_mimo(ubuf, 0, ybuf, 0, Wu, Wy, b1, W2, b2, out)
    if ybuf.shape[0] > 0:
        _shift_in(ybuf, out)
    return True


@njit(cache=True)
def narx_peek_mimo(u_k, ubuf, ybuf, scratch, out, Wu, Wy, b1, W2, b2):
    """Write y(k) for u_k into out, histories untouched (scratch (nu+1, n_in)); finite u_k."""
    if not _finite(u_k):
        return False
    scratch[:] = ubuf
    _shift_in(scratch, u_k)
    _narx_eval_mimo(scratch, 0, ybuf, 0, Wu, Wy, b1, W2, b2, out)
    return True


@njit(cache=True)
def arx_step_mimo(u_k, ubuf, ybuf, out, Bu, Ay, c):
    """As narx_step_mimo for an ARX model."""
    if not _finite(u_k):
        return False
    _shift_in(ubuf, u_k)
    _arx_eval_mimo(ubuf, 0, ybuf, 0, Bu, Ay, c, out)
    if ybuf.shape[0] > 0:
        _shift_in(ybuf, out)
    return True


@njit(cache=True)
def arx_peek_mimo(u_k, ubuf, ybuf, scratch, out, Bu, Ay, c):
    """As narx_peek_mimo for an ARX model."""
    if not _finite(u_k):
        return False
    scratch[:] = ubuf
    _shift_in(scratch, u_k)
    _arx_eval_mimo(scratch, 0, ybuf, 0, Bu, Ay, c, out)
    return True


def _block(x, rows, cols, name):
    """Validate a (rows, cols) float64 history (a flat array of rows*cols too); None: zeros."""
    if x is None:
        return np.zeros((rows, cols))
    try:
        a = np.array(x, dtype=np.float64)
    except (TypeError, ValueError):
        raise DataError(f'{name} must be an array of numbers') from None
    if a.size != rows * cols:
        raise DataError(f'{name} must hold {rows} samples of {cols} channel(s), got shape '
                        f'{a.shape}')
    if not np.all(np.isfinite(a)):
        raise DataError(f'{name} contains NaN or infinite values')
    return a.reshape(rows, cols)


def step_rows(stepper, u) -> np.ndarray:
    """
    Step a several-input Stepper through the rows of u (n, n_in) V; returns (n, n_out) m.

    The same numbers as n step() calls. Every row is checked before the first step, so a bad
    row raises DataError with the state untouched.
    """
    try:
        a = np.asarray(u, dtype=np.float64)
    except (TypeError, ValueError):
        raise DataError('stepper inputs must be an array of voltages') from None
    if a.ndim != 2 or a.shape[1] != stepper.n_in:
        raise DataError(f'stepper inputs must be rows of {stepper.n_in} voltages (n, '
                        f'{stepper.n_in}), got shape {a.shape}')
    bad = np.flatnonzero(~np.isfinite(a).all(axis=1))
    if bad.size:
        raise DataError(f'stepper input must be finite voltages, got {a[bad[0]]!r} at row '
                        f'{bad[0]}')
    out = np.empty((a.shape[0], stepper.n_out))
    for k in range(a.shape[0]):
        out[k] = stepper.step(a[k])
    return out


class VectorStepper:
    """
    Free-run a model of several inputs or outputs one sample at a time.

    ``u_past`` holds rows ``[u(k-nu) ... u(k-1)]`` (nu, n_in) V and ``y_past`` ``[y(k-ny) ...
    y(k-1)]`` (ny, n_out) m (None = rest). ``step(u_k)`` takes an (n_in,) array (V) and returns
    a NEW (n_out,) array (m, offset added): the one allocation per step. ``offset``: float or
    (n_out,) m, added to every output.
    """

    offset = 0.0
    _step = None    # the compiled step and peek of the family (set by subclasses)
    _peek = None

    def __init__(self, params, nu, ny, n_in, n_out, u_past=None, y_past=None):
        self._params = tuple(params)
        self.nu, self.ny, self.n_in, self.n_out = nu, ny, n_in, n_out
        self._ubuf = np.zeros((nu + 1, n_in))
        self._ybuf = np.zeros((ny, n_out))
        self._scratch = np.zeros((nu + 1, n_in))
        self._out = np.zeros(n_out)
        self.reset(u_past, y_past)

    def reset(self, u_past=None, y_past=None):
        """Restart from the given histories (None = rest; y_past as output, offset included)."""
        self._ubuf[1:] = _block(u_past, self.nu, self.n_in, 'u_past')
        self._ybuf[:] = _block(y_past, self.ny, self.n_out, 'y_past')
        if y_past is not None:
            self._ybuf -= self.offset

    def step(self, u_k):
        """
        Feed one input sample u_k (n_in,) V; returns the free-run output y(k) (n_out,) m.

        A non-finite u_k raises DataError and leaves the histories untouched.
        """
        u = input_vector(u_k, self.n_in)
        if not type(self)._step(u, self._ubuf, self._ybuf, self._out, *self._params):
            raise DataError(f'stepper input must be finite voltages, got {u_k!r}')
        return self._out + self.offset

    def step_many(self, u):
        """Feed input rows u (n, n_in) V in order; returns the outputs (n, n_out) m (step_rows)."""
        return step_rows(self, u)

    def peek(self, u_k):
        """Return the output step(u_k) would return (n_out,) m, without changing the histories."""
        u = input_vector(u_k, self.n_in)
        if not type(self)._peek(u, self._ubuf, self._ybuf, self._scratch, self._out,
                                *self._params):
            raise DataError(f'stepper input must be finite voltages, got {u_k!r}')
        return self._out + self.offset

    @property
    def y_past(self):
        """Copy of the output history (ny, n_out), m (as output: offset included)."""
        return self._ybuf + self.offset

    @property
    def u_past(self):
        """Copy of the input history (nu, n_in), V."""
        return self._ubuf[1:].copy()

    @property
    def state(self):
        """Return the current ModelState (past input and output rows, offsets (n_out,) m)."""
        from ..state.estimate import ModelState
        offset = np.broadcast_to(np.asarray(self.offset, dtype=np.float64), (self.n_out,))
        return ModelState(np.r_[self._ubuf[1:].ravel(), self._ybuf.ravel()], offset.copy())

    @property
    def kernel_state(self):
        """Return ((ubuf (nu+1, n_in), ybuf (ny, n_out)), kernel parameters); read only."""
        return (self._ubuf, self._ybuf), self._params


class NARXVectorStepper(VectorStepper):
    """VectorStepper of a NARXNetwork with several inputs or outputs."""

    _step = staticmethod(narx_step_mimo)
    _peek = staticmethod(narx_peek_mimo)


class ARXVectorStepper(VectorStepper):
    """VectorStepper of an ARXModel with several inputs or outputs."""

    _step = staticmethod(arx_step_mimo)
    _peek = staticmethod(arx_peek_mimo)


def channel_lag_weights(W, nu, ny, n_in, n_out):
    """
    Split weights over a channel regressor row (regressors.py order) into kernel layout.

    W (H, n_in (nu+1) + n_out ny) -> (Wu (H, nu+1, n_in), Wy (H, ny, n_out)), rows in time order
    (oldest first), C-contiguous: the layout of the channel kernels above.
    """
    H = W.shape[0]
    k = n_in * (nu + 1)
    Wu = W[:, :k].reshape(H, n_in, nu + 1)[:, :, ::-1].transpose(0, 2, 1)
    Wy = W[:, k:].reshape(H, n_out, ny)[:, :, ::-1].transpose(0, 2, 1)
    return np.ascontiguousarray(Wu), np.ascontiguousarray(Wy)
