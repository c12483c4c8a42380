"""
Scoring a fitted model on records: the experiment's judge, and evaluate's.

Its free runs and one-step predictions, the R² and RMSE of each, the noise models and the
residual correlation tests. A model whose state is a function of the whole input history is run
from its recording's start and scored on the record's own samples; the others start from the
first n0 measured outputs, or from a state set on the record's measured window
(Record.state_window).
"""
from __future__ import annotations

import numpy as np

from piezo_narx_ros.errors import DataError
from piezo_narx_ros.ident.validation import metrics
from piezo_narx_ros.ident.validation.correlation import correlation_tests
from piezo_narx_ros.ident.validation.noise_model import ARNoiseModel, fit_ar_noise_model
from piezo_narx_ros.record import Record, as_columns, channels_arg

__all__ = ['RESIDUAL_KINDS', 'free_run', 'scored_from', 'evaluate_model', 'fit_noise_models',
           'from_rest_scores', 'model_outputs', 'outputs_by_record', 'residual_correlations']


RESIDUAL_KINDS = ('prediction', 'simulation')


# Samples at the start of each free run left out of the noise model and the tests: the start-up
# transient (the model's lag states start from measured, noisy outputs) is not noise. Measured on a
# linear plant: with it, the exact ARX(4,4) got an AR(18-20) noise model from the transient alone
# and failed the tests in 6 of 6 records; without it, AR(0) and the white-noise pass rate.
SIMULATION_BURN_IN = 200


def free_run(model, record: Record) -> tuple[np.ndarray, np.ndarray]:
    """
    (one-step prediction, free run), (N, n_out) m each, of a model on a record.

    The model gets the record's channels in its own form (`channels_arg`: 1-D for one channel,
    as before several axes); its outputs come back as (N, n_out) columns.

    The free run starts from the record's first n0 measured outputs, as the paper does. A model
    whose state is a function of the whole input history (`state_from_input`) is instead run
    from the start of the recording the record was cut from (its u_before / y_before), with the
    recording's first n0 outputs, as it would have run live; the record's samples are returned.

    A record with a `state_window` N > 0 starts every family from a measured state, as a rig's
    estimator does (`--init-samples`): model.estimate_state on the record's first N samples. When
    the record continues a recording (a validation half), its input history is known: the state
    found at the recording's start is run through that history and then refined (offset, creep,
    output dynamics) on the record's first N samples; `state_past` says how the unlogged past
    ended (ident.state.estimate, step 5). A free run of NaN when no state is found.
    """
    pred, sim = _free_run(model, record)
    return as_columns(pred), as_columns(sim)


def _free_run(model, record: Record):
    """free_run in the model's own shapes ((N,) for one output)."""
    u, y, skip = channels_arg(record.u), channels_arg(record.y), 0
    u_before, y_before = channels_arg(record.u_before), channels_arg(record.y_before)
    window = record.state_window
    before = u_before is not None and y_before is not None
    with np.errstate(all='ignore'):   # a diverging network must not spam warnings
        if window is not None and record.state_policy is not None:
            # A stored start policy (ident/state/start.py): the record on its own, as a rig
            # sees it.
            from piezo_narx_ros.ident.state.start import policy_simulate
            return model.predict(u, y), policy_simulate(model, u, y, int(window),
                                                        record.state_policy, record.state_past)
        if window:
            if before:
                pred = model.predict(np.r_[u_before, u],
                                     np.r_[y_before, y])[len(u_before):]
            else:
                pred = model.predict(u, y)
            n = min(int(window), len(u))
            try:
                prior = None
                if before:
                    m = min(n, len(u_before))
                    start = model.estimate_state(u_before[:m], y_before[:m],
                                                 past=record.state_past)
                    stepper = model.stepper(state=start)
                    for value in u_before:
                        stepper.step(value)
                    prior = stepper.state
                state = model.estimate_state(u[:n], y[:n], prior=prior,
                                             past=record.state_past)
                sim = model.simulate(u, state=state)
            except DataError:
                sim = np.full(np.shape(pred), np.nan)
            return pred, sim
        if (window is not None or getattr(model, 'state_from_input', False)) and before:
            skip = len(u_before)
            u, y = np.concatenate([u_before, u]), np.concatenate([y_before, y])
        pred = model.predict(u, y)
        sim = model.simulate(u) if window == 0 else model.simulate(u, y[:model.n0])
    return pred[skip:], sim[skip:]


