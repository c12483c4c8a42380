"""
The envelope family on several axes: hysteresis operators per input, a common linear MIMO part.

HysteresisNARX fitted on n_in inputs and n_out outputs (more than one of either) uses this
structure instead of the one-axis network (hysteresis/model.py); the one-axis model is unchanged.
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

from ...errors import DataError
from ..data.checks import input_vector
from ..data.filters import lfilter
from ..narx.kernels import step_rows
from .mimo_kernels import blend_weights, features, n_cross, simulate, step, work_size

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
#: No pole nearer z = 1 than this many times the lowest frequency the data excite (_stabilise).
SLOWEST_FACTOR = 3.0


#: Products of two stage-1 outputs among the features: 0 none (files before them), 1 yt_i yt_j
#: (i < j), 2 also yt_i |yt_j| (i != j). The axes' motions mix (a mirror's tilt moves every
#: reference point): on the FSM they take 5 % off the error at 200 and 300 mV.
CROSS = 2


def n_features(n_in, n_out, cross=CROSS):
    """Features per sample: n_in (2 + len(U_RADII)) + n_out (4 + len(Y_RADII)) + products."""
    return n_in * (2 + len(U_RADII)) + n_out * (4 + len(Y_RADII)) + n_cross(n_out, cross)


def state_layout(n_in, n_out, order, n_local=1, cross=CROSS):
    """
    Return {part: (start, stop)} of the kernel state vector and its size.

    y_hist holds the (blended) outputs; with n_local > 1 local output models, yl_hist holds
    each one's own output history (local-model-major), which is what their dynamics use.
    """
    nf = n_features(n_in, n_out, cross)
    sizes = (('u_plays', n_in * len(U_RADII)), ('y_plays', n_out * len(Y_RADII)), ('env', 1),
             ('x_hist', order * nf), ('yt_hist', order * n_out), ('y_hist', order * n_out),
             ('yl_hist', order * n_out * n_local if n_local > 1 else 0))
    out, k = {}, 0
    for name, n in sizes:
        out[name] = (k, k + n)
        k += n
    return out, k


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


def _stabilise(a, slowest=0.0):
    """
    Return A(q) with every root inside MAX_POLE and at least `slowest` (rad/sample) from z = 1.

    Roots outside the unit circle are reflected inside, then shrunk to MAX_POLE. The data say
    nothing below their lowest excited frequency f_min: a pole nearer z = 1 than a few times
    f_min lets the response between 0 and f_min, and so the static gain, take any value
    (measured on the FSM: static gains of 140 where the data's are near 2, and held
    inputs that start a free run 30 µm off). Such a root is moved out along 1 - z.
    """
    roots = np.roots(a)
    mag = np.abs(roots)
    roots = np.where(mag > 1.0, roots / (mag * mag), roots)
    mag = np.abs(roots)
    roots = np.where(mag > MAX_POLE, roots * (MAX_POLE / np.maximum(mag, 1e-300)), roots)
    gap = np.abs(1.0 - roots)
    roots = np.where(gap < slowest, 1.0 - (1.0 - roots) * (slowest / np.maximum(gap, 1e-300)),
                     roots)
    return np.real(np.poly(roots))


#: Relative RMS difference below which a record repeats with a period (periodic steady state).
PERIODIC_TOL = 0.01
#: Longest segment of the pooled frequency response, samples.
MAX_SEGMENT = 1 << 16


def periodic_with(u, seg):
    """Return whether u (N, n_in) repeats with period seg samples (two periods at least)."""
    n = u.shape[0] // seg
    if n < 2:
        return False
    first = u[:seg]
    diff = max(float(np.sqrt(np.mean((u[k * seg:(k + 1) * seg] - first) ** 2)))
               for k in range(1, n))
    return diff <= PERIODIC_TOL * max(float(np.sqrt(np.mean(first * first))), 1e-300)


def leakage_free(u, seg):
    """
    Return whether segments of seg samples of u (N, n_in) need no window.

    They do not when a segment is the whole record, or one period of a record in periodic
    steady state.
    """
    return u.shape[0] == seg or periodic_with(u, seg)


def segment_length(us, n_in, order):
    """
    Return the segment length (samples, a power of two) of the pooled frequency response.

    The longest (finest resolution, least leakage) with enough segments for every bin: n_in + 1
    when every segment is leakage-free (whole records or periods: each realisation gives an
    input direction, the periods average the noise), else 4 n_in windowed segments (a noise
    input's spectra need averaging).
    """
    seg = 1 << int(math.log2(min(MAX_SEGMENT, max(u.shape[0] for u in us))))
    while seg > 4 * (order + 1):
        count = sum(u.shape[0] // seg for u in us)
        free = all(leakage_free(u, seg) for u in us if u.shape[0] >= seg)
        if count >= (n_in + 1 if free else 4 * n_in):
            break
        seg //= 2
    # Records of several periods: one period per segment (a longer one adds only bins the
    # excitation leaves empty).
    while seg > 4 * (order + 1) and all(periodic_with(u, seg // 2)
                                        for u in us if u.shape[0] >= seg):
        seg //= 2
    return seg


def frequency_response(us, ys, seg, weights=None):
    """
    Pooled MIMO frequency response G (bins, n_out, n_in) at the bins k/seg of 0 < f < fs/2.

    Every record is cut into segments of seg samples; per bin G = S_yu S_uu^-1 over every
    segment of every record (the best linear approximation of the pooled data), each segment
    normalised by its input power (a small-amplitude segment counts as much as a large one,
    as the numerators' relative-error weights) and weighted by the mean over it of `weights`
    (list of (N,) per record, default 1). Leakage-free segments (`leakage_free`) are taken as
    they are; others get a Hann window and half overlap. Returns (G, z^-1 at the bins, usable
    mask): a bin is usable when S_uu is well conditioned (every input excited there,
    independently).
    """
    U, Y = [], []
    hann = np.hanning(seg)[:, None]
    for r, (un, yn) in enumerate(zip(us, ys)):
        window, hop = (np.ones((seg, 1)), seg) if leakage_free(un, seg) else (hann, seg // 2)
        for k in range(0, un.shape[0] - seg + 1, hop):
            w = 1.0 if weights is None else float(np.mean(weights[r][k:k + seg]))
            c = math.sqrt(w / max(float(np.mean(un[k:k + seg] ** 2)), 1e-300))
            if c > 0.0:
                U.append(c * np.fft.rfft(un[k:k + seg] * window, axis=0)[1:seg // 2])
                Y.append(c * np.fft.rfft(yn[k:k + seg] * window, axis=0)[1:seg // 2])
    U, Y = np.stack(U, -1), np.stack(Y, -1)           # (bins, channels, segments)
    Suu = np.einsum('kjs,kls->kjl', U, U.conj())
    Syu = np.einsum('kis,kls->kil', Y, U.conj())
    ev = np.linalg.eigvalsh(Suu)
    # Bins the excitation leaves empty (a multisine's, or beyond its band) hold noise only.
    usable = (ev[:, 0] > 1e-6 * np.max(ev[:, -1])) & (ev[:, 0] > 1e-3 * np.median(ev[:, 0]))
    G = np.zeros(Syu.shape, dtype=complex)
    G[usable] = np.linalg.solve(Suu[usable].transpose(0, 2, 1),
                                Syu[usable].transpose(0, 2, 1)).transpose(0, 2, 1)
    zinv = np.exp(-2j * np.pi * np.arange(1, seg // 2) / seg)
    return G, zinv, usable


def fit_denominator(us, ys, order, weights=None, iterations=SK_ITER + 2):
    """
    Return the common denominator A (order + 1,), stage-1 numerators B1 (n_out, n_in, order + 1).

    Sanathanan-Koerner iterations on the pooled frequency response (frequency_response, with
    the samples' `weights`): the least squares of A(z) G_ij - B_ij(z), weighted by
    1 / |A_prev(z)|, one A for every entry; made stable at the end.
    """
    n = order
    n_in, n_out = us[0].shape[1], ys[0].shape[1]
    G, zinv, usable = frequency_response(us, ys, segment_length(us, n_in, n), weights)
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
        # Every b_ij block has the same columns: one pseudo-inverse per iteration.
        Mb = -V * w[:, None]
        Mb = np.vstack([Mb.real, Mb.imag])
        Pb = np.linalg.pinv(Mb)
        for i in range(n_out):
            for j in range(n_in):
                # Columns [a_1..a_n | b_ij,0..n]: A G - B = 0 with A's leading 1 moved right.
                Ma = (V[:, 1:] * G[:, i, j:j + 1]) * w[:, None]
                t = -G[:, i, j] * w
                Ma = np.vstack([Ma.real, Ma.imag])
                t = np.r_[t.real, t.imag]
                # Eliminate b_ij (its own block) : Schur complement onto a.
                Ra = Ma - Mb @ (Pb @ Ma)
                rt = t - Mb @ (Pb @ t)
                Nrm += Ra.T @ Ra
                rhs += Ra.T @ rt
        a = np.r_[1.0, np.linalg.solve(Nrm + 1e-12 * np.trace(Nrm) / n * np.eye(n), rhs)]
    a = _stabilise(a, SLOWEST_FACTOR * float(-np.angle(zinv[0])))
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


def running_amplitude(un, env_w, env_lam, init):
    """Return e (N,): the kernel's running amplitude of normalised inputs un (N, n_in)."""
    s = (un * un) @ env_w
    return np.sqrt(lfilter([1.0 - env_lam], [1.0, -env_lam], s, zi=[env_lam * init])[0])


def blend(e, centres):
    """Return the local models' weights (N, L) at amplitudes e (N,) (blend_weights)."""
    W = np.empty((e.size, centres.size))
    for k in range(e.size):
        blend_weights(float(e[k]), centres, W[k])
    return W


def normal_equations(a_out, X_list, ys, weights, W_list):
    """
    Return the weighted normal equations (G, g) of the output numerators (free-run error).

    Regressors: each feature filtered by q^-l / A_m(q), l = 0..n, times the local model's
    weight W[:, m] (output blending); each record's free responses (homogeneous solutions of
    every 1/A_m, weighted alike) are projected out per record (a nuisance fitted with it).
    Columns are local-model-major, then feature, then lag.
    """
    n_local, n = len(a_out), a_out[0].size - 1
    nf = X_list[0].shape[1]
    block = nf * (n + 1)
    size = n_local * block
    G = np.zeros((size, size))
    g = np.zeros((size, ys[0].shape[1]))
    for X, yn, w, W in zip(X_list, ys, weights, W_list):
        active = [m for m in range(n_local) if np.any(W[:, m] > 0.0)]
        cols = np.concatenate([np.arange(m * block, (m + 1) * block) for m in active])
        R = np.empty((X.shape[0], len(active) * block))
        H = []
        for k, m in enumerate(active):
            Xf = lfilter([1.0], a_out[m], X, axis=0)
            for f in range(nf):
                lo = k * block + f * (n + 1)
                R[:, lo:lo + n + 1] = _lags(Xf[:, f], n) * W[:, m:m + 1]
            H.append(_homogeneous(a_out[m], X.shape[0]) * W[:, m:m + 1])
        Q, _ = np.linalg.qr(np.hstack(H))
        R -= Q @ (Q.T @ R)
        Y = yn - Q @ (Q.T @ yn)
        G[np.ix_(cols, cols)] += (w * w) * (R.T @ R)
        g[cols] += (w * w) * (R.T @ Y)
    return G, g


#: Ridge of the numerators' normal equations, relative to their (unit-scaled) diagonal.
RIDGE = 1e-10


def solve_numerators(G, g, n_local, nf, n, ridge=RIDGE):
    """Return the output numerators B (L, n_out, n_f, n + 1) of the normal equations (G, g)."""
    scale = np.sqrt(np.maximum(np.diag(G), 1e-300))
    Gs = G / np.outer(scale, scale) + ridge * np.eye(G.shape[0])
    theta = np.linalg.solve(Gs, g / scale[:, None]) / scale[:, None]
    return np.ascontiguousarray(theta.T.reshape(g.shape[1], n_local, nf, n + 1)
                                .transpose(1, 0, 2, 3))


def held_state(parts, u):
    """
    Return the state of the input brought slowly from rest to u[0] (V) and held there.

    The steady state itself (no simulation): plays where a slow ramp leaves them, every history
    at the DC response. The amplitude is the window's (u's first samples: a record that does
    not start at rest moves with it), and the features hold it; estimate_state then sets the
    histories from the window.
    """
    un0 = np.asarray(u[0], dtype=np.float64) / parts.u_scale
    e2 = initial_env(u / parts.u_scale, parts.env_w, parts.env_lam)
    yt0 = (parts.B1.sum(axis=2) @ un0) / (1.0 + parts.a.sum())
    small = np.zeros(parts.layout['env'][1])
    small[-1] = e2
    # A pole of 1 on the amplitude keeps it; plays from 0 move to where a ramp leaves them.
    x0 = features(un0[None], yt0[None], small, parts.ur, parts.yr, parts.env_w, 1.0,
                  parts.cross)[0]
    yl0 = (parts.B.sum(axis=3) @ x0) / (1.0 + parts.a_out.sum(axis=1))[:, None]
    w = np.empty(parts.n_local)
    blend_weights(math.sqrt(e2), parts.centres, w)
    st = np.zeros(parts.state_size)
    st[:small.size] = small
    n, lay = parts.order, parts.layout
    for name, row in (('x_hist', x0), ('yt_hist', yt0), ('y_hist', w @ yl0)):
        st[lay[name][0]:lay[name][1]] = np.tile(row, n)
    if parts.n_local > 1:
        st[lay['yl_hist'][0]:lay['yl_hist'][1]] = np.concatenate([np.tile(r, n) for r in yl0])
    return st


#: Window (samples) and horizon (samples) of the learned start prior, starts drawn per fit.
PRIOR_WINDOW, PRIOR_HORIZON, PRIOR_STARTS = 100, 400, 240


def adjustable(parts):
    """Return the state indices estimate_state adjusts: stage-1 and output dynamics' histories."""
    return np.r_[np.arange(*parts.layout['yt_hist']), np.arange(*parts.output_histories())]


def _jacobian(parts, u, candidate, idx):
    """
    Free-run change (N * n_out, normalised) per unit change of each candidate[idx].

    The output models' own histories enter linearly: their columns are free responses of
    1 / A_l (weighted as the run blends them); any other index by a run of the kernel.
    """
    base = parts.simulate(u, candidate.copy()) / parts.y_scale
    n, n_out, N = parts.order, parts.n_out, u.shape[0]
    lo, hi = parts.output_histories()
    e = running_amplitude(u / parts.u_scale, parts.env_w, parts.env_lam,
                          candidate[parts.layout['env'][0]])
    W = blend(e, parts.centres)
    impulse = np.r_[1.0, np.zeros(N - 1)]
    cols = []
    for i in idx:
        col = np.zeros((N, n_out))
        if lo <= i < hi:
            m, rest = divmod(i - lo, n * n_out)
            lag, out = divmod(rest, n_out)
            a = parts.a_out[m]
            # y(-lag-1) = 1 reaches y(k) as 1/A driven by -a_{lag+1}, .., -a_n.
            col[:, out] = W[:, m] * lfilter(-a[lag:], np.r_[1.0, a], impulse)
        else:
            x = candidate.copy()
            x[i] += 1.0
            col = parts.simulate(u, x) / parts.y_scale - base
        cols.append(col.ravel())
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
    idx = adjustable(parts)
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
    idx = adjustable(parts)
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


#: The model file's arrays of local output models (absent for one output model).
LOCAL_ARRAYS = ('mimo_a_out', 'mimo_centres')


class MimoParts:
    """The fitted arrays of the several-axes structure (normalised units; see module docstring)."""

    def __init__(self, a, B1, B, u_scale, y_scale, env_w, env_lam, a_out=None, centres=None):
        self.a = np.ascontiguousarray(a[1:], dtype=np.float64)      # stage 1: a_1 .. a_n
        self.B1 = np.ascontiguousarray(B1, dtype=np.float64)
        B = np.asarray(B, dtype=np.float64)
        # One output model: B (n_out, n_f, n + 1) over the stage-1 denominator (as before the
        # local models); several: B (L, n_out, n_f, n + 1), a_out (L, n), centres (L,).
        self.B = np.ascontiguousarray(B[None] if B.ndim == 3 else B)
        self.a_out = (self.a[None].copy() if a_out is None
                      else np.ascontiguousarray(a_out, dtype=np.float64))
        self.centres = (np.zeros(1) if centres is None
                        else np.ascontiguousarray(centres, dtype=np.float64))
        self.u_scale = np.ascontiguousarray(u_scale, dtype=np.float64)
        self.y_scale = np.ascontiguousarray(y_scale, dtype=np.float64)
        self.env_w = np.ascontiguousarray(env_w, dtype=np.float64)
        self.env_lam = float(env_lam)
        self.ur = np.array(U_RADII, dtype=np.float64)
        self.yr = np.array(Y_RADII, dtype=np.float64)
        self.n_in, self.n_out = self.B1.shape[1], self.B1.shape[0]
        self.order = self.a.size
        self.n_local = self.B.shape[0]
        # Files written before the product features hold fewer: the count says which.
        self.cross = next((c for c in (CROSS, 0, 1, 2)
                           if n_features(self.n_in, self.n_out, c) == self.B.shape[2]), CROSS)
        nf = n_features(self.n_in, self.n_out, self.cross)
        if (self.B.shape != (self.n_local, self.n_out, nf, self.order + 1)
                or self.B1.shape[2] != self.order + 1
                or self.a_out.shape != (self.n_local, self.order)
                or self.centres.shape != (self.n_local,)
                or (self.n_local > 1 and np.any(np.diff(self.centres) <= 0))):
            raise DataError('several-axes envelope arrays do not match each other')
        self.layout, self.state_size = state_layout(self.n_in, self.n_out, self.order,
                                                    self.n_local, self.cross)
        # The kernel's numerators: rows l n_out + i; the history's in the state's order.
        rows = self.n_local * self.n_out
        self.B0 = np.ascontiguousarray(self.B[..., 0].reshape(rows, nf))
        self.Bh = np.ascontiguousarray(self.B[..., 1:].transpose(0, 1, 3, 2).reshape(rows, -1))

    @property
    def n_params(self):
        """Return the number of estimated parameters (denominators and numerators)."""
        extra = self.a_out.size if self.n_local > 1 else 0
        return int(self.a.size + extra + self.B1.size + self.B.size)

    @property
    def n_features(self):
        """Return the number of operator features per sample."""
        return int(self.B.shape[2])

    @property
    def args(self):
        """Return the kernel arguments after (u, st): operators, dynamics, scales."""
        return (self.ur, self.yr, self.env_w, self.env_lam, self.a, self.B1, self.a_out,
                self.B0, self.Bh, self.centres, self.u_scale, self.y_scale)

    def poles(self):
        """Return the roots of the stage-1 and every output denominator (z-plane)."""
        return np.concatenate([np.roots(np.r_[1.0, a]) for a in (self.a, *self.a_out)])

    def simulate(self, u, st):
        """Run u (N, n_in) V freely from state st (advanced in place): (N, n_out) m."""
        return simulate(np.ascontiguousarray(u, dtype=np.float64), st, *self.args)

    def output_histories(self):
        """Return the index ranges of the histories the output dynamics use (state vector)."""
        return self.layout['yl_hist' if self.n_local > 1 else 'y_hist']

    def set_output_history(self, st, rows):
        """Set st's output histories to rows (n, n_out) of normalised outputs, newest first."""
        lo, hi = self.layout['y_hist']
        st[lo:hi] = np.asarray(rows, dtype=np.float64).ravel()
        if self.n_local > 1:
            lo, hi = self.layout['yl_hist']
            st[lo:hi] = np.tile(st[self.layout['y_hist'][0]:self.layout['y_hist'][1]],
                                self.n_local)

    def operator_features(self, u):
        """Return the features X (N, n_f) and amplitude e (N,) of u (N, n_in) V from rest."""
        un = u / self.u_scale
        a = np.r_[1.0, self.a]
        yt = np.column_stack([sum(lfilter(self.B1[i, j], a, un[:, j])
                                  for j in range(self.n_in)) for i in range(self.n_out)])
        st = np.zeros(self.n_in * self.ur.size + self.n_out * self.yr.size + 1)
        X = features(np.ascontiguousarray(un), np.ascontiguousarray(yt), st, self.ur,
                     self.yr, self.env_w, self.env_lam, self.cross)
        return X, running_amplitude(un, self.env_w, self.env_lam, 0.0)

    def predict(self, u, y):
        """
        Return the one-step-ahead output (N, n_out) m: features from rest, measured lags.

        Every local output model's lags are the measured outputs; their predictions are blended
        as in the free run. With one output model, the error is A(q) applied to the free-run
        error (docs/mimo.md).
        """
        X, e = self.operator_features(u)
        W = blend(e, self.centres)
        yn = y / self.y_scale
        n, N = self.order, u.shape[0]
        out = np.zeros((N, self.n_out))
        for m in range(self.n_local):
            for i in range(self.n_out):
                p = -lfilter(np.r_[0.0, self.a_out[m]], [1.0], yn[:, i])
                for f in range(X.shape[1]):
                    p += lfilter(self.B[m, i, f], [1.0], X[:, f])
                out[:, i] += W[:, m] * p
        out *= self.y_scale
        out[:n] = y[:n]
        return out

    def arrays(self):
        """Return the named arrays of the model file (one output model: as before local ones)."""
        out = {'mimo_a': self.a, 'mimo_B1': self.B1,
               'mimo_B': self.B[0] if self.n_local == 1 else self.B,
               'mimo_u_scale': self.u_scale, 'mimo_y_scale': self.y_scale,
               'mimo_env_w': self.env_w, 'mimo_state_mean': self.state_mean,
               'mimo_state_cov': self.state_cov, 'mimo_resid_rms': self.resid_rms}
        if self.n_local > 1:
            out.update(mimo_a_out=self.a_out, mimo_centres=self.centres)
        return out

    @classmethod
    def from_arrays(cls, arrays, env_lam):
        """Return MimoParts from the model file's arrays (names as `arrays()`)."""
        local = {}
        for key in LOCAL_ARRAYS:
            if key in arrays:
                local[key[5:]] = np.asarray(arrays[key], dtype=np.float64)
                if not np.all(np.isfinite(local[key[5:]])):
                    raise DataError(f'{key} holds non-finite values')
        if len(local) == 1:
            raise DataError('mimo_a_out and mimo_centres come together')
        parts = cls(np.r_[1.0, arrays['mimo_a']], arrays['mimo_B1'], arrays['mimo_B'],
                    arrays['mimo_u_scale'], arrays['mimo_y_scale'], arrays['mimo_env_w'],
                    env_lam, **local)
        lo, hi = parts.layout['yt_hist']
        k = (hi - lo) + (parts.output_histories()[1] - parts.output_histories()[0])
        parts.state_mean = np.asarray(arrays['mimo_state_mean']).reshape(k)
        parts.state_cov = np.asarray(arrays['mimo_state_cov']).reshape(k, k)
        parts.resid_rms = np.asarray(arrays['mimo_resid_rms']).reshape(parts.n_out)
        return parts


#: The output dynamics are scheduled on the running amplitude (two local output models) when
#: it spreads over this ratio (its 90th to 10th percentile over the estimation data).
LOCAL_SPREAD = 1.5
#: Percentiles of the running amplitude at which the local output models are centred.
LOCAL_QUANTILES = (10.0, 90.0)


def local_centres(es):
    """Return the local models' centres (L,) from the estimation records' amplitudes e."""
    q = np.percentile(np.concatenate(es), LOCAL_QUANTILES)
    if q[0] <= 0.0 or q[-1] / q[0] < LOCAL_SPREAD:
        return np.zeros(1)
    return q


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
    env0 = [initial_env(un, env_w, env_lam) for un in uns]
    es = [running_amplitude(un, env_w, env_lam, e0) for un, e0 in zip(uns, env0)]
    centres = local_centres(es)
    W_list = [blend(e, centres) for e in es]
    a, B1 = fit_denominator(uns, yns, order)
    a_out = [a] if centres.size == 1 else [
        fit_denominator(uns, yns, order, [W[:, m] for W in W_list])[0]
        for m in range(centres.size)]
    t1 = time.perf_counter()
    X_list = []
    ur, yr = np.array(U_RADII), np.array(Y_RADII)
    n_in, n_out = u_scale.size, y_scale.size
    for un, yn, e0 in zip(uns, yns, env0):
        yt = stage1(a, B1, un, yn)
        st = np.zeros(n_in * ur.size + n_out * yr.size + 1)
        st[-1] = e0
        X_list.append(features(un, np.ascontiguousarray(yt), st, ur, yr, env_w, env_lam,
                               CROSS))
    G, g = normal_equations(a_out, X_list, yns, weights, W_list)
    B = solve_numerators(G, g, centres.size, X_list[0].shape[1], order)
    parts = MimoParts(a, B1, B, u_scale, y_scale, env_w, env_lam,
                      None if centres.size == 1 else np.array([x[1:] for x in a_out]),
                      None if centres.size == 1 else centres)
    parts.state_mean, parts.state_cov, parts.resid_rms = state_prior(parts, us, ys)
    info = {'denominator_seconds': t1 - t0, 'fit_seconds': time.perf_counter() - t0,
            'max_pole': float(np.max(np.abs(parts.poles()))), 'order': int(order),
            'n_features': int(parts.n_features), 'record_weights': [float(w) for w in weights],
            'local_centres': [float(c) for c in centres]}
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
        self._work = np.zeros(work_size(self.n_in, self.n_out, self._parts.n_features,
                                        self._parts.n_local))
        #: Added to every output (m, (n_out,)): the sensor offsets of a ModelState.
        self.offset = np.zeros(self.n_out)

    def set_state(self, values, offset):
        """Continue from a state vector (kernel layout, normalised) and offsets (m)."""
        self._st = np.array(values, dtype=np.float64)
        self.offset = np.array(offset, dtype=np.float64).reshape(self.n_out)

    def reset(self, u_past=None, y_past=None):
        """Restart from rest, feed u_past (nu, n_in) V; y_past (ny, n_out) m sets the outputs."""
        self._st = self._model._mimo_initial_state(u_past, y_past)

    def step(self, u_k):
        """
        Feed one input sample u_k (n_in,) V; returns the free-run output y(k) (n_out,) m.

        A non-finite u_k raises DataError and leaves the state untouched.
        """
        u = input_vector(u_k, self.n_in)
        if not step(u, self._st, self._out, self._work, *self._args):
            raise DataError(f'stepper input must be finite voltages, got {u_k!r}')
        return self._out + self.offset

    def step_many(self, u):
        """Feed input rows u (n, n_in) V in order; returns the outputs (n, n_out) m (step_rows)."""
        return step_rows(self, u)

    def peek(self, u_k):
        """Return the output step(u_k) would return (n_out,) m, without changing the state."""
        u = input_vector(u_k, self.n_in)
        self._scratch[:] = self._st
        if not step(u, self._scratch, self._out, self._work, *self._args):
            raise DataError(f'stepper input must be finite voltages, got {u_k!r}')
        return self._out + self.offset

    @property
    def state(self):
        """Return the current ModelState (kernel state, normalised; offsets per output, m)."""
        from ..state.estimate import ModelState
        return ModelState(self._st.copy(), self.offset.copy())

    @property
    def kernel_state(self):
        """Return the live state array and the kernel parameters (read, never write)."""
        return (self._st,), self._args

    @property
    def u_past(self):
        """Copy of the last nu inputs (nu, n_in), V (from the state's feature history)."""
        lo, _ = self._parts.layout['x_hist']
        rows = self._st[lo:lo + self.nu * self._parts.n_features].reshape(self.nu, -1)
        return rows[::-1, :self.n_in] * self._parts.u_scale

    @property
    def y_past(self):
        """Copy of the last ny outputs (ny, n_out), m (offset included)."""
        lo, _ = self._parts.layout['y_hist']
        n = self.ny * self.n_out
        rows = self._st[lo:lo + n].reshape(self.ny, self.n_out)[::-1]
        return rows * self._parts.y_scale + self.offset
