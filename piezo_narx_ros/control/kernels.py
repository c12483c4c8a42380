"""
Compiled one-sample inversion.

Find the input u (V) in [lo, hi] whose model output g(u) (m) equals a target, trying candidates on
copies of the model state (numba; never torch).

The search is bounded and allocation-free, and the same for every model family: a small state
machine (`begin` / `update`) proposes candidate inputs, a family kernel evaluates them with the
model's `peek` (the output `step` would return, state untouched) and hands the outputs back.

  1. the previous input u_prev first: while the reference holds, it usually already fits, and on
     a flat model a tie keeps the input where it is;
  2. up to LOCAL_TRIES secant guesses from u_prev (the first with the previous solve's slope):
     a sign change of g - target between u_prev's side and a guess is the nearest root;
  3. otherwise a grid of n_grid points over [lo, hi]: the sign changes bracket the roots, the
     bracket nearest u_prev is kept (a non-monotone model has several; the nearest keeps the
     input continuous);
  4. Illinois regula falsi on the bracket until it is narrower than tol_u (V), the output is
     within tol_y (m) or max_iter iterations.
With no bracket (target beyond what [lo, hi] reaches, or a flat / non-monotone model), the input
with the smallest |g - target| among those evaluated is returned, ties broken towards u_prev.
The returned input is always one that was evaluated, so its output error is known exactly.
"""
import math

import numpy as np
from numba import njit

from piezo_narx_ros.ident.hysteresis import kernels as hk
from piezo_narx_ros.ident.narx.kernels import arx_peek, narx_peek

# Solver state (sv) layout: inputs, the bracket and the best input seen so far. _SLOPE survives
# between solves (begin leaves it): the last bracket's slope, for the next sample's first guess.
(_T, _LO, _HI, _UP, _TOLU, _TOLY, _MAXIT, _NGRID, _PH, _IT, _A, _FA, _B, _FB, _SIDE, _BU, _BE,
 _BF, _NEV, _FUP, _SLOPE) = range(21)
SV_SIZE = 21
MAX_GRID = 64
LOCAL_TRIES = 3      # secant guesses from u_prev before the grid search
# Phases of the state machine.
_P_PREV, _P_LOCAL, _P_GRID, _P_REFINE = 0.0, 1.0, 2.0, 3.0


@njit(cache=True)
def begin(sv, cand, target, lo, hi, u_prev, tol_u, tol_y, max_iter, n_grid):
    """Start a solve; fills cand[0] and returns the number of candidates to evaluate (1)."""
    sv[_T] = target
    sv[_LO] = lo
    sv[_HI] = hi
    up = min(max(u_prev, lo), hi)
    sv[_UP] = up
    sv[_TOLU] = tol_u
    sv[_TOLY] = tol_y
    sv[_MAXIT] = max_iter
    sv[_NGRID] = max(2, min(n_grid, MAX_GRID))
    sv[_PH] = _P_PREV
    sv[_IT] = 0.0
    sv[_SIDE] = 0.0
    sv[_BU] = up
    sv[_BE] = math.inf
    sv[_BF] = math.nan
    sv[_NEV] = 0.0
    cand[0] = up
    return 1


@njit(cache=True)
def _bracket(sv, cand, g, n):
    """Return the grid's sign change nearest u_prev -> (found, a, fa, b, fb)."""
    t = sv[_T]
    up, fup = sv[_UP], sv[_FUP]
    best_d = math.inf
    a = fa = b = fb = 0.0
    found = False
    for j in range(n - 1):
        e0 = g[j] - t
        e1 = g[j + 1] - t
        if not (math.isfinite(e0) and math.isfinite(e1)) or e0 * e1 > 0.0:
            continue
        x0, x1 = cand[j], cand[j + 1]
        d = 0.0 if x0 <= up <= x1 else min(abs(x0 - up), abs(x1 - up))
        if d < best_d:
            best_d = d
            found = True
            a, fa, b, fb = x0, e0, x1, e1
            if d == 0.0 and math.isfinite(fup) and x0 < up < x1:
                # u_prev splits the bracket: keep the half that still changes sign.
                if fa * fup <= 0.0:
                    b, fb = up, fup
                else:
                    a, fa = up, fup
    return found, a, fa, b, fb


