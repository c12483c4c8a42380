"""Training of the single-hidden-layer NARX network (torch, float64; imported only by fit()).

Everything here works on normalised signals (zero mean, unit variance) and on one flat parameter
vector theta = [W1 (H*d, row-major), b1 (H), w2 (H), b2 (1)], with d = nu + 1 + ny inputs in the
regressor order of eq. (1).

Stage 1 minimises the one-step (series-parallel) error with Levenberg-Marquardt as MATLAB's trainlm
does: exact Jacobian (analytic for one hidden layer), mu adaptation (x10 / x0.1), seeded restarts and
early stopping on a held-out tail. Stage 2 minimises the free-run (parallel) error on many short
segments started from measured outputs, again with LM, using the exact recursive sensitivity
    dy(k)/dtheta = df/dtheta + sum_j df/dy(k-j) * dy(k-j)/dtheta,
and keeps the iterate with the lowest free-run error on the held-out tail (if any beats stage 1).
"""
import time

import numpy as np
import torch

from .kernels import narx_simulate
from .regressors import lagged_regressors

_MU_MAX = 1e10


class _Net:
    """Shape bookkeeping for theta of an H-unit, d-input network."""

    def __init__(self, hidden, d):
        self.H, self.d = hidden, d
        self.P = hidden * (d + 2) + 1

    def unpack(self, theta):
        H, d = self.H, self.d
        W1 = theta[:H * d].reshape(H, d)
        b1 = theta[H * d:H * d + H]
        w2 = theta[H * d + H:H * d + 2 * H]
        b2 = theta[-1]
        return W1, b1, w2, b2

    def pack(self, W1, b1, w2, b2):
        return torch.cat([W1.reshape(-1), b1, w2, b2.reshape(1)])

    def forward(self, theta, X):
        W1, b1, w2, b2 = self.unpack(theta)
        return torch.sigmoid(X @ W1.T + b1) @ w2 + b2

    def jacobian(self, theta, X):
        """(N, P) Jacobian of the outputs for regressor rows X (N, d), and the outputs (N,)."""
        W1, b1, w2, b2 = self.unpack(theta)
        s = torch.sigmoid(X @ W1.T + b1)
        a = s * (1.0 - s) * w2
        n = X.shape[0]
        J = torch.cat([(a[:, :, None] * X[:, None, :]).reshape(n, -1), a, s,
                       torch.ones(n, 1, dtype=X.dtype)], dim=1)
        return J, s @ w2 + b2


def _init_theta(net, X, t, gen):
    """Nguyen-Widrow-like random hidden layer; output layer by linear least squares."""
    H, d = net.H, net.d
    beta = 0.7 * H ** (1.0 / d)
    W1 = torch.rand(H, d, generator=gen, dtype=torch.float64) * 2 - 1
    W1 = beta * W1 / W1.norm(dim=1, keepdim=True)
    b1 = (torch.rand(H, generator=gen, dtype=torch.float64) * 2 - 1) * beta
    S = torch.cat([torch.sigmoid(X @ W1.T + b1), torch.ones(X.shape[0], 1, dtype=X.dtype)], dim=1)
    w = torch.linalg.lstsq(S, t[:, None], driver='gelsd').solution[:, 0]
    return net.pack(W1, b1, w[:H], w[H])


def _lm_solve(JtJ, g, mu):
    """Solve (JtJ + mu I) delta = g; None if not positive definite."""
    A = JtJ + mu * torch.eye(JtJ.shape[0], dtype=JtJ.dtype)
    L, info = torch.linalg.cholesky_ex(A)
    if int(info) != 0:
        return None
    return torch.cholesky_solve(g[:, None], L)[:, 0]


def _lm_one_step(net, theta, X, t, Xv, tv, n_iter, max_fail, mu=1e-3):
    """LM on the one-step error; early stopping on (Xv, tv). Returns (theta_best, val_mse, log)."""
    best_theta, best_val = theta, float(torch.mean((tv - net.forward(theta, Xv)) ** 2))
    fails, it = 0, 0
    e = t - net.forward(theta, X)
    sse = float(e @ e)
    for it in range(n_iter):
        J, _ = net.jacobian(theta, X)
        JtJ, g = J.T @ J, J.T @ e
        accepted = False
        while mu < _MU_MAX:
            delta = _lm_solve(JtJ, g, mu)
            if delta is not None:
                cand = theta + delta
                e_c = t - net.forward(cand, X)
                sse_c = float(e_c @ e_c)
                if sse_c < sse:
                    theta, e, mu, accepted = cand, e_c, max(mu * 0.1, 1e-20), True
                    rel = (sse - sse_c) / max(sse, 1e-300)
                    sse = sse_c
                    break
            mu *= 10.0
        if not accepted:
            break
        val = float(torch.mean((tv - net.forward(theta, Xv)) ** 2))
        if val < best_val:
            best_theta, best_val, fails = theta, val, 0
        else:
            fails += 1
            if fails >= max_fail:
                break
        if rel < 1e-12:
            break
    return best_theta, best_val, it + 1


