"""
Training of the hysteresis-operator NARX (HysteresisNARX.fit): output-error Levenberg-Marquardt.

The loss is the free-run (simulation) error of every estimation record, each simulated from rest
on its own: no state and no regressor crosses from one record to the next. Because the model's
output feedback is linear, the exact derivative of the whole free run is cheap
(hysteresis.kernels.jacobian), so the training needs no segments or truncation: it fits the slow
states (creep, hysteresis memory) over the full length of each record.

Start: the drive's rate limit at half the largest input step when the input jumps (so that the
jumps are limited and its derivative is informative), inactive when it moves smoothly; a seeded
random hidden layer; the output layer (w2, c) by least squares on the static map from the
operators to the output; the output
dynamics (a, b) by least squares (ARX) on that static prediction, replaced by a static gain when
unstable. Then Marquardt's LM (the damping
scaled by diag(J^T J)) until the error stops falling, `max_iter`, or `max_fail` iterations without
improvement of the held-out tail of each record (when `val_fraction` > 0). A step that would make
the output dynamics unstable (a root of A(q) on or outside 0.9999) is refused like one that
raises the error, so the returned model is stable. Creep weights can be held at 0 (filters the
records do not excite: `slow_creep`) and kept >= 0 (the step projected), see `train`.
"""
import math
import time

import numpy as np

from . import kernels as hk

_MU_MAX = 1e12
#: A creep filter's weight is fitted only where the estimation input moves the filter by at least
#: this share of the input's own variation (slow_creep; measured in docs/real.md, "Creep the
#: estimation record does not excite").
SLOW_CREEP_SHARE = 0.01
_MAX_POLE = 0.9999


def _split_theta(theta, lay, H, d, q):
    """
    (W1, b1, w2, c, duhem, (rho, kap), g, a, b, y_off) from the flat vector.

    rho = exp(drive[0]); kap = exp(drive[1]) with an amplifier bandwidth, else inf.
    """
    def part(name):
        lo, hi = lay[name]
        return theta[lo:hi]
    dr = part('drive')
    kap = float(np.exp(dr[1])) if dr.size > 1 else np.inf
    return (part('W1').reshape(H, d), part('b1'), part('w2'), part('c'),
            np.ascontiguousarray(part('duhem').reshape(q, 6)), (float(np.exp(dr[0])), kap),
            part('g'), part('a'), part('b'), float(part('y_off')[0]))


def operator_features(un, radii, n_lags, duhem, drive, with_jac=False):
    """
    (phi (N, d), parts) of one normalised record; drive = (rho, kap) (kap inf: slew only).

    The drive, its plays and increments, the Duhem states; parts = (F, S, JD, DF, SR, DFK, SRK)
    for the Jacobian kernel (DFK, SRK: derivatives w.r.t. kap, computed only with_jac and an
    amplifier bandwidth).
    """
    parts = _operator_parts(un, radii, n_lags, duhem, drive, with_jac, with_jac)
    return np.hstack(parts[:2]), parts


def _operator_parts(un, radii, n_lags, duhem, drive, with_jac, with_kap):
    """operator_features' parts; the kap derivatives only when with_kap (and a bandwidth)."""
    rho, kap = drive
    v, dv, dk = hk.drive(un, rho, kap)
    F, DF = hk.features(v, radii, n_lags, dv)
    S, JD, SR = hk.duhem_states(v, duhem, with_jac, dv)
    DFK, SRK = DF[:0], SR[:0]
    if with_kap and kap != np.inf:
        DFK, SRK = _kap_parts(v, dk, radii, n_lags, duhem)
    return F, S, JD, DF, SR, DFK, SRK


def _kap_parts(v, dk, radii, n_lags, duhem):
    """(DFK, SRK): the features' and Duhem states' derivatives w.r.t. kap, given dk = dv/dkap."""
    return hk.features(v, radii, n_lags, dk)[1], hk.duhem_states(v, duhem, True, dk)[2]


def _stable(a):
    return a.size == 0 or np.max(np.abs(np.roots(np.r_[1.0, a]))) < _MAX_POLE


