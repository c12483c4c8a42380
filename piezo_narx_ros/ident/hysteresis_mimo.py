"""
The envelope family on several axes: hysteresis operators per input, a common linear MIMO part.

HysteresisNARX fitted on n_in inputs and n_out outputs (more than one of either) uses this
structure instead of the one-axis network (ident/hysteresis.py); the one-axis model is unchanged.
All signals are normalised per channel (un_j = u_j / u_scale_j, yn_i = y_i / y_scale_i):

    A(q) yt_i = sum_j B1_ij(q) un_j              stage 1: linear MIMO, common denominator A
    x(k) = [un_j, plays p_r(un_j), un_j e,       operators per input, amplitude e
            yt_i, yt_i |yt_i|, stops yt_i - p_s(yt_i), yt_i e, yt_i e^2]     on the stage-1 states
    e(k) = sqrt(low-pass of sum_j w_j un_j^2)    the input's running amplitude (tau ENV_TAU_S)
    A(q) yn_i = sum_f B_if(q) x_f                output: the same denominator, a numerator per
                                                 feature and output (n_out x n_f numerators)

A(q) = 1 + a_1 q^-1 + ... + a_n q^-n, B(q) = b_0 + ... + b_n q^-n, n = `mimo_order`.

Why (bench/bench_fsm_envelope.py, docs/mimo.md): the Fine Steering Mirror's linear part needs a
high order (28 in the published baseline), its gain rises with amplitude (piezo hysteresis) and
its resonances shift with amplitude (a softening stiffness). Plays of each input carry the
hysteresis; features of the stage-1 response yt (the resonant motion) filtered again by 1/A make
double poles, which is how a numerator moves a resonance; scaled by the running amplitude e they
move it with the amplitude. The output feedback is linear (A, stability checked) and every
feature is bounded for a bounded input, so the free run is bounded; the model is a NARX
y(k) = -sum a_l y(k-l) + sum b x(k-l) over well-chosen regressors of the input history.

Fit (no torch): the denominator by Steiglitz-McBride iterations (least squares on signals
filtered by the previous 1/A, the common denominator shared by every output), kept at the
iteration of lowest free-run error and made stable; then every numerator by one weighted least
squares on the features filtered by 1/A, which is the free-run (output) error itself because
the output feedback is fixed. Each record starts wherever it is (not at rest): its free response
(homogeneous solutions of 1/A) is fitted as a nuisance per record and output, and the stage-1
state likewise, so no sample is thrown away. Each record is weighted by 1 / its output RMS, so
small-amplitude records count as much as large ones (relative error).
"""
import math

import numpy as np
from numba import njit
from scipy.signal import lfilter

from ..errors import DataError
from .checks import input_vector
from .kernels import step_rows

#: Play radii of each input, fractions of its largest |u| (normalised units).
U_RADII = (0.02, 0.05, 0.1, 0.2, 0.4)
#: Play radii of each stage-1 output (stops yt - p(yt)), fractions of the output's RMS.
Y_RADII = (0.15, 0.3, 0.6, 1.2)
#: Time constant of the running amplitude e, s.
ENV_TAU_S = 0.02
#: Steiglitz-McBride iterations for the common denominator.
SK_ITER = 8
#: Records are weighted by (output RMS)^-WEIGHT_POWER: 1 balances relative errors.
WEIGHT_POWER = 1.0
#: Largest pole modulus kept (poles outside are reflected inside, then shrunk to this).
MAX_POLE = 0.999


def n_features(n_in, n_out):
    """Features per sample: 2 n_in + n_in len(U_RADII) + n_out (4 + len(Y_RADII))."""
    return n_in * (2 + len(U_RADII)) + n_out * (4 + len(Y_RADII))


def state_layout(n_in, n_out, order):
    """Return {part: (start, stop)} of the kernel state vector and its size."""
    nf = n_features(n_in, n_out)
    sizes = (('u_plays', n_in * len(U_RADII)), ('y_plays', n_out * len(Y_RADII)), ('env', 1),
             ('x_hist', order * nf), ('yt_hist', order * n_out), ('y_hist', order * n_out))
    out, k = {}, 0
    for name, n in sizes:
        out[name] = (k, k + n)
        k += n
    return out, k


