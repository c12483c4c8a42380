"""
The envelope family on several axes as one chain per axis, mixed (ident/hysteresis/chains.py).

The coupling of the two-axis cantilever (config/plant_2axis.yaml: y moves by 0.12 of x's chain,
x by 0.05 of y's) is found before any chain is fitted; the outputs of a stage whose axes share
their dynamics are refused by the structure test; the fitted model's free run is the chains'
mixed, step by step as in one call, through a model file, and from an estimated state.
"""
import shutil
import subprocess

import numpy as np
import pytest
from scipy.signal import lfilter

from piezo_narx_ros.errors import DataError
from piezo_narx_ros.ident.hysteresis.chains import (HysteresisChains, check_coupling,
                                                    coupling_matrix)
from piezo_narx_ros.ident.model_io import load_model, save_model

FS = 2000.0


def test_coupling_of_the_stage_is_found_before_the_chains(stage_data):
    u, y = stage_data
    M, info = coupling_matrix([u], [y], FS)
    assert M[0, 1] == pytest.approx(0.05, abs=0.005)
    assert M[1, 0] == pytest.approx(0.12, abs=0.005)
    assert np.diag(M).tolist() == [1.0, 1.0]
    assert info['structure_r2'] > 0.99 and info['free_r2'] - info['structure_r2'] < 1e-3


def test_outputs_that_share_their_dynamics_are_not_taken_for_chains():
    """Both outputs respond to the product of the inputs: no mix of one chain per input."""
    rng = np.random.default_rng(0)
    u = rng.uniform(-1.0, 1.0, (4000, 2))
    u = lfilter([0.1], [1.0, -0.9], u, axis=0)
    y = np.column_stack([u[:, 0] * u[:, 1], lfilter([1.0], [1.0, -0.5], u[:, 0] * u[:, 1])])
    with pytest.raises(DataError, match='not a mix of one actuator chain per input'):
        HysteresisChains(hidden=2, n_plays=2, max_iter=1).fit(u, y, fs=FS)


def test_a_chain_per_axis_needs_as_many_inputs_as_outputs(stage_data):
    u, y = stage_data
    with pytest.raises(DataError, match='as many inputs as outputs'):
        HysteresisChains().fit(u, y[:, :1].copy(), fs=FS)
    with pytest.raises(DataError, match='singular'):
        check_coupling([[1.0, 1.0], [1.0, 1.0]])


def test_free_run_is_the_chains_mixed_and_the_stepper_agrees(chains2, stage_data):
    u, y = stage_data
    m = chains2
    z = np.column_stack([c.simulate(u[:, j]) for j, c in enumerate(m.chains_)])
    sim = m.simulate(u)
    assert np.array_equal(sim, z @ m.coupling_.T)
    # The model was fitted on this record: it follows the stage on both axes.
    rmse = np.sqrt(np.mean((sim - y) ** 2, axis=0))
    assert (rmse < 0.01 * y.std(axis=0)).all()
    st = m.stepper()
    steps = np.array([st.step(u[k]) for k in range(500)])
    assert np.allclose(steps, sim[:500], rtol=0, atol=1e-15)
    assert np.array_equal(st.peek(u[500]), st.step(u[500]))
    many = m.stepper()
    assert np.allclose(many.step_many(u[:300]), sim[:300], rtol=0, atol=1e-15)
    assert np.allclose(many.step_many(u[300:501]), sim[300:501], rtol=0, atol=1e-15)
    with pytest.raises(DataError, match='row 1'):
        many.step_many([[0.0, 0.0], [np.inf, 0.0]])
    assert np.array_equal(many.step(u[501]), st.step(u[501]))      # the bad rows left no trace
    with pytest.raises(DataError, match='finite'):
        st.step([np.nan, 0.0])
    with pytest.raises(DataError, match='2 voltages'):
        st.step([1.0])


def test_model_file_round_trip_gives_the_same_free_run(chains2, stage_data, tmp_path):
    u, _ = stage_data
    path = save_model(chains2, tmp_path / 'chains.json')
    back = load_model(path)
    assert isinstance(back, HysteresisChains)
    assert back.inputs == back.outputs == ('x', 'y')
    assert np.array_equal(back.coupling_, chains2.coupling_)
    assert np.array_equal(back.simulate(u), chains2.simulate(u))
    for a, b in zip(back.chains_, chains2.chains_):
        assert a.input_range == b.input_range and a.output_range == b.output_range
        assert a.metadata['data']['line'] == b.metadata['data']['line']