def monotone_mask(lay, P, H, m, n_lags, q):
    """
    Parameters held >= 0 so that the output rises with every play operator (`monotone`).

    The hidden layer's weights from the plays, the output weights and the plays' linear
    weights. Every play rises with the drive, so along any path the plays' part of the output
    moves with the input, as a Preisach operator with a positive density does (the Duhem
    states are left free: a Bouc-Wen deflection is the drive minus its Duhem state; so are the
    drive increments, a rate effect).
    """
    mask = np.zeros(P, dtype=bool)
    d = m + n_lags + q
    plays = np.zeros(d, dtype=bool)
    plays[:m] = True
    lo = lay['W1'][0]
    mask[lo:lo + H * d] = np.tile(plays, H)
    mask[lay['w2'][0]:lay['w2'][1]] = True
    mask[lay['c'][0]:lay['c'][1]] = plays
    return mask


#: The input's largest step is a jump when it is this many times the steps beside it.
JUMP_FACTOR = 10.0
#: Quantiles of a smooth input's steps at which an active drive limit is tried as a start ...
DRIVE_LIMIT_QUANTILES = (0.95, 0.85)
#: ... when it is at least this fraction of the input range per sample: a slew shows only where
#: the command moves far within one sample (a 1 Hz sweep at 2 kHz moves 0.15 % of its range; a
#: limit there would cap any faster input later).
DRIVE_LIMIT_MIN_STEP = 0.05
#: amplifier='auto' (drive_slews): this quantile of the command's steps is at least this share
#: of its range per sample (twice the largest share measured on records that do not slew).
DRIVE_SLEW_QUANTILE = 0.95
DRIVE_SLEW_MIN_STEP = 0.1
#: LM iterations from each drive-limit start before the best one is trained on.
TRIAL_ITER = 5
#: Starting amplifier bandwidth kap = 2*pi*f_a/fs (`amplifier`): f_a at the Nyquist frequency
#: (the simulated amplifier: 3 kHz at 5 kHz, kap 3.77); the training moves log kap.
KAP_START = math.pi


def _initial_drive_limit(un):
    """
    Return the starting drive limit rho (normalised input per sample) for one record.

    Half the largest step when that step is a jump (far larger than the steps beside it: a step
    command the amplifier's slew must ramp), so that the limit acts on the jumps and its
    derivative is informative; when the input moves smoothly there (a sine, a sweep, a
    multisine) the data say nothing about a slew limit, and the limit starts where no input can
    reach it (a full-range swing in one sample): a limit just above the record's fastest motion
    would cap any faster input later (measured: a model fitted on a 1 Hz sweep held a 10 Hz one
    to 40 % of its amplitude).
    """
    steps = np.abs(np.diff(np.r_[0.0, un]))
    k = int(np.argmax(steps))
    largest = float(steps[k])
    beside = max(float(steps[k - 1]) if k > 0 else 0.0,
                 float(steps[k + 1]) if k + 1 < steps.size else 0.0)
    jump = largest > JUMP_FACTOR * beside
    return max(0.5 * largest, 1e-6) if jump else max(2.0 * largest, 2.0)


def drive_limit_candidates(uns):
    """
    Return the starting drive limits to try (normalised input per sample), the rule's first.

    The rule of `_initial_drive_limit`; when it leaves the limit inactive (no jump in any record),
    also limits at quantiles of the input's steps (DRIVE_LIMIT_QUANTILES) that are at least
    DRIVE_LIMIT_MIN_STEP of the input range. An inactive limit has no derivative, so training
    can never find a slew the data do show: an amplifier that cannot follow a wideband command
    (measured on a 0.1-1500 Hz multisine at 5 kHz: the plant's drive slew-limited on 11 % of
    the samples). Which start is kept is the data's call (`train`: a few iterations from each).
    """
    rule = max(_initial_drive_limit(un) for un in uns)
    steps = np.concatenate([np.abs(np.diff(un)) for un in uns])
    if steps.size == 0 or rule < float(np.max(steps)):
        return (rule,)
    span = max(float(np.max(un)) for un in uns) - min(float(np.min(un)) for un in uns)
    limits = np.quantile(steps, DRIVE_LIMIT_QUANTILES)
    return (rule,) + tuple(float(x) for x in limits if x >= DRIVE_LIMIT_MIN_STEP * span > 0)