def _segment_starts(k_lo, k_hi, length, n_segments):
    """Start indices of free-run segments inside [k_lo, k_hi): tiled, or n_segments evenly spread."""
    avail = k_hi - k_lo - length
    if avail < 0:
        return np.zeros(0, dtype=np.int64)
    n_tile = (k_hi - k_lo) // length
    if not n_segments or n_segments >= n_tile:
        return k_lo + length * np.arange(n_tile)
    return np.round(np.linspace(k_lo, k_lo + avail, n_segments)).astype(np.int64)


class _SimProblem:
    """Batched free-run segments: inputs (B, L + nu) and initial outputs (B, ny), targets (B, L)."""

    def __init__(self, net, un, yn, nu, ny, starts, length):
        idx = starts[:, None] + np.arange(length)[None, :]
        self.net, self.nu, self.ny, self.L = net, nu, ny, length
        self.U = torch.from_numpy(np.stack([un[s - nu:s + length] for s in starts]))
        self.Y0 = torch.from_numpy(np.stack([yn[s - ny:s] for s in starts]))
        self.T = torch.from_numpy(yn[idx])

    def _regressor(self, t, yhist):
        # u(k) .. u(k-nu) are columns t+nu .. t of U; yhist[j-1] holds y(k-j).
        u_part = self.U[:, t:t + self.nu + 1].flip(1)
        return torch.cat([u_part, torch.stack(yhist[:self.ny], dim=1)], dim=1)

    def simulate(self, theta):
        """Free-run outputs (B, L)."""
        W1, b1, w2, b2 = self.net.unpack(theta)
        yhist = [self.Y0[:, -j] for j in range(1, self.ny + 1)]
        out = []
        for t in range(self.L):
            y = torch.sigmoid(self._regressor(t, yhist) @ W1.T + b1) @ w2 + b2
            out.append(y)
            yhist.insert(0, y)
            yhist.pop()
        return torch.stack(out, dim=1)

    def normal_equations(self, theta):
        """JtJ (P, P), J^T e (P,) and SSE of the free-run error, with the recursive sensitivities."""
        net, nu, ny = self.net, self.nu, self.ny
        W1, b1, w2, b2 = net.unpack(theta)
        B = self.U.shape[0]
        P = net.P
        Wy = W1[:, nu + 1:]                      # (H, ny): weights of y(k-1) .. y(k-ny)
        ones = torch.ones(B, 1, dtype=theta.dtype)
        yhist = [self.Y0[:, -j] for j in range(1, ny + 1)]
        shist = [None] * ny                      # sensitivities of y(k-1) .. y(k-ny); None = measured
        JtJ = torch.zeros(P, P, dtype=theta.dtype)
        g = torch.zeros(P, dtype=theta.dtype)
        sse = 0.0
        for t in range(self.L):
            x = self._regressor(t, yhist)
            s = torch.sigmoid(x @ W1.T + b1)
            a = s * (1.0 - s) * w2               # (B, H)
            y = s @ w2 + b2
            S = torch.cat([(a[:, :, None] * x[:, None, :]).reshape(B, -1), a, s, ones], dim=1)
            if shist[0] is not None:
                dydy = a @ Wy                    # (B, ny): df/dy(k-j)
                for j in range(ny):
                    if shist[j] is None:
                        break
                    S = S + dydy[:, j:j + 1] * shist[j]
            e = self.T[:, t] - y
            JtJ += S.T @ S
            g += S.T @ e
            sse += float(e @ e)
            yhist.insert(0, y)
            yhist.pop()
            shist.insert(0, S)
            shist.pop()
        return JtJ, g, sse


def _freerun_mse(net, theta, un, yn, nu, ny, k_start):
    """Free-run MSE (normalised units) on un/yn[k_start:], started from measured outputs."""
    W1, b1, w2, b2 = (p.numpy() for p in net.unpack(theta))
    n0 = max(nu, ny)
    u = un[k_start - n0:]
    y = np.empty(u.size)
    y[:n0] = yn[k_start - n0:k_start]
    narx_simulate(u, y, n0, np.ascontiguousarray(W1[:, :nu + 1][:, ::-1]),
                  np.ascontiguousarray(W1[:, nu + 1:][:, ::-1]), b1, w2, float(b2))
    err = y[n0:] - yn[k_start:]
    mse = float(np.mean(err * err))
    return mse if np.isfinite(mse) else np.inf


