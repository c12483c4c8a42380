"""
`piezo-narx export MODEL --c DIR`: the C free run and inverse against the Python ones.

Every family (ARX and the envelope family fitted here on the simulated plant, the paper's NARX
network of bags/model.json) is exported through the command line and compiled once per module
with a small harness under -std=c99 -O2 -Wall -Wextra -pedantic -Werror. The harness runs the
DESIGN.md API on signals piped in as doubles; the Python side is the model's own free run,
Stepper and PositionController.
"""
import importlib.util
import json
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from piezo_narx_ros.cli.main import main as cli_main
from piezo_narx_ros.export import ExportError
from piezo_narx_ros.export.writer import render
from piezo_narx_ros.ident.arx.model import ARXModel
from piezo_narx_ros.ident.hysteresis.model import HysteresisNARX
from piezo_narx_ros.ident.model_io import load_model, save_model
from piezo_narx_ros.ident.narx.model import NARXNetwork
from piezo_narx_ros.plant import PiezoCantilever, generate, load_plant_params

REPO = Path(__file__).resolve().parents[1]
FS = 2000.0
CC = shutil.which('gcc')
CFLAGS = ['-std=c99', '-O2', '-Wall', '-Wextra', '-pedantic', '-Werror', '-Wshadow',
          '-Wstrict-prototypes', '-Wmissing-prototypes']
FREE_RUN_TOL = 1e-12      # m: DESIGN.md's contract
INVERSE_TOL = 1e-9        # V: issue 22's
INVERSE_SAMPLES = 4000    # of each control-bench reference (the bench runs them whole)
KINDS = ('arx', 'narx', 'hysteresis_narx')

pytestmark = pytest.mark.skipif(CC is None, reason='gcc is needed to compile the export')

