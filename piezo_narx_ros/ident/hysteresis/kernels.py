"""
Compiled kernels of the hysteresis-operator NARX (numpy + numba only, never torch).

Everything here works in normalised units: un = u / u_scale, yn = y / y_scale. One sample k:

  drive    v(k) = v(k-1) + clip(un(k) - v(k-1), -rho, rho),  rho = exp(drive) (learned): the
           voltage the actuator gets when the amplifier's slew rate limits a jump (a capacitive
           load fed by a current-limited amplifier); rho large = no limit.
           With an amplifier bandwidth kap = 2*pi*f_a/fs (learned; inf = none) the drive is the
           exact end-of-sample output of dv/dt = clip(kap*(un - v), -rho, rho), un held over the
           sample (`amplifier`): a ramp at the slew limit while the error is above rho/kap, then
           the first-order decay, as the simulated amplifier (plant/)
  operators of the drive (rate-independent: frozen while the input holds)
    p_i(k)  play of radius r_i:       p_i = min(v + r_i, max(v - r_i, p_i(k-1)))
    s_j(k)  Duhem state j, along the drive's path d = v(k) - v(k-1) with sign sg and slope
            ds/dun = sg*alpha - beta*s solved exactly over the step:
                s = s*E + sg*alpha*(1 - E)/beta,  E = exp(-beta*|d|),  beta = rho^2 + BETA_MIN,
            alpha and rho chosen by the signs of d and s (6 parameters per state)
  short-term drive increments  d_j(k) = v(k-j) - v(k-j-1), j < n_lags (the drive's dynamics)
  network  w(k) = sum_h w2_h (sig(b1_h + W1_h.phi) - sig(b1_h)) + c.phi,  phi = [p, d, s]
           (zero at rest: every operator and increment is 0 there)
  creep    x_l(k) = lam_l x_l(k-1) + (1 - lam_l) w(k),  z(k) = w(k) + sum_l g_l x_l(k)
  output   yl(k) = -sum_j a_j yl(k-j) + sum_i b_i z(k-i),  yn(k) = yl(k) + y_off

Parameter vector theta = [W1 (H*d, row-major), b1 (H), w2 (H), c (d), duhem (6 per state),
drive (1: log rho; 2 with an amplifier bandwidth: log rho, log kap), g (n_creep), a (na),
b (nb+1), y_off]; `layout` gives the offsets.

The state of a free run (`step`) is one float array:
  [v(k-1) .. v(k-Lh) (Lh = max(n_lags, 1)), plays (m), duhem (q), creep (n_creep),
   z(k-1) .. z(k-nb), yl(k-1) .. yl(k-na)].
`simulate` loops `step` inside numba, so a Stepper and simulate() give the same bits.
"""
import math

import numpy as np
from numba import njit

# Smallest Duhem decay rate (normalised): keeps every Duhem state bounded, |s| <= |alpha|/BETA_MIN.
BETA_MIN = 0.01
TINY = np.finfo(np.float64).tiny


def layout(hidden, d, n_duhem, n_creep, na, nb, n_drive=1):
    """Offsets into theta: dict of name -> (start, stop), and the total size (n_drive: 1, 2)."""
    sizes = (('W1', hidden * d), ('b1', hidden), ('w2', hidden), ('c', d), ('duhem', 6 * n_duhem),
             ('drive', n_drive), ('g', n_creep), ('a', na), ('b', nb + 1), ('y_off', 1))
    out, k = {}, 0
    for name, n in sizes:
        out[name] = (k, k + n)
        k += n
    return out, k


def state_size(n_plays, n_lags, n_duhem, n_creep, na, nb):
    """Length of the free-run state array."""
    return max(n_lags, 1) + n_plays + n_duhem + n_creep + nb + na


@njit(cache=True)
def _sig(z):
    return 1.0 / (1.0 + math.exp(-z))


@njit(cache=True)
def _network(phi, W1, b1, w2, c, w_rest):
    """Evaluate w = sum_h w2_h sig(b1_h + W1_h . phi) + c . phi - w_rest (zero at rest)."""
    w = -w_rest
    for h in range(W1.shape[0]):
        zh = b1[h]
        for i in range(W1.shape[1]):
            zh += W1[h, i] * phi[i]
        w += w2[h] * _sig(zh)
    for i in range(W1.shape[1]):
        w += c[i] * phi[i]
    return w


