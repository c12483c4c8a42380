"""
Training of the hysteresis-operator NARX (HysteresisNARX.fit): output-error Levenberg-Marquardt.

The loss is the free-run (simulation) error of every estimation record, each simulated from rest
on its own: no state and no regressor crosses from one record to the next. Because the model's
output feedback is linear, the exact derivative of the whole free run is cheap
(hysteresis_kernels.jacobian), so the training needs no segments or truncation: it fits the slow
states (creep, hysteresis memory) over the full length of each record.

Start: the drive's rate limit at half the largest input step (so that the largest jumps of the
data are limited and its derivative is informative); a seeded random hidden layer; the output
layer (w2, c) by least squares on the static map from the operators to the output; the output
dynamics (a, b) by least squares (ARX) on that static prediction, replaced by a static gain when
unstable. Then Marquardt's LM (the damping
scaled by diag(J^T J)) until the error stops falling, `max_iter`, or `max_fail` iterations without
improvement of the held-out tail of each record (when `val_fraction` > 0). A step that would make
the output dynamics unstable (a root of A(q) on or outside 0.9999) is refused like one that
raises the error, so the returned model is stable.
"""
import time

import numpy as np

from . import hysteresis_kernels as hk

_MU_MAX = 1e12
_MAX_POLE = 0.9999


def _split_theta(theta, lay, H, d, q):
    """(W1, b1, w2, c, duhem, rho, g, a, b, y_off) from the flat vector (rho = exp(drive))."""
    def part(name):
        lo, hi = lay[name]
        return theta[lo:hi]
    return (part('W1').reshape(H, d), part('b1'), part('w2'), part('c'),
            np.ascontiguousarray(part('duhem').reshape(q, 6)), float(np.exp(part('drive')[0])),
            part('g'), part('a'), part('b'), float(part('y_off')[0]))


def operator_features(un, radii, n_lags, duhem, rho, with_jac=False):
    """
    (phi (N, d), parts) of one normalised record.

    The drive, its plays and increments, the Duhem states; parts = (F, S, JD, DF, SR) for the
    Jacobian kernel.
    """
    v, dv = hk.drive(un, rho)
    F, DF = hk.features(v, radii, n_lags, dv)
    S, JD, SR = hk.duhem_states(v, duhem, with_jac, dv)
    return np.hstack([F, S]), (F, S, JD, DF, SR)


def _stable(a):
    return a.size == 0 or np.max(np.abs(np.roots(np.r_[1.0, a]))) < _MAX_POLE


def initial_theta(uns, yns, radii, n_lags, H, q, n_creep, na, nb, rng, mask=None):
    """
    Return starting parameters for records of inputs uns and outputs yns (normalised).

    See the module docstring.
    """
    rho = 0.5 * max(float(np.max(np.abs(np.diff(np.r_[0.0, un])))) for un in uns)
    rho = max(rho, 1e-6)
    duhem = np.array([[1.0, 1.0] + [np.sqrt(1.0 + 2.0 * j)] * 4 for j in range(q)]).reshape(q, 6)
    phis = [operator_features(un, radii, n_lags, duhem, rho)[0] for un in uns]
    d = phis[0].shape[1]
    if mask is None:
        W1 = rng.normal(0.0, 1.0, (H, d)) * (2.0 / np.sqrt(d))
    else:
        fan_in = np.maximum(mask.sum(axis=1, keepdims=True), 1)
        W1 = rng.normal(0.0, 1.0, (H, d)) * (2.0 / np.sqrt(fan_in)) * mask
    b1 = rng.uniform(-1.0, 1.0, H)
    phi = np.vstack(phis)
    sig = 1.0 / (1.0 + np.exp(-(phi @ W1.T + b1))) - 1.0 / (1.0 + np.exp(-b1))
    A = np.hstack([sig, phi])
    # A little ridge: the sigmoid columns of a random layer can be nearly collinear.
    lam = 1e-8 * np.trace(A.T @ A) / A.shape[1]
    sol = np.linalg.solve(A.T @ A + lam * np.eye(A.shape[1]), A.T @ np.concatenate(yns))
    w2, c = sol[:H], sol[H:]
    a, b = np.zeros(na), np.zeros(nb + 1)
    b[0] = 1.0
    rows, targets, start = [], [], 0
    n0 = max(na, nb)
    for phi_r, yn in zip(phis, yns):
        w0 = A[start:start + yn.size] @ sol
        start += yn.size
        cols = ([-np.r_[np.zeros(j), yn[:yn.size - j]] for j in range(1, na + 1)]
                + [np.r_[np.zeros(i), w0[:w0.size - i]] for i in range(nb + 1)])
        rows.append(np.column_stack(cols)[n0:])
        targets.append(yn[n0:])
    ab = np.linalg.lstsq(np.vstack(rows), np.concatenate(targets), rcond=None)[0]
    if np.all(np.isfinite(ab)) and _stable(ab[:na]):
        a, b = ab[:na], ab[na:]
    return np.concatenate([W1.ravel(), b1, w2, c, duhem.ravel(), [np.log(rho)], np.zeros(n_creep),
                           a, b, [0.0]])


