"""
NARX network: one hidden layer of logistic (sigmoid) units and a linear output.

    y(k) = f(u(k), ..., u(k-nu), y(k-1), ..., y(k-ny))
    f(x) = ym + ys * (w2 . sigmoid(W1 xn + b1) + b2),   xn = (x - mean) / std   per signal (u or y)

The normalisation (u_mean, u_std, y_mean, y_std) is fitted on the estimation data only. Training
(torch, imported only inside fit) lives in training.py; inference uses the numba kernels.
"""
import time

import numpy as np

from ..errors import ConfigError, DataError, ModelFileError
from . import document
from .base import as_record_list, register_family
from .kernels import NARXStepper, narx_predict, narx_simulate
from .regressors import LaggedModel, as_signal, check_orders

#: Training options and their defaults (fast enough for a 16-network grid on 50k samples).
TRAINING_DEFAULTS = {
    'restarts': 3,             # seeded random initialisations screened in the one-step stage
    'restart_iter': 8,         # LM iterations each restart gets before the best one is kept
    'restart_samples': 2000,   # one-step rows (random subset) used while screening restarts
    'max_iter': 25,            # LM iterations of the one-step stage for the best restart
    'onestep_samples': 4000,   # one-step rows (random subset; 0 = all) for that stage
    'val_fraction': 0.15,      # tail of the estimation data held out for early stopping/selection
    'max_fail': 6,             # early stopping: LM iterations without held-out improvement
    'refine_iter': 40,         # simulation-error LM iterations (0 disables the refinement)
    'refine_max_fail': 40,     # its early stopping (held-out free-run error often rises first)
    'segment_length': 200,     # samples per free-run segment in the refinement
    'n_segments': 40,          # segments (evenly spread; 0 = tile all the data)
    'hessian_stride': 2,       # refinement J^T J from every k-th row (gradient uses all rows)
    'threads': 1,              # torch threads inside fit
}


#: Smallest allowed value of each integer option.
_MIN_INT = {'restarts': 1, 'restart_iter': 0, 'restart_samples': 0, 'max_iter': 0,
            'onestep_samples': 0, 'max_fail': 1, 'refine_iter': 0, 'refine_max_fail': 1,
            'segment_length': 1, 'n_segments': 0, 'hessian_stride': 1, 'threads': 1}


def _check_options(options):
    """Training options merged over the defaults; ConfigError naming an unknown or bad one."""
    unknown = set(options) - set(TRAINING_DEFAULTS)
    if unknown:
        raise ConfigError(f'unknown training option(s): {", ".join(sorted(unknown))}; '
                          f'known: {", ".join(TRAINING_DEFAULTS)}')
    merged = {**TRAINING_DEFAULTS, **options}
    for name, lo in _MIN_INT.items():
        v = merged[name]
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < lo:
            raise ConfigError(f'training option {name} must be an integer >= {lo}, got {v!r}')
        merged[name] = int(v)
    v = merged['val_fraction']
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0.0 <= v <= 0.5:
        raise ConfigError(f'training option val_fraction must be a number in [0, 0.5], got {v!r}')
    merged['val_fraction'] = float(v)
    return merged