@njit(cache=True)
def _duhem_update(s, d, al_p, al_m, r_pp, r_pm, r_mp, r_mm):
    """One exact Duhem step (see module docstring) without derivatives."""
    if d == 0.0:
        return s
    if d > 0.0:
        sg, alpha, rho = 1.0, al_p, (r_pp if s >= 0.0 else r_pm)
    else:
        sg, alpha, rho = -1.0, al_m, (r_mp if s >= 0.0 else r_mm)
    beta = rho * rho + BETA_MIN
    ad = abs(d)
    x = beta * ad
    e = math.exp(-x)
    phi = (1.0 - e) / beta if x > 1e-8 else ad * (1.0 - 0.5 * x)
    return s * e + sg * alpha * phi


@njit(cache=True)
def amplifier(prev, un_k, rho, kap):
    """
    Drive at the end of a sample from prev toward un_k held over it (normalised, per sample).

    Exact solution of dv/dt = clip(kap*(un_k - v), -rho, rho) over one sample (time in samples):
    first-order with the pole exp(-kap) while |un_k - v| <= rho/kap, else a ramp at rho until
    the error is rho/kap, then the decay. kap = inf: the plain clip (the slew-only drive).
    """
    e = un_k - prev
    if kap == np.inf:
        if e > rho:
            e = rho
        elif e < -rho:
            e = -rho
        return prev + e
    ae = abs(e)
    eps = rho / kap
    if ae <= eps:
        return un_k - e * math.exp(-kap)
    sg = 1.0 if e > 0.0 else -1.0
    t = (ae - eps) / rho
    if t >= 1.0:
        return prev + sg * rho
    return un_k - sg * eps * math.exp(-kap * (1.0 - t))


@njit(cache=True)
def amplifier_derivatives(prev, un_k, rho, kap):
    """
    Return (v, dv/dprev, dv/drho, dv/dkap) of `amplifier` (kap finite).

    Continuous across the three pieces (first-order, ramp then decay, ramp): with
    Q = exp(-kap*(1 - t)), t the ramp's share of the sample, dv/dprev = Q, dv/drho = sg*Q*t,
    dv/dkap = sg*Q*rho*(1 - t)/kap.
    """
    e = un_k - prev
    ae = abs(e)
    eps = rho / kap
    if ae <= eps:
        q = math.exp(-kap)
        return un_k - e * q, q, 0.0, e * q
    sg = 1.0 if e > 0.0 else -1.0
    t = (ae - eps) / rho
    if t >= 1.0:
        return prev + sg * rho, 1.0, sg, 0.0
    q = math.exp(-kap * (1.0 - t))
    return un_k - sg * eps * q, q, sg * q * t, sg * q * rho * (1.0 - t) / kap