# ------------------------------------------------------------------------------ kernels
@njit(cache=True)
def _features_row(un, yt, st, ur, yr, env_w, env_lam, x, i_up, i_yp, i_env):
    """Advance the operators (plays, amplitude) by one sample and fill x (n_f,)."""
    n_in, n_out = un.size, yt.size
    e2 = env_lam * st[i_env]
    for j in range(n_in):
        e2 += (1.0 - env_lam) * env_w[j] * un[j] * un[j]
    st[i_env] = e2
    e = math.sqrt(e2)
    f = 0
    for j in range(n_in):
        x[f] = un[j]
        f += 1
    for j in range(n_in):
        for r in range(ur.size):
            p = st[i_up + j * ur.size + r]
            if p < un[j] - ur[r]:
                p = un[j] - ur[r]
            elif p > un[j] + ur[r]:
                p = un[j] + ur[r]
            st[i_up + j * ur.size + r] = p
            x[f] = p
            f += 1
    for j in range(n_in):
        x[f] = un[j] * e
        f += 1
    for i in range(n_out):
        x[f] = yt[i]
        x[f + 1] = yt[i] * abs(yt[i])
        x[f + 2] = yt[i] * e
        x[f + 3] = yt[i] * e * e
        f += 4
    for i in range(n_out):
        for r in range(yr.size):
            p = st[i_yp + i * yr.size + r]
            if p < yt[i] - yr[r]:
                p = yt[i] - yr[r]
            elif p > yt[i] + yr[r]:
                p = yt[i] + yr[r]
            st[i_yp + i * yr.size + r] = p
            x[f] = yt[i] - p
            f += 1


@njit(cache=True)
def features(un, yt, st, ur, yr, env_w, env_lam):
    """Return features X (N, n_f) of normalised inputs un (N, n_in), stage-1 outputs yt."""
    n_in, n_out = un.shape[1], yt.shape[1]
    nf = n_in * (2 + ur.size) + n_out * (4 + yr.size)
    X = np.empty((un.shape[0], nf))
    i_yp = n_in * ur.size
    i_env = i_yp + n_out * yr.size
    for k in range(un.shape[0]):
        _features_row(un[k], yt[k], st, ur, yr, env_w, env_lam, X[k], 0, i_yp, i_env)
    return X


@njit(cache=True)
def step(u, st, out, x, yt, ur, yr, env_w, env_lam, a, B1, B, u_scale, y_scale):
    """
    Advance the state st by one input u (n_in,) V; fill out (n_out,) with y(k) in m.

    x (n_f,), yt (n_out,): scratch. Returns False (state untouched) when u is not finite.
    """
    n_in, n_out = u.size, out.size
    n = a.size
    nf = x.size
    for j in range(n_in):
        if not math.isfinite(u[j]):
            return False
    i_yp = n_in * ur.size
    i_env = i_yp + n_out * yr.size
    i_x = i_env + 1
    i_yt = i_x + n * nf
    i_y = i_yt + n * n_out
    # Stage 1: yt(k) from the input history (the first n_in features are the inputs).
    for i in range(n_out):
        s = 0.0
        for j in range(n_in):
            s += B1[i, j, 0] * (u[j] / u_scale[j])
            for lag in range(1, n + 1):
                s += B1[i, j, lag] * st[i_x + (lag - 1) * nf + j]
        for lag in range(1, n + 1):
            s -= a[lag - 1] * st[i_yt + (lag - 1) * n_out + i]
        yt[i] = s
    un = np.empty(n_in)
    for j in range(n_in):
        un[j] = u[j] / u_scale[j]
    _features_row(un, yt, st, ur, yr, env_w, env_lam, x, 0, i_yp, i_env)
    for i in range(n_out):
        s = 0.0
        for f in range(nf):
            s += B[i, f, 0] * x[f]
        for lag in range(1, n + 1):
            row = i_x + (lag - 1) * nf
            for f in range(nf):
                s += B[i, f, lag] * st[row + f]
            s -= a[lag - 1] * st[i_y + (lag - 1) * n_out + i]
        out[i] = s
    # Shift the histories (newest first) and store this sample.
    for k in range(n * nf - 1, nf - 1, -1):
        st[i_x + k] = st[i_x + k - nf]
    for f in range(nf):
        st[i_x + f] = x[f]
    for k in range(n * n_out - 1, n_out - 1, -1):
        st[i_yt + k] = st[i_yt + k - n_out]
        st[i_y + k] = st[i_y + k - n_out]
    for i in range(n_out):
        st[i_yt + i] = yt[i]
        st[i_y + i] = out[i]
        out[i] *= y_scale[i]
    return True


