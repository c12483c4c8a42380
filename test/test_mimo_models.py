"""Several inputs and outputs in the lagged families: ARX, the paper's network, C export (#20)."""
import json
import shutil
import subprocess

import numpy as np
import pytest

from conftest import SHARED
from piezo_narx_ros.errors import DataError
from piezo_narx_ros.ident.arx.model import ARXModel
from piezo_narx_ros.ident.model_io import load_model, save_model
from piezo_narx_ros.ident.narx.model import NARXNetwork
from piezo_narx_ros.ident.narx.regressors import lagged_regressors

FS = 1000.0


def mimo_plant(n=3000, seed=1, noise=0.0):
    """Return a coupled 2-input 3-output ARX system (m, V): y1 feels y2, y3 feels y1."""
    rng = np.random.default_rng(seed)
    u = rng.standard_normal((n, 2)) * 5
    y = np.zeros((n, 3))
    for k in range(2, n):
        y[k, 0] = 1.2 * y[k - 1, 0] - 0.5 * y[k - 2, 0] + 0.1 * y[k - 1, 1] + 1e-7 * u[k, 0] \
            + 2e-8 * u[k - 1, 1]
        y[k, 1] = 0.8 * y[k - 1, 1] + 3e-8 * u[k - 1, 0] + 1e-7 * u[k, 1]
        y[k, 2] = 0.5 * y[k - 1, 2] + 0.2 * y[k - 2, 0] + 5e-8 * u[k, 1] + 2e-9
    return u, y + noise * rng.standard_normal(y.shape)


def test_channel_regressors_take_each_column_from_its_own_channel_and_record():
    u = np.arange(10.0)[:, None] * [1.0, 100.0]          # two inputs, told apart by scale
    y = np.arange(10.0)[:, None] * [-1.0]
    X, t = lagged_regressors(u, y, nu=1, ny=2)
    # Row for k = 2: [u1(2), u1(1), u2(2), u2(1), y1(1), y1(0)].
    np.testing.assert_array_equal(X[0], [2.0, 1.0, 200.0, 100.0, -1.0, 0.0])
    np.testing.assert_array_equal(t[:, 0], -np.arange(2.0, 10.0))
    # Two records fitted together give exactly the rows of each, none across the join.
    a, b = mimo_plant(400, seed=2), mimo_plant(400, seed=3)
    both = ARXModel(2, 1).fit([a[0], b[0]], [a[1], b[1]])
    joined = ARXModel(2, 1).fit(np.r_[a[0], b[0]], np.r_[a[1], b[1]])
    rows = [lagged_regressors(r[0], r[1], 1, 2) for r in (a, b)]
    X = np.hstack([np.vstack([r[0] for r in rows]), np.ones((796, 1))])
    theta = np.linalg.lstsq(X, np.vstack([r[1] for r in rows]), rcond=None)[0]
    np.testing.assert_allclose(both.b[:, :, 0], theta[[0, 2]].T, rtol=1e-6, atol=1e-14)
    assert not np.allclose(joined.a, both.a, rtol=1e-9, atol=0)     # the join would leak


def test_mimo_arx_recovers_a_coupled_system_and_steps_as_it_simulates():
    u, y = mimo_plant()
    m = ARXModel(2, 1).fit(u, y, fs=FS)
    assert (m.n_in, m.n_out, m.n_params) == (2, 3, 3 * (2 * 2 + 3 * 2 + 1))
    np.testing.assert_allclose(m.a[0, :, 0], [-1.2, -0.1, 0.0], atol=1e-9)
    np.testing.assert_allclose(m.a[2, 0], [0.0, -0.2], atol=1e-9)
    np.testing.assert_allclose(m.b[0, 1], [0.0, 2e-8], atol=1e-15)
    sim = m.simulate(u, y[:2])
    assert sim.shape == (3000, 3) and np.max(np.abs(sim - y)) < 1e-15
    s = m.stepper(u_past=u[1:2], y_past=y[:2])
    first = s.step(u[2])
    assert first.shape == (3,) and s.step(u[3]) is not first     # a new array each step
    rest = np.array([s.step(v) for v in u[4:]])
    assert np.array_equal(rest, sim[4:])
    with pytest.raises(DataError, match=r'^stepper input must be 2 voltages .* shape \(3,\)$'):
        s.step(np.zeros(3))
    before = s.state.values.copy()
    with pytest.raises(DataError, match='finite'):
        s.step(np.array([1.0, np.nan]))
    assert np.array_equal(s.state.values, before)