@njit(cache=True)
def step(un_k, st, radii, n_lags, duhem, rho, kap, W1, b1, w2, c, w_rest, g, lam, a, b, y_off):
    """Advance the free-run state `st` by one normalised input un_k; returns yn(k)."""
    if kap == np.inf:
        dv = un_k - st[0]
        if dv > rho:
            dv = rho
        elif dv < -rho:
            dv = -rho
    else:
        dv = amplifier(st[0], un_k, rho, kap) - st[0]
    un_k = st[0] + dv
    m = radii.size
    q = duhem.shape[0]
    nl = lam.size
    na = a.size
    nb = b.size - 1
    lh = max(n_lags, 1)
    i_p = lh
    i_s = i_p + m
    i_x = i_s + q
    i_z = i_x + nl
    i_y = i_z + nb
    H, d = W1.shape
    phi = np.empty(d)
    for i in range(m):
        v = st[i_p + i]
        lo = un_k - radii[i]
        hi = un_k + radii[i]
        if v < lo:
            v = lo
        elif v > hi:
            v = hi
        st[i_p + i] = v
        phi[i] = v
    prev = un_k
    for j in range(n_lags):
        cur = prev
        prev = st[j]
        phi[m + j] = cur - prev
    dk = un_k - st[0]
    for j in range(q):
        s = _duhem_update(st[i_s + j], dk, duhem[j, 0], duhem[j, 1], duhem[j, 2], duhem[j, 3],
                          duhem[j, 4], duhem[j, 5])
        st[i_s + j] = s
        phi[m + n_lags + j] = s
    for j in range(lh - 1, 0, -1):
        st[j] = st[j - 1]
    st[0] = un_k
    w = _network(phi, W1, b1, w2, c, w_rest)
    z = w
    for il in range(nl):
        x = lam[il] * st[i_x + il] + (1.0 - lam[il]) * w
        st[i_x + il] = x
        z += g[il] * x
    yl = b[0] * z
    for i in range(nb):
        yl += b[i + 1] * st[i_z + i]
    for j in range(na):
        yl -= a[j] * st[i_y + j]
    for i in range(nb - 1, 0, -1):
        st[i_z + i] = st[i_z + i - 1]
    if nb > 0:
        st[i_z] = z
    for j in range(na - 1, 0, -1):
        st[i_y + j] = st[i_y + j - 1]
    if na > 0:
        st[i_y] = yl
    return yl + y_off


@njit(cache=True)
def step_many(un, yn, st, radii, n_lags, duhem, rho, kap, W1, b1, w2, c, w_rest, g,
              lam, a, b, y_off):
    """Run step for each normalised input un[k] in order, yn[k] filled: one call per batch."""
    for k in range(un.size):
        yn[k] = step(un[k], st, radii, n_lags, duhem, rho, kap, W1, b1, w2, c, w_rest, g, lam, a,
                     b, y_off)


@njit(cache=True)
def peek(un_k, st, scratch, radii, n_lags, duhem, rho, kap, W1, b1, w2, c, w_rest, g, lam, a,
         b, y_off):
    """
    yn(k) that `step` would return for un_k, leaving st untouched (scratch: same size as st).

    For solvers that try candidate inputs (control/).
    """
    for i in range(st.size):
        scratch[i] = st[i]
    return step(un_k, scratch, radii, n_lags, duhem, rho, kap, W1, b1, w2, c, w_rest, g, lam, a,
                b, y_off)


@njit(cache=True)
def peek_static(un_k, st, scratch, scratch2, radii, n_lags, duhem, rho, kap, W1, b1, w2, c, w_rest,
                g, lam, gain, y_off):
    """
    gain*z(k) + y_off for un_k with the input increments at their held value 0.

    The output the rate-independent operators (plays and Duhem states moved along un(k-1) -> un_k)
    and the creep settle to, without the drive's short-term dynamics (its slew limit included) or
    the output dynamics. st is untouched (scratch, scratch2: same size as st); gain: [G], the
    output dynamics' DC gain; rho and kap are taken for the signature's sake (the settled drive
    reaches un_k).
    """
    lh = max(n_lags, 1)
    hi = lh + radii.size + duhem.shape[0]
    no_a = gain[:0]
    for i in range(st.size):
        scratch[i] = st[i]
        scratch2[i] = st[i]
    # First step: the operators move to un_k along the real path, the drive reaching it.
    step(un_k, scratch, radii, n_lags, duhem, np.inf, np.inf, W1, b1, w2, c, w_rest, g, lam, no_a,
         gain, y_off)
    for i in range(lh, hi):
        scratch2[i] = scratch[i]
    for j in range(lh):
        scratch2[j] = un_k               # increments 0; the operators stay where they are
    return step(un_k, scratch2, radii, n_lags, duhem, np.inf, np.inf, W1, b1, w2, c, w_rest, g,
                lam, no_a, gain, y_off)


@njit(cache=True)
def simulate(un, st, radii, n_lags, duhem, rho, kap, W1, b1, w2, c, w_rest, g, lam, a, b,
             y_off):
    """Free run over un (N,) from state st (updated in place); returns yn (N,)."""
    out = np.empty(un.size)
    for k in range(un.size):
        out[k] = step(un[k], st, radii, n_lags, duhem, rho, kap, W1, b1, w2, c, w_rest, g, lam, a,
                      b, y_off)
    return out


