"""
Numba kernels of the several-axes envelope structure (mimo.py states it).

The features of one sample (plays of each input, stops of each stage-1 output, the running
amplitude), the local blend and the free-run step and simulation, in normalised units.
"""
import math

import numpy as np
from numba import njit


@njit(cache=True)
def n_cross(n_out, cross):
    """Return the number of product features of n_out stage-1 outputs (CROSS)."""
    pairs = n_out * (n_out - 1) // 2
    return (pairs if cross >= 1 else 0) + (2 * pairs if cross >= 2 else 0)


# ------------------------------------------------------------------------------ kernels
@njit(cache=True)
def _play(p, v, r):
    """Return a play operator's new output: its last output p held within [v - r, v + r]."""
    if p < v - r:
        return v - r
    if p > v + r:
        return v + r
    return p


@njit(cache=True)
def _features_row(un, yt, st, ur, yr, env_w, env_lam, cross, x, i_up, i_yp, i_env):
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
            p = _play(st[i_up + j * ur.size + r], un[j], ur[r])
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
            p = _play(st[i_yp + i * yr.size + r], yt[i], yr[r])
            st[i_yp + i * yr.size + r] = p
            x[f] = yt[i] - p
            f += 1
    if cross >= 1:
        for i in range(n_out):
            for j in range(i + 1, n_out):
                x[f] = yt[i] * yt[j]
                f += 1
    if cross >= 2:
        for i in range(n_out):
            for j in range(n_out):
                if j != i:
                    x[f] = yt[i] * abs(yt[j])
                    f += 1


@njit(cache=True)
def cross_of(n_in, n_out, nf, ur, yr):
    """Return the CROSS setting that n_f features per sample imply."""
    extra = nf - n_in * (2 + ur.size) - n_out * (4 + yr.size)
    return 0 if extra == 0 else (1 if extra == n_cross(n_out, 1) else 2)


@njit(cache=True)
def features(un, yt, st, ur, yr, env_w, env_lam, cross):
    """Return features X (N, n_f) of normalised inputs un (N, n_in), stage-1 outputs yt."""
    n_in, n_out = un.shape[1], yt.shape[1]
    nf = n_in * (2 + ur.size) + n_out * (4 + yr.size) + n_cross(n_out, cross)
    X = np.empty((un.shape[0], nf))
    i_yp = n_in * ur.size
    i_env = i_yp + n_out * yr.size
    for k in range(un.shape[0]):
        _features_row(un[k], yt[k], st, ur, yr, env_w, env_lam, cross, X[k], 0, i_yp, i_env)
    return X


@njit(cache=True)
def work_size(n_in, n_out, nf, n_local):
    """Return the length of step's scratch: features, stage-1 and local outputs, weights."""
    return nf + n_out + n_local * (n_out + 1) + n_in


@njit(cache=True, fastmath=True)
def dot(a, b, lo, n):
    """
    Return sum a[k] b[lo + k], k < n.

    The compiler may reorder the sum (vector lanes); the C export sums in order, equal to
    rounding. b is sliced first: indexed as b[lo + k] the loop stayed scalar (the index may be
    negative, so numba wraps it), 3.3x slower (4.6 against 1.4 us for the FSM's six 1512-term
    sums per step, measured side by side).
    """
    bb = b[lo:lo + n]
    s = 0.0
    for k in range(n):
        s += a[k] * bb[k]
    return s


@njit(cache=True)
def blend_weights(e, centres, w):
    """Fill w (L,) with the local models' weights at amplitude e: hats on the centres."""
    n_local = centres.size
    w[:] = 0.0
    if n_local == 1:
        w[0] = 1.0
        return
    ec = min(max(e, centres[0]), centres[n_local - 1])
    j = 0
    while j < n_local - 2 and ec > centres[j + 1]:
        j += 1
    t = (ec - centres[j]) / (centres[j + 1] - centres[j])
    w[j] = 1.0 - t
    w[j + 1] = t