def test_one_axis_model_is_the_same_given_1d_or_column_arrays(tmp_path):
    u, y = mimo_plant(1500)
    flat = ARXModel(3, 2).fit(u[:, 0], y[:, 0], fs=FS)
    col = ARXModel(3, 2).fit(u[:, :1], y[:, :1], fs=FS)
    assert np.array_equal(flat.a, col.a) and np.array_equal(flat.b, col.b) and flat.c == col.c
    assert flat.simulate(u[:, 0]).shape == (1500,) and col.simulate(u[:, 0]).shape == (1500, 1)
    assert np.array_equal(flat.simulate(u[:, 0]), col.simulate(u[:, 0])[:, 0])
    assert isinstance(flat.stepper().step(1.0), float)
    doc = json.loads(save_model(flat, tmp_path / 'one.json').read_text())
    assert doc['format_version'] == 1 and 'inputs' not in doc and 'n_in' not in doc['structure']
    loaded = load_model(tmp_path / 'one.json')
    assert loaded.inputs == ('u',) and loaded.outputs == ('y',)
    assert np.array_equal(loaded.simulate(u[:, 0]), flat.simulate(u[:, 0]))


@pytest.fixture(scope='module')
def narx_2x3():
    u, y = mimo_plant(2000, noise=1e-10)
    m = NARXNetwork(2, 2, 5, restarts=1, max_iter=10, refine_iter=4, n_segments=6).fit(
        u, y, fs=FS)
    m.inputs, m.outputs = ('vx', 'vy'), ('dz', 'dx', 'dy')
    return m, u, y


def test_mimo_narx_free_run_steps_and_file_round_trip(narx_2x3, tmp_path):
    m, u, y = narx_2x3
    sim = m.simulate(u, y[:2])
    r2 = 1 - ((sim - y)[2:] ** 2).sum(0) / ((y - y.mean(0))[2:] ** 2).sum(0)
    assert sim.shape == (2000, 3) and np.all(r2 > 0.95), r2
    s = m.stepper(u_past=u[:2], y_past=y[:2])
    assert np.array_equal(np.array([s.step(v) for v in u[2:10]]), sim[2:10])
    assert np.array_equal(s.step_many(u[10:]), sim[10:])       # the rest as one batch
    before = s.state.values.copy()
    with pytest.raises(DataError, match=r'finite voltages, got .* at row 1$'):
        s.step_many(np.array([[0.0, 0.0], [np.nan, 1.0]]))
    with pytest.raises(DataError, match=r'rows of 2 voltages \(n, 2\), got shape \(4,\)$'):
        s.step_many(np.zeros(4))
    assert np.array_equal(s.state.values, before)
    path = save_model(m, tmp_path / 'n.json')
    doc = json.loads(path.read_text())
    assert doc['format_version'] == 3 and doc['inputs'] == ['vx', 'vy']
    assert doc['outputs'] == ['dz', 'dx', 'dy'] and doc['structure']['n_out'] == 3
    back = load_model(path)
    assert back.outputs == ('dz', 'dx', 'dy') and np.array_equal(back.simulate(u, y[:2]), sim)
    state = back.estimate_state(u[500:700], y[500:700] + np.array([1e-8, 0.0, -1e-8]))
    assert state.offset.shape == (3,) and abs(state.offset[0] - 1e-8) < 3e-9