def drive_slews(uns) -> bool:
    """
    Return True when the command moves fast enough, often enough, for an amplifier to shape it.

    The DRIVE_SLEW_QUANTILE of the steps within the records (not the step from rest to a
    record's first sample) is at least DRIVE_SLEW_MIN_STEP of the input range per sample: where
    HysteresisNARX's amplifier='auto' gives the drive a learned bandwidth. Measured (95th
    percentile, share of the range): a 0.1-1500 Hz multisine at 5 kHz 25 %, 0.1-800 Hz at
    2 kHz 34 %; the identification protocol at 2 kHz 4.0 % (its jumps are too few), at 10 kHz
    1.1 %, the default multisine at 2 kHz 4.7 %, a growing sine 0.13 %, the micromanipulator
    1.6 %: every record the battery and bench_real fit besides the wideband ones stays as it was.
    """
    steps = np.concatenate([np.abs(np.diff(un)) for un in uns])
    if steps.size == 0:
        return False
    span = max(float(np.max(un)) for un in uns) - min(float(np.min(un)) for un in uns)
    return float(np.quantile(steps, DRIVE_SLEW_QUANTILE)) >= DRIVE_SLEW_MIN_STEP * span > 0


def slow_creep(taus_s, uns, fs):
    """
    Return, per creep time constant (s), True where the estimation inputs uns hardly move it.

    uns: normalised input records; fs: Hz. A filter is not excited when the std of its response
    to the input's moves (the input less its first sample) stays below SLOW_CREEP_SHARE of the
    input's own std in every record: its weight would then be set by the output's slow drift,
    which after an unknown past is the past's, and overstate creep on other records. A 1 Hz sine
    of 20 s: 0.5 % at 30 s, 0.2 % at 100 s; the identification protocol's 25 s: 9.1 % and 3.3 %.
    """
    from scipy.signal import lfilter
    out = []
    for tau in taus_s:
        pole = math.exp(-1.0 / (float(tau) * float(fs)))
        share = max(float(np.std(lfilter([1.0 - pole], [1.0, -pole], un - un[0])))
                    / max(float(np.std(un)), 1e-300) for un in uns)
        out.append(share < SLOW_CREEP_SHARE)
    return out


def initial_theta(uns, yns, radii, n_lags, H, q, n_creep, na, nb, rng, monotone=False,
                  record_offsets=False, rho=None, kap=np.inf):
    """
    Return (starting parameters, per-record offsets) for inputs uns and outputs yns (normalised).

    See the module docstring. monotone: the start satisfies monotone_mask's signs (a positive
    hidden layer, the output layer by bounded least squares). record_offsets: the records after
    the first get their own output offset in the least squares (returned, normalised). rho: the
    starting drive limit (normalised input per sample; None: `_initial_drive_limit`'s rule).
    kap: the starting amplifier bandwidth (2*pi*f_a/fs; inf: none, the drive has rho alone).
    """
    if rho is None:
        rho = max(_initial_drive_limit(un) for un in uns)
    duhem = np.array([[1.0, 1.0] + [np.sqrt(1.0 + 2.0 * j)] * 4 for j in range(q)]).reshape(q, 6)
    phis = [operator_features(un, radii, n_lags, duhem, (rho, kap))[0] for un in uns]
    d = phis[0].shape[1]
    W1 = rng.normal(0.0, 1.0, (H, d)) * (2.0 / np.sqrt(d))
    b1 = rng.uniform(-1.0, 1.0, H)
    m = radii.size
    if monotone:
        W1[:, :m] = np.abs(W1[:, :m])
    phi = np.vstack(phis)
    sig = 1.0 / (1.0 + np.exp(-(phi @ W1.T + b1))) - 1.0 / (1.0 + np.exp(-b1))
    A = np.hstack([sig, phi])
    # A little ridge: the sigmoid columns of a random layer can be nearly collinear.
    lam = 1e-8 * np.trace(A.T @ A) / A.shape[1]
    target = np.concatenate(yns)
    y_off = 0.0
    # One column per record after the first: its own offset (sensor zero), never penalised.
    n_rec = len(yns) - 1 if record_offsets else 0
    sizes = [yn.size for yn in yns]
    dummies = np.zeros((A.shape[0], n_rec))
    for r in range(n_rec):
        lo = sum(sizes[:r + 1])
        dummies[lo:lo + sizes[r + 1], r] = 1.0
    n_col = A.shape[1]
    if monotone:
        # Bounded least squares with a free intercept: positive weights alone cannot make the
        # output's mean (the records need not be centred).
        from scipy.optimize import lsq_linear
        lower = np.full(n_col + 1 + n_rec, -np.inf)
        lower[:H + m] = 0.0
        ridge = np.sqrt(lam) * np.eye(n_col + 1 + n_rec)[:n_col]
        aug = np.vstack([np.hstack([A, np.ones((A.shape[0], 1)), dummies]), ridge])
        sol = lsq_linear(aug, np.r_[target, np.zeros(n_col)], bounds=(lower, np.inf)).x
        offsets, y_off, sol = sol[n_col + 1:], float(sol[n_col]), sol[:n_col]
        # Strictly inside the constraint (the training moves the log of these weights), and no
        # unit left dead: an output weight of 0 would give its hidden weights no gradient.
        w_top = max(float(np.max(sol[:H])), 1e-3)
        sol[:H] = np.maximum(sol[:H], 0.05 * w_top)
        c_top = max(float(np.max(sol[H:H + m])), 1e-3)
        sol[H:H + m] = np.maximum(sol[H:H + m], 1e-3 * c_top)
    else:
        Ad = np.hstack([A, dummies])
        reg = lam * np.r_[np.ones(n_col), np.zeros(n_rec)]
        sol = np.linalg.solve(Ad.T @ Ad + np.diag(reg), Ad.T @ target)
        offsets, sol = sol[n_col:], sol[:n_col]
    w2, c = sol[:H], sol[H:]
    a, b = np.zeros(na), np.zeros(nb + 1)
    b[0] = 1.0
    rows, targets, start = [], [], 0
    n0 = max(na, nb)
    for r, yn in enumerate(yns):
        w0 = A[start:start + yn.size] @ sol
        start += yn.size
        yl = yn - y_off - (offsets[r - 1] if r and n_rec else 0.0)
        cols = ([-np.r_[np.zeros(j), yl[:yl.size - j]] for j in range(1, na + 1)]
                + [np.r_[np.zeros(i), w0[:w0.size - i]] for i in range(nb + 1)])
        rows.append(np.column_stack(cols)[n0:])
        targets.append(yl[n0:])
    ab = np.linalg.lstsq(np.vstack(rows), np.concatenate(targets), rcond=None)[0]
    if np.all(np.isfinite(ab)) and _stable(ab[:na]):
        a, b = ab[:na], ab[na:]
    theta = np.concatenate([W1.ravel(), b1, w2, c, duhem.ravel(),
                            [np.log(rho)] + ([np.log(kap)] if kap != np.inf else []),
                            np.zeros(n_creep), a, b, [y_off]])
    return theta, offsets


