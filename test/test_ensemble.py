"""The ensemble model (ident/ensemble/model.py): the mean of its members, file, C, selection."""
import shutil
import subprocess
from dataclasses import replace

import numpy as np
import pytest

from piezo_narx_ros.errors import ModelFileError
from piezo_narx_ros.export import ExportError
from piezo_narx_ros.ident.ensemble.model import EnsembleModel
from piezo_narx_ros.ident.selection.experiment import (PRESETS, ExperimentConfig,
                                                       consider_ensemble, run_experiment)
from piezo_narx_ros.ident.hysteresis.model import HysteresisNARX
from piezo_narx_ros.ident.model_io import load_model, save_model
from piezo_narx_ros.plant import PiezoCantilever, generate, load_plant_params
from piezo_narx_ros.record import Record
from piezo_narx_ros.share import config_path

FS = 2000.0


@pytest.fixture(scope='module')
def one_axis():
    """2 s of the identification protocol through the default plant: (u V, y m)."""
    u = generate('protocol', FS, 2.0, 100.0, seed=3)
    return u, PiezoCantilever(load_plant_params(config_path('plant.yaml')), FS, seed=3).run(u).y


@pytest.fixture(scope='module')
def members(one_axis):
    """Two small envelope networks of different seeds and drive lags (nu 4 and 6)."""
    u, y = one_axis
    return [HysteresisNARX(hidden=3, n_plays=4, max_iter=8, seed=s, n_lags=lags).fit(u, y, fs=FS)
            for s, lags in ((0, 4), (1, 6))]


def test_free_run_and_stepper_are_the_mean_of_the_members(members, one_axis):
    """Simulate from rest, from a state and the Stepper: each the mean of the members' own."""
    u, y = one_axis
    ens = EnsembleModel(members)
    runs = [m.simulate(u) for m in members]
    assert np.max(np.abs(runs[0] - runs[1])) > 1e-8        # the members differ
    assert np.allclose(ens.simulate(u), np.mean(runs, axis=0), rtol=0, atol=1e-15)
    state = ens.estimate_state(u[:400], y[:400])
    sim = ens.simulate(u, state=state)
    own = [m.simulate(u, state=s) for m, s in zip(members, ens.as_member_states(state))]
    assert np.allclose(sim, np.mean(own, axis=0), rtol=0, atol=1e-15)
    assert np.sqrt(np.mean((sim[:400] - y[:400]) ** 2)) < np.sqrt(np.mean(y[:400] ** 2))
    stepper = ens.stepper(state=state)
    assert np.max(np.abs(stepper.step_many(u) - sim)) <= 1e-12
    nu = ens.nu
    assert nu == 6
    by_hand = [m.stepper(u_past=u[nu - m.nu:nu]).step_many(u[nu:]) for m in members]
    assert np.max(np.abs(ens.stepper(u_past=u[:nu]).step_many(u[nu:])
                         - np.mean(by_hand, axis=0))) <= 1e-15


def test_bracket_states_are_the_members_own_and_evaluate_reads_them(members, one_axis):
    """From above / below: each member's own extreme past; the spread evaluate reports."""
    from piezo_narx_ros.cli.evaluate import memory_windows
    u, y = one_axis
    ens = EnsembleModel(members)
    pair = ens._bracket_states(20.0)
    for i in range(2):
        own = [m.simulate(u, state=m._bracket_states(20.0)[i]) for m in members]
        assert np.allclose(ens.simulate(u, state=pair[i]), np.mean(own, axis=0), rtol=0,
                           atol=1e-15)
    held = Record(u=np.full(1000, 20.0), y=np.zeros(1000), fs=FS, source='held')
    windows, notes = memory_windows(ens, [held], 500)
    assert not windows[0]['determined'] and windows[0]['memory_spread_m'] > 0 and notes


def test_model_file_round_trip_is_bit_identical(members, one_axis, chains2, arx2, stage_data,
                                                tmp_path):
    """One axis (two envelope networks) and two axes (chains + ARX): same numbers after load."""
    u, _ = one_axis
    ens = EnsembleModel(members)
    back = load_model(save_model(ens, tmp_path / 'one.json'))
    assert isinstance(back, EnsembleModel) and back.n_params == ens.n_params
    assert np.array_equal(back.simulate(u), ens.simulate(u))
    assert back.input_range == ens.input_range and back.members[1].nu == 6
    u2, _ = stage_data
    ens2 = EnsembleModel([chains2, arx2])
    back2 = load_model(save_model(ens2, tmp_path / 'two.json'))
    assert back2.outputs == ens2.outputs and back2.simulate(u2).shape == (len(u2), 2)
    assert np.array_equal(back2.simulate(u2), ens2.simulate(u2))
    with pytest.raises(ExportError, match='envelope members only'):
        ens2.c_emitter()
    doc = (tmp_path / 'one.json').read_text()
    (tmp_path / 'bad.json').write_text(doc.replace('"kind": "hysteresis_narx"', '"kind": "x"',
                                                   1))
    (tmp_path / 'bad.npz').write_bytes((tmp_path / 'one.npz').read_bytes())
    with pytest.raises(ModelFileError, match='member 0'):
        load_model(tmp_path / 'bad.json')


