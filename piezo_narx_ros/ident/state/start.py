"""
Start policies: how a model's free run uses the first N measured samples of a record.

A rig's estimator gets the commands from the start and, for a short window, the measured output
too. What the window is best used for depends on the model and the rig, so the structure search
(ident/selection/search.py) scores every fitted model under each policy on the validation records
and the model file records the one that won (`start` in the file: policy and window):

* ``rest``: the window is ignored; the free run starts from rest at the record's first sample
  (every past input and output zero, the hysteresis memory empty).
* ``offset``: from rest as above, plus one constant per output, the median of the window's
  residual (a sensor whose zero moved since the fit; nothing else is read from the window).
* ``state``: the window sets the state. A family whose whole state is its last inputs and
  outputs (ARX, the paper's NARX) takes its lags from the measurement (`relag_window`): the
  paper's start, from the window's first measured samples and free through the rest of it, while
  that run stays within the model's own error of the window; else from the window's last
  measured samples (a glitch or a sensor's start-up transient at the window's start). A family
  whose state is a function of the whole input history (the hysteresis-operator NARX) takes the
  state that best explains the window (memory, creep, output dynamics and offset:
  ident/state/estimate.py).

Every policy is expressed as a `ModelState` at the window's first sample (`window_state`), which
the estimator node and `simulate(u, state=...)` take as they are; `relag_window` says when and
with which measured samples the lags are then replaced.
`policy_simulate` is the offline free run of a whole record under a policy.
"""
from __future__ import annotations

import numpy as np

from piezo_narx_ros.errors import DataError
from piezo_narx_ros.ident.state.estimate import ERROR_FLOOR, MIN_WINDOW, ModelState, error_scale

#: The policies, simplest first (a tie in score goes to the earlier one).
START_POLICIES = ('rest', 'offset', 'state')


def check_policy(policy, name: str = 'start policy', error: type[Exception] = DataError) -> str:
    """Return `policy` if it is one of START_POLICIES; `error` naming it otherwise."""
    if policy not in START_POLICIES:
        raise error(f'{name} must be one of {", ".join(START_POLICIES)}, got {policy!r}')
    return policy


def lagged(model) -> bool:
    """Return True when the model's whole state is its last nu inputs and ny outputs."""
    return not getattr(model, 'state_from_input', False)


def relags(model, policy: str) -> bool:
    """Return True when `policy` sets this model's lags from the window's last samples."""
    return policy == 'state' and lagged(model)


def model_start(model) -> dict:
    """Return the start the model file stores ({'policy', 'window_samples', ...}; {} if none)."""
    return (getattr(model, 'metadata', None) or {}).get('start') or {}


def relag_window(model, policy: str, u_win, y_win) -> tuple | None:
    """
    Return the measured samples (u, y) whose last lags replace the state once they are stepped.

    None when `policy` keeps the state it set (see `relags`). For 'state' on a lagged family:
    the window's first n0 samples (the paper's start, the run free through the rest of the
    window) while that run misses the window's later samples by no more than ERROR_FLOOR x the
    model's own free-run RMSE (`error_scale`); else the whole window (the lags at its end). A
    later start replaces a run that is on track by a fresh transient: on the Bouc-Wen benchmark
    the end's lags were up to 0.45 % worse than the paper's start on the same samples.
    """
    if not relags(model, policy):
        return None
    n0, n = int(model.n0), len(u_win)
    scale = error_scale(model)
    if 0 < n0 < n and scale > 0:
        with np.errstate(all='ignore'):
            run = np.asarray(model.simulate(u_win, y_win[:n0]), dtype=np.float64)
        miss = np.asarray(y_win, dtype=np.float64)[n0:] - run[n0:]
        rms = float(np.sqrt(np.mean(miss * miss)))
        if rms <= ERROR_FLOOR * scale:
            return u_win[:n0], y_win[:n0]
    return u_win, y_win