@njit(cache=True)
def operator_chain(un, radii, n_lags, duhem, rho, kap, W1, b1, w2, c, w_rest, g, lam):
    """
    z(k) (N,) of the operator/network/creep chain from rest.

    What the output dynamics are driven by (it does not depend on the output, so one-step
    prediction can reuse it).
    """
    m = radii.size
    q = duhem.shape[0]
    nl = lam.size
    lh = max(n_lags, 1)
    st = np.zeros(lh + m + q + nl)
    one = np.ones(1)
    none = np.zeros(0)
    out = np.empty(un.size)
    # The output part of `step` is skipped by giving it b = [1], no a: yl(k) = z(k).
    for k in range(un.size):
        out[k] = step(un[k], st, radii, n_lags, duhem, rho, kap, W1, b1, w2, c, w_rest, g, lam,
                      none, one, 0.0)
    return out


# ------------------------------------------------------------------------------ training kernels
@njit(cache=True)
def drive(un, rho, kap=np.inf):
    """
    Rate-limited drive v (N,) from rest, dv/drho (N,) and dv/dkap (N,; zeros when kap = inf).

    With kap finite, the amplifier's drive (`amplifier`), its derivatives carried through
    v(k-1) (dv(k)/dtheta = dv/dprev * dv(k-1)/dtheta + the sample's own).
    """
    n = un.size
    v = np.empty(n)
    dv = np.empty(n)
    dk = np.zeros(n)
    prev, dprev = 0.0, 0.0
    if kap != np.inf:
        dkprev = 0.0
        for k in range(n):
            prev, gp, gr, gk = amplifier_derivatives(prev, un[k], rho, kap)
            dprev = gp * dprev + gr
            dkprev = gp * dkprev + gk
            v[k] = prev
            dv[k] = dprev
            dk[k] = dkprev
        return v, dv, dk
    for k in range(n):
        e = un[k] - prev
        if e > rho:
            prev, dprev = prev + rho, dprev + 1.0
        elif e < -rho:
            prev, dprev = prev - rho, dprev - 1.0
        else:
            prev, dprev = un[k], 0.0
        v[k] = prev
        dv[k] = dprev
    return v, dv, dk


@njit(cache=True)
def features(v, radii, n_lags, dv):
    """
    Network inputs (N, m + n_lags) from rest: plays of the drive v, then its increments.

    And their derivatives (N, m + n_lags) with respect to rho given dv = dv/drho.
    """
    n = v.size
    m = radii.size
    F = np.empty((n, m + n_lags))
    DF = np.empty((n, m + n_lags))
    p = np.zeros(m)
    dp = np.zeros(m)
    for k in range(n):
        for i in range(m):
            lo = v[k] - radii[i]
            hi = v[k] + radii[i]
            if p[i] < lo:
                p[i] = lo
                dp[i] = dv[k]
            elif p[i] > hi:
                p[i] = hi
                dp[i] = dv[k]
            F[k, i] = p[i]
            DF[k, i] = dp[i]
        for j in range(n_lags):
            cur = v[k - j] if k - j >= 0 else 0.0
            prv = v[k - j - 1] if k - j - 1 >= 0 else 0.0
            F[k, m + j] = cur - prv
            dcur = dv[k - j] if k - j >= 0 else 0.0
            dprv = dv[k - j - 1] if k - j - 1 >= 0 else 0.0
            DF[k, m + j] = dcur - dprv
    return F, DF