HARNESS = r"""
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <math.h>
#include "pnr_model.h"

#define MAXN 600000
static double in_[MAXN];
static size_t n_in_, pos_;

static const double *take(size_t n)
{
    const double *p = in_ + pos_;
    if (pos_ + n > n_in_) {
        fprintf(stderr, "harness: input too short\n");
        exit(3);
    }
    pos_ += n;
    return p;
}

static void put(const double *v, size_t n)
{
    fwrite(v, sizeof(double), n, stdout);
}

static void checks(void)
{
    pnr_state_t s, t;
    pnr_inverse_params_t p, q;
    pnr_inverse_t inv;
    double u[PNR_N_INPUTS], y[PNR_N_OUTPUTS], x[PNR_STATE_SIZE], v[PNR_STATE_SIZE];
    double hist[PNR_NU + PNR_NY + 1];
    int i, same = 1;
    for (i = 0; i < PNR_N_INPUTS; ++i) {
        u[i] = 30.0;
    }
    pnr_init(&s);
    pnr_step(&s, u, y);
    pnr_step(&s, u, y);
    pnr_get_state(&s, x);
    u[0] = NAN;
    pnr_step(&s, u, y);
    printf("nan_output %d\n", isnan(y[0]) ? 1 : 0);
    pnr_get_state(&s, v);
    for (i = 0; i < PNR_STATE_SIZE; ++i) {
        same = same && x[i] == v[i];
    }
    printf("nan_keeps_state %d\n", same);
    u[0] = 12.5;
    pnr_peek(&s, u, y);
    t = s;
    pnr_step(&t, u, x);
    pnr_get_state(&s, v);
    printf("peek_is_step %d\n", y[0] == x[0] ? 1 : 0);
    pnr_get_state(&s, x);
    same = 1;
    for (i = 0; i < PNR_STATE_SIZE; ++i) {
        same = same && x[i] == v[i];
    }
    printf("peek_keeps_state %d\n", same);
    x[PNR_STATE_SIZE - 1] = INFINITY;
    printf("set_state_inf %d\n", pnr_set_state(&s, x));
    for (i = 0; i < PNR_NU + PNR_NY + 1; ++i) {
        hist[i] = NAN;
    }
    printf("history_nan %d\n", pnr_init_history(&s, hist, hist));
    printf("history_null %d\n", pnr_init_history(&s, NULL, NULL));
    pnr_get_state(&s, x);
    same = 1;
    for (i = 0; i < PNR_STATE_SIZE; ++i) {
        same = same && x[i] == 0.0;
    }
    printf("history_null_is_rest %d\n", same);
    pnr_inverse_default_params(&p);
    printf("default_params %d\n", pnr_inverse_init(&inv, &p));
    printf("default_target %d\n", p.target);
    printf("default_y_min %.17g\n", p.y_min);
    printf("default_y_max %.17g\n", p.y_max);
    u[0] = NAN;
    printf("no_reference %d\n", pnr_inverse_step(&inv, u, y));
    printf("no_reference_u %.17g\n", y[0]);
    q = p; q.u_min = q.u_max;
    printf("bad_u_range %d\n", pnr_inverse_init(&inv, &q));
    q = p; q.slew_rate = 0.0;
    printf("bad_slew %d\n", pnr_inverse_init(&inv, &q));
    q = p; q.n_grid = 1;
    printf("bad_grid_low %d\n", pnr_inverse_init(&inv, &q));
    q = p; q.n_grid = PNR_MAX_GRID + 1;
    printf("bad_grid_high %d\n", pnr_inverse_init(&inv, &q));
    q = p; q.tol = 0.0;
    printf("bad_tol %d\n", pnr_inverse_init(&inv, &q));
    q = p; q.reach_tol = q.tol / 2.0;
    printf("bad_reach %d\n", pnr_inverse_init(&inv, &q));
    q = p; q.y_min = q.y_max;
    printf("bad_y_range %d\n", pnr_inverse_init(&inv, &q));
    q = p; q.advance = INFINITY;
    printf("bad_advance %d\n", pnr_inverse_init(&inv, &q));
    q = p; q.max_iter = 0;
    printf("bad_iter %d\n", pnr_inverse_init(&inv, &q));
    q = p; q.target = PNR_TARGET_QUASI_STATIC;
    printf("quasi_static %d\n", pnr_inverse_init(&inv, &q));
    q = p; q.target = 7;
    printf("bad_target %d\n", pnr_inverse_init(&inv, &q));
}

int main(int argc, char **argv)
{
    const char *mode = argc > 1 ? argv[1] : "free";
    long n = argc > 2 ? atol(argv[2]) : 0, k, m;
    pnr_state_t s;
    pnr_inverse_params_t p;
    pnr_inverse_t inv;
    double y[PNR_N_OUTPUTS], x[PNR_STATE_SIZE], out[4];
    const double *up, *yp;
    if (!strcmp(mode, "checks")) {
        checks();
        return 0;
    }
    if (!strcmp(mode, "inverse")) {
        pnr_inverse_default_params(&p);
        p.target = atoi(argv[3]);
        p.slew_rate = atof(argv[4]);
        p.u_min = atof(argv[5]);
        p.u_max = atof(argv[6]);
        if (pnr_inverse_init(&inv, &p)) {
            return 5;
        }
    }
    n_in_ = fread(in_, sizeof(double), MAXN, stdin);
    while (pos_ < n_in_) {
        if (!strcmp(mode, "inverse")) {
            pnr_inverse_reset(&inv);
            for (k = 0; k < n; ++k) {
                out[1] = pnr_inverse_step(&inv, take(PNR_N_OUTPUTS), out);
                out[2] = inv.y_model;
                out[3] = inv.miss;
                put(out, 4);
            }
            continue;
        }
        if (!strcmp(mode, "free")) {
            pnr_init(&s);
        } else if (!strcmp(mode, "history")) {
            up = take(PNR_NU * PNR_N_INPUTS);
            yp = take(PNR_NY * PNR_N_OUTPUTS);
            if (pnr_init_history(&s, up, yp)) {
                return 4;
            }
        } else if (!strcmp(mode, "state")) {
            if (pnr_set_state(&s, take(PNR_STATE_SIZE))) {
                return 4;
            }
        } else {
            m = (long)*take(1);
            pnr_init_inputs(&s, take((size_t)m * PNR_N_INPUTS), m);
        }
        for (k = 0; k < n; ++k) {
            pnr_step(&s, take(PNR_N_INPUTS), y);
            put(y, PNR_N_OUTPUTS);
        }
        pnr_get_state(&s, x);
        put(x, PNR_STATE_SIZE);
    }
    return 0;
}
"""