def scored_from(model, record: Record) -> int:
    """
    First sample of `record` that is scored.

    n0 (the paper's convention), 0 from rest, or the first after the record's state window.
    """
    if record.state_window is None:
        return int(model.n0)
    return int(record.state_window)


def outputs_by_record(model, records: list[Record]) -> list[dict[str, np.ndarray]]:
    """
    Per record, the scored samples (`scored_from`): u (V), y, prediction, simulation (m).

    Each (n, channels): u (n, n_in), the others (n, n_out).
    """
    parts = []
    for r in records:
        pred, sim = free_run(model, r)
        k = scored_from(model, r)
        parts.append({'u': r.u[k:], 'y': r.y[k:], 'prediction': pred[k:],
                      'simulation': sim[k:]})
    return parts


def from_rest_scores(model, records: list[Record]) -> dict:
    """
    Score a free run from rest on the samples after each record's state window.

    The comparison for a state set from measurement (`--init-samples N`): the same scored samples,
    the model started at rest with its fitted zero. Records of the fit's own session may free-run
    better so when the fit learned their usual past as its rest (docs/real.md).
    """
    parts = []
    for r in records:
        with np.errstate(all='ignore'):
            sim = as_columns(model.simulate(channels_arg(r.u)))
        k = scored_from(model, r)
        parts.append({'y': r.y[k:], 'simulation': sim[k:]})
    scores = _scores(parts, [r.source for r in records], records[0].outputs, ('simulation',))
    result = scores['simulation']
    if 'records' in scores:
        result['records'] = [{'source': e['source'], 'samples': e['samples'], **e['simulation']}
                             for e in scores['records']]
    return result


def model_outputs(model, records: list[Record]) -> dict[str, np.ndarray]:
    """
    Pooled samples k >= n0 of every record: 'u' (V), 'y' (m), 'prediction', 'simulation' (m).

    (n, channels) each, as outputs_by_record.

    Each record is predicted from its measured past and simulated from its first n0 outputs.
    """
    parts = outputs_by_record(model, records)
    return {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}


def _residual(part: dict, mode: str) -> np.ndarray:
    """
    Return the residual y - ŷ of one record (m).

    A free run without its start-up transient (SIMULATION_BURN_IN), kept whole when the record is
    too short to spare it. (n, n_out).
    """
    e = part['y'] - part[mode]
    skip = SIMULATION_BURN_IN if mode == 'simulation' else 0
    return e[skip:] if len(e) > 10 * skip else e