@register_family
class NARXNetwork(LaggedModel):
    """
    Single-hidden-layer sigmoid NARX model (scikit-learn style fit/predict/simulate).

    nu, ny : input/output lags; hidden : number of sigmoid units H; seed : training RNG seed.
    training_options : see TRAINING_DEFAULTS. After fit: ``training_info_`` (dict of losses, times,
    stages).
    """

    kind = 'narx'
    activation = 'logistic'

    def __init__(self, nu=4, ny=4, hidden=10, seed=0, **training_options):
        self.nu, self.ny = check_orders(nu, ny)
        try:
            self.hidden = int(hidden)
        except (TypeError, ValueError):
            raise DataError(f'hidden must be a positive integer, got {hidden!r}') from None
        if self.hidden != hidden or self.hidden < 1:
            raise DataError(f'hidden must be a positive integer, got {hidden!r}')
        self.seed = int(seed)
        self.training_options = _check_options(training_options)
        self.W1 = None
        self.training_info_ = {}

    @property
    def n_inputs(self):
        """Regressor size nu + 1 + ny."""
        return self.nu + 1 + self.ny

    @property
    def n_params(self):
        """Return the number of trainable weights H (d + 1) + H + 1."""
        return self.hidden * (self.n_inputs + 2) + 1

    def _is_fitted(self):
        return self.W1 is not None

    # ---------------------------------------------------------------- weights
    def set_weights(self, W1, b1, w2, b2, normalisation):
        """
        Set the weights in normalised units.

        W1 : (H, nu+1+ny) input weights, columns in regressor order
             [u(k)..u(k-nu), y(k-1)..y(k-ny)];
        b1 : (H,); w2 : (H,); b2 : scalar; normalisation : (u_mean V, u_std V, y_mean m, y_std m).
        """
        H, d = self.hidden, self.n_inputs
        W1 = np.array(W1, dtype=np.float64)
        b1 = np.array(b1, dtype=np.float64).ravel()
        w2 = np.array(w2, dtype=np.float64).ravel()
        b2_size = np.size(b2)
        b2 = float(np.asarray(b2, dtype=np.float64).reshape(-1)[0]) if b2_size == 1 else None
        norm = np.array(normalisation, dtype=np.float64).ravel()
        if W1.shape != (H, d) or b1.shape != (H,) or w2.shape != (H,) or b2 is None:
            raise DataError(f'NARX weights must be W1 {(H, d)}, b1 ({H},), w2 ({H},), b2 scalar; '
                            f'got '
                            f'W1 {W1.shape}, b1 {b1.shape}, w2 {w2.shape}, b2 size {b2_size}')
        if norm.shape != (4,) or norm[1] <= 0 or norm[3] <= 0:
            raise DataError('normalisation must be (u_mean, u_std > 0, y_mean, y_std > 0)')
        for name, a in (('W1', W1), ('b1', b1), ('w2', w2), ('normalisation', norm)):
            if not np.all(np.isfinite(a)):
                raise DataError(f'NARX weight {name} contains NaN or infinite values')
        self.W1, self.b1, self.w2, self.b2, self.normalisation = W1, b1, w2, b2, norm
        self._fold()
        return self

    def _fold(self):
        """Fold the normalisation into raw-unit, time-ordered kernel weights."""
        um, us, ym, ys = self.normalisation
        n_u = self.nu + 1
        mean = np.r_[np.full(n_u, um), np.full(self.ny, ym)]
        std = np.r_[np.full(n_u, us), np.full(self.ny, ys)]
        Wr = self.W1 / std
        self._b1r = self.b1 - Wr @ mean
        self._Wu = np.ascontiguousarray(Wr[:, :n_u][:, ::-1])
        self._Wy = np.ascontiguousarray(Wr[:, n_u:][:, ::-1])
        self._w2r = self.w2 * ys
        self._b2r = float(ym + ys * self.b2)

    # ---------------------------------------------------------------- training
    def fit(self, u, y, u_val=None, y_val=None, fs=None):
        """
        Train on estimation data u (V), y (m).

        1-D arrays, or lists of arrays for several records (no regressor row or free-run segment
        spans two records); returns self.

        Stage 1: Levenberg-Marquardt on the one-step error (seeded restarts, early stopping on a
        held-out tail). Stage 2: simulation-error LM on free-run segments, kept only if the
        held-out free-run error improves. u_val/y_val (if given) are only scored into
        ``training_info_``, never used for a choice, so they stay an honest validation set.
        """
        from . import training  # torch lives there; inference never imports it

        opts = self.training_options
        if (u_val is None) != (y_val is None):
            raise DataError('give both u_val and y_val, or neither')
        u_list, y_list = as_record_list(u, y, min_len=self.n0 + 20)
        u, y = np.concatenate(u_list), np.concatenate(y_list)
        us, ys = float(u.std()), float(y.std())
        if us == 0 or ys == 0:
            raise DataError('estimation data is constant (zero variance in u or y); cannot fit')
        norm = np.array([u.mean(), us, y.mean(), ys])
        t0 = time.perf_counter()
        un = [(x - norm[0]) / norm[1] for x in u_list]
        yn = [(x - norm[2]) / norm[3] for x in y_list]
        W1, b1, w2, b2, info = training.train_narx(
            un if len(un) > 1 else un[0], yn if len(yn) > 1 else yn[0], self.nu, self.ny,
            self.hidden, self.seed, **opts)
        self.set_weights(W1, b1, w2, b2, norm)
        self._record_ranges(u, y, fs)
        info['fit_seconds'] = time.perf_counter() - t0
        if u_val is not None and y_val is not None:
            u_val = as_signal(u_val, 'u_val', min_len=self.n0 + 1)
            y_val = as_signal(y_val, 'y_val', n=u_val.size)
            info['val_r2_predict'] = _r2(y_val[self.n0:], self.predict(u_val, y_val)[self.n0:])
            info['val_r2_simulate'] = _r2(y_val[self.n0:],
                                          self.simulate(u_val, y_val[:self.n0])[self.n0:])
        self.training_info_ = info
        return self

    # ---------------------------------------------------------------- inference
    def _one_step(self, u, y, start):
        return narx_predict(u, y, start, self._Wu, self._Wy, self._b1r, self._w2r, self._b2r)

    def _simulate_inplace(self, u, y, start):
        narx_simulate(u, y, start, self._Wu, self._Wy, self._b1r, self._w2r, self._b2r)

    def _make_stepper(self, u_past, y_past):
        return NARXStepper((self._Wu, self._Wy, self._b1r, self._w2r, self._b2r),
                           self.nu, self.ny, u_past, y_past)

    # ------------------------------------------------------------------ model file and export
    def file_document(self):
        """Return the NARX blocks of the model file (structure, normalisation, training)."""
        return {'structure': {'kind': 'narx', 'nu': self.nu, 'ny': self.ny,
                              'hidden': self.hidden, 'activation': self.activation,
                              'output': 'linear', 'n_params': self.n_params},
                'normalisation': dict(zip(('u_mean', 'u_std', 'y_mean', 'y_std'),
                                          self.normalisation.tolist())),
                'training': {'seed': self.seed, 'options': self.training_options,
                             'info': self.training_info_}}

    def file_weights(self):
        """Return W1, b1, w2, b2 (1,) and the normalisation (4,) as written to the .npz."""
        return {'W1': self.W1, 'b1': self.b1, 'w2': self.w2, 'b2': np.array([self.b2]),
                'normalisation': self.normalisation}

    @classmethod
    def from_file_document(cls, doc, arrays, name, wpath, fs):
        """Return the NARXNetwork of a model file (see DynamicModel.from_file_document)."""
        nu = document.get_int(doc, 'structure.nu', name, 0)
        ny = document.get_int(doc, 'structure.ny', name, 1)
        hidden = document.get_int(doc, 'structure.hidden', name, 1)
        act = document.get(doc, 'structure.activation', name, (str,))
        if act != cls.activation:
            raise ModelFileError(f'{name}: unsupported activation {act!r} (only logistic)')
        training = document.training_block(doc)
        seed = training.get('seed', 0)
        model = cls(nu, ny, hidden, seed=seed if isinstance(seed, int) else 0)
        d = nu + 1 + ny
        model.set_weights(document.weight_array(arrays, 'W1', (hidden, d), wpath),
                          document.weight_array(arrays, 'b1', (hidden,), wpath),
                          document.weight_array(arrays, 'w2', (hidden,), wpath),
                          document.weight_array(arrays, 'b2', (1,), wpath)[0],
                          document.weight_array(arrays, 'normalisation', (4,), wpath))
        model.training_info_ = training.get('info') or {}
        return model

    def c_emitter(self):
        """Return the C emitter of this model (piezo_narx_ros.ident.narx_export)."""
        from .narx_export import NARXEmitter
        return NARXEmitter(self)

    def __repr__(self):
        return f'NARXNetwork(nu={self.nu}, ny={self.ny}, hidden={self.hidden}, seed={self.seed})'


def _r2(y, yhat):
    """Coefficient of determination 1 - SSE/SST (for training_info_ only)."""
    d = y - y.mean()
    return float(1.0 - np.sum((y - yhat) ** 2) / np.sum(d * d))