def replay_start(model, state, u_run, relag=None) -> tuple:
    """
    Return (stepper, last output): the model from `state` stepped through the commands u_run.

    u_run (n,) or (n, n_in) V: the commands sent from the state's sample on; relag: (u, y), the
    measured samples whose last lags replace the state once they are stepped (`relag_window`;
    the offset is dropped then: the lags carry it). The last output is None when u_run is
    empty. How a controller continues once its start window is whole.
    """
    stepper = model.stepper(state=state)
    n_win = len(relag[0]) if relag is not None else -1
    y = None
    for i, u in enumerate(u_run):
        y = stepper.step(u)
        if i == n_win - 1:
            stepper.offset = np.zeros(model.n_out) if model.n_out > 1 else 0.0
            stepper.reset(*window_lags(model, *relag))
    return stepper, y


def window_lags(model, u_win, y_win) -> tuple:
    """Return (u_past, y_past): the window's last nu inputs and ny outputs (None where 0)."""
    nu, ny = int(model.nu), int(model.ny)
    return (u_win[len(u_win) - nu:] if nu else None, y_win[len(y_win) - ny:] if ny else None)


def first_full_window(stamps, measured, n: int) -> int | None:
    """Index of the first of n consecutive `stamps` all in `measured`; None while there is none."""
    run = 0
    for j, t in enumerate(stamps):
        run = run + 1 if t in measured else 0
        if run >= n:
            return j + 1 - n
    return None


def min_window(model, policy: str) -> int:
    """Fewest measured samples `policy` needs (0 for rest)."""
    if policy == 'rest':
        return 0
    return max(MIN_WINDOW, int(model.n0))


def check_window(model, policy: str, n: int, n_record: int, source: str = 'record') -> None:
    """
    Raise DataError (one line) when a record of n_record samples cannot serve a window of n.

    The window must hold what the policy needs (`min_window`) and leave at least two samples to
    score after it.
    """
    need = min_window(model, policy)
    if n < need:
        raise DataError(f'{source}: the start policy {policy!r} needs at least {need} measured '
                        f'samples, got {n}')
    if n_record < n + 2:
        raise DataError(f'{source}: {n_record} samples, too short for a window of {n} measured '
                        f'samples and a scored free run after it')


def _median_offset(model, residual: np.ndarray):
    """Per-output median of a window's residual: a float for one output, else (n_out,) m."""
    res = np.asarray(residual, dtype=np.float64).reshape(len(residual), -1)
    offset = np.median(res, axis=0)
    if not np.all(np.isfinite(offset)):
        raise DataError('the free run from rest is not finite over the window: no offset')
    return float(offset[0]) if model.n_out == 1 else offset


def rest_state(model) -> ModelState:
    """Return the model's state at rest (no past input, the memory empty, offset 0)."""
    return model.stepper().state


def window_state(model, u, y, policy: str, past: str = 'any') -> ModelState:
    """
    Return the ModelState at u[0] that `policy` takes from a window u (N, ...) V, y (N, ...) m.

    In the model's own shapes ((N,) for one channel). For `state` on a lagged family this is the
    state that best explains the window (the samples inside it are then estimated from it); the
    lags at its end come from the measurement (`relags`). DataError when no state is found.
    """
    check_policy(policy)
    if policy == 'rest':
        return rest_state(model)
    if policy == 'offset':
        start = rest_state(model)
        with np.errstate(all='ignore'):
            sim = model.simulate(u, state=start)
        return ModelState(start.values, _median_offset(model, np.asarray(y) - sim),
                          {'policy': 'offset', 'window': int(len(u))})
    return model.estimate_state(u, y, past=past)


def policy_simulate(model, u, y, n: int, policy: str, past: str = 'any') -> np.ndarray:
    """
    Free run of a whole record u (N, ...) V under `policy` with its first n samples measured.

    y (N, ...) m supplies the window y[:n] only. Returns the output in the model's shape; the
    samples from n on are the ones a score may use. A window no state explains gives NaN.
    """
    check_policy(policy)
    with np.errstate(all='ignore'):
        if policy == 'rest':
            return model.simulate(u)
        try:
            state = window_state(model, u[:n], y[:n], policy, past)
        except DataError:
            if not relags(model, policy):
                return np.full(np.shape(model.simulate(u)), np.nan)
            state = rest_state(model)
        sim = model.simulate(u, state=state)
        relag = relag_window(model, policy, u[:n], y[:n])
        if relag is not None:
            m, n0 = len(relag[0]), int(model.n0)
            if n0:
                sim[m:] = model.simulate(u[m - n0:], y[m - n0:m])[n0:]
            else:
                sim[m:] = model.simulate(u[m:])
        return sim