def fit_noise_models(model, records: list[Record], max_order: int = 20,
                     max_lag: int = 20) -> dict[str, ARNoiseModel | None]:
    """
    AR noise model of the model's residuals on (estimation) records, per residual kind.

    The order is capped by `max_order` and by what the data allow (10 samples per coefficient,
    and 4 * max_lag samples left per record after whitening). None for a kind whose output is not
    finite (a diverged free run). Several outputs: a list of noise models, one per output (each
    output's residual is whitened on its own).
    """
    parts = outputs_by_record(model, records)
    shortest = min(len(p['y']) for p in parts)
    result = {}
    for mode in RESIDUAL_KINDS:
        resid = np.concatenate([_residual(p, mode) for p in parts])
        if not np.all(np.isfinite(resid)):
            result[mode] = None
            continue
        cap = max(0, min(int(max_order), len(resid) // 10 - 1, shortest - 4 * int(max_lag)))
        fitted = [fit_ar_noise_model(resid[:, j], cap) for j in range(resid.shape[1])]
        result[mode] = fitted[0] if len(fitted) == 1 else fitted
    return result


def _mode_scores(out: dict, names=None, modes=RESIDUAL_KINDS) -> dict:
    result = {}
    for mode in modes:
        y_hat = out[mode]
        if np.all(np.isfinite(y_hat)):
            result[mode] = metrics.channel_scores(out['y'], y_hat, names)
        else:
            result[mode] = {'r2': None, 'rmse': None, 'nrmse': None, 'fit_percent': None,
                            'diverged': True}
    return result


def _scores(parts: list[dict], sources: list[str] | None = None, names=None,
            modes=RESIDUAL_KINDS) -> dict:
    """
    Scores pooled over the records (and over outputs: metrics.channel_scores).

    With several records also 'records': one entry each (source, samples, prediction and simulation
    scores). names: the output names (several outputs also get 'per_output' scores). modes: the
    outputs of `parts` to score besides 'y'.
    """
    out = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
    result = _mode_scores(out, names, modes)
    if sources is not None and len(parts) > 1:
        result['records'] = [{'source': src, 'samples': int(len(p['y'])),
                              **_mode_scores(p, names, modes)}
                             for src, p in zip(sources, parts)]
    return result


def _failed_tests(reason: str) -> dict:
    return {'passed': False, reason: True, 'tests': {}}


def residual_correlations(parts: list[dict], mode: str, max_lag: int,
                          max_outside_fraction: float, noise_model: ARNoiseModel | None = None):
    """
    Test the residuals of `mode` pooled over records: a CorrelationResult, None when not finite.

    Each record is whitened on its own by `noise_model`, its first `order` samples dropped.
    Several channels: the tests run on each output's residual (whitened by its own noise model,
    `noise_model` a list) against each input; the result is the pair that fails most (fewest
    tests passed, then most lags outside), with 'output' and 'input' indices in its `pair`.
    """
    n_out, n_in = parts[0]['y'].shape[1], parts[0]['u'].shape[1]
    models = noise_model if isinstance(noise_model, (list, tuple)) else [noise_model] * n_out
    worst = None
    for j in range(n_out):
        resid, u = [], []
        for p in parts:
            e = _residual(p, mode)[:, j]
            if not np.all(np.isfinite(e)):
                return None
            if models[j] is not None and models[j].order:
                e = models[j].whiten(e)
            resid.append(e)
            u.append(p['u'][len(p['u']) - e.size:])
        e_all, u_all = np.concatenate(resid), np.concatenate(u)
        for i in range(n_in):
            corr = correlation_tests(e_all, u_all[:, i], max_lag, max_outside_fraction)
            if n_out == 1 and n_in == 1:
                return corr
            corr.pair = {'output': j, 'input': i}
            key = (sum(corr.verdicts().values()),
                   -sum(t.n_outside for t in corr.tests.values()))
            if worst is None or key < worst[0]:
                worst = (key, corr)
    return worst[1]


def evaluate_model(model, records: list[Record], max_lag: int = 20,
                   max_outside_fraction: float = 0.05, with_tests: bool = True,
                   noise_models: dict | None = None) -> dict:
    """
    Scores of a fitted model on records.

    {'prediction': scores, 'simulation': scores, 'tests': {...}} (tests omitted when with_tests is
    False).

    `noise_models` ({'prediction'|'simulation': ARNoiseModel | None}) whitens the residuals before
    the tests; then tests[mode] holds the verdicts on the innovations with the noise model that
    produced them under 'noise_model', and tests['raw'][mode] the verdicts on the raw residuals.
    Without noise models, tests[mode] are the raw verdicts (and tests['raw'] repeats them).
    A non-finite simulation (diverged network) gets scores of None and failing tests.
    """
    parts = outputs_by_record(model, records)
    result = _scores(parts, [r.source for r in records], records[0].outputs)
    if not with_tests:
        return result
    tests = {'raw': {}}
    for mode in RESIDUAL_KINDS:
        raw = residual_correlations(parts, mode, max_lag, max_outside_fraction)
        tests['raw'][mode] = (_failed_tests('diverged') if raw is None
                              else raw.to_dict(with_values=False))
        if noise_models is None:
            tests[mode] = tests['raw'][mode]
            continue
        nm = noise_models.get(mode)
        if raw is None:
            tests[mode] = _failed_tests('diverged')
        elif nm is None:   # its free run diverged on the estimation data
            tests[mode] = _failed_tests('no_noise_model')
        else:
            corr = residual_correlations(parts, mode, max_lag, max_outside_fraction, nm)
            tests[mode] = {**corr.to_dict(with_values=False),
                           'noise_model': ([m.to_dict() for m in nm]
                                           if isinstance(nm, (list, tuple)) else nm.to_dict())}
    result['tests'] = tests
    return result