HARNESS = r"""
#include <stdio.h>
#include "pnr_model.h"
static double in[100000];
int main(void)
{
    double y[PNR_N_OUTPUTS];
    size_t n = fread(in, sizeof(double), 100000, stdin), k;
    pnr_state_t s;
    pnr_init(&s);
    for (k = 0; k < n; ++k) {
        pnr_step(&s, in + k, y);
        fwrite(y, sizeof(double), 1, stdout);
    }
    if (pnr_init_history(&s, in, NULL) != 0) {
        return 3;
    }
    for (k = PNR_NU; k < n; ++k) {
        pnr_step(&s, in + k, y);
        fwrite(y, sizeof(double), 1, stdout);
    }
    return 0;
}
"""


@pytest.mark.skipif(shutil.which('gcc') is None, reason='gcc compiles the export')
def test_c_export_equals_the_python_stepper(members, one_axis, tmp_path):
    """The exported C: free run from rest and from an input history equal Python's to 1e-12 m."""
    from piezo_narx_ros.export.writer import write_c
    u, _ = one_axis
    ens = load_model(save_model(EnsembleModel(members), tmp_path / 'm.json'))
    c = tmp_path / 'c'
    write_c(ens, c)
    (c / 'h.c').write_text(HARNESS)
    flags = ['-std=c99', '-O2', '-Wall', '-Wextra', '-pedantic', '-Werror', '-Wshadow',
             '-Wstrict-prototypes', '-Wmissing-prototypes']
    out = subprocess.run(['gcc', *flags, '-I', str(c), str(c / 'h.c'), str(c / 'pnr_model.c'),
                          '-lm', '-o', str(c / 'h')], capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr
    v = np.ascontiguousarray(u[:2000])
    run = subprocess.run([str(c / 'h')], input=v.tobytes(), capture_output=True, timeout=60)
    assert run.returncode == 0
    raw = np.frombuffer(run.stdout, dtype=np.float64)
    y_py = ens.stepper().step_many(v)
    assert np.ptp(y_py) > 1e-6 and np.max(np.abs(raw[:v.size] - y_py)) <= 1e-12
    nu = ens.nu
    y_hist = ens.stepper(u_past=v[:nu]).step_many(v[nu:])
    assert np.max(np.abs(raw[v.size:] - y_hist)) <= 1e-12
    stepper = ens.stepper()
    stepper.step_many(v)
    assert np.array_equal(ens.c_emitter().state_vector(stepper), stepper.state.values)


def test_selection_keeps_the_single_model_unless_the_ensemble_is_better(one_axis):
    """The ensemble candidate is scored and listed; it replaces the selection only when better."""
    u, y = one_axis
    cfg = replace(ExperimentConfig(), **{
        **PRESETS['envelope'], 'n_seeds': 2, 'hnarx_grid': (), 'narx_beside': 'no',
        'arx_na': (2,), 'arx_nb': (2,), 'hidden': 3, 'hnarx': {'n_plays': 4, 'max_iter': 8},
        'jobs': 1, 'progress': False, 'ensemble': 2})
    result = run_experiment([Record(u=u, y=y, fs=FS, source='protocol')], cfg)
    ens = [c for c in result.candidates if c.spec.kind == 'ensemble']
    assert len(ens) == 1 and isinstance(ens[0].model, EnsembleModel)
    singles = [c for c in result.candidates if c.spec.kind != 'ensemble']
    best_single = max(c.free_run_r2() for c in singles)
    picked_ensemble = result.best is ens[0]
    assert picked_ensemble == (ens[0].free_run_r2() > best_single)
    # Forced either way through the margin: a margin of 1 never takes the ensemble.
    cands = list(singles)
    index = max(range(len(cands)), key=lambda i: cands[i].free_run_r2())
    kept = consider_ensemble(cands, (index, False), _halves(u, y, cfg),
                             replace(cfg, ensemble_margin=0.999))
    assert kept == (index, False) and cands[-1].spec.kind == 'ensemble'
    # ... and a margin of -1 always does (the setting for an offline model).
    cands = list(singles)
    kept = consider_ensemble(cands, (index, False), _halves(u, y, cfg),
                             replace(cfg, ensemble_margin=-1.0))
    assert kept[0] == len(cands) - 1 and cands[-1].spec.kind == 'ensemble'


def _halves(u, y, cfg):
    from piezo_narx_ros.ident.selection.experiment import split_records, with_state_window
    return split_records(with_state_window([Record(u=u, y=y, fs=FS, source='p')], cfg),
                         cfg.split)


def test_ensemble_settings_are_checked():
    """Ensemble K and margin out of range: one ConfigError naming the setting."""
    from piezo_narx_ros.errors import ConfigError
    for bad, name in (({'ensemble': 1}, 'ensemble'), ({'ensemble': 17}, 'ensemble'),
                      ({'ensemble_margin': -2.0}, 'ensemble_margin')):
        with pytest.raises(ConfigError, match=name):
            replace(ExperimentConfig(), **bad).validate()


def test_fit_settings_reach_the_experiment(tmp_path):
    """The --config keys ensemble / ensemble_margin set ExperimentConfig's (off in the presets)."""
    from piezo_narx_ros.ident.pipeline.settings import experiment_config, merge_settings
    path = tmp_path / 'fit.yaml'
    path.write_text('preset: envelope\nensemble: 5\nensemble_margin: -1.0e-4\n')
    cfg = experiment_config(merge_settings(config_file=str(path)), progress=False)
    assert (cfg.ensemble, cfg.ensemble_margin) == (5, -1e-4)
    path.write_text('preset: envelope\n')
    assert experiment_config(merge_settings(config_file=str(path)), progress=False).ensemble == 0