@njit(cache=True)
def duhem_states(v, duhem, with_jac, dv):
    """
    Integrate the Duhem states S (N, q) of the drive v from rest.

    When with_jac, also their derivatives J (N, q, 6) with respect to each state's parameters and
    SR (N, q) with respect to rho (given dv = dv/drho).
    """
    n = v.size
    q = duhem.shape[0]
    S = np.zeros((n, q))
    J = np.zeros((n, q, 6) if with_jac else (1, q, 6))
    SR = np.zeros((n, q) if with_jac else (1, q))
    gr = np.zeros(6)
    for j in range(q):
        s = 0.0
        sr = 0.0
        prev = 0.0
        dprev = 0.0
        gr[:] = 0.0
        for k in range(n):
            d = v[k] - prev
            dd = dv[k] - dprev
            prev = v[k]
            dprev = dv[k]
            if d != 0.0:
                if d > 0.0:
                    sg, ia = 1.0, 0
                    ir = 2 if s >= 0.0 else 3
                else:
                    sg, ia = -1.0, 1
                    ir = 4 if s >= 0.0 else 5
                alpha = duhem[j, ia]
                rho = duhem[j, ir]
                beta = rho * rho + BETA_MIN
                ad = abs(d)
                x = beta * ad
                e = math.exp(-x)
                if x > 1e-8:
                    phi = (1.0 - e) / beta
                    dphi = (ad * e - phi) / beta
                else:
                    phi = ad * (1.0 - 0.5 * x)
                    dphi = -0.5 * ad * ad
                if with_jac:
                    gb = -ad * s * e + sg * alpha * dphi
                    for p in range(6):
                        gr[p] *= e
                    gr[ia] += sg * phi
                    gr[ir] += 2.0 * rho * gb
                    sr = e * sr + e * (alpha - beta * sg * s) * dd
                s = s * e + sg * alpha * phi
            S[k, j] = s
            if with_jac:
                SR[k, j] = sr
                for p in range(6):
                    J[k, j, p] = gr[p]
    return S, J, SR


@njit(cache=True)
def forward(F, S, W1, b1, w2, c, g, lam, a, b, y_off):
    """Free-run output yn (N,) from the features F and Duhem states S (training path)."""
    n = F.shape[0]
    H, d = W1.shape
    df = F.shape[1]
    nl = lam.size
    na = a.size
    nb = b.size - 1
    w_rest = 0.0
    for h in range(H):
        w_rest += w2[h] * _sig(b1[h])
    phi = np.empty(d)
    x = np.zeros(nl)
    zs = np.zeros(n)
    y = np.empty(n)
    for k in range(n):
        for i in range(df):
            phi[i] = F[k, i]
        for i in range(d - df):
            phi[df + i] = S[k, i]
        w = _network(phi, W1, b1, w2, c, w_rest)
        z = w
        for il in range(nl):
            x[il] = lam[il] * x[il] + (1.0 - lam[il]) * w
            z += g[il] * x[il]
        zs[k] = z
        yl = 0.0
        for i in range(nb + 1):
            if k - i >= 0:
                yl += b[i] * zs[k - i]
        for j in range(1, na + 1):
            if k - j >= 0:
                yl -= a[j - 1] * (y[k - j] - y_off)
        y[k] = yl + y_off
    return y