@njit(cache=True)
def simulate(u, st, ur, yr, env_w, env_lam, a, B1, B, u_scale, y_scale):
    """Run u (N, n_in) V freely from state st (advanced in place); returns (N, n_out) m."""
    n_out = B.shape[0]
    nf = B.shape[1]
    y = np.empty((u.shape[0], n_out))
    x = np.empty(nf)
    yt = np.empty(n_out)
    for k in range(u.shape[0]):
        if not step(u[k], st, y[k], x, yt, ur, yr, env_w, env_lam, a, B1, B, u_scale, y_scale):
            y[k:] = np.nan
            break
    return y


# ------------------------------------------------------------------------------ fitting
def _lags(x, n):
    """[x(k), x(k-1), .., x(k-n)] as columns (N, n + 1) of a 1-D signal, zeros before 0."""
    out = np.zeros((x.size, n + 1))
    for lag in range(n + 1):
        out[lag:, lag] = x[:x.size - lag]
    return out


def _homogeneous(a, n_samples):
    """Return free responses of 1/A(q) (N, n): impulse responses starting at 0 .. n-1."""
    n = a.size - 1
    imp = lfilter([1.0], a, np.r_[1.0, np.zeros(n_samples - 1)])
    H = np.zeros((n_samples, n))
    for m in range(n):
        H[m:, m] = imp[:n_samples - m]
    return H


def _stabilise(a):
    """Return A(q) with every root inside MAX_POLE (outside roots reflected, then shrunk)."""
    roots = np.roots(a)
    mag = np.abs(roots)
    roots = np.where(mag > 1.0, roots / (mag * mag), roots)
    mag = np.abs(roots)
    roots = np.where(mag > MAX_POLE, roots * (MAX_POLE / np.maximum(mag, 1e-300)), roots)
    return np.real(np.poly(roots))


