"""
Ablation: which plant element keeps NARX 4/4/10 from passing Billings' tests.

One PlantParams field (or a small named group) is changed at a time from config/plant.yaml; for
each variant the paper's experiment is rerun on 25 s of the default identification multisine
(2 kHz, 100 V peak, fit on the first half, free run on the second) with the project's own tools
and defaults: NARXNetwork(4, 4, 10) and ARXModel(4, 4), an AR noise model fitted on the
estimation half (scoring.fit_noise_models) and the five tests on the whitened free-run
residuals of the validation half under the chance-rate rule (scoring.residual_correlations).

Printed per fit: free-run error against the noise-free sensor output (nm RMS, and its RMS in the
lowest / highest quartile of |u|), std of the whitened validation residuals (nm), free-run R²
against the measurement, max |φ| / band of the five tests (x = test fails) and the verdict.

    python bench/ablation_plant.py                       # every variant, record seed 0, seeds 0 1
    python bench/ablation_plant.py --variants default amp_off --record-seeds 0 1 2
    python bench/ablation_plant.py --variants default --arx-all   # also ARX 1..10 x 1..10
    python bench/ablation_plant.py --variants default --calibrate  # error scaled by 0..1
    python bench/ablation_plant.py --variants default --capacity   # 2x64 MLP on clean data

Serial, one torch thread (the trainer's default); about 2-4 s per network fit.
"""
from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from piezo_narx_ros.ident.arx.model import ARXModel
from piezo_narx_ros.ident.validation.correlation import TEST_NAMES
from piezo_narx_ros.record import Record
from piezo_narx_ros.ident.selection.scoring import (evaluate_model, fit_noise_models,
                                                    outputs_by_record, residual_correlations)
from piezo_narx_ros.ident.narx.model import NARXNetwork
from piezo_narx_ros.ident.validation.noise_model import fit_ar_noise_model
from piezo_narx_ros.plant import PiezoCantilever, generate, load_plant_params
from piezo_narx_ros.plant.figures import loop_width, sine_period

FS = 2000.0          # Hz
SECONDS = 25.0       # s, the paper's record length
AMPLITUDE = 100.0    # V peak, the default identification record
CAL_SCALES = (0.0, 0.05, 0.1, 0.2, 0.3, 0.5, 0.7, 1.0)
OFF_HZ = 1.0e6       # Hz: a first-order lag this fast is "off" at 2 kHz (tau = 0.16 us)

#: name -> PlantParams changes. One element at a time, then a few combinations.
VARIANTS = {
    'default': {},
    'noise_free': {'noise_std': 0.0, 'quantisation': 0.0},
    'quant_off': {'quantisation': 0.0},
    'amp_10k': {'amp_bandwidth': 1.0e4},
    'amp_30k': {'amp_bandwidth': 3.0e4},
    'amp_off': {'amp_bandwidth': OFF_HZ},
    'amp_1k': {'amp_bandwidth': 1.0e3},
    'sensor_20k': {'sensor_bandwidth': 2.0e4},
    'sensor_off': {'sensor_bandwidth': OFF_HZ},
    'sensor_2k': {'sensor_bandwidth': 2.0e3},
    'creep_off': {'creep_gains': (0.0, 0.0, 0.0, 0.0)},
    'slew_off': {'slew_rate': float('inf')},
    'substeps_4': {'substeps': 4},
    'substeps_64': {'substeps': 64},
    'damping_0.05': {'mode_damping': 0.05},
    'damping_0.1': {'mode_damping': 0.1},
    'damping_0.01': {'mode_damping': 0.01},
    'mode_400': {'mode_frequency': 400.0},
    'mode_20k': {'mode_frequency': 2.0e4},   # quasi-static beam (no mode below Nyquist)
    'loop_A0.15': {'A': 0.15},              # narrower loop
    'loop_A0': {'A': 0.0},                  # no hysteresis: a linear plant (control)
    'bw_Bx2': {'B': 0.022, 'gamma': 0.008},  # loop saturates at half the voltage
    'bw_Bx0.5': {'B': 0.0055, 'gamma': 0.002},
    'electronics_off': {'amp_bandwidth': OFF_HZ, 'sensor_bandwidth': OFF_HZ,
                        'slew_rate': float('inf'), 'quantisation': 0.0},
    'linear_static': {'A': 0.0, 'mode_frequency': 2.0e4},
    # Control: a linear plant of order 4 (amplifier, mode, sensor): ARX 4/4 is the right structure.
    'linear_pure': {'A': 0.0, 'creep_gains': (0.0, 0.0, 0.0, 0.0), 'slew_rate': float('inf'),
                    'quantisation': 0.0},
    # Linear plant with one non-ideal element left: which of them costs a 4/4 model accuracy?
    'linear_creep': {'A': 0.0, 'slew_rate': float('inf'), 'quantisation': 0.0},
    'linear_slew': {'A': 0.0, 'creep_gains': (0.0, 0.0, 0.0, 0.0), 'quantisation': 0.0},
    # Bouc-Wen and the mode alone (every other element ideal).
    'hysteresis_only': {'creep_gains': (0.0, 0.0, 0.0, 0.0), 'slew_rate': float('inf'),
                        'amp_bandwidth': OFF_HZ, 'sensor_bandwidth': OFF_HZ, 'quantisation': 0.0},
    # Realistic lab electronics (docs/ablation.md): HV amplifier of ~100 kHz small-signal bandwidth
    # and >= 1e7 V/s on a few-nF load, 20 kHz optical sensor, Q = 10 mode, loop at the 10 % end.
    'realistic_best': {'amp_bandwidth': 1.0e5, 'slew_rate': 1.0e7, 'sensor_bandwidth': 2.0e4,
                       'mode_damping': 0.05, 'B': 0.0055, 'gamma': 0.002},
    'noise_66nm': {'noise_std': 6.6e-8},     # ~100 nm precision read as 1.5 sigma
    'noise_100nm': {'noise_std': 1.0e-7},    # ~100 nm precision read as 1 sigma
}