# fastmath: the training's derivatives may be summed in any order (vectorised); the free run
# (step / simulate), which the estimator and the scores use, stays exact IEEE arithmetic.
@njit(cache=True, fastmath=True)
def jacobian(F, S, JD, DF, SR, rho, DFK, SRK, kap, W1, b1, w2, c, g, lam, a, b, y_off, J):
    """
    Compute the free-run output yn (N,) and its exact derivative J (N, P) w.r.t. theta.

    Layout in the module docstring; from the features F, Duhem states S, their derivatives JD
    (Duhem parameters) and DF, SR (rho), and rho itself (the drive parameter is log rho); with
    an amplifier bandwidth (the drive's second parameter, log kap) DFK, SRK (N rows) are the
    features' and Duhem states' derivatives with respect to kap; without one they have no rows
    and kap is not used.
    """
    n = F.shape[0]
    H, d = W1.shape
    df = F.shape[1]
    q = d - df
    nl = lam.size
    na = a.size
    nb = b.size - 1
    o_b1 = H * d
    o_w2 = o_b1 + H
    o_c = o_w2 + H
    o_dh = o_c + d
    o_dr = o_dh + 6 * q
    amp = DFK.shape[0] > 0        # (not kap != inf: fastmath assumes no infinities)
    o_g = o_dr + (2 if amp else 1)
    o_a = o_g + nl
    o_b = o_a + na
    o_y = o_b + nb + 1
    s0 = np.empty(H)
    w_rest = 0.0
    for h in range(H):
        s0[h] = _sig(b1[h])
        w_rest += w2[h] * s0[h]
    phi = np.empty(d)
    sh = np.empty(H)
    r = np.zeros(o_a)                      # d w / d theta (network and Duhem), then creep
    X = np.zeros((nl, o_a))                # creep filter states of each column
    x = np.zeros(nl)
    ZR = np.zeros((nb + 1, o_a))           # d z / d theta, ring over the last nb+1 samples
    zs = np.zeros(n)
    yl_hist = np.zeros(n)
    y = np.empty(n)
    for k in range(n):
        for i in range(df):
            phi[i] = F[k, i]
        for i in range(q):
            phi[df + i] = S[k, i]
        w = -w_rest
        for h in range(H):
            zh = b1[h]
            for i in range(d):
                zh += W1[h, i] * phi[i]
            sh[h] = _sig(zh)
            w += w2[h] * sh[h]
        for i in range(d):
            w += c[i] * phi[i]
        for h in range(H):
            dh = w2[h] * sh[h] * (1.0 - sh[h])
            for i in range(d):
                r[h * d + i] = dh * phi[i]
            r[o_b1 + h] = dh - w2[h] * s0[h] * (1.0 - s0[h])
            r[o_w2 + h] = sh[h] - s0[h]
        for i in range(d):
            r[o_c + i] = phi[i]
        drho = 0.0
        for i in range(d):
            mi = c[i]
            for h in range(H):
                mi += w2[h] * sh[h] * (1.0 - sh[h]) * W1[h, i]
            if i < df:
                drho += mi * DF[k, i]
            else:
                j = i - df
                drho += mi * SR[k, j]
                for p in range(6):
                    r[o_dh + 6 * j + p] = mi * JD[k, j, p]
        r[o_dr] = rho * drho
        if amp:
            # A loop of its own: inside the one above it changed how the compiler orders that
            # loop's sums (fastmath), and with them the bits of every fit without a bandwidth.
            dkap = 0.0
            for i in range(d):
                mi = c[i]
                for h in range(H):
                    mi += w2[h] * sh[h] * (1.0 - sh[h]) * W1[h, i]
                dkap += mi * (DFK[k, i] if i < df else SRK[k, i - df])
            r[o_dr + 1] = kap * dkap
        z = w
        for il in range(nl):
            x[il] = lam[il] * x[il] + (1.0 - lam[il]) * w
            z += g[il] * x[il]
        zs[k] = z
        zr = ZR[k % (nb + 1)]
        for p in range(o_g):
            zr[p] = r[p]
        for il in range(nl):
            lm, gl = lam[il], g[il]
            Xl = X[il]
            for p in range(o_g):
                v = lm * Xl[p] + (1.0 - lm) * r[p]
                if abs(v) < TINY:
                    v = 0.0
                Xl[p] = v
                zr[p] += gl * v
        for il in range(nl):
            zr[o_g + il] = x[il]
        yl = 0.0
        for i in range(nb + 1):
            if k - i >= 0:
                yl += b[i] * zs[k - i]
        for j in range(1, na + 1):
            if k - j >= 0:
                yl -= a[j - 1] * yl_hist[k - j]
        yl_hist[k] = yl
        y[k] = yl + y_off
        row = J[k]
        for p in range(o_y):
            row[p] = 0.0
        for i in range(nb + 1):
            if k - i >= 0:
                bi = b[i]
                zri = ZR[(k - i) % (nb + 1)]
                for p in range(o_a):
                    row[p] += bi * zri[p]
                row[o_b + i] += zs[k - i]
        for jj in range(na):
            if k - 1 - jj >= 0:
                row[o_a + jj] -= yl_hist[k - 1 - jj]
        for j in range(1, na + 1):
            if k - j >= 0:
                aj = a[j - 1]
                prev = J[k - j]
                for p in range(o_y):
                    row[p] -= aj * prev[p]
        for p in range(o_y):
            if abs(row[p]) < TINY:
                row[p] = 0.0
        row[o_y] = 1.0
    return y