def train(uns, yns, radii, n_lags, hidden, n_duhem, lam, na, nb, seed, max_iter=60,
          val_fraction=0.0, max_fail=8, hessian_stride=2, tol=1e-7, ridge=0.0, mask=None):
    """
    Fit on normalised records (lists of (N_r,) arrays); returns (theta, info).

    radii: play radii (normalised); lam: creep filter poles exp(-1/(tau fs)); the rest as
    HysteresisNARX. info: iterations, losses (normalised mean squares), seconds, stop reason.
    """
    t0 = time.perf_counter()
    rng = np.random.default_rng(int(seed))
    H, q, n_lags = int(hidden), int(n_duhem), int(n_lags)
    d = radii.size + n_lags + q
    lay, P = hk.layout(H, d, q, lam.size, na, nb)
    splits = [un.size - int(round(val_fraction * un.size)) if val_fraction > 0 else un.size
              for un in uns]
    theta = initial_theta([u[:s] for u, s in zip(uns, splits)],
                          [y[:s] for y, s in zip(yns, splits)],
                          radii, n_lags, H, q, lam.size, na, nb, rng, mask)
    n_train = sum(splits)
    n_hold = sum(un.size for un in uns) - n_train
    # Ridge on the hidden layer's input weights (per training sample, so independent of N).
    pen = np.zeros(P)
    pen[lay['W1'][0]:lay['W1'][1]] = ridge * n_train
    pen[lay['w2'][0]:lay['w2'][1]] = ridge * n_train
    fixed = (np.flatnonzero(np.asarray(mask).ravel() == 0) + lay['W1'][0] if mask is not None
             else np.zeros(0, dtype=int))

    def errors(th):
        """(train SSE, holdout MSE) of the free run; inf when not finite or unstable."""
        W1, b1, w2, c, dh, rho, g, a, b, y_off = _split_theta(th, lay, H, d, q)
        if not _stable(a) or not np.isfinite(rho):
            return np.inf, np.inf
        sse, hold = 0.0, 0.0
        for un, yn, s in zip(uns, yns, splits):
            _, (F, S, _, _, _) = operator_features(un, radii, n_lags, dh, rho)
            e = yn - hk.forward(F, S, W1, b1, w2, c, g, lam, a, b, y_off)
            sse += float(e[:s] @ e[:s])
            hold += float(e[s:] @ e[s:])
        if not np.isfinite(sse) or not np.isfinite(hold):
            return np.inf, np.inf
        sse += float(pen @ (th * th))
        return sse, (hold / n_hold if n_hold else sse / n_train)

    def normal_equations(th):
        W1, b1, w2, c, dh, rho, g, a, b, y_off = _split_theta(th, lay, H, d, q)
        JtJ = np.zeros((P, P))
        Jte = np.zeros(P)
        for un, yn, s in zip(uns, yns, splits):
            _, parts = operator_features(un, radii, n_lags, dh, rho, with_jac=True)
            J = np.empty((un.size, P))
            y = hk.jacobian(*parts, rho, W1, b1, w2, c, g, lam, a, b, y_off, J)
            e = yn[:s] - y[:s]
            Jt = J[:s]
            Jte += Jt.T @ e
            # Neighbouring rows of densely sampled data are nearly collinear: estimate the
            # curvature from every stride-th row (the gradient uses all; a step must still lower
            # the exact error to be taken).
            Js = Jt[::hessian_stride]
            JtJ += (Js.T @ Js) * (Jt.shape[0] / max(Js.shape[0], 1))
        JtJ[np.diag_indices(P)] += pen
        Jte -= pen * th
        if fixed.size:   # weights the structure holds at 0: no step along them
            JtJ[fixed, :] = 0.0
            JtJ[:, fixed] = 0.0
            JtJ[fixed, fixed] = 1.0
            Jte[fixed] = 0.0
        return JtJ, Jte

    sse, hold = errors(theta)
    best_theta, best_hold = theta.copy(), hold
    mu, fails, it, reason = 1e-2, 0, 0, 'max_iter'
    history = [float(sse / n_train)]
    for it in range(1, int(max_iter) + 1):
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
    sse, hold = errors(best_theta)
    info = {'iterations': it, 'stop': reason, 'n_train': int(n_train), 'n_holdout': int(n_hold),
            'n_params': int(P), 'train_mse': float(sse / n_train), 'holdout_mse': float(hold),
            'loss_history': history, 'fit_seconds': time.perf_counter() - t0}
    return best_theta, info
