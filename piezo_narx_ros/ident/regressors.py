"""
Lagged regressors of the NARX/ARX models (the paper's eq. (1)).

    y(k) = f(u(k), u(k-1), ..., u(k-nu), y(k-1), ..., y(k-ny))

A regressor row holds ``nu + 1 + ny`` entries in exactly that order; ``n0 = max(nu, ny)`` leading
samples have no full row and are skipped.
"""
import numpy as np

from ..errors import DataError
from .base import DynamicModel
from .checks import as_signal


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


#: Samples of a held input after which a lagged model's output is taken as settled.
SETTLE_SAMPLES = 2000


class LaggedModel(DynamicModel):
    """
    Shared predict/simulate/stepper plumbing of ARXModel and NARXNetwork.

    Subclasses set ``nu``, ``ny`` and implement ``_one_step(u, y, start)`` (one-step outputs),
    ``_simulate_inplace(u, y, start)`` (free run filling y[start:]) and ``_make_stepper(u_past,
    y_past)``; ``_is_fitted()`` tells whether weights exist. Their whole state is the last nu
    inputs and ny outputs, so n0 measured outputs initialise a free run exactly.
    """

    def predict(self, u, y):
        """
        One-step-ahead prediction from measured past outputs.

        u : (N,) input, V; y : (N,) measured output, m. Returns (N,) m with ``[:n0] = y[:n0]``.
        """
        self._require_fitted()
        u = as_signal(u, 'u', min_len=self.n0 + 1)
        y = as_signal(y, 'y', n=u.size)
        return self._one_step(u, y, self.n0)

    def simulate(self, u, y0=None, state=None):
        """
        Free-run simulation from the input alone.

        u : (N,) input, V. y0 : None to start from rest (every u, y before k = 0 is 0; all N
        samples simulated), or the first n0 measured outputs (m), copied to the output for k < n0.
        state : a ModelState at u[0] (estimate_state), instead of y0: all N samples simulated
        from it, its offset added. Returns (N,) simulated output, m.
        """
        self._require_fitted()
        n0 = self.n0
        if state is not None:
            if y0 is not None:
                raise DataError('give y0 or state, not both')
            return self._run_from(self._check_state(state), as_signal(u, 'u')) + state.offset
        if y0 is None:
            u = as_signal(u, 'u')
            u_pad = np.concatenate([np.zeros(n0), u])
            y_pad = np.zeros(u_pad.size)
            self._simulate_inplace(u_pad, y_pad, n0)
            return y_pad[n0:]
        u = as_signal(u, 'u', min_len=n0)
        y0 = as_signal(y0, 'y0', n=n0, min_len=0)
        y = np.empty(u.size)
        y[:n0] = y0
        self._simulate_inplace(u, y, n0)
        return y

    def stepper(self, u_past=None, y_past=None, state=None):
        """
        Return a Stepper (free-run one sample at a time) started from the given histories.

        u_past : [u(k-nu) ... u(k-1)] (V), y_past : [y(k-ny) ... y(k-1)] (m), None = rest; or
        state : a ModelState (estimate_state), whose offset the Stepper adds to every output.
        """
        self._require_fitted()
        if state is not None:
            if u_past is not None or y_past is not None:
                raise DataError('give u_past/y_past or state, not both')
            values = self._check_state(state)
            stepper = self._make_stepper(values[:self.nu], values[self.nu:])
            stepper.offset = float(state.offset)
            return stepper
        return self._make_stepper(u_past, y_past)

    # ------------------------------------------------------------ state from measurement
    @property
    def state_size(self) -> int:
        """Length of the state vector: nu past inputs and ny past outputs."""
        return self.nu + self.ny

    def _run_from(self, values, u):
        """Free run (m, without offset) of u (N,) V from the state vector values."""
        n0, nu, ny = self.n0, self.nu, self.ny
        u_pad = np.concatenate([np.zeros(n0 - nu), values[:nu], u])
        y_pad = np.concatenate([np.zeros(n0 - ny), values[nu:], np.zeros(u.size)])
        self._simulate_inplace(u_pad, y_pad, n0)
        return y_pad[n0:]

    def _state_candidates(self, u):
        """One candidate: the input held at u[0] (V) long enough for the output to settle."""
        from .state import ModelState
        u0 = float(u[0])
        with np.errstate(all='ignore'):
            held = self.simulate(np.full(SETTLE_SAMPLES, u0))
        values = np.r_[np.full(self.nu, u0), held[held.size - self.ny:]]
        if not np.all(np.isfinite(values)):   # a network that runs away on the hold
            values = np.r_[np.full(self.nu, u0), np.zeros(self.ny)]
        return [ModelState(values, 0.0, {'history': f'input held at {u0:.6g} V'})]

    def _bracket_states(self, u0):
        """Rest, and the input held at u0 (V) (estimator.memory)."""
        from .state import ModelState
        return [ModelState(np.zeros(self.state_size), 0.0, {'history': 'rest'}),
                self._state_candidates(np.array([u0]))[0]]

    def _adjustable_state(self, n_window):
        """Return the output history's indices, on the scale of the trained output span (m)."""
        lo, hi = self.output_range if self.output_range is not None else (0.0, 1.0)
        span = hi - lo if hi > lo else max(abs(hi), 1e-6)
        return np.arange(self.nu, self.nu + self.ny), np.full(self.ny, span)