def test_mimo_segment_sensitivities_match_finite_differences():
    from piezo_narx_ros.ident.narx import training
    rng = np.random.default_rng(0)
    u, y = rng.standard_normal((60, 2)), rng.standard_normal((60, 3))
    H, nu, ny = 3, 1, 2
    d = 2 * (nu + 1) + 3 * ny
    P = H * (d + 1) + 3 * (H + 1)
    theta = 0.3 * rng.standard_normal(P)
    starts, L = np.array([5, 30], dtype=np.int64), 12
    J, e = np.empty((2 * L * 3, P)), np.empty(2 * L * 3)
    training._segments_ch(u, y, starts, L, nu, ny, theta, H, J, e, True)
    e0 = e.copy()
    for p in rng.choice(P, 12, replace=False):
        th = theta.copy()
        th[p] += 1e-6
        e1 = np.empty_like(e)
        training._segments_ch(u, y, starts, L, nu, ny, th, H, J[:1].copy(), e1, False)
        # e = y - y_hat, so d y_hat / d theta = -(e1 - e0) / h.
        np.testing.assert_allclose(-(e1 - e0) / 1e-6, J[:, p], rtol=1e-4, atol=1e-6)


HARNESS = r"""
#include <stdio.h>
#include "pnr_model.h"
int main(void)
{
    static double in[100000];
    double y[PNR_N_OUTPUTS], x[PNR_STATE_SIZE];
    size_t n = fread(in, sizeof(double), 100000, stdin) / PNR_N_INPUTS, k;
    pnr_state_t s;
    pnr_init(&s);
    for (k = 0; k < n; ++k) {
        pnr_step(&s, in + k * PNR_N_INPUTS, y);
        fwrite(y, sizeof(double), PNR_N_OUTPUTS, stdout);
    }
    pnr_get_state(&s, x);
    fwrite(x, sizeof(double), PNR_STATE_SIZE, stdout);
    return 0;
}
"""