def make_records(params, record_seed: int) -> tuple[Record, Record]:
    """
    (estimation, validation) halves of the default 25 s multisine record on `params`.

    y_true is the noise-free sensor output (same command, no noise, no quantisation): the output
    a perfect model of the measured signal would give.
    """
    u = generate('multisine', FS, SECONDS, AMPLITUDE, seed=record_seed)
    y = PiezoCantilever(params, FS, seed=record_seed).run(u).y
    clean = PiezoCantilever(params.replace(noise_std=0.0, quantisation=0.0), FS,
                            seed=record_seed).run(u).y
    return Record(u=u, y=y, fs=FS, source='plant', y_true=clean).split(0.5)


def reversal_mask(u: np.ndarray, half_width: int = 1) -> np.ndarray:
    """(N,) bool: samples within half_width samples of a reversal of the command's direction."""
    du = np.sign(np.diff(u))
    rev = np.zeros(u.size, bool)
    rev[1:-1] = du[1:] * du[:-1] < 0
    return np.convolve(rev, np.ones(2 * half_width + 1), 'same') > 0


BURN_IN = 200  # samples (100 ms, ~10 decay times of the 765 Hz, zeta 0.02 mode)


def scores_of(parts: list[dict], est_parts: list[dict], y_true: np.ndarray, u: np.ndarray) -> dict:
    """
    Judge given outputs as the experiment does: test values and error figures.

    The outputs are the 'simulation' of each part; judged with the AR noise model on the estimation
    residuals, whitened validation residuals and the chance-rate rule. `y_true` and `u` are the
    validation samples k >= n0.

    'passed_burn' is the verdict when the noise model is fitted on the estimation residuals
    without their first BURN_IN samples: the free run starts from n0 noisy outputs and its
    start-up transient alone can make BIC choose a high AR order (docs/ablation.md).
    """
    resid_est = np.concatenate([p['y'] - p['simulation'] for p in est_parts])
    shortest = min(p['y'].size for p in est_parts)
    cap = max(0, min(20, resid_est.size // 10 - 1, shortest - 80))
    nm = fit_ar_noise_model(resid_est, cap)
    corr = residual_correlations(parts, 'simulation', 20, 0.05, nm)
    nm_burn = fit_ar_noise_model(
        np.concatenate([(p['y'] - p['simulation'])[BURN_IN:] for p in est_parts]), cap)
    corr_burn = residual_correlations(parts, 'simulation', 20, 0.05, nm_burn)
    sim = parts[0]['simulation']
    err = y_true - sim
    au = np.abs(u)
    lo, hi = np.quantile(au, [0.25, 0.75])
    rev = reversal_mask(u)
    ratio = {}
    for name in TEST_NAMES:
        t = corr.tests[name]
        tested = t.lags != 0
        ratio[name] = (float(np.max(np.abs(t.values[tested]))) / corr.band, t.passed)
    innov = nm.whiten(parts[0]['y'] - sim) if nm.order else parts[0]['y'] - sim
    return {'err': float(np.sqrt(np.mean(err ** 2))),
            'err_lo': float(np.sqrt(np.mean(err[au <= lo] ** 2))),
            'err_hi': float(np.sqrt(np.mean(err[au >= hi] ** 2))),
            'err_rev': float(np.sqrt(np.mean(err[rev] ** 2))),
            'innov': float(np.std(innov)), 'order': nm.order, 'tests': ratio,
            'passed': corr.passed, 'passed_burn': corr_burn.passed, 'order_burn': nm_burn.order}


def judge(model, est: Record, val: Record) -> dict:
    """
    Scores, whitened free-run test values and model error of a fitted model (SI units).

    The verdict is the experiment's own (evaluate_model with fit_noise_models); the max |φ|/band
    values come from residual_correlations with the same noise model. 'step1' is the one-step
    error from the noise-free past (what the network's map itself misses).
    """
    noise = fit_noise_models(model, [est])
    out = evaluate_model(model, [val], noise_models=noise)
    n0 = model.n0
    res = scores_of(outputs_by_record(model, [val]), outputs_by_record(model, [est]),
                    val.y_true[n0:], val.u[n0:])
    assert res['passed'] == bool(out['tests']['simulation']['passed'])  # same pipeline
    one_step = model.predict(val.u, val.y_true)[n0:]
    res.update(r2=out['simulation']['r2'],
               step1=float(np.sqrt(np.mean((val.y_true[n0:] - one_step) ** 2))))
    return res


def calibrate(model, est: Record, val: Record, scales) -> list[tuple[float, dict]]:
    """
    Verdicts when the model's free-run error (against y_true) is scaled by each factor c.

    The output judged is y_true - c * (y_true - simulation), on estimation and validation halves
    alike, so the residual is the record's own sensor noise plus c times the model's error: how
    small this error pattern must be for the tests to stop seeing it at this N and noise.
    """
    n0 = model.n0
    est_p, val_p = outputs_by_record(model, [est]), outputs_by_record(model, [val])
    out = []
    for c in scales:
        def scaled(parts, rec):
            truth = rec.y_true[n0:]
            return [{**parts[0], 'simulation': truth - c * (truth - parts[0]['simulation'])}]
        out.append((c, scores_of(scaled(val_p, val), scaled(est_p, est), val.y_true[n0:],
                                 val.u[n0:])))
    return out


def width_at_100v(params) -> float:
    """Loop width (fraction) of a 0.1 Hz, ±100 V sine, as docs/plant.md defines it."""
    u, y, _ = sine_period(params, 100.0, 0.1)
    return loop_width(u, y)[0]


def states_and_output(params, record_seed: int):
    """
    Return the default record with its noise-free output and the plant state after each sample.

    (u V, noise-free sensor output m, state (N, n_states)), by step() (bit-identical to run()).
    State columns: v, h, creep..., y, dy/dt, sensor (PiezoCantilever.state).
    """
    u = generate('multisine', FS, SECONDS, AMPLITUDE, seed=record_seed)
    plant = PiezoCantilever(params.replace(noise_std=0.0, quantisation=0.0), FS, seed=record_seed)
    y = np.empty(u.size)
    states = np.empty((u.size, plant.state.size))
    for k, uk in enumerate(u):
        y[k] = plant.step(uk)[0]
        states[k] = plant.state
    return u, y, states


def mlp_one_step_error(x: np.ndarray, t: np.ndarray, n_est: int, seed: int = 0,
                       steps: int = 3000) -> float:
    """
    Return the validation RMS one-step error (units of t) of a 2 x 64 tanh MLP.

    Trained with Adam on the first n_est rows of regressors x (N, d) -> target t (N,): what a
    flexible learner can get out of these regressors on noise-free data (an upper bound on what 10
    sigmoids can).

    The linear least-squares part is fitted first and the MLP learns what it leaves: Adam's
    mini-batch noise would otherwise stop near 1 % of the output, the size of the effect sought.
    """
    import torch
    torch.manual_seed(seed)
    mx, sx = x[:n_est].mean(0), x[:n_est].std(0) + 1e-30
    xa = np.column_stack([(x - mx) / sx, np.ones(len(x))])
    coef = np.linalg.lstsq(xa[:n_est], t[:n_est], rcond=None)[0]
    t = t - xa @ coef
    mt, st = t[:n_est].mean(), t[:n_est].std()
    X = torch.tensor((x - mx) / sx, dtype=torch.float32)
    T = torch.tensor((t - mt) / st, dtype=torch.float32)
    net = torch.nn.Sequential(torch.nn.Linear(x.shape[1], 64), torch.nn.Tanh(),
                              torch.nn.Linear(64, 64), torch.nn.Tanh(), torch.nn.Linear(64, 1))
    opt = torch.optim.Adam(net.parameters(), lr=3e-3)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, steps)
    gen = torch.Generator().manual_seed(seed)
    for _ in range(steps):
        idx = torch.randint(0, n_est, (2048,), generator=gen)
        loss = torch.mean((net(X[idx]).squeeze(1) - T[idx]) ** 2)
        opt.zero_grad()
        loss.backward()
        opt.step()
        sched.step()
    with torch.no_grad():
        pred = net(X[n_est:]).squeeze(1).double().numpy() * st + mt
    return float(np.sqrt(np.mean((pred - t[n_est:]) ** 2)))


def capacity_probe(params, record_seed: int) -> list[tuple[str, float]]:
    """
    Measure the one-step validation error (m) of a flexible learner for several regressor sets.

    On noise-free data: is the 4/4 regressor enough to determine y(k), or is state missing?
    """
    from piezo_narx_ros.ident.narx.regressors import lagged_regressors
    u, y, states = states_and_output(params, record_seed)
    half = u.size // 2
    out = []
    for name, lags, extra in (('4/4 lags', 4, None), ('8/8 lags', 8, None),
                              ('4/4 + true h(k-1)', 4, [1]),
                              ('1/1 + full state(k-1)', 1, list(range(states.shape[1])))):
        x, t = lagged_regressors(u, y, lags, lags)
        if extra is not None:
            x = np.column_stack([x, states[lags - 1:-1][:, extra]])
        out.append((name, mlp_one_step_error(x, t, half - lags)))
    return out


def white_noise_pass_rate(record_seed: int = 0, draws: int = 200) -> tuple[int, dict]:
    """
    How often white residuals pass against the validation half of the default multisine.

    (all five passed, {test: passes}) over `draws` seeded draws (chance-rate rule, L = 20).
    """
    from piezo_narx_ros.ident.validation.correlation import correlation_tests
    u = generate('multisine', FS, SECONDS, AMPLITUDE, seed=record_seed)[int(SECONDS * FS) // 2:]
    rng = np.random.default_rng(123)
    all_five, per_test = 0, dict.fromkeys(TEST_NAMES, 0)
    for _ in range(draws):
        result = correlation_tests(rng.standard_normal(u.size), u, 20, 0.05)
        all_five += result.passed
        for name, ok in result.verdicts().items():
            per_test[name] += ok
    return all_five, per_test


def row(variant, rseed, label, res, seconds=None) -> str:
    tests = ' '.join(f'{v:5.1f}{" " if ok else "x"}' for v, ok in res['tests'].values())
    r2 = f'{res["r2"]:.6f}' if 'r2' in res else ' ' * 8
    step1 = f'{res["step1"] * 1e9:6.1f}' if 'step1' in res else ' ' * 6
    took = f' {seconds:5.1f}s' if seconds is not None else ''
    return (f'{variant:16s} {rseed:2d} {label:12s} {res["err"] * 1e9:7.1f} '
            f'{res["err_lo"] * 1e9:6.1f} {res["err_hi"] * 1e9:6.1f} {res["err_rev"] * 1e9:6.1f} '
            f'{step1} {res["innov"] * 1e9:6.1f} {r2}  {tests}  '
            f'{"PASS" if res["passed"] else "fail"} {"PASS" if res["passed_burn"] else "fail"} '
            f'AR{res["order"]}/{res["order_burn"]}{took}')


HEADER = (f'{"variant":16s} rs {"model":12s} {"err nm":>7s} {"|u|lo":>6s} {"|u|hi":>6s} '
          f'{"rev":>6s} {"1step":>6s} {"innov":>6s} {"R2 sim":8s}  {"ee":>5s}  {"ue":>5s}  '
          f'{"u2e":>5s}  {"u2e2":>5s}  {"e(eu)":>5s}  dflt burn')


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.strip().split('\n')[0])
    ap.add_argument('--variants', nargs='+', default=list(VARIANTS),
                    help=f'variants to run (default all): {", ".join(VARIANTS)}')
    ap.add_argument('--record-seeds', nargs='+', type=int, default=[0])
    ap.add_argument('--train-seeds', nargs='+', type=int, default=[0, 1])
    ap.add_argument('--hidden', type=int, default=10)
    ap.add_argument('--lags', type=int, default=4, help='NARX nu = ny')
    ap.add_argument('--no-arx', action='store_true', help='skip ARX 4/4')
    ap.add_argument('--arx-all', action='store_true',
                    help='also ARX 1..10 x 1..10: how many pass, smallest max phi_u2e2/band')
    ap.add_argument('--calibrate', action='store_true',
                    help='also judge each network with its free-run error scaled by '
                         f'{", ".join(map(str, CAL_SCALES))}')
    ap.add_argument('--capacity', action='store_true',
                    help='also the one-step error a 2x64 MLP reaches on noise-free data with '
                         '4/4, 8/8, 4/4 + true Bouc-Wen state, full plant state regressors')
    ap.add_argument('--white', action='store_true',
                    help='only: pass rate of 200 white residual draws against the multisine')
    ap.add_argument('--set', nargs='*', default=[], metavar='FIELD=VALUE',
                    help='extra PlantParams changes applied to every variant (floats)')
    args = ap.parse_args(argv)
    unknown = [v for v in args.variants if v not in VARIANTS]
    if unknown:
        print(f'ablation_plant: unknown variant {unknown[0]!r}', file=sys.stderr)
        return 2
    if args.white:
        for rseed in args.record_seeds:
            all_five, per_test = white_noise_pass_rate(rseed)
            print(f'record seed {rseed}: white residuals pass all five tests {all_five}/200; '
                  'per test ' + ', '.join(f'{k} {v}/200' for k, v in per_test.items()))
        return 0
    extra = {}
    for item in args.set:
        key, _, value = item.partition('=')
        extra[key] = int(value) if key == 'substeps' else float(value)
    base = load_plant_params()
    tally = {}
    print('err: free-run error vs the noise-free sensor output (RMS, nm), also in the lowest and\n'
          'highest |u| quartile and within 1 sample of a command reversal (rev); 1step: one-step\n'
          'error from the noise-free past; innov: std of the whitened validation residuals;\n'
          'max |phi|/band over lags 1..20 of the whitened free-run residuals; x = test fails;\n'
          f'dflt: verdict of the default pipeline; burn: noise model fitted without the first '
          f'{BURN_IN} samples; AR orders of both')
    print(HEADER)
    for variant in args.variants:
        params = base.replace(**{**VARIANTS[variant], **extra})
        print(f'# {variant}: loop width at 0.1 Hz, +/-100 V: {100 * width_at_100v(params):.1f} %',
              flush=True)
        for rseed in args.record_seeds:
            if args.capacity:
                for name, err in capacity_probe(params, rseed):
                    print(f'{variant:16s} {rseed:2d} MLP 2x64 one-step, noise-free, {name}: '
                          f'{err * 1e9:.1f} nm', flush=True)
            est, val = make_records(params, rseed)
            for tseed in args.train_seeds:
                t0 = time.perf_counter()
                model = NARXNetwork(args.lags, args.lags, args.hidden, seed=tseed)
                model.fit(est.u, est.y, fs=FS)
                label = f'NARX{args.lags}/{args.hidden} s{tseed}'
                res = judge(model, est, val)
                print(row(variant, rseed, label, res, time.perf_counter() - t0), flush=True)
                count(tally, (variant, 'NARX'), res)
                if args.calibrate:
                    for c, res in calibrate(model, est, val, CAL_SCALES):
                        print(row(variant, rseed, f'  err x{c:g}', res), flush=True)
                        if c == 0.0 and tseed == args.train_seeds[0]:
                            count(tally, (variant, 'perfect'), res)
            if not args.no_arx:
                t0 = time.perf_counter()
                arx = ARXModel(4, 4).fit(est.u, est.y, fs=FS)
                res = judge(arx, est, val)
                print(row(variant, rseed, 'ARX 4/4', res, time.perf_counter() - t0), flush=True)
                count(tally, (variant, 'ARX 4/4'), res)
            if args.arx_all:
                passed, worst = 0, np.inf
                for na in range(1, 11):
                    for nb in range(1, 11):
                        res = judge(ARXModel(na, nb).fit(est.u, est.y, fs=FS), est, val)
                        passed += res['passed']
                        worst = min(worst, res['tests']['phi_u2e2'][0])
                print(f'{variant:16s} {rseed:2d} ARX 1..10 x 1..10: {passed}/100 pass, '
                      f'smallest max phi_u2e2/band {worst:.1f}', flush=True)
    print('\nsummary: fits passing (default pipeline / burn-in noise model), median error nm')
    for (variant, model), (n, ok, ok_burn, errs) in tally.items():
        print(f'{variant:16s} {model:8s} {ok}/{n} / {ok_burn}/{n}   '
              f'err {np.median(errs) * 1e9:6.1f}')
    return 0


def count(tally: dict, key, res) -> None:
    """Accumulate (fits, passes, passes with burn-in, errors) per (variant, model)."""
    n, ok, ok_burn, errs = tally.get(key, (0, 0, 0, []))
    tally[key] = (n + 1, ok + res['passed'], ok_burn + res['passed_burn'], errs + [res['err']])


if __name__ == '__main__':
    sys.exit(main())