def _bench(name):
    """Import a bench script by path (the battery and the control bench's references)."""
    spec = importlib.util.spec_from_file_location(f'_bench_{name}', REPO / 'bench' / f'{name}.py')
    mod = importlib.util.module_from_spec(spec)
    sys.path.insert(0, str(REPO / 'bench'))      # the scripts import each other
    try:
        spec.loader.exec_module(mod)
    finally:
        sys.path.remove(str(REPO / 'bench'))
    return mod


def compile_export(directory: Path, flags=CFLAGS) -> Path:
    """Compile the harness against DIR/pnr_model.c; returns the program."""
    (directory / 'harness.c').write_text(HARNESS)
    exe = directory / 'harness'
    out = subprocess.run([CC, *flags, '-I', str(directory), str(directory / 'harness.c'),
                          str(directory / 'pnr_model.c'), '-lm', '-o', str(exe)],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    return exe


def run(exe, args, data, width):
    """Run the harness on the doubles `data`; returns its output as rows of `width` doubles."""
    out = subprocess.run([str(exe), *map(str, args)], input=np.ascontiguousarray(
        data, dtype=np.float64).tobytes(), capture_output=True, timeout=120)
    assert out.returncode == 0, out.stderr.decode()
    return np.frombuffer(out.stdout, dtype=np.float64).reshape(-1, width)


def export(model_path, directory, *extra):
    """Run `piezo-narx export MODEL --c DIR` in-process; returns its exit code."""
    with pytest.raises(SystemExit) as stop:
        cli_main(['export', str(model_path), '--c', str(directory), *extra])
    return stop.value.code


@pytest.fixture(scope='module')
def exported(tmp_path_factory):
    """{kind: (model as loaded from its file, compiled harness, export directory)}."""
    root = tmp_path_factory.mktemp('export')
    u = generate('protocol', FS, 6.0, 100.0, seed=0)
    y = PiezoCantilever(load_plant_params(), FS, seed=0).run(u).y
    arx = ARXModel(3, 3).fit(u, y, fs=FS)
    hnarx = HysteresisNARX(hidden=4, n_plays=6, n_duhem=1, n_lags=2, na=2, nb=2,
                           creep_taus=(0.05, 1.0), max_iter=4).fit(u, y, fs=FS)
    paths = {'arx': save_model(arx, root / 'arx.json'),
             'hysteresis_narx': save_model(hnarx, root / 'hnarx.json'),
             'narx': REPO / 'bags' / 'model.json'}
    out = {}
    for kind, path in paths.items():
        directory = root / kind
        assert export(path, directory) in (0, None)
        model = load_model(path)
        assert model.kind == kind
        out[kind] = (model, compile_export(directory), directory)
    return out


def _battery():
    bench = _bench('bench_envelope')
    signals = []
    for name, (kind, amp, opt) in bench.BATTERY.items():
        opt = dict(opt)
        seed = 7919 if opt.pop('seeded', False) else 0
        signals.append((name, generate(kind, FS, bench.TEST_SECONDS, amp, seed=seed, **opt)))
    return signals


@pytest.fixture(scope='module')
def battery():
    return _battery()


# ------------------------------------------------------------------------------ the free run

@pytest.mark.parametrize('kind', KINDS)
def test_free_run_equals_the_python_free_run_on_the_battery(exported, battery, kind):
    model, exe, _ = exported[kind]
    n = battery[0][1].size
    u = np.concatenate([s for _, s in battery])
    rows = run(exe, ['free', n], u, 1).ravel()
    per_run = n + exported[kind][0].c_emitter().state_size
    for i, (name, signal) in enumerate(battery):
        y_c = rows[i * per_run:i * per_run + n]
        y_py = model.simulate(signal)
        err = np.max(np.abs(y_c - y_py))
        assert err <= FREE_RUN_TOL, f'{kind} {name}: max |C - Python| = {err:g} m'
        assert np.ptp(y_py) > 1e-6        # the signal moved the model (a real comparison)


@pytest.mark.parametrize('kind', KINDS)
def test_init_history_is_the_estimators_init_from_measurement(exported, kind):
    model, exe, _ = exported[kind]
    rng = np.random.default_rng(4)
    u = generate('multisine', FS, 1.0, 80.0, seed=3)
    u_past = rng.uniform(-80, 80, model.nu)
    y_past = rng.uniform(-2e-5, 2e-5, model.ny)
    rows = run(exe, ['history', u.size], np.r_[u_past, y_past, u], 1).ravel()
    stepper = model.stepper(u_past, y_past)
    y_py = np.array([stepper.step(x) for x in u])
    assert np.max(np.abs(rows[:u.size] - y_py)) <= FREE_RUN_TOL


@pytest.mark.parametrize('kind', KINDS)
def test_a_python_state_handed_to_c_continues_the_same(exported, kind):
    # The full state vector in the family's documented layout: the Python Stepper's state at
    # sample k, set in C, gives the rest of the run; the C state at the end is the Python one.
    model, exe, _ = exported[kind]
    emitter = model.c_emitter()
    u = generate('aprbs', FS, 2.0, 100.0, seed=5)
    k = 1234
    stepper = model.stepper()
    for x in u[:k]:
        stepper.step(x)
    state = emitter.state_vector(stepper)
    assert state.size == emitter.state_size and np.any(state != 0.0)
    rows = run(exe, ['state', u.size - k], np.r_[state, u[k:]], 1).ravel()
    y_py = np.array([stepper.step(x) for x in u[k:]])
    assert np.max(np.abs(rows[:u.size - k] - y_py)) <= FREE_RUN_TOL
    assert np.array_equal(rows[u.size - k:], emitter.state_vector(stepper))


@pytest.mark.parametrize('kind', KINDS)
def test_init_inputs_feeds_a_history_from_rest(exported, kind):
    model, exe, _ = exported[kind]
    u = generate('protocol', FS, 3.0, 100.0, seed=2)
    k = 2500
    rows = run(exe, ['inputs', u.size - k], np.r_[k, u], 1).ravel()
    assert np.max(np.abs(rows[:u.size - k] - model.simulate(u)[k:])) <= FREE_RUN_TOL


@pytest.mark.parametrize('kind', KINDS)
def test_bad_inputs_and_parameters_are_refused_without_harm(exported, kind):
    model, exe, _ = exported[kind]
    out = subprocess.run([str(exe), 'checks'], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    got = dict(line.split() for line in out.stdout.splitlines())
    expect = {'nan_output': '1', 'nan_keeps_state': '1', 'peek_is_step': '1',
              'peek_keeps_state': '1', 'set_state_inf': '-1', 'history_nan': '-1',
              'history_null': '0', 'history_null_is_rest': '1', 'default_params': '0',
              'no_reference': '4', 'no_reference_u': '0', 'bad_u_range': '-1',
              'bad_slew': '-1', 'bad_grid_low': '-1', 'bad_grid_high': '-1', 'bad_tol': '-1',
              'bad_reach': '-1', 'bad_y_range': '-1', 'bad_advance': '-1', 'bad_iter': '-1',
              'bad_target': '-1',
              'quasi_static': '0' if kind == 'hysteresis_narx' else '-1',
              'default_target': '1' if kind == 'hysteresis_narx' else '0'}
    assert {k: got[k] for k in expect} == expect
    lo, hi = model.output_range
    pad = 0.05 * (hi - lo)
    assert (float(got['default_y_min']), float(got['default_y_max'])) == (lo - pad, hi + pad)


# ------------------------------------------------------------------------------ the inverse

def _references():
    bench = _bench('bench_control')
    return [(task, bench.reference(task, 0)[0][:INVERSE_SAMPLES]) for task in bench.TASKS], \
        bench.SLEW


def _python_inverse(model, ref, target, slew, u_min=-200.0, u_max=200.0):
    from piezo_narx_ros.control.controller import PositionController
    ctl = PositionController(model, mode='inverse', target=target, slew_rate=slew, u_min=u_min,
                             u_max=u_max)
    period = int(1e9 / FS)
    u, y = np.empty(ref.size), np.empty(ref.size)
    for k, r in enumerate(ref):
        (_, u[k]), = ctl.on_reference(k * period, r)
        y[k] = ctl.y_model
    return u, y, ctl.stats


@pytest.mark.parametrize('kind, target', [('arx', 'output'), ('narx', 'output'),
                                          ('hysteresis_narx', 'output'),
                                          ('hysteresis_narx', 'quasi_static')])
def test_inverse_equals_the_controllers_inverse_mode_on_the_bench_references(exported, kind,
                                                                             target):
    model, exe, _ = exported[kind]
    refs, slew = _references()
    n = INVERSE_SAMPLES
    code = {'output': 0, 'quasi_static': 1}[target]
    rows = run(exe, ['inverse', n, code, slew, -200.0, 200.0],
               np.concatenate([r for _, r in refs]), 4)
    reached = 0
    for i, (task, ref) in enumerate(refs):
        u_py, y_py, stats = _python_inverse(model, ref, target, slew)
        c = rows[i * n:(i + 1) * n]
        err = np.max(np.abs(c[:, 0] - u_py))
        assert err <= INVERSE_TOL, f'{kind} {target} {task}: max |C - Python| = {err:g} V'
        assert np.max(np.abs(c[:, 2] - y_py)) <= FREE_RUN_TOL
        assert int(np.sum(c[:, 1] != 0)) == stats.unreachable, task
        reached += int(np.sum(c[:, 1] == 0))
    assert reached > n // 2     # many targets are reached: the refinement path is compared


def test_inverse_limits_and_odd_references_agree_with_the_controller(exported):
    # Tight voltage and slew limits, references beyond the accepted range and NaN references
    # (held): the same commands and the same reasons for missing a target.
    model, exe, _ = exported['hysteresis_narx']
    lo, hi = model.output_range
    t = np.arange(3000) / FS
    ref = 1.3 * hi * np.sin(2 * np.pi * 3.0 * t)
    ref[:3] = np.nan
    ref[1500:1510] = np.nan
    ref[2000] = 10 * lo
    for target in ('output', 'quasi_static'):
        rows = run(exe, ['inverse', ref.size, int(target == 'quasi_static'), 2e4, -60.0, 60.0],
                   ref, 4)
        u_py, y_py, stats = _python_inverse(model, ref, target, 2e4, -60.0, 60.0)
        assert np.max(np.abs(rows[:, 0] - u_py)) <= INVERSE_TOL
        assert np.max(np.abs(rows[:, 2] - y_py)) <= FREE_RUN_TOL
        codes = rows[3:, 1].astype(int)
        assert list(rows[:3, 1]) == [4, 4, 4] and not np.any(rows[:3, 0])
        assert (np.sum(codes == 1), np.sum(codes == 2), np.sum(codes == 3)) == \
            (stats.voltage_limited, stats.slew_limited, stats.not_invertible)
        assert stats.voltage_limited > 0 and stats.slew_limited > 0


# ------------------------------------------------------------------------------ the files

def test_the_files_use_libm_only_and_allocate_nothing(exported):
    for kind, (_, _, directory) in exported.items():
        source = (directory / 'pnr_model.c').read_text()
        includes = [ln for ln in source.splitlines() if ln.startswith('#include')]
        assert includes == ['#include <math.h>', '#include "pnr_model.h"'], kind
        obj = directory / 'pnr_model.o'
        out = subprocess.run([CC, *CFLAGS, '-c', str(directory / 'pnr_model.c'), '-o',
                              str(obj)], capture_output=True, text=True, timeout=60)
        assert out.returncode == 0, out.stderr
        nm = subprocess.run(['nm', '-u', str(obj)], capture_output=True, text=True, timeout=60)
        undefined = {ln.split()[-1] for ln in nm.stdout.splitlines() if ln.strip()}
        assert undefined <= {'exp', 'fabs'}, (kind, undefined)
        header = (directory / 'pnr_model.h').read_text()
        for name in ('PNR_N_INPUTS 1', 'PNR_N_OUTPUTS 1', 'PNR_FS_HZ 2000.0'):
            assert f'#define {name}' in header
        for proto in ('void pnr_init(pnr_state_t *s);',
                      'void pnr_step(pnr_state_t *s, const double *u, double *y);'):
            assert proto in header


def test_the_header_compiles_as_cpp_for_s_functions(exported, tmp_path):
    cxx = shutil.which('g++')
    if cxx is None:
        pytest.skip('g++ not installed')
    directory = exported['hysteresis_narx'][2]
    src = tmp_path / 'use.cpp'
    src.write_text('#include "pnr_model.h"\nint main() { pnr_state_t s; double u[1] = {1.0}, '
                   'y[1]; pnr_init(&s); pnr_step(&s, u, y); return 0; }\n')
    out = subprocess.run([cxx, '-std=c++11', '-Wall', '-Werror', '-fsyntax-only', '-I',
                          str(directory), str(src)], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr


def _edge_models():
    # The smallest structures: no input lags, no Duhem state, no creep, no output dynamics;
    # the emitters leave out empty arrays and loops (C has no zero-length arrays).
    from test_ident_hysteresis import amplifier_model, random_model
    arx = ARXModel(1, 0, fit_intercept=False).set_coefficients([-0.5], [2e-7])
    rng = np.random.default_rng(2)
    narx = NARXNetwork(0, 1, 1).set_weights(rng.normal(size=(1, 2)), [0.1], [0.2], 0.3,
                                            (0.0, 50.0, 0.0, 1e-5))
    bare = random_model(seed=1, scale=0.5, n_lags=0, n_duhem=0, creep_taus=(), na=0, nb=0)
    one = random_model(seed=2, scale=0.5, n_lags=1, n_duhem=1, creep_taus=(0.1,), na=1, nb=0)
    for m in (arx, narx):
        m.fs = FS
    return {'arx nb=0': arx, 'narx nu=0': narx, 'hnarx bare': bare, 'hnarx one': one,
            'hnarx amplifier': amplifier_model()}


@pytest.mark.parametrize('name', list(_edge_models()))
def test_smallest_structures_compile_strictly_and_run_the_same(tmp_path, name):
    model = _edge_models()[name]
    model.output_range = (-1e-4, 1e-4)
    h, c = render(model)
    (tmp_path / 'pnr_model.h').write_text(h)
    (tmp_path / 'pnr_model.c').write_text(c)
    exe = compile_export(tmp_path)
    u = generate('multisine', FS, 1.0, 100.0, seed=1)
    rows = run(exe, ['free', u.size], u, 1).ravel()
    assert np.max(np.abs(rows[:u.size] - model.simulate(u))) <= FREE_RUN_TOL


# ------------------------------------------------------------------------------ refusals

def test_a_model_file_the_exporter_does_not_know_is_refused(tmp_path, capsys):
    arx = ARXModel(2, 1).set_coefficients([-1.2, 0.4], [0.1, 0.2])
    arx.fs = FS
    path = save_model(arx, tmp_path / 'm.json')
    doc = json.loads(path.read_text())
    doc['structure']['kind'] = 'lstm'
    path.write_text(json.dumps(doc))
    assert export(path, tmp_path / 'c') == 2
    err = capsys.readouterr().err
    assert err.startswith('piezo-narx: error: ') and "unknown model kind 'lstm'" in err
    assert err.count('\n') == 1 and not (tmp_path / 'c').exists()
    assert export(tmp_path / 'missing.json', tmp_path / 'c') == 2
    assert 'model file not found' in capsys.readouterr().err


def test_a_registered_family_without_a_c_emitter_is_refused(tmp_path, capsys, monkeypatch):
    from test_ident_model_io import register_toy_family

    Gain = register_toy_family(monkeypatch)
    g = Gain(1e-7)
    g.fs = FS
    path = save_model(g, tmp_path / 'g.json')
    assert export(path, tmp_path / 'c') == 2
    err = capsys.readouterr().err
    assert err == ("piezo-narx: error: the C export does not know model kind 'test_gain' "
                   '(its family has no C emitter)\n')


def test_sample_rate_and_channel_problems_are_one_line_errors(tmp_path, capsys):
    arx = ARXModel(2, 1).set_coefficients([-1.2, 0.4], [0.1, 0.2])
    path = save_model(arx, tmp_path / 'a.json')          # no fs in the file
    assert export(path, tmp_path / 'c') == 2
    assert 'the model file has no fs (give --fs)' in capsys.readouterr().err
    assert export(path, tmp_path / 'c', '--fs', '5000') in (0, None)
    assert '#define PNR_FS_HZ 5000.0' in (tmp_path / 'c' / 'pnr_model.h').read_text()
    capsys.readouterr()
    arx.fs = FS
    path = save_model(arx, tmp_path / 'b.json')
    assert export(path, tmp_path / 'c', '--fs', '1000') == 2
    assert 'fitted at 2000 Hz' in capsys.readouterr().err
    (tmp_path / 'file').write_text('x')
    assert export(path, tmp_path / 'file') == 2
    err = capsys.readouterr().err
    assert 'cannot write the C files' in err and err.count('\n') == 1
    from piezo_narx_ros.ident.arx.export import ARXEmitter
    arx.n_in = 2             # several axes: a family's emitter says what it supports
    with pytest.raises(ExportError, match='supports 1 input.*this model has 2'):
        ARXEmitter(arx)      # (a MIMO ARX gets ARXChannelEmitter: test_mimo_models)
    with pytest.raises(ExportError, match='no weights'):
        render(ARXModel(2, 1))


def test_the_worked_example_of_docs_export_md_builds_and_runs(exported, tmp_path):
    text = (REPO / 'docs' / 'export.md').read_text()
    start = text.index('/* example: loop.c')
    (tmp_path / 'loop.c').write_text(text[start:text.index('```', start)])
    directory = exported['hysteresis_narx'][2]
    exe = tmp_path / 'loop'
    out = subprocess.run([CC, *CFLAGS, '-I', str(directory), str(tmp_path / 'loop.c'),
                          str(directory / 'pnr_model.c'), '-lm', '-o', str(exe)],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    out = subprocess.run([str(exe)], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0
    lines = out.stdout.splitlines()
    assert len(lines) == 9 and all(ln.startswith('t ') for ln in lines)
    r = [float(ln.split()[4]) for ln in lines]
    y = [float(ln.split()[10]) for ln in lines]
    assert max(abs(a - b) for a, b in zip(r, y)) < 0.05       # um: the inverse reached them
