"""
Lagged regressors of the NARX/ARX models (the paper's eq. (1)).

    y(k) = f(u(k), u(k-1), ..., u(k-nu), y(k-1), ..., y(k-ny))

A regressor row holds ``nu + 1 + ny`` entries in exactly that order; ``n0 = max(nu, ny)`` leading
samples have no full row and are skipped.

Several inputs and outputs: every output is regressed on the lags of every channel, the row being
``[u_1(k) .. u_1(k-nu), ..., u_nin(k) .. u_nin(k-nu), y_1(k-1) .. y_1(k-ny), ..., y_nout(k-1) ..
y_nout(k-ny)]`` (channel by channel, each as the one-axis row), ``n_in (nu + 1) + n_out ny``
entries; for one input and one output it is the row above.
"""
import numpy as np

from ...errors import DataError
from ...record import as_columns
from ..base import DynamicModel, as_channel_lists
from ..data.checks import as_channels, as_signal


def check_orders(nu, ny):
    """Validate input/output lag orders; returns ``(nu, ny)`` as ints (nu >= 0, ny >= 1)."""
    try:
        nu_i, ny_i = int(nu), int(ny)
    except (TypeError, ValueError):
        raise DataError(f'lag orders must be integers, got nu={nu!r}, ny={ny!r}') from None
    if nu_i != nu or ny_i != ny or nu_i < 0 or ny_i < 1:
        raise DataError(f'lag orders must be integers with nu >= 0 and ny >= 1, '
                        f'got nu={nu!r}, ny={ny!r}')
    return nu_i, ny_i


def lagged_regressors(u, y, nu, ny):
    """
    Build the regressor matrix and target of eq. (1).

    Parameters
    ----------
    u : (N,) array
        Input (V).
    y : (N,) array
        Output (m).
    nu, ny : int
        Input and output lag orders.

    Returns
    -------
    X : (N - n0, nu + 1 + ny) rows ``[u(k), ..., u(k-nu), y(k-1), ..., y(k-ny)]`` for k = n0..N-1
    target : (N - n0,) ``y(k)`` for the same k, with ``n0 = max(nu, ny)``.

    """
    nu, ny = check_orders(nu, ny)
    n0 = max(nu, ny)
    if np.ndim(u) != 1 or np.ndim(y) != 1:
        return channel_regressors(u, y, nu, ny)
    u = as_signal(u, 'u', min_len=n0 + 1)
    y = as_signal(y, 'y', n=u.size)
    n = u.size
    m = n - n0
    X = np.empty((m, nu + 1 + ny))
    for i in range(nu + 1):
        X[:, i] = u[n0 - i:n - i]
    for j in range(1, ny + 1):
        X[:, nu + j] = y[n0 - j:n - j]
    return X, y[n0:].copy()


def channel_regressors(u, y, nu, ny):
    """
    Regressors of several channels (module docstring): u (N, n_in) V, y (N, n_out) m.

    Returns X (N - n0, n_in (nu + 1) + n_out ny) and target (N - n0, n_out) y(k). Rows come
    from this record only; columns never mix channels (each column is one channel's lag).
    """
    nu, ny = check_orders(nu, ny)
    n0 = max(nu, ny)
    u = as_channels(u, 'u', min_len=n0 + 1)
    y = as_channels(y, 'y', n=u.shape[0])
    n = u.shape[0]
    m = n - n0
    n_in, n_out = u.shape[1], y.shape[1]
    X = np.empty((m, n_in * (nu + 1) + n_out * ny))
    col = 0
    for c in range(n_in):
        for i in range(nu + 1):
            X[:, col] = u[n0 - i:n - i, c]
            col += 1
    for c in range(n_out):
        for j in range(1, ny + 1):
            X[:, col] = y[n0 - j:n - j, c]
            col += 1
    return X, y[n0:].copy()


#: Samples of a held input after which a lagged model's output is taken as settled.
SETTLE_SAMPLES = 2000


