"""
A model's free-run state set from a short measured window: a record that does not start at rest.

A real rig's record starts wherever the actuator is: mid-range, after an unknown input history
(hysteresis memory), with creep in progress and a sensor whose zero moved since the model was
fitted. `estimate_state(model, u, y)` returns the `ModelState` at the window's first sample that
best explains the measured window, for every family:

1. **Memory candidates** (the family's `_state_candidates(u)`): states the model reaches through
   input histories that end at u(0) and settle there. The hysteresis family enumerates histories
   of up to two turning points on a grid of its trained input range: its operators' memory is a
   function of the input's past extrema, so a consistent memory is one a real input could have
   written (a state vector fitted freely would not be). The lagged families (ARX, the paper's
   network) have one candidate: the input held at u(0).
2. **What enters linearly** (the family's `_adjustable_state()`: creep states and the output
   dynamics' history of the hysteresis family, the output history of the lagged families) and the
   sensor offset are then fitted by Gauss-Newton with a ridge that keeps them near the
   candidate's settled values: a short window cannot tell a 100 s creep state from an offset, and
   the ridge makes it take the equilibrium where the data do not decide.
3. Candidates are ranked with the offset alone (cheap), the best few refined as in 2, and the
   most probable wins. Residuals are weighted by Huber's rule (scale from the median absolute
   deviation), so a sensor's start-up transient or a glitch in the window does not set the state.
4. **Memory against a moved sensor zero.** Every past explains a window with its own offset, and
   a window that moves the input little cannot tell a past from a zero that moved: on a hold
   they all explain it. A candidate's score is therefore its window cost relative to the best,
   in units of `TIE`, plus a prior on the offset (scale `OFFSET_PRIOR` of the trained output
   span): where the window decides, the cost does; where it cannot, the past that explains the
   level with the zero the model was fitted with. Measured over random pasts and zeros moved by
   up to +-2.5 um (docs/real.md): error after a 0.5 s window 1.33x the start from rest on
   average, 6.4x at worst (the median of the tied offsets, the rule before: 2.34x, 14x).
   The prior is Cauchy, not Gaussian: a rig's zero moves by a few scales between days (the
   issue's rig by 4.7 um), and a Gaussian's quadratic tail then outweighs clear differences in
   the window's cost and takes a past that explains part of the moved zero by memory (zeros
   moved by up to +-14 um: the worst moved record 62x -> 11x; within +-2.5 um the same choices).
   The TIE is a share of the best cost, but never of less than the model's own error
   (`ERROR_FLOOR` x the free-run RMSE its fit measured): a window the model fits better than
   it fits anything, above all a small move like the start of a fade-in, must not choose a
   past, and with it a zero micrometres away, by differences far below that error (the real
   micromanipulator's second segment: a 0.5 s window on its fade-in chose an offset of
   +4.4 um where the state carried through the record has -0.9 um; 5.0 um after the window,
   0.18-1.3 um with the floor; docs/real.md, "A model's own error as the window's floor").
5. **A hold after a fade-out** (`past='fade-out'`, opt-in). Some rigs end a move by fading
   its amplitude out (the real micromanipulator's test record fades each segment out, then
   holds), which leaves the memory demagnetised about the hold level: a past of many turning
   points, none of the candidates of 1. Told so, the hysteresis family adds that candidate and
   takes it unless the window rejects it (its cost more than `DEMAG_MARGIN` TIEs above the
   best). The window cannot tell it from the pasts of 1 on a hold, so this is the user's
   knowledge of the rig, not a default: on the micromanipulator's two holds 1.20 and 0.96 um
   after the window -> 0.33 and 0.16 um; told so wrongly (simulated pasts that end with a
   ramp), the summed error grew 1.2-3.5x (docs/real.md, "A hold after a fade-out").

`model.simulate(u, state=s)` and `model.stepper(state=s)` then free-run from it; the offset (m) is
added to every output. docs/real.md has the measurements behind the choices.
"""
from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field

import numpy as np

from piezo_narx_ros.errors import DataError
from piezo_narx_ros.ident.data.checks import as_channels, as_signal

