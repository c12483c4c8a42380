"""
Linear ARX baseline fitted by least squares.

    y(k) + a1 y(k-1) + ... + a_na y(k-na) = b0 u(k) + b1 u(k-1) + ... + b_nb u(k-nb) + c

``nu = nb`` and ``ny = na`` so the model shares the regressors (eq. (1)) and the
predict/simulate/stepper API of NARXNetwork.
"""
import numpy as np

from ..errors import DataError
from . import document
from .kernels import ARXStepper, arx_predict, arx_simulate
from .base import as_record_list, register_family
from .regressors import LaggedModel, check_orders, lagged_regressors


@register_family
class ARXModel(LaggedModel):
    """
    ARX(na, nb) model; after fit, ``a`` (na,), ``b`` (nb+1,) and intercept ``c`` (m) are set.

    fit_intercept : estimate the constant c (absorbs sensor/voltage offsets); False forces c = 0.
    """

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
        """Return the number of estimated coefficients."""
        return self.na + self.nb + 1 + int(self.fit_intercept)

    def _is_fitted(self):
        return self.a is not None

    def fit(self, u, y, u_val=None, y_val=None, fs=None):
        """
        Least-squares fit on estimation data u (V), y (m).

        1-D arrays, or lists of arrays for several records (each record's regressor rows come from
        that record only); u_val/y_val are unused (no tuning).
        """
        u_list, y_list = as_record_list(u, y, min_len=self.n0 + 1)
        rows = [lagged_regressors(ur, yr, self.nu, self.ny) for ur, yr in zip(u_list, y_list)]
        X = np.vstack([r[0] for r in rows])
        t = np.concatenate([r[1] for r in rows])
        if X.shape[0] < self.n_params:
            raise DataError(f'ARX({self.na},{self.nb}) needs at least {self.n_params} regressor '
                            f'rows, got {X.shape[0]}')
        u, y = np.concatenate(u_list), np.concatenate(y_list)
        if self.fit_intercept:
            X = np.hstack([X, np.ones((X.shape[0], 1))])
        # Columns in V and m differ by orders of magnitude; scaling keeps lstsq well conditioned.
        scale = np.sqrt(np.mean(X * X, axis=0))
        scale[scale == 0] = 1.0
        theta, *_ = np.linalg.lstsq(X / scale, t, rcond=None)
        theta = theta / scale
        if not np.all(np.isfinite(theta)):
            raise DataError('ARX least squares gave non-finite coefficients (degenerate data)')
        self.set_coefficients(a=-theta[self.nu + 1:self.nu + 1 + self.ny], b=theta[:self.nu + 1],
                              c=theta[-1] if self.fit_intercept else 0.0)
        self._record_ranges(u, y, fs)
        return self

    def set_coefficients(self, a, b, c=0.0):
        """Set the polynomial coefficients a (na,), b (nb+1,) and intercept c (m) directly."""
        a = np.array(a, dtype=np.float64).ravel()
        b = np.array(b, dtype=np.float64).ravel()
        if a.size != self.na or b.size != self.nb + 1:
            raise DataError(f'ARX({self.na},{self.nb}) needs a of size {self.na} and b of size '
                            f'{self.nb + 1}, got {a.size} and {b.size}')
        self.a, self.b, self.c = a, b, float(c)
        # Kernel layout: time order, u[k-nu .. k] and y[k-ny .. k-1].
        self._bu = np.ascontiguousarray(b[::-1])
        self._ay = np.ascontiguousarray(-a[::-1])
        return self

    def _one_step(self, u, y, start):
        return arx_predict(u, y, start, self._bu, self._ay, self.c)

    def _simulate_inplace(self, u, y, start):
        arx_simulate(u, y, start, self._bu, self._ay, self.c)

    def _make_stepper(self, u_past, y_past):
        return ARXStepper((self._bu, self._ay, self.c), self.nu, self.ny, u_past, y_past)

    # ------------------------------------------------------------------ model file and export
    def file_document(self):
        """Return the ARX blocks of the model file (structure, no normalisation, training)."""
        return {'structure': {'kind': 'arx', 'na': self.na, 'nb': self.nb, 'nu': self.nu,
                              'ny': self.ny, 'fit_intercept': self.fit_intercept,
                              'n_params': self.n_params},
                'normalisation': None,
                'training': {'method': 'least squares'}}

    def file_weights(self):
        """Return a (na,), b (nb+1,) and c (1,) as written to the .npz."""
        return {'a': self.a, 'b': self.b, 'c': np.array([self.c])}

    @classmethod
    def from_file_document(cls, doc, arrays, name, wpath, fs):
        """Return the ARXModel of a model file (see DynamicModel.from_file_document)."""
        na = document.get_int(doc, 'structure.na', name, 1)
        nb = document.get_int(doc, 'structure.nb', name, 0)
        icpt = document.get(doc, 'structure.fit_intercept', name, (bool,))
        return cls(na, nb, fit_intercept=icpt).set_coefficients(
            document.weight_array(arrays, 'a', (na,), wpath),
            document.weight_array(arrays, 'b', (nb + 1,), wpath),
            document.weight_array(arrays, 'c', (1,), wpath)[0])

    def c_emitter(self):
        """Return the C emitter of this model (piezo_narx_ros.ident.arx_export)."""
        from .arx_export import ARXEmitter
        return ARXEmitter(self)

    def __repr__(self):
        return f'ARXModel(na={self.na}, nb={self.nb})'