@njit(cache=True)
def _grid(sv, cand):
    """Start the grid search over [lo, hi]; returns its size."""
    lo, hi = sv[_LO], sv[_HI]
    m = int(sv[_NGRID])
    for j in range(m):
        cand[j] = lo + (hi - lo) * j / (m - 1)
    cand[m - 1] = hi
    sv[_PH] = _P_GRID
    return m


@njit(cache=True)
def _refine(sv, cand, a, fa, b, fb):
    """Start (or continue) regula falsi on the bracket [a, b]; writes its next point."""
    if a > b:
        a, fa, b, fb = b, fb, a, fa
    sv[_A], sv[_FA], sv[_B], sv[_FB] = a, fa, b, fb
    sv[_PH] = _P_REFINE
    x = (fb * a - fa * b) / (fb - fa) if fb != fa else 0.5 * (a + b)
    if not a < x < b:
        x = 0.5 * (a + b)
    cand[0] = x
    return 1


@njit(cache=True)
def _secant(sv, cand, x0, e0, slope):
    """
    Next local guess x0 - e0/slope within [lo, hi] (written to cand[0]).

    0 when there is none (no usable slope, or the guess is x0 itself: the window's edge).
    """
    if not (math.isfinite(slope) and slope != 0.0):
        return 0
    x = min(max(x0 - e0 / slope, sv[_LO]), sv[_HI])
    if x == x0:
        return 0
    cand[0] = x
    return 1


@njit(cache=True)
def _done(sv):
    """Finish: keep the last bracket's slope for the next solve's first guess."""
    if sv[_PH] == _P_REFINE and sv[_B] > sv[_A]:
        sv[_SLOPE] = (sv[_FB] - sv[_FA]) / (sv[_B] - sv[_A])
    return 0


@njit(cache=True)
def update(sv, cand, g, n):
    """
    Take the outputs g[:n] of the candidates cand[:n].

    Returns how many new candidates were written to cand (0: finished, the answer is in sv, see
    `result`).
    """
    t = sv[_T]
    up = sv[_UP]
    for j in range(n):
        e = g[j] - t
        sv[_NEV] += 1.0
        ae = abs(e) if math.isfinite(e) else math.inf
        if ae < sv[_BE] or (ae == sv[_BE] and abs(cand[j] - up) < abs(sv[_BU] - up)):
            sv[_BU] = cand[j]
            sv[_BE] = ae
            sv[_BF] = e
    if sv[_BE] <= sv[_TOLY]:
        return _done(sv)
    phase = sv[_PH]
    if phase == _P_PREV:
        e = g[0] - t
        sv[_FUP] = e
        if not sv[_HI] - sv[_LO] > sv[_TOLU] or not math.isfinite(e):
            return _grid(sv, cand) if sv[_HI] - sv[_LO] > sv[_TOLU] else 0
        # Local first: a secant guess from u_prev with the last solve's slope.
        sv[_A], sv[_FA] = up, e
        sv[_PH] = _P_LOCAL
        return _secant(sv, cand, up, e, sv[_SLOPE]) or _grid(sv, cand)
    if phase == _P_LOCAL:
        x, e = cand[0], g[0] - t
        a, fa = sv[_A], sv[_FA]
        if math.isfinite(e) and e * fa <= 0.0:
            return _refine(sv, cand, a, fa, x, e)
        sv[_IT] += 1.0
        if not math.isfinite(e) or sv[_IT] >= LOCAL_TRIES:
            return _grid(sv, cand)
        sv[_A], sv[_FA] = x, e            # still on the same side: secant through both
        return _secant(sv, cand, x, e, (e - fa) / (x - a)) or _grid(sv, cand)
    if phase == _P_GRID:
        found, a, fa, b, fb = _bracket(sv, cand, g, n)
        if not found or not b - a > sv[_TOLU]:
            return 0
        sv[_IT] = 0.0
        return _refine(sv, cand, a, fa, b, fb)
    # Refine: Illinois regula falsi.
    x, e = cand[0], g[0] - t
    if not math.isfinite(e):
        return 0
    if e * sv[_FB] > 0.0:
        sv[_B], sv[_FB] = x, e
        if sv[_SIDE] == -1.0:
            sv[_FA] *= 0.5
        sv[_SIDE] = -1.0
    elif e * sv[_FA] > 0.0:
        sv[_A], sv[_FA] = x, e
        if sv[_SIDE] == 1.0:
            sv[_FB] *= 0.5
        sv[_SIDE] = 1.0
    else:
        return _done(sv)
    sv[_IT] += 1.0
    if sv[_IT] >= sv[_MAXIT] or not sv[_B] - sv[_A] > sv[_TOLU]:
        return _done(sv)
    return _refine(sv, cand, sv[_A], sv[_FA], sv[_B], sv[_FB])