#: Three runs of the same rows: from rest (then the final state), from a state vector given first,
#: and from pnr_init_history on the first PNR_NU rows.
HARNESS = r"""
#include <stdio.h>
#include "pnr_model.h"
static double in[200000];
int main(void)
{
    double y[PNR_N_OUTPUTS], x[PNR_STATE_SIZE];
    size_t n = (fread(in, sizeof(double), 200000, stdin) - PNR_STATE_SIZE) / PNR_N_INPUTS, k;
    const double *u = in + PNR_STATE_SIZE;
    pnr_state_t s;
    pnr_init(&s);
    for (k = 0; k < n; ++k) {
        pnr_step(&s, u + k * PNR_N_INPUTS, y);
        fwrite(y, sizeof(double), PNR_N_OUTPUTS, stdout);
    }
    pnr_get_state(&s, x);
    fwrite(x, sizeof(double), PNR_STATE_SIZE, stdout);
    if (pnr_set_state(&s, in) != 0) {
        return 2;
    }
    for (k = 0; k < n; ++k) {
        pnr_step(&s, u + k * PNR_N_INPUTS, y);
        fwrite(y, sizeof(double), PNR_N_OUTPUTS, stdout);
    }
    if (pnr_init_history(&s, u, NULL) != 0) {
        return 3;
    }
    for (k = PNR_NU; k < n; ++k) {
        pnr_step(&s, u + k * PNR_N_INPUTS, y);
        fwrite(y, sizeof(double), PNR_N_OUTPUTS, stdout);
    }
    return 0;
}
"""