def frequency_response(us, ys, seg):
    """
    Pooled MIMO frequency response G (bins, n_out, n_in) at the bins k/seg of 0 < f < fs/2.

    Every record is cut into segments of seg samples (one period of a periodic excitation is
    leakage-free); per bin G = S_yu S_uu^-1 over every segment of every record (the best linear
    approximation of the pooled data). Returns (G, z^-1 at the bins, usable mask): a bin is
    usable when S_uu is well conditioned (every input excited there, independently).
    """
    U, Y = [], []
    # Segments shorter than 8192 samples cut a record that is not periodic in them: a Hann
    # window and half overlap keep their leakage down (8192: the periods of a multisine).
    window = np.hanning(seg)[:, None] if seg < 8192 else np.ones((seg, 1))
    hop = seg // 2 if seg < 8192 else seg
    for un, yn in zip(us, ys):
        for k in range(0, un.shape[0] - seg + 1, hop):
            U.append(np.fft.rfft(un[k:k + seg] * window, axis=0)[1:seg // 2])
            Y.append(np.fft.rfft(yn[k:k + seg] * window, axis=0)[1:seg // 2])
    U, Y = np.stack(U, -1), np.stack(Y, -1)           # (bins, channels, segments)
    Suu = np.einsum('kjs,kls->kjl', U, U.conj())
    Syu = np.einsum('kis,kls->kil', Y, U.conj())
    ev = np.linalg.eigvalsh(Suu)
    usable = ev[:, 0] > 1e-6 * np.max(ev[:, -1])
    G = np.zeros(Syu.shape, dtype=complex)
    G[usable] = np.linalg.solve(Suu[usable].transpose(0, 2, 1),
                                Syu[usable].transpose(0, 2, 1)).transpose(0, 2, 1)
    zinv = np.exp(-2j * np.pi * np.arange(1, seg // 2) / seg)
    return G, zinv, usable


def fit_denominator(us, ys, order, iterations=SK_ITER + 2):
    """
    Return the common denominator A (order + 1,), stage-1 numerators B1 (n_out, n_in, order + 1).

    Sanathanan-Koerner iterations on the pooled frequency response (frequency_response): the
    least squares of A(z) G_ij - B_ij(z), weighted by 1 / |A_prev(z)|, one A for every entry;
    made stable at the end.
    """
    n = order
    n_in, n_out = us[0].shape[1], ys[0].shape[1]
    # The longest segments (finest resolution, up to 8192 samples) that still give every bin
    # 4 n_in segments to average: independent input directions at every frequency.
    seg = 8192
    while seg > 4 * (n + 1) and sum(u.shape[0] // seg for u in us) < 4 * n_in:
        seg //= 2
    G, zinv, usable = frequency_response(us, ys, seg)
    if np.count_nonzero(usable) < 2 * n:
        raise DataError(f'the estimation data do not excite the {n_in} inputs independently at '
                        f'enough frequencies for dynamics of order {n}')
    G, zinv = G[usable], zinv[usable]
    V = zinv[:, None] ** np.arange(n + 1)              # z^-l, l = 0..n
    a = np.r_[1.0, np.zeros(n)]
    for _ in range(iterations):
        w = 1.0 / np.abs(V @ a)
        Nrm = np.zeros((n, n))
        rhs = np.zeros(n)
        blocks = {}
        for i in range(n_out):
            for j in range(n_in):
                # Columns [a_1..a_n | b_ij,0..n]: A G - B = 0 with A's leading 1 moved right.
                Ma = (V[:, 1:] * G[:, i, j:j + 1]) * w[:, None]
                Mb = -V * w[:, None]
                t = -G[:, i, j] * w
                Ma = np.vstack([Ma.real, Ma.imag])
                Mb = np.vstack([Mb.real, Mb.imag])
                t = np.r_[t.real, t.imag]
                # Eliminate b_ij (its own block) : Schur complement onto a.
                Pb = np.linalg.pinv(Mb)
                Ra = Ma - Mb @ (Pb @ Ma)
                rt = t - Mb @ (Pb @ t)
                Nrm += Ra.T @ Ra
                rhs += Ra.T @ rt
                blocks[i, j] = (Pb, Ma, t)
        a = np.r_[1.0, np.linalg.solve(Nrm + 1e-12 * np.trace(Nrm) / n * np.eye(n), rhs)]
    a = _stabilise(a)
    # Numerators for the stable A: least squares of B_ij(z) ~ A(z) G_ij, weighted by 1/|A|.
    w = 1.0 / np.abs(V @ a)
    B1 = np.zeros((n_out, n_in, n + 1))
    Mb = V * w[:, None]
    Mb = np.vstack([Mb.real, Mb.imag])
    Pb = np.linalg.pinv(Mb)
    for i in range(n_out):
        for j in range(n_in):
            t = (V @ a) * G[:, i, j] * w
            B1[i, j] = Pb @ np.r_[t.real, t.imag]
    return a, B1


def stage1(a, B1, un, yn):
    """Return the stage-1 output yt (N, n_out) of one record, its free response fitted to yn."""
    H = _homogeneous(a, un.shape[0])
    yt = np.empty((un.shape[0], B1.shape[0]))
    for i in range(B1.shape[0]):
        y = sum(lfilter(B1[i, j], a, un[:, j]) for j in range(un.shape[1]))
        yt[:, i] = y + H @ np.linalg.lstsq(H, yn[:, i] - y, rcond=None)[0]
    return yt


def initial_env(un, env_w, env_lam):
    """Return the amplitude state at a record's start: its first 1/(1-lam) samples' mean square."""
    n = max(1, min(un.shape[0], int(round(1.0 / (1.0 - env_lam)))))
    return float(np.mean(un[:n] ** 2 @ env_w))


def fit_numerators(a, X_list, ys, weights, ridge=1e-7):
    """
    Return the output numerators B (n_out, n_f, n + 1) by weighted least squares (free-run error).

    Regressors: each feature filtered by q^-l / A(q), l = 0..n; each record's free response
    (homogeneous solutions of 1/A) is projected out per record (a nuisance, fitted with it).
    """
    n = a.size - 1
    nf = X_list[0].shape[1]
    n_out = ys[0].shape[1]
    size = nf * (n + 1)
    G = np.zeros((size, size))
    g = np.zeros((size, n_out))
    for X, yn, w in zip(X_list, ys, weights):
        Xf = lfilter([1.0], a, X, axis=0)
        R = np.empty((X.shape[0], size))
        for f in range(nf):
            R[:, f * (n + 1):(f + 1) * (n + 1)] = _lags(Xf[:, f], n)
        H = _homogeneous(a, X.shape[0])
        Q, _ = np.linalg.qr(H)
        R -= Q @ (Q.T @ R)
        Y = yn - Q @ (Q.T @ yn)
        G += (w * w) * (R.T @ R)
        g += (w * w) * (R.T @ Y)
    scale = np.sqrt(np.maximum(np.diag(G), 1e-300))
    Gs = G / np.outer(scale, scale) + ridge * np.eye(size)
    theta = np.linalg.solve(Gs, g / scale[:, None]) / scale[:, None]
    return np.ascontiguousarray(theta.T.reshape(n_out, nf, n + 1))


def held_state(parts, u):
    """
    Return the state of the input held at u[0] (V) until settled, amplitude from the window u.

    The window's first samples tell the amplitude the input moves with (a record that does not
    start at rest); its histories are then set from the window (estimate_state).
    """
    poles = np.abs(parts.poles())
    n = int(min(20000, max(50, math.log(1e-9) / math.log(max(float(np.max(poles)), 0.5)))))
    st = np.zeros(parts.state_size)
    parts.simulate(np.tile(u[0], (n, 1)), st)
    st[parts.layout['env'][0]] = initial_env(u / parts.u_scale, parts.env_w, parts.env_lam)
    return st


#: Window (samples) and horizon (samples) of the learned start prior, starts drawn per fit.
PRIOR_WINDOW, PRIOR_HORIZON, PRIOR_STARTS = 100, 400, 240


def _adjustable(parts):
    lay = parts.layout
    return np.r_[np.arange(*lay['yt_hist']), np.arange(*lay['y_hist'])]


def _jacobian(parts, u, candidate, idx):
    """Free-run change (N * n_out, normalised) per unit change of each candidate[idx]."""
    base = parts.simulate(u, candidate.copy()) / parts.y_scale
    cols = []
    for i in idx:
        x = candidate.copy()
        x[i] += 1.0
        cols.append((parts.simulate(u, x) / parts.y_scale - base).ravel())
    return np.column_stack(cols), base


def state_prior(parts, us, ys, seed=0):
    """
    Return the learned prior of the start correction and the free run's RMS error per output (m).

    At PRIOR_STARTS random samples of the estimation records, the model's true state (its free
    run from the record's start) is compared with the candidate estimate_state starts from (the
    input held there): the correction of the stage-1 and output histories that best turns the
    candidate's free run over PRIOR_HORIZON samples into the true one is recorded (it also makes
    up for the unknown input history, which the candidate cannot know). Its mean and covariance
    are the prior estimate_state weighs a window against.
    """
    rng = np.random.default_rng(seed)
    idx = _adjustable(parts)
    err, deltas = [], []
    J = None
    per = max(1, PRIOR_STARTS // len(us))
    for u, y in zip(us, ys):
        k_lo = max(4 * parts.order, u.shape[0] // 4)
        k_hi = u.shape[0] - PRIOR_HORIZON
        starts = np.sort(rng.integers(k_lo, k_hi, per)) if k_hi > k_lo else []
        st = np.zeros(parts.state_size)
        prev = 0
        for k0 in starts:
            parts.simulate(u[prev:k0], st)
            prev = k0
            seg = u[k0:k0 + PRIOR_HORIZON]
            cand = held_state(parts, seg[:PRIOR_WINDOW])
            if J is None:
                J, _ = _jacobian(parts, seg, cand, idx)
                pinv = np.linalg.pinv(J, rcond=1e-10)
            true = parts.simulate(seg, st.copy()) / parts.y_scale
            base = parts.simulate(seg, cand.copy()) / parts.y_scale
            deltas.append(pinv @ (true - base).ravel())
        sim = parts.simulate(u, np.zeros(parts.state_size))
        err.append(sim[k_lo:] - y[k_lo:])
    err = np.vstack(err)
    rms = np.sqrt(np.mean(err * err, axis=0))
    d = np.array(deltas)
    if d.shape[0] < 2:
        return np.zeros(idx.size), np.eye(idx.size), rms
    cov = np.cov(d.T)
    # Shrunk toward its diagonal: fewer starts than dimensions would leave it singular.
    cov = 0.9 * cov + 0.1 * np.diag(np.diag(cov)) + 1e-9 * np.trace(cov) / idx.size * np.eye(
        idx.size)
    return d.mean(axis=0), cov, rms


#: Relative weight of the sensor-offset prior: std of an output's offset as a fraction of the
#: output's RMS (a record whose sensor zero moved a little; the FSM's outputs are centred).
OFFSET_PRIOR = 0.02


def estimate_state(model, parts, u, y, candidate):
    """
    Return (state vector, offsets m, info) at u[0] explaining the window u (N, n_in), y (N, n_out).

    The correction of the stage-1 and output histories that enter linearly, by its posterior
    mean: the window's residual, weighted by the free run's training error per output, against
    the learned prior of the correction (state_prior) and a small offset prior. Exact in one
    step (the free run is linear in those histories).
    """
    idx = _adjustable(parts)
    J, base = _jacobian(parts, u, candidate, idx)
    sig = np.maximum(parts.resid_rms, 1e-3 * parts.y_scale) / parts.y_scale
    n_out = parts.n_out
    k = idx.size
    w = np.tile(1.0 / sig, u.shape[0])
    Jw = np.column_stack([J * w[:, None], np.kron(np.ones((u.shape[0], 1)), np.diag(1.0 / sig))])
    r = ((y / parts.y_scale - base) / sig).ravel()
    P = np.zeros((k + n_out, k + n_out))
    P[:k, :k] = np.linalg.inv(parts.state_cov)
    P[k:, k:] = np.eye(n_out) / OFFSET_PRIOR ** 2
    mu = np.r_[parts.state_mean, np.zeros(n_out)]
    delta = np.linalg.solve(Jw.T @ Jw + P, Jw.T @ r + P @ mu)
    values = candidate.copy()
    values[idx] += delta[:k]
    fit = (r - Jw @ delta).reshape(-1, n_out) * sig * parts.y_scale
    return values, delta[k:] * parts.y_scale, {'rms_m': float(np.sqrt(np.mean(fit * fit)))}


class MimoParts:
    """The fitted arrays of the several-axes structure (normalised units; see module docstring)."""

    def __init__(self, a, B1, B, u_scale, y_scale, env_w, env_lam):
        self.a = np.ascontiguousarray(a[1:], dtype=np.float64)      # a_1 .. a_n
        self.B1 = np.ascontiguousarray(B1, dtype=np.float64)
        self.B = np.ascontiguousarray(B, dtype=np.float64)
        self.u_scale = np.ascontiguousarray(u_scale, dtype=np.float64)
        self.y_scale = np.ascontiguousarray(y_scale, dtype=np.float64)
        self.env_w = np.ascontiguousarray(env_w, dtype=np.float64)
        self.env_lam = float(env_lam)
        self.ur = np.array(U_RADII, dtype=np.float64)
        self.yr = np.array(Y_RADII, dtype=np.float64)
        self.n_in, self.n_out = self.B1.shape[1], self.B1.shape[0]
        self.order = self.a.size
        if self.B.shape != (self.n_out, n_features(self.n_in, self.n_out), self.order + 1) \
                or self.B1.shape[2] != self.order + 1:
            raise DataError('several-axes envelope arrays do not match each other')
        self.layout, self.state_size = state_layout(self.n_in, self.n_out, self.order)

    @property
    def args(self):
        """Return the kernel arguments after (u, st): operators, dynamics, scales."""
        return (self.ur, self.yr, self.env_w, self.env_lam, np.r_[1.0, self.a][1:], self.B1,
                self.B, self.u_scale, self.y_scale)

    def poles(self):
        """Return the roots of A(q) (z-plane)."""
        return np.roots(np.r_[1.0, self.a])

    def simulate(self, u, st):
        """Run u (N, n_in) V freely from state st (advanced in place): (N, n_out) m."""
        return simulate(np.ascontiguousarray(u, dtype=np.float64), st, *self.args)

    def operator_features(self, u):
        """Return the features X (N, n_f) of u (N, n_in) V run from rest (stage 1 included)."""
        un = u / self.u_scale
        a = np.r_[1.0, self.a]
        yt = np.column_stack([sum(lfilter(self.B1[i, j], a, un[:, j])
                                  for j in range(self.n_in)) for i in range(self.n_out)])
        st = np.zeros(self.n_in * self.ur.size + self.n_out * self.yr.size + 1)
        return features(np.ascontiguousarray(un), np.ascontiguousarray(yt), st, self.ur,
                        self.yr, self.env_w, self.env_lam)

    def predict(self, u, y):
        """Return the one-step-ahead output (N, n_out) m: features from rest, measured lags."""
        X = self.operator_features(u)
        yn = y / self.y_scale
        n, N = self.order, u.shape[0]
        out = np.zeros((N, self.n_out))
        for i in range(self.n_out):
            for f in range(X.shape[1]):
                out[:, i] += lfilter(self.B[i, f], [1.0], X[:, f])
            out[:, i] -= lfilter(np.r_[0.0, self.a], [1.0], yn[:, i])
        out *= self.y_scale
        out[:n] = y[:n]
        return out

    def arrays(self):
        """Return the named arrays of the model file."""
        return {'mimo_a': self.a, 'mimo_B1': self.B1, 'mimo_B': self.B,
                'mimo_u_scale': self.u_scale, 'mimo_y_scale': self.y_scale,
                'mimo_env_w': self.env_w, 'mimo_state_mean': self.state_mean,
                'mimo_state_cov': self.state_cov, 'mimo_resid_rms': self.resid_rms}

    @classmethod
    def from_arrays(cls, arrays, env_lam):
        """Return MimoParts from the model file's arrays (names as `arrays()`)."""
        parts = cls(np.r_[1.0, arrays['mimo_a']], arrays['mimo_B1'], arrays['mimo_B'],
                    arrays['mimo_u_scale'], arrays['mimo_y_scale'], arrays['mimo_env_w'],
                    env_lam)
        k = 2 * parts.order * parts.n_out
        parts.state_mean = np.asarray(arrays['mimo_state_mean']).reshape(k)
        parts.state_cov = np.asarray(arrays['mimo_state_cov']).reshape(k, k)
        parts.resid_rms = np.asarray(arrays['mimo_resid_rms']).reshape(parts.n_out)
        return parts


def fit(us, ys, fs, order):
    """
    Fit the several-axes structure on records us (N_r, n_in) V, ys (N_r, n_out) m.

    Returns (MimoParts, info).
    """
    import time
    t0 = time.perf_counter()
    u_all, y_all = np.vstack(us), np.vstack(ys)
    u_scale = np.max(np.abs(u_all), axis=0)
    y_scale = np.std(y_all, axis=0)
    if np.any(u_scale == 0) or np.any(y_scale == 0):
        raise DataError('estimation data has a constant input or output channel; cannot fit')
    u_rms = np.sqrt(np.mean((u_all / u_scale) ** 2, axis=0))
    env_w = 1.0 / (u_rms * u_rms * u_scale.size)
    env_lam = math.exp(-1.0 / (ENV_TAU_S * fs))
    uns = [np.ascontiguousarray(u / u_scale) for u in us]
    yns = [np.ascontiguousarray(y / y_scale) for y in ys]
    weights = [max(float(np.sqrt(np.mean(y * y))), 1e-12) ** -WEIGHT_POWER for y in yns]
    a, B1 = fit_denominator(uns, yns, order)
    t1 = time.perf_counter()
    X_list = []
    ur, yr = np.array(U_RADII), np.array(Y_RADII)
    n_in, n_out = u_scale.size, y_scale.size
    for un, yn in zip(uns, yns):
        yt = stage1(a, B1, un, yn)
        st = np.zeros(n_in * ur.size + n_out * yr.size + 1)
        st[-1] = initial_env(un, env_w, env_lam)
        X_list.append(features(un, np.ascontiguousarray(yt), st, ur, yr, env_w, env_lam))
    B = fit_numerators(a, X_list, yns, weights)
    parts = MimoParts(a, B1, B, u_scale, y_scale, env_w, env_lam)
    parts.state_mean, parts.state_cov, parts.resid_rms = state_prior(parts, us, ys)
    info = {'denominator_seconds': t1 - t0, 'fit_seconds': time.perf_counter() - t0,
            'max_pole': float(np.max(np.abs(parts.poles()))), 'order': int(order),
            'n_features': int(B.shape[1]), 'record_weights': [float(w) for w in weights]}
    return parts, info


class MimoStepper:
    """
    Stepper of a several-axes HysteresisNARX: step(u_k (n_in,) V) -> y_k (n_out,) m.

    One compiled call per step on a preallocated state; step and peek return a NEW (n_out,)
    array (offset added), the one allocation per step.
    """

    def __init__(self, model):
        self._model = model
        self._parts = model.mimo_
        self.n_in, self.n_out = self._parts.n_in, self._parts.n_out
        self.nu, self.ny = model.nu, model.ny
        self._args = self._parts.args
        self._st = np.zeros(self._parts.state_size)
        self._scratch = np.zeros_like(self._st)
        self._out = np.zeros(self.n_out)
        self._x = np.zeros(self._parts.B.shape[1])
        self._yt = np.zeros(self.n_out)
        self._u_hist = np.zeros((self.nu, self.n_in))
        #: Added to every output (m, (n_out,)): the sensor offsets of a ModelState.
        self.offset = np.zeros(self.n_out)

    def set_state(self, values, offset):
        """Continue from a state vector (kernel layout, normalised) and offsets (m)."""
        self._st = np.array(values, dtype=np.float64)
        self.offset = np.array(offset, dtype=np.float64).reshape(self.n_out)
        lo, _ = self._parts.layout['x_hist']
        nf = self._x.size
        rows = [self._st[lo + k * nf: lo + k * nf + self.n_in] for k in range(self.nu)]
        self._u_hist = np.array(rows[::-1]).reshape(self.nu, self.n_in) * self._parts.u_scale

    def reset(self, u_past=None, y_past=None):
        """Restart from rest, feed u_past (nu, n_in) V; y_past (ny, n_out) m sets the outputs."""
        self._st = self._model._mimo_initial_state(u_past, y_past)
        self._u_hist = np.zeros((self.nu, self.n_in)) if u_past is None else \
            np.array(u_past, dtype=np.float64).reshape(self.nu, self.n_in)

    def step(self, u_k):
        """
        Feed one input sample u_k (n_in,) V; returns the free-run output y(k) (n_out,) m.

        A non-finite u_k raises DataError and leaves the state untouched.
        """
        u = input_vector(u_k, self.n_in)
        if not step(u, self._st, self._out, self._x, self._yt, *self._args):
            raise DataError(f'stepper input must be finite voltages, got {u_k!r}')
        self._u_hist[:-1] = self._u_hist[1:]
        self._u_hist[-1] = u
        return self._out + self.offset

    def step_many(self, u):
        """Feed input rows u (n, n_in) V in order; returns the outputs (n, n_out) m (step_rows)."""
        return step_rows(self, u)

    def peek(self, u_k):
        """Return the output step(u_k) would return (n_out,) m, without changing the state."""
        u = input_vector(u_k, self.n_in)
        self._scratch[:] = self._st
        if not step(u, self._scratch, self._out, self._x, self._yt, *self._args):
            raise DataError(f'stepper input must be finite voltages, got {u_k!r}')
        return self._out + self.offset

    @property
    def state(self):
        """Return the current ModelState (kernel state, normalised; offsets per output, m)."""
        from .state import ModelState
        return ModelState(self._st.copy(), self.offset.copy())

    @property
    def kernel_state(self):
        """Return the live state array and the kernel parameters (read, never write)."""
        return (self._st,), self._args

    @property
    def u_past(self):
        """Copy of the last nu inputs (nu, n_in), V."""
        return self._u_hist.copy()

    @property
    def y_past(self):
        """Copy of the last ny outputs (ny, n_out), m (offset included)."""
        lo, _ = self._parts.layout['y_hist']
        n = self.ny * self.n_out
        rows = self._st[lo:lo + n].reshape(self.ny, self.n_out)[::-1]
        return rows * self._parts.y_scale + self.offset