class LaggedModel(DynamicModel):
    """
    Shared predict/simulate/stepper plumbing of ARXModel and NARXNetwork.

    Subclasses set ``nu``, ``ny`` and implement ``_one_step(u, y, start)`` (one-step outputs),
    ``_simulate_inplace(u, y, start)`` (free run filling y[start:]) and ``_make_stepper(u_past,
    y_past)``; ``_is_fitted()`` tells whether weights exist. Their whole state is the last nu
    inputs and ny outputs, so n0 measured outputs initialise a free run exactly.

    Inside, a one-input one-output model works on (N,) arrays with the one-axis kernels (bit for
    bit as before several axes); a model with several channels on (N, n_in) / (N, n_out) arrays
    with the channel kernels. `_signal` converts what the user gives; `_as_output` hands outputs
    out as (N,) or (N, n_out) (DynamicModel.output_2d_).
    """

    @property
    def _scalar_io(self) -> bool:
        """Tell whether the model has one input and one output: (N,) arrays inside, floats."""
        return self.n_in == 1 and self.n_out == 1

    def _signal(self, x, name, width, n=None, min_len=1):
        """Return a user array as the model works on it: (N,) for one axis, else (N, width)."""
        a = as_channels(x, name, n=n, width=width, min_len=min_len)
        return a[:, 0] if self._scalar_io else a

    def _out(self, y):
        """Return an inside output ((N,) or (N, n_out)) as the user gets it."""
        return self._as_output(as_columns(y))

    def _set_channels(self, us, ys, y_is_1d):
        """Record the channels of the estimation data (lists of (N, n) arrays) before fitting."""
        self.n_in_, self.n_out_ = us[0].shape[1], ys[0].shape[1]
        self.output_2d_ = not y_is_1d
        self._inputs = self._outputs = None
        if self._scalar_io:
            return [x[:, 0] for x in us], [x[:, 0] for x in ys]
        return us, ys

    def _records(self, u, y, min_len):
        """Return the estimation records as the model works on them (see _set_channels)."""
        return self._set_channels(*as_channel_lists(u, y, min_len=min_len))

    def predict(self, u, y):
        """
        One-step-ahead prediction from measured past outputs.

        u : (N,) or (N, n_in) input, V; y : (N,) or (N, n_out) measured output, m. Returns (N,)
        m (or (N, n_out) for a model fitted on a 2-D y) with ``[:n0] = y[:n0]``.
        """
        self._require_fitted()
        u = self._signal(u, 'u', self.n_in, min_len=self.n0 + 1)
        y = self._signal(y, 'y', self.n_out, n=len(u))
        return self._out(self._one_step(u, y, self.n0))

    def simulate(self, u, y0=None, state=None):
        """
        Free-run simulation from the input alone.

        u : (N,) or (N, n_in) input, V. y0 : None to start from rest (every u, y before k = 0 is
        0; all N samples simulated), or the first n0 measured outputs (m; (n0, n_out) for several
        outputs), copied to the output for k < n0. state : a ModelState at u[0]
        (estimate_state), instead of y0: all N samples simulated from it, its offset added.
        Returns (N,) simulated output, m ((N, n_out) for a model fitted on a 2-D y).
        """
        self._require_fitted()
        n0 = self.n0
        if state is not None:
            if y0 is not None:
                raise DataError('give y0 or state, not both')
            values = self._check_state(state)
            return self._out(self._run_from(values, self._signal(u, 'u', self.n_in))
                             + self._check_offset(state))
        if y0 is None:
            u = self._signal(u, 'u', self.n_in)
            u_pad = np.concatenate([np.zeros((n0,) + u.shape[1:]), u])
            y_pad = np.zeros((len(u_pad),) + self._y_tail())
            self._simulate_inplace(u_pad, y_pad, n0)
            return self._out(y_pad[n0:])
        u = self._signal(u, 'u', self.n_in, min_len=n0)
        y0 = self._signal(y0, 'y0', self.n_out, n=n0, min_len=0)
        y = np.empty((len(u),) + self._y_tail())
        y[:n0] = y0
        self._simulate_inplace(u, y, n0)
        return self._out(y)

    def _y_tail(self) -> tuple:
        """Trailing shape of an inside output array: () for one axis, (n_out,) otherwise."""
        return () if self._scalar_io else (self.n_out,)

    def stepper(self, u_past=None, y_past=None, state=None):
        """
        Return a Stepper (free-run one sample at a time) started from the given histories.

        u_past : [u(k-nu) ... u(k-1)] (V; rows (nu, n_in) for several inputs), y_past :
        [y(k-ny) ... y(k-1)] (m; (ny, n_out)), None = rest; or state : a ModelState
        (estimate_state), whose offset the Stepper adds to every output. A one-input one-output
        model's Stepper takes and returns floats, any other (n_in,) and (n_out,) arrays.
        """
        self._require_fitted()
        if state is not None:
            if u_past is not None or y_past is not None:
                raise DataError('give u_past/y_past or state, not both')
            values = self._check_state(state)
            k = self.nu * self.n_in
            stepper = self._make_stepper(values[:k], values[k:])
            stepper.offset = self._check_offset(state)
            return stepper
        return self._make_stepper(u_past, y_past)

    # ------------------------------------------------------------ state from measurement
    @property
    def state_size(self) -> int:
        """Length of the state vector: nu past input rows and ny past output rows."""
        return self.nu * self.n_in + self.ny * self.n_out

    def _run_from(self, values, u):
        """Free run (m, without offset) of u (inside shape) V from the state vector values."""
        n0, nu, ny = self.n0, self.nu, self.ny
        k = nu * self.n_in
        tail_u = () if self._scalar_io else (self.n_in,)
        tail_y = self._y_tail()
        u_pad = np.concatenate([np.zeros((n0 - nu,) + tail_u), values[:k].reshape((nu,) + tail_u),
                                u])
        y_pad = np.concatenate([np.zeros((n0 - ny,) + tail_y),
                                values[k:].reshape((ny,) + tail_y),
                                np.zeros((len(u),) + tail_y)])
        self._simulate_inplace(u_pad, y_pad, n0)
        return y_pad[n0:]

    def _zero_offset(self):
        return 0.0 if self.n_out == 1 else np.zeros(self.n_out)

    def _state_candidates(self, u, past='any'):
        """One candidate (any past): the input held at u[0] (V) until the output settles."""
        from ..state.estimate import ModelState
        u0 = u[0] if self._scalar_io else np.asarray(u[0], dtype=np.float64)
        label = (f'{float(u0):.6g} V' if self._scalar_io
                 else '(' + ', '.join(f'{v:.6g}' for v in u0) + ') V')
        held_u = (np.full(SETTLE_SAMPLES, float(u0)) if self._scalar_io
                  else np.tile(u0, (SETTLE_SAMPLES, 1)))
        with np.errstate(all='ignore'):
            held = as_columns(self.simulate(held_u))
        u_rows = np.tile(np.atleast_1d(u0).astype(np.float64), self.nu)
        values = np.r_[u_rows, held[len(held) - self.ny:].ravel()]
        if not np.all(np.isfinite(values)):   # a network that runs away on the hold
            values = np.r_[u_rows, np.zeros(self.ny * self.n_out)]
        return [ModelState(values, self._zero_offset(), {'history': f'input held at {label}'})]

    def _bracket_states(self, u0):
        """Rest, and the input held at u0 (V; (n_in,) for several inputs) (estimator.memory)."""
        from ..state.estimate import ModelState
        u0 = np.asarray(u0, dtype=np.float64)
        return [ModelState(np.zeros(self.state_size), self._zero_offset(), {'history': 'rest'}),
                self._state_candidates(u0.reshape(1) if self._scalar_io
                                       else u0.reshape(1, self.n_in))[0]]

    def _adjustable_state(self, n_window):
        """Return the output history's indices, on the scale of each output's trained span (m)."""
        from ..base import channel_ranges
        _, out = channel_ranges(self)
        if out is None:
            out = np.tile([0.0, 1.0], (self.n_out, 1))
        span = out[:, 1] - out[:, 0]
        span = np.where(span > 0, span, np.maximum(np.abs(out[:, 1]), 1e-6))
        k = self.nu * self.n_in
        return np.arange(k, k + self.ny * self.n_out), np.tile(span, self.ny)