def train(uns, yns, radii, n_lags, hidden, n_duhem, lam, na, nb, seed, max_iter=60,
          val_fraction=0.0, max_fail=8, hessian_stride=2, tol=1e-7, theta0=None, skip=None,
          record_offsets=False, monotone=False, amplifier=False, creep_fixed=None,
          creep_nonneg=False):
    """
    Fit on normalised records (lists of (N_r,) arrays); returns (theta, info).

    radii: play radii (normalised); lam: creep filter poles exp(-1/(tau fs)); the rest as
    HysteresisNARX. theta0: start from these parameters instead of a seeded start. skip: per
    record, leading samples left out of the loss (an input history prepended to set the state a
    record starts in). record_offsets: every record after the first gets its own output offset
    (a sensor zero that moved between sessions), fitted with the model and returned in info.
    info: iterations, losses (normalised mean squares), seconds, stop reason, and the drive
    limits tried as starts ('drive_starts': rho normalised per sample, 'trial_mse' after
    TRIAL_ITER iterations when several were tried, 'kept' on the one trained; empty when theta0
    is given). amplifier: the drive also learns an amplifier bandwidth (hk.amplifier; started
    at KAP_START). creep_fixed: per creep filter, True where its weight stays at 0 (a filter the
    records do not excite: `slow_creep`). creep_nonneg: every creep weight stays >= 0 (the
    step is projected): a piezo creeps on in the direction it moved.
    """
    t0 = time.perf_counter()
    H, q, n_lags = int(hidden), int(n_duhem), int(n_lags)
    d = radii.size + n_lags + q
    lay, P = hk.layout(H, d, q, lam.size, na, nb, 2 if amplifier else 1)
    skip = [0] * len(uns) if skip is None else [int(k) for k in skip]
    splits = [un.size - int(round(val_fraction * (un.size - k))) if val_fraction > 0 else un.size
              for un, k in zip(uns, skip)]
    n_off = len(uns) - 1 if record_offsets else 0
    pos = np.zeros(P + n_off, dtype=bool)
    if monotone:
        pos[:P] = monotone_mask(lay, P, H, radii.size, n_lags, q)
    creep = np.zeros(P + n_off, dtype=bool)
    creep[lay['g'][0]:lay['g'][1]] = True
    fixed = np.zeros(P + n_off, dtype=bool)
    if creep_fixed is not None:
        fixed[creep] = np.asarray(creep_fixed, dtype=bool)
    nonneg = creep & ~fixed & bool(creep_nonneg)

    def as_raw(theta, offsets):
        # The iterations move `raw`; the model's parameters are actual(raw) (logs where positive).
        raw = np.r_[theta[:P], offsets]
        raw[pos] = np.log(np.maximum(raw[pos], 1e-12))
        raw[fixed] = 0.0
        raw[nonneg] = np.maximum(raw[nonneg], 0.0)
        return raw

    def actual(r):
        th = r.copy()
        th[pos] = np.exp(r[pos])
        return th
    n_train = sum(s - k for s, k in zip(splits, skip))
    n_hold = sum(un.size for un in uns) - sum(splits)
    # Per record, the operator features of the last drive and Duhem parameters errors() ran:
    # the accepted step's, which the next normal_equations needs (its derivatives included).
    feats = [None] * len(uns)
    scored = {}                 # theta bytes -> errors(theta) of the latest evaluations
    J_buf = np.empty((max(un.size for un in uns), P))    # one Jacobian buffer, reused

    def record_parts(r, dh, dr, with_kap):
        key = (dh.tobytes(), dr)
        if feats[r] is None or feats[r][0] != key:
            feats[r] = (key, _operator_parts(uns[r], radii, n_lags, dh, dr, True, with_kap))
        elif with_kap and dr[1] != np.inf and feats[r][1][5].shape[0] == 0:
            v, _, dk = hk.drive(uns[r], *dr)
            feats[r] = (key, feats[r][1][:5] + _kap_parts(v, dk, radii, n_lags, dh))
        return feats[r][1]

    def errors(r):
        """(train SSE, holdout MSE) of the free run; inf when not finite or unstable."""
        key = r.tobytes()
        if key not in scored:
            if len(scored) > 8:
                scored.clear()
            scored[key] = _errors(r)
        return scored[key]

    def _errors(r):
        with np.errstate(over='ignore'):
            th = actual(r)
        if not np.all(np.isfinite(th)):
            return np.inf, np.inf
        W1, b1, w2, c, dh, dr, g, a, b, y_off = _split_theta(th, lay, H, d, q)
        if not _stable(a) or not np.isfinite(dr[0]) or (amplifier and not 0.0 < dr[1] < np.inf):
            return np.inf, np.inf
        sse, hold = 0.0, 0.0
        for r, (un, yn, s, k) in enumerate(zip(uns, yns, splits, skip)):
            F, S = record_parts(r, dh, dr, False)[:2]
            with np.errstate(all='ignore'):   # a diverging trial step is refused below
                e = yn - hk.forward(F, S, W1, b1, w2, c, g, lam, a, b, y_off)
            if r and n_off:
                e -= th[P + r - 1]
            with np.errstate(all='ignore'):
                sse += float(e[k:s] @ e[k:s])
                hold += float(e[s:] @ e[s:])
        if not np.isfinite(sse) or not np.isfinite(hold):
            return np.inf, np.inf
        return sse, (hold / n_hold if n_hold else sse / n_train)

    def normal_equations(r):
        th = actual(r)
        W1, b1, w2, c, dh, dr, g, a, b, y_off = _split_theta(th, lay, H, d, q)
        chain = np.where(pos[:P], th[:P], 1.0)      # d(actual)/d(raw)
        n = P + n_off
        JtJ = np.zeros((n, n))
        Jte = np.zeros(n)
        for r, (un, yn, s, k) in enumerate(zip(uns, yns, splits, skip)):
            F, S, JD, DF, SR, DFK, SRK = record_parts(r, dh, dr, amplifier)
            J = J_buf[:un.size]
            y = hk.jacobian(F, S, JD, DF, SR, dr[0], DFK, SRK, dr[1], W1, b1, w2, c, g, lam, a,
                            b, y_off, J)
            if monotone:
                J *= chain
            e = yn[k:s] - y[k:s]
            Jt = J[k:s]
            if r and n_off:
                e -= th[P + r - 1]
                o = P + r - 1
                col = Jt.sum(axis=0)
                JtJ[o, :P] += col
                JtJ[:P, o] += col
                JtJ[o, o] += Jt.shape[0]
                Jte[o] += e.sum()
            Jte[:P] += Jt.T @ e
            # Neighbouring rows of densely sampled data are nearly collinear: estimate the
            # curvature from every stride-th row (the gradient uses all; a step must still lower
            # the exact error to be taken).
            Js = Jt[::hessian_stride]
            JtJ[:P, :P] += (Js.T @ Js) * (Jt.shape[0] / max(Js.shape[0], 1))
        # A held parameter gets no step: its row and column leave the system.
        JtJ[fixed, :] = 0.0
        JtJ[:, fixed] = 0.0
        JtJ[fixed, fixed] = 1.0
        Jte[fixed] = 0.0
        return JtJ, Jte

    def descend(theta, n_iter):
        """At most n_iter LM iterations from theta: (theta, sse, iterations, reason, history)."""
        sse, hold = errors(theta)
        best_theta, best_hold = theta.copy(), hold
        mu, fails, it, reason = 1e-2, 0, 0, 'max_iter'
        history = [float(sse / n_train)]
        for it in range(1, int(n_iter) + 1):
            JtJ, Jte = normal_equations(theta)
            diag = np.diag(JtJ).copy() + 1e-12 * (np.max(np.diag(JtJ)) + 1e-300)
            new = None
            while mu < _MU_MAX:
                try:
                    delta = np.linalg.solve(JtJ + mu * np.diag(diag), Jte)
                except np.linalg.LinAlgError:
                    mu *= 10.0
                    continue
                cand = theta + delta
                cand[nonneg] = np.maximum(cand[nonneg], 0.0)
                c_sse, c_hold = errors(cand)
                if c_sse < sse:
                    new = (cand, c_sse, c_hold)
                    mu = max(mu * 0.1, 1e-15)
                    break
                mu *= 10.0
            if new is None:
                reason = 'converged (no step lowers the error)'
                break
            rel = (sse - new[1]) / sse
            theta, sse, hold = new
            history.append(float(sse / n_train))
            if hold < best_hold:
                best_theta, best_hold, fails = theta.copy(), hold, 0
            else:
                fails += 1
                if n_hold and fails >= max_fail:
                    reason = f'early stop ({max_fail} iterations without held-out improvement)'
                    break
            if rel < tol:
                reason = 'converged (relative improvement below tol)'
                break
        if not n_hold:
            best_theta = theta
        return best_theta, errors(best_theta)[0], it, reason, history

    kap = KAP_START if amplifier else np.inf
    drive_starts, trial, first = [], 0, []
    if theta0 is None:
        fit_u = [u[k:s] for u, k, s in zip(uns, skip, splits)]
        fit_y = [y[k:s] for y, k, s in zip(yns, skip, splits)]
        starts = [as_raw(*initial_theta(fit_u, fit_y, radii, n_lags, H, q, lam.size, na, nb,
                                        np.random.default_rng(int(seed)), monotone,
                                        record_offsets, rho, kap))
                  for rho in drive_limit_candidates(fit_u)]   # the same seeded hidden layer
        theta = starts[0]
        if len(starts) > 1:
            # A few iterations from each start decide: the starting error does not (measured on
            # the Preisach plant at 5 kHz: the active starts began 28-48 % higher and ended at
            # 0.25 um against 0.61 um for the inactive one).
            trial = min(TRIAL_ITER, int(max_iter))
            runs = [descend(t, trial) for t in starts]
            pick = min(range(len(runs)), key=lambda i: runs[i][1])
            theta, first = runs[pick][0], runs[pick][4]
            for run, rho in zip(runs, drive_limit_candidates(fit_u)):
                drive_starts.append({'rho': rho, 'trial_mse': run[4][-1]})
            drive_starts[pick]['kept'] = True
        else:
            drive_starts.append({'rho': drive_limit_candidates(fit_u)[0], 'kept': True})
    else:
        theta = as_raw(np.array(theta0, dtype=np.float64), np.zeros(n_off))
    best_theta, sse, it, reason, history = descend(theta, int(max_iter) - trial)
    history = first[:-1] + history
    _, hold = errors(best_theta)
    info = {'iterations': it + trial, 'stop': reason, 'n_train': int(n_train),
            'n_holdout': int(n_hold), 'n_params': int(P), 'train_mse': float(sse / n_train),
            'holdout_mse': float(hold), 'loss_history': history,
            'fit_seconds': time.perf_counter() - t0,
            'record_offsets': [0.0] + best_theta[P:].tolist() if n_off else [],
            'drive_starts': drive_starts}
    return actual(best_theta)[:P], info