@pytest.mark.skipif(shutil.which('gcc') is None, reason='gcc compiles the export')
def test_c_export_equals_the_python_stepper(chains2, stage_data, tmp_path, capsys):
    """`piezo-narx export` of a 2-axis chains model file: C free run and state equal Python's."""
    from piezo_narx_ros.cli.main import main
    from piezo_narx_ros.ident.state.estimate import ModelState
    u, _ = stage_data
    path = save_model(chains2, tmp_path / 'chains.json')
    with pytest.raises(SystemExit) as stop:
        main(['export', str(path), '--c', str(tmp_path / 'c')])
    assert stop.value.code == 0
    assert 'hysteresis_narx' in capsys.readouterr().out
    c = tmp_path / 'c'
    header = (c / 'pnr_model.h').read_text()
    assert '#define PNR_N_INPUTS 2' in header and '#define PNR_N_OUTPUTS 2' in header
    assert '#define PNR_HAS_INVERSE 0' in header
    (c / 'h.c').write_text(HARNESS)
    flags = ['-std=c99', '-O2', '-Wall', '-Wextra', '-pedantic', '-Werror', '-Wshadow',
             '-Wstrict-prototypes', '-Wmissing-prototypes']
    out = subprocess.run(['gcc', *flags, '-I', str(c), str(c / 'h.c'), str(c / 'pnr_model.c'),
                          '-lm', '-o', str(c / 'h')], capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr
    model, n = load_model(path), 1500
    v = np.ascontiguousarray(u[1000:1000 + n])
    handed = model.stepper()
    handed.step_many(u[:1000])                  # a state in mid-motion, handed to C
    size = model.c_emitter().state_size
    x0 = model.c_emitter().state_vector(handed)
    assert x0.size == size == model.state_size and np.ptp(x0) > 0
    run = subprocess.run([str(c / 'h')], input=np.concatenate([x0, v.ravel()]).tobytes(),
                         capture_output=True, timeout=60)
    assert run.returncode == 0
    raw = np.frombuffer(run.stdout, dtype=np.float64)
    y_rest, raw = raw[:2 * n].reshape(n, 2), raw[2 * n:]
    state_c, raw = raw[:size], raw[size:]
    y_handed, y_hist = raw[:2 * n].reshape(n, 2), raw[2 * n:].reshape(-1, 2)
    stepper = model.stepper()
    y_py = np.array([stepper.step(row) for row in v])
    assert np.ptp(y_py) > 1e-6
    assert np.max(np.abs(y_rest - y_py)) <= 1e-12          # m, DESIGN.md's contract
    # The state (normalised, order 1) to rounding; its layout is the Stepper's state vector.
    assert np.max(np.abs(state_c - model.c_emitter().state_vector(stepper))) <= 1e-12
    assert np.array_equal(model.c_emitter().state_vector(stepper), stepper.state.values)
    y_py = model.simulate(v, state=ModelState(x0, np.zeros(2)))
    assert np.max(np.abs(y_handed - y_py)) <= 1e-12
    assert np.max(np.abs(y_py - model.simulate(v))) > 1e-8   # the handed state mattered
    nu = model.nu
    y_py = model.stepper(u_past=v[:nu]).step_many(v[nu:])
    assert y_hist.shape == (n - nu, 2) and np.max(np.abs(y_hist - y_py)) <= 1e-12


def test_state_estimated_from_a_window_continues_the_free_run(chains2, stage_data):
    u, _ = stage_data
    m = chains2
    k0, n = 2000, 400
    truth = m.simulate(u)                       # the model as the plant: its state is known
    offset = np.array([1e-6, -2e-6])            # sensor zeros moved
    state = m.estimate_state(u[k0:k0 + n], truth[k0:k0 + n] + offset)
    assert state.offset.shape == (2,) and state.info['rms_m'] < 0.01 * truth.std()
    run = m.simulate(u[k0:], state=state)
    err = np.sqrt(np.mean((run - truth[k0:] - offset) ** 2, axis=0))
    rest = np.sqrt(np.mean((m.simulate(u[k0:]) - truth[k0:] - offset) ** 2, axis=0))
    assert (err < 0.02 * truth.std(axis=0)).all() and (err < 0.2 * rest).all()
    st = m.stepper(state=state)
    assert np.allclose(st.step(u[k0]), m.simulate(u[k0:k0 + 1], state=state)[0], atol=1e-15)


def test_estimator_runs_the_chains_as_offline(chains2, stage_data):
    """Run the estimator node's logic (FreeRunEstimator): from rest and from a window."""
    from piezo_narx_ros.estimator.free_run import FreeRunEstimator
    u, y = stage_data
    n, period, t0 = 3000, 500_000, 10**18
    t = t0 + np.arange(n, dtype=np.int64) * period
    est = FreeRunEstimator(chains2, init='rest')
    ts, y_hat = est.on_commands(t, u[:n])
    assert np.allclose(y_hat, chains2.simulate(u[:n]), rtol=0, atol=1e-15)
    est = FreeRunEstimator(chains2, init='measurement', init_window=0.1, window=500)
    est.on_measurements(t[1000:1300], y[1000:1300])
    ts, y_hat = est.on_commands(t[1000:], u[1000:n])
    assert est.stats.init == 'measurement' and len(ts) == n - 1000
    assert np.sqrt(np.mean((y_hat - y[1000:n]) ** 2)) < 0.02 * y.std()


def test_envelope_preset_on_several_axes_adds_a_chain_per_axis_candidate(stage_data):
    """The experiment fits both several-axes structures when inputs and outputs pair up."""
    from dataclasses import replace

    from piezo_narx_ros.ident.selection.experiment import PRESETS, ExperimentConfig
    from piezo_narx_ros.ident.selection.grid import auto_grid, distinct_specs
    from piezo_narx_ros.record import Record
    u, y = stage_data
    cfg = replace(ExperimentConfig(), **PRESETS['envelope'])
    square = [Record(u=u, y=y, fs=FS, source='s')]
    # As run_experiment trims the grid: the structure without increments is for one axis only.
    specs = auto_grid(distinct_specs(cfg.specs(), square), cfg, square)
    nets = [s for s in specs if s.kind == 'hysteresis_narx']
    chains = [s for s in nets if dict(s.options).get('structure') == 'chains']
    assert len(nets) == 1 + len(chains) == 1 + 6           # one common fit, 3 seeds x 2 lags
    assert isinstance(chains[0].build(), HysteresisChains) and 'chain per axis' in chains[0].label
    assert type(nets[0].build()).__name__ == 'HysteresisNARX'
    tall = [Record(u=u[:, :1].copy(), y=y, fs=FS, source='s')]
    assert not any(dict(s.options).get('structure') for s in distinct_specs(cfg.specs(), tall))
    one = [Record(u=u[:, 0].copy(), y=y[:, 0].copy(), fs=FS, source='s')]
    assert distinct_specs(cfg.specs(), one) == cfg.specs()