@pytest.mark.skipif(shutil.which('gcc') is None, reason='gcc compiles the export')
@pytest.mark.parametrize('kind', ['arx', 'narx'])
def test_c_export_of_several_axes_equals_python(kind, narx_2x3, tmp_path):
    from piezo_narx_ros.export.writer import write_c
    u, y = mimo_plant(800)
    model = ARXModel(2, 1).fit(u, y, fs=FS) if kind == 'arx' else narx_2x3[0]
    write_c(model, tmp_path)
    header = (tmp_path / 'pnr_model.h').read_text()
    assert '#define PNR_N_INPUTS 2' in header and '#define PNR_N_OUTPUTS 3' in header
    (tmp_path / 'h.c').write_text(HARNESS)
    out = subprocess.run(['gcc', '-std=c99', '-O2', '-Wall', '-Wextra', '-pedantic', '-Werror',
                          '-I', str(tmp_path), str(tmp_path / 'h.c'),
                          str(tmp_path / 'pnr_model.c'), '-lm', '-o', str(tmp_path / 'h')],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    run = subprocess.run([str(tmp_path / 'h')], input=u.tobytes(), capture_output=True,
                         timeout=60)
    raw = np.frombuffer(run.stdout, dtype=np.float64)
    y_c, state_c = raw[:800 * 3].reshape(800, 3), raw[800 * 3:]
    y_py = model.simulate(u)
    assert np.max(np.abs(y_c - y_py)) <= 1e-12 and np.ptp(y_py) > 1e-7
    stepper = model.stepper()
    for v in u:
        stepper.step(v)
    assert np.max(np.abs(state_c - model.c_emitter().state_vector(stepper))) <= 1e-12


FSM = SHARED / 'data' / 'fsm'


@pytest.mark.skipif(not (FSM / 'train_100mV_r1.npz').is_file(),
                    reason=f'FSM benchmark data not found at {FSM}')
def test_fsm_record_fits_and_evaluates_per_output_after_100_samples(tmp_path, capsys):
    """Before: piezo-narx fit stopped at 'u must be 1-D, got shape (16384, 3)'."""
    from piezo_narx_ros.cli.main import main
    (tmp_path / 'fit.yaml').write_text(
        'training: {restarts: 1, max_iter: 3, refine_iter: 2, n_segments: 4}\n'
        'final_training: {}\n')
    args = ['fit', '--preset', 'paper',
            str(FSM / 'train_100mV_r1.npz'), '--out', str(tmp_path / 'm'), '--ny', '1',
            '--nu', '1', '--hidden', '2', '--arx-na', '4', '--arx-nb', '4', '--no-report',
            '--config', str(tmp_path / 'fit.yaml'), '--jobs', '1', '--quiet']
    with pytest.raises(SystemExit) as stop:
        main(args)
    assert stop.value.code in (0, None)
    doc = json.loads((tmp_path / 'm' / 'model.json').read_text())
    assert doc['inputs'] == ['u1', 'u2', 'u3'] and doc['outputs'] == ['y1', 'y2', 'y3']
    capsys.readouterr()
    with pytest.raises(SystemExit) as stop:
        main(['evaluate', str(tmp_path / 'm' / 'model.json'), str(FSM / 'train_100mV_r2.npz'),
              '--init-samples', '100', '--json'])
    assert stop.value.code in (0, None)
    out = json.loads(capsys.readouterr().out)
    per = out['simulation']['per_output']
    assert [o['name'] for o in per] == ['y1', 'y2', 'y3'] and out['n'] == 16384 - 100
    rmse = [o['rmse'] for o in per]
    assert out['simulation']['rmse'] == pytest.approx(np.sqrt(np.mean(np.square(rmse))))
    assert all(0 < r < 2e-6 for r in rmse)          # a model, not a flat line (std ~1.3 µm)
    rest = out['simulation_from_rest']                # the same samples from rest, per axis too
    assert [o['name'] for o in rest['per_output']] == ['y1', 'y2', 'y3'] and rest['rmse'] > 0


def test_a_committed_one_axis_model_file_is_rewritten_as_it_was(tmp_path):
    """The one-axis file format does not change: bags/model.json saved again is the same file."""
    from pathlib import Path
    repo = Path(__file__).resolve().parents[1]
    original = json.loads((repo / 'bags' / 'model.json').read_text())
    model = load_model(repo / 'bags' / 'model.json')
    assert (model.n_in, model.n_out, model.inputs, model.outputs) == (1, 1, ('u',), ('y',))
    again = json.loads(save_model(model, tmp_path / 'model.json').read_text())
    for key in ('weights',):           # the .npz bytes hold the zip's time stamps
        original.pop(key), again.pop(key)
    assert again == original
    old = np.load(repo / 'bags' / 'model.npz')
    new = np.load(tmp_path / 'model.npz')
    assert sorted(old.files) == sorted(new.files)
    assert all(np.array_equal(old[k], new[k]) and old[k].dtype == new[k].dtype for k in old.files)


def test_experiment_selects_on_the_worst_output_and_reports_each_axis(tmp_path):
    from piezo_narx_ros.ident.selection.experiment import ExperimentConfig, run_experiment
    from piezo_narx_ros.ident.validation.report import write_report
    from piezo_narx_ros.record import Record
    recs = []
    for seed in (1, 2):
        u, y = mimo_plant(1600, seed=seed, noise=1e-10)
        recs.append(Record(u=u, y=y, fs=FS, source=f'r{seed}', inputs=('a', 'b'),
                           outputs=('p', 'q', 'r')))
    cfg = ExperimentConfig(narx=False, arx_na=(1, 2), arx_nb=(1,), jobs=1, max_lag=10)
    result = run_experiment(recs, cfg)
    best = result.best
    assert best.spec.ny == 2 and best.model.outputs == ('p', 'q', 'r')
    per = best.scores['validation']['simulation']['per_output']
    assert [o['name'] for o in per] == ['p', 'q', 'r']
    # The worst case is the lowest R² of any output in any block (pooled halves, each record).
    worse = next(c for c in result.candidates if c.spec.ny == 1)
    blocks = [worse.scores[b]['simulation'] for b in ('estimation', 'validation')]
    blocks += [r['simulation'] for r in worse.scores['validation']['records']]
    lows = [o['r2'] for b in blocks for o in b['per_output']]
    assert worse.free_run_r2() == pytest.approx(min(lows)) and min(lows) < best.free_run_r2()
    assert best.tests['simulation']['pair'].keys() == {'output', 'input'}
    paths = write_report(result, [r.split(0.5)[1] for r in recs], tmp_path)
    assert {'simulation_p', 'simulation_q', 'simulation_r', 'hysteresis_r'} <= set(paths)
