"""
Linear noise model of the residuals, so that the correlation tests judge the innovations.

Billings (Nonlinear System Identification, 2013, ch. 5) applies the correlation tests to the
residuals of the process model *plus its noise model* (NARMAX): a residual that is coloured only
because noise enters the output through the lags (output-error noise seen by a one-step predictor
is a moving average of the sensor noise) does not mean that the process model misses a term. Here
the noise model is a linear autoregression of the residuals ε (m),

    ε(k) = a1 ε(k-1) + ... + ap ε(k-p) + e(k),

fitted by least squares on the ESTIMATION residuals only (order p by BIC, 0 <= p <= max_order) and
then applied as a fixed whitening filter e(k) = ε(k) - Σ aj ε(k-j) to the validation residuals. An
AR(p) is the truncated inverse of an MA noise model, and is linear least squares.

Why this keeps the tests honest: the filter uses past residuals only, never the input, so whatever
of the residual the input can still predict (a missing linear or nonlinear process term) stays in
the innovations and is still caught by φuε, φu²'ε, φu²'ε² and φε(εu); and because the filter is
fixed from the estimation half, it cannot adapt to the validation data it is judged on.

The free-run estimate (what the estimator publishes) is the process model alone: the noise model is
for validation only.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from piezo_narx_ros.errors import DataError

NOISE_MODELS = ('none', 'ar')


@dataclass(frozen=True)
class ARNoiseModel:
    """Whitening filter e(k) = ε(k) - Σ_j coef[j-1] ε(k-j), j = 1..order (coef unit-free)."""

    coef: np.ndarray          # (order,) AR coefficients a1..ap
    residual_std: float       # std of the estimation innovations, m
    input_std: float          # std of the estimation residuals it was fitted on, m

    @property
    def order(self) -> int:
        """Return the number of AR coefficients p (the residual history the filter needs)."""
        return int(self.coef.size)

    def whiten(self, residuals) -> np.ndarray:
        """
        Innovations (N - order,) of residuals (N,).

        The first `order` samples only fill the filter's history, so they are dropped.
        """
        e = np.asarray(residuals, dtype=np.float64)
        p = self.order
        if e.ndim != 1 or e.size <= p:
            raise DataError(f'noise model: need a 1-D residual longer than its order {p}, got '
                            f'shape {e.shape}')
        out = e[p:].copy()
        for j in range(1, p + 1):
            out -= self.coef[j - 1] * e[p - j:e.size - j]
        return out

    def to_dict(self) -> dict:
        """JSON-ready description (kind, order, coefficients, stds in m)."""
        return {'kind': 'ar', 'order': self.order, 'coef': self.coef.tolist(),
                'residual_std': self.residual_std, 'input_std': self.input_std}

    @classmethod
    def from_dict(cls, doc) -> 'ARNoiseModel':
        """Inverse of to_dict (numbers only are read); DataError when malformed."""
        try:
            coef = np.asarray(doc['coef'], dtype=np.float64).reshape(-1)
            if doc.get('kind') != 'ar' or coef.size != int(doc['order']) \
                    or not np.all(np.isfinite(coef)):
                raise ValueError
            return cls(coef=coef, residual_std=float(doc['residual_std']),
                       input_std=float(doc['input_std']))
        except (AttributeError, KeyError, TypeError, ValueError):
            raise DataError('noise model: malformed description (need kind ar, order, coef, '
                            'residual_std, input_std)') from None


def _lagged(e: np.ndarray, p: int, start: int) -> tuple[np.ndarray, np.ndarray]:
    """Regressors [ε(k-1) .. ε(k-p)] and targets ε(k) for k = start..N-1."""
    n = e.size
    X = np.empty((n - start, p))
    for j in range(1, p + 1):
        X[:, j - 1] = e[start - j:n - j]
    return X, e[start:]


def fit_ar_noise_model(residuals, max_order: int = 20, criterion: str = 'bic') -> ARNoiseModel:
    """
    AR noise model of estimation residuals ε (m), order 0..max_order chosen by BIC or AIC.

    Every order is scored on the same samples k >= max_order, so the criteria compare like with
    like. Order 0 (no filter) is chosen when the residuals are already white.
    """
    e = np.asarray(residuals, dtype=np.float64)
    max_order = int(max_order)
    if e.ndim != 1 or not np.all(np.isfinite(e)):
        raise DataError('noise model: residuals must be a finite 1-D array')
    if max_order < 0:
        raise DataError(f'noise model: max_order must be >= 0, got {max_order}')
    if criterion not in ('bic', 'aic'):
        raise DataError(f'noise model: criterion must be bic or aic, got {criterion!r}')
    if e.size < 10 * (max_order + 1):
        raise DataError(f'noise model: {e.size} residual samples are too few for order '
                        f'{max_order} (need >= {10 * (max_order + 1)})')
    e = e - e.mean()
    X, t = _lagged(e, max_order, max_order)
    n = t.size
    penalty = np.log(n) if criterion == 'bic' else 2.0
    # Nested least squares from one Cholesky factor of the Gram matrix G = X^T X = L L^T: with
    # z = L^-1 X^T t the residual sum of squares of the first p columns is |t|^2 - sum(z[:p]^2),
    # and their coefficients solve L[:p,:p]^T c = z[:p]. einsum, not a BLAS QR of the tall X: a
    # threaded BLAS call on a busy machine stalled for 250 ms where this takes ~5 ms.
    tt = float(np.einsum('k,k->', t, t))
    if max_order:
        gram = np.einsum('ki,kj->ij', X, X)
        scale = np.sqrt(np.maximum(np.diag(gram), 1e-300))
        try:   # scaled for conditioning; a constant residual makes G singular
            chol = np.linalg.cholesky(gram / np.outer(scale, scale))
            z = np.linalg.solve(chol, np.einsum('ki,k->i', X, t) / scale)
        except np.linalg.LinAlgError:
            chol, z = np.zeros((0, 0)), np.zeros(0)
    else:
        chol, z = np.zeros((0, 0)), np.zeros(0)
    rss = tt - np.concatenate([[0.0], np.cumsum(z * z)])
    orders = np.arange(rss.size)
    with np.errstate(divide='ignore', invalid='ignore'):
        score = n * np.log(np.maximum(rss, 0.0) / n) + orders * penalty
    score[~np.isfinite(score)] = np.inf
    p = int(np.argmin(score)) if np.any(np.isfinite(score)) else 0
    coef = np.linalg.solve(chol[:p, :p].T, z[:p]) / scale[:p] if p else np.zeros(0)
    resid = t - np.einsum('ki,i->k', X[:, :p], coef) if p else t
    return ARNoiseModel(coef=np.asarray(coef, dtype=np.float64),
                        residual_std=float(np.std(resid)), input_std=float(np.std(e)))


def noise_models_from_doc(doc):
    """
    Return an ARNoiseModel from its description, or a list of them (one per output) from a list.

    Several outputs store one noise model per output (scoring.fit_noise_models); DataError
    when malformed.
    """
    if isinstance(doc, list):
        return [ARNoiseModel.from_dict(d) for d in doc]
    return ARNoiseModel.from_dict(doc)


def describe(doc) -> str:
    """Return 'AR(p) noise model' ('AR(p, q, ...)' per output for several), or 'raw'."""
    if not doc:
        return 'raw'
    if isinstance(doc, list):
        return 'AR(' + ', '.join(str(d.get('order')) for d in doc) + ') noise models'
    return f'AR({doc["order"]}) noise model'