@njit(cache=True)
def result(sv):
    """(u V, signed output error g(u) - target m, evaluations) of a finished solve."""
    return sv[_BU], sv[_BF], int(sv[_NEV])


@njit(cache=True)
def solve_hysteresis(target, lo, hi, u_prev, tol_u, tol_y, max_iter, n_grid, sv, cand, g, static,
                     st, scratch, scratch2, u_scale, y_scale, radii, n_lags, duhem, rho, kap, W1,
                     b1, w2, c, w_rest, gc, lam, a, b, y_off):
    """
    Solve a HysteresisNARX (state st, normalised units) for g(u) = target (m), u in [lo, hi] V.

    Its next output y(k), or with `static` its quasi-static output (hk.peek_static, b = [G]).
    """
    n = begin(sv, cand, target, lo, hi, u_prev, tol_u, tol_y, max_iter, n_grid)
    while n > 0:
        for j in range(n):
            un = cand[j] / u_scale
            if static:
                yn = hk.peek_static(un, st, scratch, scratch2, radii, n_lags, duhem, rho, kap,
                                    W1, b1, w2, c, w_rest, gc, lam, b, y_off)
            else:
                yn = hk.peek(un, st, scratch, radii, n_lags, duhem, rho, kap, W1, b1, w2, c,
                             w_rest, gc, lam, a, b, y_off)
            g[j] = y_scale * yn
        n = update(sv, cand, g, n)
    return result(sv)


@njit(cache=True)
def solve_narx(target, lo, hi, u_prev, tol_u, tol_y, max_iter, n_grid, sv, cand, g, ubuf, ybuf,
               scratch, Wu, Wy, b1, w2, b2):
    """Solve a NARX network (histories ubuf V, ybuf m) for y(k) = target (m), u in [lo, hi]."""
    n = begin(sv, cand, target, lo, hi, u_prev, tol_u, tol_y, max_iter, n_grid)
    while n > 0:
        for j in range(n):
            g[j] = narx_peek(cand[j], ubuf, ybuf, scratch, Wu, Wy, b1, w2, b2)
        n = update(sv, cand, g, n)
    return result(sv)


@njit(cache=True)
def solve_arx(target, lo, hi, u_prev, tol_u, tol_y, max_iter, n_grid, sv, cand, g, ubuf, ybuf,
              scratch, bu, ay, c):
    """
    Solve an ARX model for y(k) = target (m), u in [lo, hi].

    A line: one regula falsi step is exact, the state machine keeps the limits and reporting the
    same.
    """
    n = begin(sv, cand, target, lo, hi, u_prev, tol_u, tol_y, max_iter, n_grid)
    while n > 0:
        for j in range(n):
            g[j] = arx_peek(cand[j], ubuf, ybuf, scratch, bu, ay, c)
        n = update(sv, cand, g, n)
    return result(sv)


def work_arrays():
    """(sv, cand, g): the solver's state and candidate buffers, allocated once per solver."""
    return np.zeros(SV_SIZE), np.zeros(MAX_GRID), np.zeros(MAX_GRID)
