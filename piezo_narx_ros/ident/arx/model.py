"""
Linear ARX baseline fitted by least squares.

    y(k) + a1 y(k-1) + ... + a_na y(k-na) = b0 u(k) + b1 u(k-1) + ... + b_nb u(k-nb) + c

``nu = nb`` and ``ny = na`` so the model shares the regressors (eq. (1)) and the
predict/simulate/stepper API of NARXNetwork.

Several inputs and outputs (MIMO ARX): every output is regressed by least squares on the lags of
every input and every output (regressors.py), one least-squares problem with n_out right-hand
sides:

    y_j(k) + sum_m sum_l a[j, m, l-1] y_m(k-l) = sum_i sum_l b[j, i, l] u_i(k-l) + c_j
"""
import numpy as np

from ...errors import DataError
from .. import document
from ..narx.kernels import (ARXStepper, ARXVectorStepper, arx_predict, arx_predict_mimo,
                            arx_simulate, arx_simulate_mimo, channel_lag_weights)
from ..base import register_family
from ..narx.regressors import LaggedModel, check_orders, lagged_regressors


@register_family
class ARXModel(LaggedModel):
    """
    ARX(na, nb) model; after fit, ``a`` (na,), ``b`` (nb+1,) and intercept ``c`` (m) are set.

    Several channels: ``a`` (n_out, n_out, na), ``b`` (n_out, n_in, nb+1), ``c`` (n_out,) m.
    fit_intercept : estimate the constant c (absorbs sensor/voltage offsets); False forces c = 0.
    """

    adjustable_state_linear = True   # output lags enter linearly (ident/state/estimate.py)
    kind = 'arx'

    def __init__(self, na=2, nb=2, fit_intercept=True):
        self.nu, self.ny = check_orders(nb, na)
        self.na, self.nb = self.ny, self.nu
        self.fit_intercept = bool(fit_intercept)
        self.a = None
        self.b = None
        self.c = 0.0

    @property
    def n_params(self):
        """Return the number of estimated coefficients (over every output)."""
        if self.n_in == 1 and self.n_out == 1:
            return self.na + self.nb + 1 + int(self.fit_intercept)
        return self.n_out * self._row_params()

    def _row_params(self):
        """Coefficients of one output's equation."""
        return self.n_in * (self.nb + 1) + self.n_out * self.na + int(self.fit_intercept)

    def _is_fitted(self):
        return self.a is not None

    def fit(self, u, y, u_val=None, y_val=None, fs=None):
        """
        Least-squares fit on estimation data u (V), y (m).

        u (N,) or (N, n_in) V, y (N,) or (N, n_out) m, or lists of such for several records (each
        record's regressor rows come from that record only); u_val/y_val are unused (no tuning).
        """
        u_list, y_list = self._records(u, y, min_len=self.n0 + 1)
        rows = [lagged_regressors(ur, yr, self.nu, self.ny) for ur, yr in zip(u_list, y_list)]
        X = np.vstack([r[0] for r in rows])
        t = np.concatenate([r[1] for r in rows])
        need = self.n_params if self._scalar_io else self._row_params()
        if X.shape[0] < need:
            raise DataError(f'ARX({self.na},{self.nb}) needs at least {need} regressor '
                            f'rows, got {X.shape[0]}')
        u, y = np.concatenate(u_list), np.concatenate(y_list)
        if self.fit_intercept:
            X = np.hstack([X, np.ones((X.shape[0], 1))])
        # Columns in V and m differ by orders of magnitude; scaling keeps lstsq well conditioned.
        scale = np.sqrt(np.mean(X * X, axis=0))
        scale[scale == 0] = 1.0
        theta, *_ = np.linalg.lstsq(X / scale, t, rcond=None)
        theta = theta / (scale if theta.ndim == 1 else scale[:, None])
        if not np.all(np.isfinite(theta)):
            raise DataError('ARX least squares gave non-finite coefficients (degenerate data)')
        if self._scalar_io:
            self.set_coefficients(a=-theta[self.nu + 1:self.nu + 1 + self.ny],
                                  b=theta[:self.nu + 1],
                                  c=theta[-1] if self.fit_intercept else 0.0)
        else:
            # theta (regressors, n_out): column j is output j's equation (regressors.py order).
            k = self.n_in * (self.nu + 1)
            b = theta[:k].T.reshape(self.n_out, self.n_in, self.nu + 1)
            a = -theta[k:k + self.n_out * self.ny].T.reshape(self.n_out, self.n_out, self.ny)
            c = theta[-1] if self.fit_intercept else np.zeros(self.n_out)
            self.set_coefficients(a=a, b=b, c=c)
        self._record_ranges(u, y, fs)
        return self

    def set_coefficients(self, a, b, c=0.0):
        """
        Set the polynomial coefficients a (na,), b (nb+1,) and intercept c (m) directly.

        Several channels: a (n_out, n_out, na), b (n_out, n_in, nb+1), c (n_out,); the model's
        n_in / n_out follow from their shapes.
        """
        a = np.array(a, dtype=np.float64)
        b = np.array(b, dtype=np.float64)
        if a.ndim == 3 or b.ndim == 3:
            return self._set_channel_coefficients(a, b, c)
        a, b = a.ravel(), b.ravel()
        if a.size != self.na or b.size != self.nb + 1:
            raise DataError(f'ARX({self.na},{self.nb}) needs a of size {self.na} and b of size '
                            f'{self.nb + 1}, got {a.size} and {b.size}')
        self.n_in_ = self.n_out_ = 1
        self.a, self.b, self.c = a, b, float(np.asarray(c, dtype=np.float64).reshape(-1)[0])
        # Kernel layout: time order, u[k-nu .. k] and y[k-ny .. k-1].
        self._bu = np.ascontiguousarray(b[::-1])
        self._ay = np.ascontiguousarray(-a[::-1])
        return self

    def _set_channel_coefficients(self, a, b, c):
        if a.ndim != 3 or b.ndim != 3 or a.shape[0] != a.shape[1] or a.shape[2] != self.na \
                or b.shape[0] != a.shape[0] or b.shape[2] != self.nb + 1:
            raise DataError(f'ARX({self.na},{self.nb}) with channels needs a (n_out, n_out, '
                            f'{self.na}) and b (n_out, n_in, {self.nb + 1}), got {a.shape} and '
                            f'{b.shape}')
        n_out, n_in = b.shape[0], b.shape[1]
        c = np.broadcast_to(np.asarray(c, dtype=np.float64), (n_out,)).copy()
        self.n_in_, self.n_out_ = n_in, n_out
        self.a, self.b, self.c = a, b, c
        # Kernel layout: rows in time order, Bu (n_out, nu+1, n_in), Ay (n_out, ny, n_out).
        self._bu, self._ay = channel_lag_weights(
            np.concatenate([b.reshape(n_out, -1), -a.reshape(n_out, -1)], axis=1),
            self.nu, self.ny, n_in, n_out)
        return self

    def _one_step(self, u, y, start):
        if self._scalar_io:
            return arx_predict(u, y, start, self._bu, self._ay, self.c)
        return arx_predict_mimo(u, y, start, self._bu, self._ay, self.c)

    def _simulate_inplace(self, u, y, start):
        if self._scalar_io:
            arx_simulate(u, y, start, self._bu, self._ay, self.c)
        else:
            arx_simulate_mimo(u, y, start, self._bu, self._ay, self.c)

    def _make_stepper(self, u_past, y_past):
        if self._scalar_io:
            return ARXStepper((self._bu, self._ay, self.c), self.nu, self.ny, u_past, y_past)
        return ARXVectorStepper((self._bu, self._ay, self.c), self.nu, self.ny, self.n_in,
                                self.n_out, u_past, y_past)

    # ------------------------------------------------------------------ model file and export
    def file_document(self):
        """Return the ARX blocks of the model file (structure, no normalisation, training)."""
        return {'structure': {'kind': 'arx', 'na': self.na, 'nb': self.nb, 'nu': self.nu,
                              'ny': self.ny, 'fit_intercept': self.fit_intercept,
                              'n_params': self.n_params},
                'normalisation': None,
                'training': {'method': 'least squares'}}

    def file_weights(self):
        """
        Return a (na,), b (nb+1,) and c (1,) as written to the .npz.

        Several channels: a (n_out, n_out, na), b (n_out, n_in, nb+1), c (n_out,).
        """
        return {'a': self.a, 'b': self.b, 'c': np.atleast_1d(np.asarray(self.c, dtype=float))}

    @classmethod
    def from_file_document(cls, doc, arrays, name, wpath, fs):
        """Return the ARXModel of a model file (see DynamicModel.from_file_document)."""
        na = document.get_int(doc, 'structure.na', name, 1)
        nb = document.get_int(doc, 'structure.nb', name, 0)
        icpt = document.get(doc, 'structure.fit_intercept', name, (bool,))
        n_in, n_out = document.channel_counts(doc, name)
        if n_in == 1 and n_out == 1:
            return cls(na, nb, fit_intercept=icpt).set_coefficients(
                document.weight_array(arrays, 'a', (na,), wpath),
                document.weight_array(arrays, 'b', (nb + 1,), wpath),
                document.weight_array(arrays, 'c', (1,), wpath)[0])
        return cls(na, nb, fit_intercept=icpt).set_coefficients(
            document.weight_array(arrays, 'a', (n_out, n_out, na), wpath),
            document.weight_array(arrays, 'b', (n_out, n_in, nb + 1), wpath),
            document.weight_array(arrays, 'c', (n_out,), wpath))

    def c_emitter(self):
        """Return the C emitter of this model (piezo_narx_ros.ident.arx.export)."""
        from .export import ARXChannelEmitter, ARXEmitter
        return ARXEmitter(self) if self._scalar_io else ARXChannelEmitter(self)

    def __repr__(self):
        if self.n_in == 1 and self.n_out == 1:
            return f'ARXModel(na={self.na}, nb={self.nb})'
        return f'ARXModel(na={self.na}, nb={self.nb}, {self.n_in}x{self.n_out})'