#: Fewest samples a window may have to set a state.
MIN_WINDOW = 10
#: Candidates refined with the adjustable states after the offset-only ranking.
N_REFINE = 6
#: Ridge of the adjustable states (relative to the basis' mean square: a prior, not a constraint).
RIDGE = 1e-2
#: Huber's tuning constant (95 % efficiency for Gaussian residuals).
HUBER = 1.345
#: Relative window cost worth one unit of log-likelihood (step 4 above): candidates within it are
#: reported as indistinguishable. At 1 % a model's own error on the window already decided
#: between pasts that fit it equally (costs 0.026 against 0.027 um, the wrong past chosen).
TIE = 0.05
#: Floor of the window-cost unit (step 4), in multiples of the model's own free-run RMSE
#: (`error_scale`): a window fitted better than the model can be trusted does not decide between
#: pasts by differences the model's own error could make. 0: no floor (the rule before).
ERROR_FLOOR = 4.0
#: Scale of the sensor offset's (Cauchy) prior, as a fraction of the trained output span
#: (2.5 um on the simulators' 82 um; the issue's rig moved its zero by up to 4.7 um).
OFFSET_PRIOR = 0.03
#: How a record's unlogged past ended (step 5): 'any' (the candidates of 1; the default) or
#: 'fade-out' (a move ended by fading its amplitude out: the demagnetised memory).
PASTS = ('any', 'fade-out')
#: TIEs of window cost above the best within which past='fade-out' keeps the demagnetised memory.
DEMAG_MARGIN = 1.0
#: Cycles of the fade-out that writes the demagnetised candidate (its amplitude falls linearly).
FADE_CYCLES = 40


@dataclass(frozen=True)
class ModelState:
    """
    A model's free-run state at one sample and the offset of its output.

    values : the family's state vector in its own layout and units (hysteresis family: the kernel
    state, normalised; lagged families: [u(k-nu) .. u(k-1) V, y(k-ny) .. y(k-1) m], outputs
    without the offset; several channels: those blocks time-major, each sample's channels in
    order); offset : m, added to every output (a sensor zero that moved): a float for one
    output, an (n_out,) array for several (one zero per output);
    info : how it was obtained (window samples, cost, the history of the winning candidate).
    """

    values: np.ndarray
    offset: float | np.ndarray = 0.0
    info: dict = field(default_factory=dict, compare=False)


def robust_weights(r: np.ndarray) -> tuple[np.ndarray, float]:
    """
    Huber weights (sqrt form, multiply rows by them) for residuals r; and the scale used (m).

    Scale: 1.4826 x the median absolute deviation, so Gaussian residuals keep weight 1.
    """
    s = 1.4826 * float(np.median(np.abs(r - np.median(r))))
    if not s > 0:
        return np.ones_like(r), 0.0
    c = HUBER * s
    a = np.abs(r)
    return np.sqrt(np.where(a <= c, 1.0, c / np.maximum(a, 1e-300))), s


def robust_cost(r: np.ndarray) -> float:
    """Trimmed mean square of r (the largest 10 % left out): comparable across candidates."""
    sq = np.sort(r * r)
    keep = max(1, int(math.ceil(0.9 * sq.size)))
    return float(np.mean(sq[:keep]))


def _offset_only(base: np.ndarray, y: np.ndarray):
    """Offset (float m, or (n_out,) per output) as the median residual, and the robust cost."""
    if y.ndim == 2:
        d = np.median(y - base, axis=0)
        return d, robust_cost((y - base - d).ravel())
    d = float(np.median(y - base))
    return d, robust_cost(y - base - d)


def offset_prior(model) -> np.ndarray:
    """
    Sensor-offset prior's scale per output (m): OFFSET_PRIOR of the trained span.

    inf (no prior) for a model that does not know its output range.
    """
    rng = getattr(model, 'output_range', None)
    if rng is None:
        return np.full(max(1, int(getattr(model, 'n_out', 1))), np.inf)
    span = np.ravel(np.asarray(rng[1], dtype=np.float64) - np.asarray(rng[0], dtype=np.float64))
    return np.where(span > 0, OFFSET_PRIOR * span, np.inf)


def error_scale(model) -> float:
    """
    Return the model's own free-run error (m): the RMSE its fit measured, else 0 (unknown).

    From the model file's metrics (`fit` writes them): the validation records' free run, else
    the estimation records'. fit's candidates get their estimation records' error before their
    validation windows (experiment.score_candidate); any other model fitted in-process carries
    none, and its windows are then judged by their best cost alone (step 4 of the module
    docstring).
    """
    metrics = (getattr(model, 'metadata', None) or {}).get('metrics') or {}
    for part in ('validation', 'estimation'):
        rmse = ((metrics.get(part) or {}).get('simulation') or {}).get('rmse')
        if isinstance(rmse, (int, float)) and math.isfinite(rmse) and rmse > 0:
            return float(rmse)
    return 0.0


def _ties(cost: float, unit: float, best: float) -> float:
    """Window cost (m^2) above the best, in TIEs of `unit` (m^2: step 4's unit); inf if unit 0."""
    return (cost / unit - best / unit) / TIE if unit > 0 else (0.0 if cost <= 0 else math.inf)


def _score(cost: float, unit: float, best: float, offset, sigma: np.ndarray) -> float:
    """
    Return a candidate's negative log-posterior, up to a constant.

    Its window cost above the best, in TIEs of `unit` (m^2: the best cost, or the model's own
    error floor if larger), plus the offset's Cauchy prior (scale sigma m per output, inf:
    none): quadratic within a scale, logarithmic beyond, so a zero that moved by several
    scales costs little more than one that moved by a few.
    """
    return _ties(cost, unit, best) + float(np.sum(np.log1p((np.ravel(offset) / sigma) ** 2)))


