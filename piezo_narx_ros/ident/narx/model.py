"""
NARX network: one hidden layer of logistic (sigmoid) units and a linear output.

    y(k) = f(u(k), ..., u(k-nu), y(k-1), ..., y(k-ny))
    f(x) = ym + ys * (w2 . sigmoid(W1 xn + b1) + b2),   xn = (x - mean) / std   per signal (u or y)

The normalisation (u_mean, u_std, y_mean, y_std) is fitted on the estimation data only. Training
(torch, imported only inside fit) lives in training.py; inference uses the numba kernels.

Several inputs and outputs: one network with n_out linear outputs over the lags of every channel
(regressors.py), y(k) = ym + ys * (W2 sigmoid(W1 xn + b1) + b2), each channel normalised by its
own mean and std; weights W1 (H, n_in (nu+1) + n_out ny), W2 (n_out, H), b2 (n_out,).
"""
import time

import numpy as np

from ...errors import ConfigError, DataError, ModelFileError
from .. import document
from ..base import register_family
from .kernels import (NARXStepper, NARXVectorStepper, channel_lag_weights, narx_predict,
                      narx_predict_mimo, narx_simulate, narx_simulate_mimo)
from .regressors import LaggedModel, check_orders

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
        """Regressor size nu + 1 + ny (n_in (nu + 1) + n_out ny with channels)."""
        return self.n_in * (self.nu + 1) + self.n_out * self.ny

    @property
    def n_params(self):
        """Return the number of trainable weights H (d + 1) + n_out (H + 1)."""
        return self.hidden * (self.n_inputs + 1) + self.n_out * (self.hidden + 1)

    def _is_fitted(self):
        return self.W1 is not None

    # ---------------------------------------------------------------- weights
    def set_weights(self, W1, b1, w2, b2, normalisation):
        """
        Set the weights in normalised units.

        W1 : (H, nu+1+ny) input weights, columns in regressor order
             [u(k)..u(k-nu), y(k-1)..y(k-ny)];
        b1 : (H,); w2 : (H,); b2 : scalar; normalisation : (u_mean V, u_std V, y_mean m, y_std m).
        Several channels: w2 (n_out, H), b2 (n_out,), normalisation (u_mean (n_in,), u_std
        (n_in,), y_mean (n_out,), y_std (n_out,)); n_in / n_out follow from their shapes.
        """
        if np.ndim(w2) == 2:
            return self._set_channel_weights(W1, b1, w2, b2, normalisation)
        self.n_in_ = self.n_out_ = 1
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

    def _set_channel_weights(self, W1, b1, W2, b2, normalisation):
        try:
            um, us, ym, ys = (np.array(a, dtype=np.float64).ravel() for a in normalisation)
        except (TypeError, ValueError):
            raise DataError('normalisation must be (u_mean, u_std, y_mean, y_std) arrays '
                            'per channel') from None
        W2 = np.array(W2, dtype=np.float64)
        n_out, n_in = W2.shape[0], um.size
        H = self.hidden
        d = n_in * (self.nu + 1) + n_out * self.ny
        W1 = np.array(W1, dtype=np.float64)
        b1 = np.array(b1, dtype=np.float64).ravel()
        b2 = np.array(b2, dtype=np.float64).ravel()
        if W1.shape != (H, d) or b1.shape != (H,) or W2.shape != (n_out, H) \
                or b2.shape != (n_out,) or us.size != n_in or ys.size != n_out \
                or ym.size != n_out:
            raise DataError(f'NARX weights for {n_in} input(s) and {n_out} output(s) must be W1 '
                            f'{(H, d)}, b1 ({H},), W2 ({n_out}, {H}), b2 ({n_out},); got W1 '
                            f'{W1.shape}, b1 {b1.shape}, W2 {W2.shape}, b2 {b2.shape}')
        if np.any(us <= 0) or np.any(ys <= 0):
            raise DataError('normalisation stds must be > 0')
        for name, a in (('W1', W1), ('b1', b1), ('W2', W2), ('b2', b2),
                        ('normalisation', np.r_[um, us, ym, ys])):
            if not np.all(np.isfinite(a)):
                raise DataError(f'NARX weight {name} contains NaN or infinite values')
        self.n_in_, self.n_out_ = n_in, n_out
        self.W1, self.b1, self.w2, self.b2 = W1, b1, W2, b2
        self.normalisation = (um, us, ym, ys)
        self._fold()
        return self

    def _fold(self):
        """Fold the normalisation into raw-unit, time-ordered kernel weights."""
        if not self._scalar_io:
            um, us, ym, ys = self.normalisation
            mean = np.r_[np.repeat(um, self.nu + 1), np.repeat(ym, self.ny)]
            std = np.r_[np.repeat(us, self.nu + 1), np.repeat(ys, self.ny)]
            Wr = self.W1 / std
            self._b1r = self.b1 - Wr @ mean
            self._Wu, self._Wy = channel_lag_weights(Wr, self.nu, self.ny, self.n_in,
                                                     self.n_out)
            self._w2r = np.ascontiguousarray(self.w2 * ys[:, None])
            self._b2r = ym + ys * self.b2
            return
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

        u (N,) or (N, n_in) V, y (N,) or (N, n_out) m, or lists of such for several records (no
        regressor row or free-run segment spans two records); returns self.

        Stage 1: Levenberg-Marquardt on the one-step error (seeded restarts, early stopping on a
        held-out tail). Stage 2: simulation-error LM on free-run segments, kept only if the
        held-out free-run error improves. u_val/y_val (if given) are only scored into
        ``training_info_``, never used for a choice, so they stay an honest validation set.
        """
        from . import training  # torch lives there; inference never imports it

        opts = self.training_options
        if (u_val is None) != (y_val is None):
            raise DataError('give both u_val and y_val, or neither')
        u_list, y_list = self._records(u, y, min_len=self.n0 + 20)
        u, y = np.concatenate(u_list), np.concatenate(y_list)
        if self._scalar_io:
            us, ys = float(u.std()), float(y.std())
            if us == 0 or ys == 0:
                raise DataError('estimation data is constant (zero variance in u or y); '
                                'cannot fit')
            norm = np.array([u.mean(), us, y.mean(), ys])
            mu_u, sd_u, mu_y, sd_y = norm
        else:
            mu_u, sd_u, mu_y, sd_y = u.mean(axis=0), u.std(axis=0), y.mean(axis=0), y.std(axis=0)
            if np.any(sd_u == 0) or np.any(sd_y == 0):
                flat = [f'u{i + 1}' for i in np.flatnonzero(sd_u == 0)] + \
                    [f'y{i + 1}' for i in np.flatnonzero(sd_y == 0)]
                raise DataError(f'estimation data is constant in {", ".join(flat)} (zero '
                                'variance); cannot fit')
            norm = (mu_u, sd_u, mu_y, sd_y)
        t0 = time.perf_counter()
        un = [(x - mu_u) / sd_u for x in u_list]
        yn = [(x - mu_y) / sd_y for x in y_list]
        W1, b1, w2, b2, info = training.train_narx(
            un if len(un) > 1 else un[0], yn if len(yn) > 1 else yn[0], self.nu, self.ny,
            self.hidden, self.seed, **opts)
        self.set_weights(W1, b1, w2, b2, norm)
        self._record_ranges(u, y, fs)
        info['fit_seconds'] = time.perf_counter() - t0
        if u_val is not None and y_val is not None:
            u_val = self._signal(u_val, 'u_val', self.n_in, min_len=self.n0 + 1)
            y_val = self._signal(y_val, 'y_val', self.n_out, n=len(u_val))
            n0 = self.n0
            info['val_r2_predict'] = _r2(y_val[n0:], self._one_step(u_val, y_val, n0)[n0:])
            info['val_r2_simulate'] = _r2(y_val[n0:], np.reshape(
                self.simulate(u_val, y_val[:n0]), y_val.shape)[n0:])
        self.training_info_ = info
        return self

    # ---------------------------------------------------------------- inference
    def _kernel_params(self):
        return (self._Wu, self._Wy, self._b1r, self._w2r, self._b2r)

    def _one_step(self, u, y, start):
        run = narx_predict if self._scalar_io else narx_predict_mimo
        return run(u, y, start, *self._kernel_params())

    def _simulate_inplace(self, u, y, start):
        run = narx_simulate if self._scalar_io else narx_simulate_mimo
        run(u, y, start, *self._kernel_params())

    def _make_stepper(self, u_past, y_past):
        if self._scalar_io:
            return NARXStepper(self._kernel_params(), self.nu, self.ny, u_past, y_past)
        return NARXVectorStepper(self._kernel_params(), self.nu, self.ny, self.n_in, self.n_out,
                                 u_past, y_past)

    # ------------------------------------------------------------------ model file and export
    def file_document(self):
        """Return the NARX blocks of the model file (structure, normalisation, training)."""
        norm = (self.normalisation.tolist() if self._scalar_io
                else [a.tolist() for a in self.normalisation])
        return {'structure': {'kind': 'narx', 'nu': self.nu, 'ny': self.ny,
                              'hidden': self.hidden, 'activation': self.activation,
                              'output': 'linear', 'n_params': self.n_params},
                'normalisation': dict(zip(('u_mean', 'u_std', 'y_mean', 'y_std'), norm)),
                'training': {'seed': self.seed, 'options': self.training_options,
                             'info': self.training_info_}}

    def file_weights(self):
        """
        Return W1, b1, w2, b2 (1,) and the normalisation (4,) as written to the .npz.

        Several channels: W1, b1, W2 (n_out, H), b2 (n_out,), u_norm (2, n_in) and y_norm
        (2, n_out) (rows mean, std).
        """
        if not self._scalar_io:
            um, us, ym, ys = self.normalisation
            return {'W1': self.W1, 'b1': self.b1, 'W2': self.w2, 'b2': self.b2,
                    'u_norm': np.vstack([um, us]), 'y_norm': np.vstack([ym, ys])}
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
        n_in, n_out = document.channel_counts(doc, name)
        if n_in > 1 or n_out > 1:
            d = n_in * (nu + 1) + n_out * ny
            un = document.weight_array(arrays, 'u_norm', (2, n_in), wpath)
            yn = document.weight_array(arrays, 'y_norm', (2, n_out), wpath)
            model.set_weights(document.weight_array(arrays, 'W1', (hidden, d), wpath),
                              document.weight_array(arrays, 'b1', (hidden,), wpath),
                              document.weight_array(arrays, 'W2', (n_out, hidden), wpath),
                              document.weight_array(arrays, 'b2', (n_out,), wpath),
                              (un[0], un[1], yn[0], yn[1]))
            model.training_info_ = training.get('info') or {}
            return model
        d = nu + 1 + ny
        model.set_weights(document.weight_array(arrays, 'W1', (hidden, d), wpath),
                          document.weight_array(arrays, 'b1', (hidden,), wpath),
                          document.weight_array(arrays, 'w2', (hidden,), wpath),
                          document.weight_array(arrays, 'b2', (1,), wpath)[0],
                          document.weight_array(arrays, 'normalisation', (4,), wpath))
        model.training_info_ = training.get('info') or {}
        return model

    def c_emitter(self):
        """Return the C emitter of this model (piezo_narx_ros.ident.narx.export)."""
        from .export import NARXChannelEmitter, NARXEmitter
        return NARXEmitter(self) if self._scalar_io else NARXChannelEmitter(self)

    def __repr__(self):
        axes = '' if self._scalar_io else f', {self.n_in}x{self.n_out}'
        return (f'NARXNetwork(nu={self.nu}, ny={self.ny}, hidden={self.hidden}, '
                f'seed={self.seed}{axes})')


def _r2(y, yhat):
    """Coefficient of determination 1 - SSE/SST (for training_info_ only)."""
    d = y - y.mean(axis=0)
    return float(1.0 - np.sum((y - yhat) ** 2) / np.sum(d * d))