@njit(cache=True)
def step(u, st, out, work, ur, yr, env_w, env_lam, a1, B1, a_out, B0, Bh, centres, u_scale,
         y_scale):
    """
    Advance the state st by one input u (n_in,) V; fill out (n_out,) with y(k) in m.

    work: scratch of work_size(). Returns False (state untouched) when u is not finite. B0
    (L n_out, n_f) and Bh (L n_out, n n_f) are the output numerators of the current features
    and of the feature history (row l n_out + i, history columns in the state's order), a_out
    (L, n) the local denominators.
    """
    n_in, n_out = u.size, out.size
    n = a1.size
    nf = B0.shape[1]
    n_local = a_out.shape[0]
    for j in range(n_in):
        if not math.isfinite(u[j]):
            return False
    x = work[:nf]
    yt = work[nf:nf + n_out]
    yl = work[nf + n_out:nf + n_out + n_local * n_out]
    wl = work[nf + n_out + n_local * n_out:nf + n_out + n_local * (n_out + 1)]
    un = work[nf + n_out + n_local * (n_out + 1):nf + n_out + n_local * (n_out + 1) + n_in]
    i_yp = n_in * ur.size
    i_env = i_yp + n_out * yr.size
    i_x = i_env + 1
    i_yt = i_x + n * nf
    i_y = i_yt + n * n_out
    i_yl = i_y + n * n_out if n_local > 1 else i_y
    # Stage 1: yt(k) from the input history (the first n_in features are the inputs).
    for i in range(n_out):
        s = 0.0
        for j in range(n_in):
            s += B1[i, j, 0] * (u[j] / u_scale[j])
            for lag in range(1, n + 1):
                s += B1[i, j, lag] * st[i_x + (lag - 1) * nf + j]
        for lag in range(1, n + 1):
            s -= a1[lag - 1] * st[i_yt + (lag - 1) * n_out + i]
        yt[i] = s
    for j in range(n_in):
        un[j] = u[j] / u_scale[j]
    _features_row(un, yt, st, ur, yr, env_w, env_lam, cross_of(n_in, n_out, nf, ur, yr), x, 0,
                  i_yp, i_env)
    for r in range(n_local * n_out):
        lo = i_yl + (r // n_out) * n * n_out + r % n_out
        s = dot(B0[r], x, 0, nf) + dot(Bh[r], st, i_x, n * nf)
        for lag in range(1, n + 1):
            s -= a_out[r // n_out, lag - 1] * st[lo + (lag - 1) * n_out]
        yl[r] = s
    blend_weights(math.sqrt(st[i_env]), centres, wl)
    for i in range(n_out):
        s = 0.0
        for m in range(n_local):
            s += wl[m] * yl[m * n_out + i]
        out[i] = s
    # Shift the histories (newest first) and store this sample.
    # One row at a time, newest last: rows do not overlap, so each is a plain copy.
    for lag in range(n - 1, 0, -1):
        st[i_x + lag * nf:i_x + (lag + 1) * nf] = st[i_x + (lag - 1) * nf:i_x + lag * nf]
    st[i_x:i_x + nf] = x
    for k in range(n * n_out - 1, n_out - 1, -1):
        st[i_yt + k] = st[i_yt + k - n_out]
        st[i_y + k] = st[i_y + k - n_out]
    if n_local > 1:
        for m in range(n_local):
            lo = i_yl + m * n * n_out
            for k in range(n * n_out - 1, n_out - 1, -1):
                st[lo + k] = st[lo + k - n_out]
            for i in range(n_out):
                st[lo + i] = yl[m * n_out + i]
    for i in range(n_out):
        st[i_yt + i] = yt[i]
        st[i_y + i] = out[i]
        out[i] *= y_scale[i]
    return True


@njit(cache=True)
def simulate(u, st, ur, yr, env_w, env_lam, a1, B1, a_out, B0, Bh, centres, u_scale, y_scale):
    """Run u (N, n_in) V freely from state st (advanced in place); returns (N, n_out) m."""
    n_local = a_out.shape[0]
    n_out = B0.shape[0] // n_local
    y = np.empty((u.shape[0], n_out))
    work = np.empty(work_size(u.shape[1], n_out, B0.shape[1], n_local))
    for k in range(u.shape[0]):
        if not step(u[k], st, y[k], work, ur, yr, env_w, env_lam, a1, B1, a_out, B0, Bh,
                    centres, u_scale, y_scale):
            y[k:] = np.nan
            break
    return y