def _refine(model, values: np.ndarray, u: np.ndarray, y: np.ndarray, idx: np.ndarray,
            scale: np.ndarray, iterations: int) -> tuple[np.ndarray, float, float]:
    """
    Gauss-Newton with Huber weights on values[idx] and the offset; returns (values, offset, cost).

    Finite differences of the free run give the Jacobian; exact in one step for the families whose
    adjustable states enter linearly (the hysteresis family, ARX: `adjustable_state_linear`),
    whose Jacobian is therefore computed once and reused by the Huber reweighting's iterations.
    """
    prior = values[idx].copy()
    x = values.copy()
    eps = 1e-3   # finite-difference step, in units of `scale`
    base = model._run_from(x, u)
    offset, _ = _offset_only(base, y)
    # Several outputs: residuals flattened sample-major, one offset column per output.
    n_off = 1 if y.ndim == 1 else y.shape[1]
    ones = [np.ones(len(u))] if y.ndim == 1 else list(np.kron(np.ones((len(u), 1)),
                                                              np.eye(n_off)).T)
    linear = bool(getattr(model, 'adjustable_state_linear', False))
    A = None
    for _ in range(max(1, iterations)):
        r = (y - base - offset).ravel()
        if A is None or not linear:
            cols = []
            for i, h in zip(idx, scale):
                xi = x.copy()
                xi[i] += eps * h
                cols.append(((model._run_from(xi, u) - base) / eps).ravel())   # per unit of scale
            A = np.column_stack(cols + ones)
        w, _ = robust_weights(r)
        Aw, rw = A * w[:, None], r * w
        n_adj = len(idx)
        norm2 = float(np.mean(np.sum(Aw[:, :n_adj] ** 2, axis=0))) if n_adj else 0.0
        lam = np.r_[np.full(n_adj, RIDGE * norm2 + 1e-300), np.zeros(n_off)]
        # The prior pulls x[idx] back to the candidate's settled values.
        dev = np.r_[(x[idx] - prior) / scale, np.zeros(n_off)]
        try:
            step = np.linalg.solve(Aw.T @ Aw + np.diag(lam), Aw.T @ rw - lam * dev)
        except np.linalg.LinAlgError:
            break
        x_new = x.copy()
        x_new[idx] += step[:n_adj] * scale
        base_new = model._run_from(x_new, u)
        if not np.all(np.isfinite(base_new)):
            break
        offset_new = offset + (float(step[-1]) if y.ndim == 1 else step[n_adj:])
        # Several channels: tens of output lags of a network make the Gauss-Newton step
        # overshoot (measured on the FSM: window RMS 1e-6 m -> 2e-5 m); keep only steps that
        # lower the robust cost. (One axis: unchanged, bit for bit.)
        if y.ndim == 2 and robust_cost((y - base_new - offset_new).ravel()) > \
                robust_cost((y - base - offset).ravel()):
            break
        x, base, offset = x_new, base_new, offset_new
        if np.max(np.abs(step[:n_adj]), initial=0.0) < 1e-6:
            break
    return x, offset, robust_cost((y - base - offset).ravel())