def _lm_simulation(net, theta, problem, n_iter, score, mu=1e-2):
    """LM on the free-run segment error; returns (best theta by score(), best score, iterations)."""
    best_theta, best_score = theta, score(theta)
    JtJ, g, sse = problem.normal_equations(theta)
    it = 0
    for it in range(n_iter):
        accepted = False
        while mu < _MU_MAX:
            delta = _lm_solve(JtJ, g, mu)
            if delta is not None:
                cand = theta + delta
                e_c = problem.T - problem.simulate(cand)
                sse_c = float(torch.sum(e_c * e_c))
                if sse_c < sse:
                    theta, mu, accepted = cand, max(mu * 0.1, 1e-20), True
                    break
            mu *= 10.0
        if not accepted:
            break
        sc = score(theta)
        if sc < best_score:
            best_theta, best_score = theta, sc
        if it + 1 < n_iter:
            JtJ, g, sse = problem.normal_equations(theta)
    return best_theta, best_score, it + 1


def train_narx(un, yn, nu, ny, hidden, seed, restarts=3, max_iter=60, restart_iter=15,
               restart_samples=6000, val_fraction=0.15, max_fail=6, refine_iter=15,
               segment_length=100, n_segments=120, threads=1):
    """Fit the network on normalised signals un, yn (N,).

    Returns (W1 (H, d), b1 (H,), w2 (H,), b2 float, info dict) in normalised units.
    """
    t_start = time.perf_counter()
    n_threads = torch.get_num_threads()
    torch.set_num_threads(max(1, int(threads)))
    try:
        gen = torch.Generator().manual_seed(int(seed))
        rng = np.random.default_rng(int(seed))
        n0 = max(nu, ny)
        N = un.size
        n_val = int(round(val_fraction * N))
        n_val = min(max(n_val, 0), N - n0 - 10)
        k_split = N - n_val                       # samples k >= k_split are held out
        X_all, t_all = lagged_regressors(un, yn, nu, ny)
        X_all, t_all = torch.from_numpy(X_all), torch.from_numpy(t_all)
        r_split = k_split - n0
        X, t = X_all[:r_split], t_all[:r_split]
        if n_val > 0:
            Xv, tv = X_all[r_split:], t_all[r_split:]
        else:                                     # no hold-out: select on the training rows
            Xv, tv = X, t
        net = _Net(hidden, nu + 1 + ny)
        info = {'n_train': int(k_split), 'n_holdout': int(n_val)}

        # Stage 1: screen seeded restarts on a row subsample, continue the best on all rows.
        if restart_samples and restart_samples < X.shape[0]:
            rows = torch.from_numpy(np.sort(rng.choice(X.shape[0], restart_samples, replace=False)))
            Xs, ts = X[rows], t[rows]
        else:
            Xs, ts = X, t
        best = None
        for _ in range(max(1, int(restarts))):
            th0 = _init_theta(net, Xs, ts, gen)
            th, val, _ = _lm_one_step(net, th0, Xs, ts, Xv, tv, restart_iter, max_fail)
            if best is None or val < best[1]:
                best = (th, val)
        theta, val_os, n_it = _lm_one_step(net, best[0], X, t, Xv, tv, max_iter, max_fail)
        info.update(holdout_mse_onestep=val_os, lm_iterations=n_it,
                    stage1_seconds=time.perf_counter() - t_start)

        # Stage 2: simulation-error refinement, judged by held-out free-run error.
        stage = 'one-step'
        k_val = k_split if n_val > 2 * n0 else n0
        score = lambda th: _freerun_mse(net, th, un, yn, nu, ny, k_val)  # noqa: E731
        info['holdout_mse_freerun_stage1'] = score(theta)
        if refine_iter > 0:
            length = min(int(segment_length), k_split - n0)
            starts = _segment_starts(n0, k_split, length, n_segments)
            if starts.size:
                t2 = time.perf_counter()
                problem = _SimProblem(net, un, yn, nu, ny, starts, length)
                th2, sc2, n_it2 = _lm_simulation(net, theta, problem, int(refine_iter), score)
                info.update(refine_iterations=n_it2, stage2_seconds=time.perf_counter() - t2)
                if sc2 < info['holdout_mse_freerun_stage1']:
                    theta, stage = th2, 'simulation'
        info['holdout_mse_freerun'] = score(theta)
        info['selected_stage'] = stage
        W1, b1, w2, b2 = (p.numpy().copy() for p in net.unpack(theta))
        return W1, b1, w2, float(b2), info
    finally:
        torch.set_num_threads(n_threads)