def estimate_state(model, u, y, prior: ModelState | None = None,
                   iterations: int = 5, past: str = 'any', error: float | None = None
                   ) -> ModelState:
    """
    Return the ModelState at u[0] that best explains the window u (N,) V, y (N,) m.

    Several channels: u (N, n_in), y (N, n_out); the offset is then one per output (n_out,) m.
    See the module docstring. prior: the state the model is believed to be in (e.g. run through
    a known input history): the only candidate, refined on the window. past: how the record's
    unlogged past ended, one of PASTS (step 5). error: the model's own free-run error (m) that
    sets the floor of step 4; None: `error_scale(model)`, 0: no floor. N >= MIN_WINDOW;
    DataError otherwise. The window's own samples are part of the run: simulate(u_window,
    state=s) reproduces y_window as well as the model can.
    """
    model._require_fitted()
    check_past(past)
    if model.n_in == 1 and model.n_out == 1:
        u = as_signal(u, 'u (state window)', min_len=MIN_WINDOW)
        y = as_signal(y, 'y (state window)', n=u.size)
    else:
        u = model._signal(u, 'u (state window)', model.n_in, min_len=MIN_WINDOW)
        y = as_channels(y, 'y (state window)', n=len(u), width=model.n_out)
    if prior is not None:
        candidates = [ModelState(model._check_state(prior), model._check_offset(prior),
                                 {'history': 'given'})]
    else:
        candidates = model._state_candidates(u, past)
    idx, scale = model._adjustable_state(len(u))
    ranked = []
    with np.errstate(all='ignore'):   # a candidate that diverges is ranked last, not reported
        for i, cand in enumerate(candidates):
            base = model._run_from(cand.values, u)
            if not np.all(np.isfinite(base)):
                continue
            offset, cost = _offset_only(base, y)
            ranked.append((cost, i, offset))
        if not ranked:
            raise DataError('no initial state reproduces the window: the model diverges on it')
        ranked.sort(key=lambda r: (r[0], r[1]))   # (offsets may be vectors: never compared)
        best = ranked[0][0]
        # Step 4's unit: the best cost, or the model's own error if larger (m^2).
        floor = (ERROR_FLOOR * (error_scale(model) if error is None else float(error))) ** 2
        unit = max(best, floor)
        tied = [r for r in ranked if r[0] <= best + TIE * unit]
        sigma = offset_prior(model)
        # Step 4: the window's cost and the offset's prior, both in units of log-likelihood.
        order = sorted(ranked, key=lambda r: (_score(r[0], unit, best, r[2], sigma), r[1]))
        keep = order[:N_REFINE]
        keep += [r for r in order[N_REFINE:] if candidates[r[1]].info.get('demagnetised')][:1]
        refined = {r[1]: _refine(model, candidates[r[1]].values.astype(np.float64), u, y, idx,
                                 scale, iterations)
                   for r in keep}
    low = min(c for _, _, c in refined.values())
    unit = max(low, floor)
    i = min(refined, key=lambda k: (_score(refined[k][2], unit, low, refined[k][1], sigma), k))
    if past == 'fade-out':
        i = _after_fade_out(candidates, refined, i, unit, low)
    values, offset, cost = refined[i]
    info = {**candidates[i].info, 'window_samples': int(len(u)), 'rms_m': math.sqrt(cost),
            'candidates': len(candidates), 'indistinguishable': len(tied)}
    offset = float(offset) if np.ndim(offset) == 0 else np.asarray(offset, dtype=np.float64)
    return ModelState(values=values, offset=offset, info=info)


def check_past(past, name: str = 'past', error: type[Exception] = DataError) -> str:
    """Return past if it is one of PASTS; else raise error naming `name` and the choices."""
    if past not in PASTS:
        raise error(f'{name} must be one of {", ".join(PASTS)}, got {past!r}')
    return past


def _after_fade_out(candidates, refined: dict, i: int, unit: float, low: float) -> int:
    """
    Return the demagnetised candidate's index unless the window rejects it (step 5), else i.

    refined: index -> (values, offset m, cost m^2); low: the lowest refined cost (m^2); unit:
    the cost that is one TIE's worth (m^2, as in _score).
    """
    d = next((k for k in refined if candidates[k].info.get('demagnetised')), None)
    if d is None:
        return i
    return d if _ties(refined[d][2], unit, low) <= DEMAG_MARGIN else i


def fade_out(u0: float, lo: float, hi: float, cycles: int = FADE_CYCLES) -> tuple[float, ...]:
    """
    Return the turning points (V) of an oscillation about u0 fading out, within [lo, hi] V.

    Its amplitude starts at the largest [lo, hi] allows about u0 and falls linearly to 0 over
    `cycles` cycles: what it leaves is the memory of a move ended by a fade-out, demagnetised
    about u0 down to the last cycle's amplitude.
    """
    top = max(hi - u0, u0 - lo)
    pts = []
    for k in range(int(cycles)):
        a = top * (1.0 - k / cycles)
        pts += [min(hi, u0 + a), max(lo, u0 - a)]
    return tuple(float(p) for p in pts)


def turning_point_histories(lo: float, hi: float, u0: float, n_levels: int = 13,
                            max_turns: int = 2) -> list[tuple[float, ...]]:
    """
    Input histories as turning points (V) on n_levels levels of [lo, hi], ending at u0.

    Every sequence of 0..max_turns levels whose consecutive points differ (a turning point equal
    to its neighbour is no turn).
    """
    levels = np.linspace(lo, hi, n_levels)
    out = [()]
    for k in range(1, max_turns + 1):
        for pts in itertools.product(levels, repeat=k):
            seq = (0.0,) + pts + (u0,)
            if all(abs(a - b) > 1e-12 * max(1.0, abs(hi - lo)) for a, b in zip(seq, seq[1:])):
                out.append(tuple(float(p) for p in pts))
    return out


def ramp(points, step: float) -> np.ndarray:
    """Input (V) moving from 0 through `points` with increments of at most `step` (V)."""
    seq = [0.0] + list(points)
    parts = [np.linspace(a, b, max(1, int(math.ceil(abs(b - a) / step))) + 1)[1:]
             for a, b in zip(seq, seq[1:])]
    return np.concatenate(parts) if parts else np.zeros(0)
