"""
Issue 45, files: what a path, an output name or a plant file may do to the files the tools write.

No tool overwrites a file it did not create without --force; temporary files are fresh and
exclusive, so a planted symlink is never followed; every string that reaches generated C goes
through one escaping rule; a stage plant file is simulated as a stage or refused, never read as
one cantilever; evaluate refuses a state window too short to set a state.
"""
import json
import os
import shutil
import subprocess

import numpy as np
import pytest
from test_faults_cli import cli, one_error_line

CC = shutil.which('gcc')


@pytest.fixture
def toy(tmp_path):
    """Return a toy model file and a record it scores (its own free run plus noise)."""
    from piezo_narx_ros.estimator.toy import toy_narx
    from piezo_narx_ros.ident.model_io import save_model
    model = toy_narx(fs=2000.0)
    path = save_model(model, tmp_path / 'toy.json')
    u = np.random.default_rng(0).uniform(-100, 100, 3000)
    y = model.simulate(u) + 1e-9 * np.random.default_rng(1).standard_normal(u.size)
    np.savez(tmp_path / 'rec.npz', u=u, y=y, fs=2000.0)
    return path, tmp_path / 'rec.npz'


# --------------------------------------------------------------------- overwriting files
def test_evaluate_save_output_never_overwrites_without_force(toy, capsys):
    model, rec = toy
    before = rec.read_bytes()
    code, _, err = cli(['evaluate', str(model), str(rec), '--save-output', str(rec)], capsys)
    assert code == 2 and one_error_line(err) and '--force' in err, err
    assert rec.read_bytes() == before                       # the input record is intact
    out = rec.with_name('out.npz')
    code, _, _ = cli(['evaluate', str(model), str(rec), '--save-output', str(out)], capsys)
    assert code == 0 and 'y_sim' in np.load(out)
    code, _, err = cli(['evaluate', str(model), str(rec), '--save-output', str(out)], capsys)
    assert code == 2 and 'exists' in err
    code, _, _ = cli(['evaluate', str(model), str(rec), '--save-output', str(out), '--force'],
                     capsys)
    assert code == 0


def test_export_replaces_its_own_files_but_not_anyone_elses(toy, tmp_path, capsys):
    model, _ = toy
    c = tmp_path / 'c'
    assert cli(['export', str(model), '--c', str(c)], capsys)[0] == 0
    assert cli(['export', str(model), '--c', str(c)], capsys)[0] == 0     # its own: replaced
    (c / 'pnr_model.c').write_text('int my_own_work;\n')
    code, _, err = cli(['export', str(model), '--c', str(c)], capsys)
    assert code == 2 and one_error_line(err) and 'not written by piezo-narx export' in err
    assert (c / 'pnr_model.c').read_text() == 'int my_own_work;\n'
    assert cli(['export', str(model), '--c', str(c), '--force'], capsys)[0] == 0


def plant(victim, folder, names):
    """Create `folder` with symlinks `names` in it pointing at `victim` (a file to protect)."""
    victim.write_text('precious')
    folder.mkdir(exist_ok=True)
    for name in names:
        os.symlink(victim, folder / name)


def test_a_symlink_planted_at_the_old_temporary_names_is_not_followed(toy, tmp_path, capsys):
    model, rec = toy
    victim = tmp_path / 'victim.txt'
    c = tmp_path / 'c'
    plant(victim, c, ('pnr_model.h.tmp', 'pnr_model.c.tmp'))
    os.symlink(victim, tmp_path / 'o.npz.tmp')
    assert cli(['export', str(model), '--c', str(c)], capsys)[0] == 0
    assert cli(['evaluate', str(model), str(rec), '--save-output', str(tmp_path / 'o.npz')],
               capsys)[0] == 0
    assert victim.read_text() == 'precious'
    assert (c / 'pnr_model.h').stat().st_mode & 0o777 == 0o666 & ~_umask()
    leftovers = [p.name for p in c.iterdir() if p.name.startswith('.')]
    assert leftovers == []


def _umask():
    mask = os.umask(0)
    os.umask(mask)
    return mask


# ---------------------------------------------------------------------- generated C text
HOSTILE = 'a*/b\n#error injected\n/* "q" ??/ \\ \u00b5m \t end'


def test_one_escaping_rule_keeps_any_text_inert():
    from piezo_narx_ros.export.c_code import c_comment, c_escape, c_string
    assert c_escape('plain/path-1.json') == 'plain/path-1.json'
    body = c_comment(HOSTILE)
    assert '*/' not in body and '/*' not in body and '\n' not in body and '??/' not in body
    assert all(32 <= ord(ch) < 127 for ch in c_string(HOSTILE))


@pytest.mark.skipif(CC is None, reason='gcc is needed')
def test_a_string_literal_reads_back_the_same_bytes(tmp_path):
    from piezo_narx_ros.export.c_code import c_string
    src = tmp_path / 's.c'
    src.write_text('#include <stdio.h>\nint main(void) { fputs(' + c_string(HOSTILE)
                   + ', stdout); return 0; }\n')
    exe = tmp_path / 's'
    subprocess.run([CC, '-std=c99', '-Wall', '-Werror', '-trigraphs', str(src), '-o', str(exe)],
                   check=True, capture_output=True)
    assert subprocess.run([str(exe)], capture_output=True).stdout == HOSTILE.encode()


@pytest.mark.skipif(CC is None, reason='gcc is needed')
def test_a_model_path_holding_comment_ends_and_newlines_stays_a_comment(toy, tmp_path, capsys):
    model, _ = toy
    evil = tmp_path / 'x*/\n#error injected\n'
    evil.mkdir(parents=True)      # 'x*' holding a folder named '\n#error injected\n'
    for suffix in ('.json', '.npz'):
        shutil.copy(model.with_suffix(suffix), evil)
    c = tmp_path / 'c'
    assert cli(['export', str(evil / model.name), '--c', str(c)], capsys)[0] == 0
    header = (c / 'pnr_model.h').read_text()
    assert '#error' not in [ln.strip()[:6] for ln in header.splitlines()]
    done = subprocess.run([CC, '-std=c99', '-Wall', '-Werror', '-trigraphs', '-c',
                           str(c / 'pnr_model.c'), '-o', str(tmp_path / 'm.o')],
                          capture_output=True, text=True)
    assert done.returncode == 0, done.stderr


# ------------------------------------------------------------------------ plants and windows
def test_simulate_a_stage_file_writes_every_axis(tmp_path, capsys):
    from piezo_narx_ros.ident.data.loaders import load_records
    from piezo_narx_ros.share import config_path
    out = tmp_path / 's.npz'
    code, _, err = cli(['simulate', '--plant-config', str(config_path('plant_2axis.yaml')),
                        '--seconds', '0.5', '--out', str(out)], capsys)
    assert code == 0, err
    with np.load(out) as z:
        assert z['u'].shape == z['y'].shape == z['y_true'].shape == (1000, 2)
        assert list(z['inputs']) == list(z['outputs']) == ['x', 'y']
        assert not np.array_equal(z['u'][:, 0], z['u'][:, 1])     # axis i seeded seed + i
        assert json.loads(str(z['meta']))['axes'] == ['x', 'y']
    [rec] = load_records([str(out)])
    assert (rec.n_in, rec.n_out) == (2, 2)
    code, _, err = cli(['simulate', '--plant-config', str(config_path('plant_2axis.yaml')),
                        '--seconds', '0.5', '--history', '2', '--out',
                        str(tmp_path / 'h.npz')], capsys)
    assert code == 2 and one_error_line(err) and 'stage of 2 axes' in err


def test_a_stage_file_is_not_read_as_one_cantilever():
    from piezo_narx_ros.errors import ConfigError
    from piezo_narx_ros.plant import load_plant_params
    from piezo_narx_ros.share import config_path
    with pytest.raises(ConfigError, match='describes a stage of several axes'):
        load_plant_params(config_path('plant_2axis.yaml'))


@pytest.mark.parametrize('n', [1, 9])
def test_evaluate_refuses_a_state_window_too_short_to_set_a_state(toy, capsys, n):
    model, rec = toy
    code, out, err = cli(['evaluate', str(model), str(rec), '--init-samples', str(n)], capsys)
    assert code == 2 and one_error_line(err), err
    assert f'--init-samples {n} is too few to set the state' in err and 'FAIL' not in out


# ------------------------------------------------------------------- what a model file holds
def _resign(model_json):
    import hashlib
    doc = json.loads(model_json.read_text())
    doc['weights']['sha256'] = hashlib.sha256(
        model_json.with_suffix('.npz').read_bytes()).hexdigest()
    model_json.write_text(json.dumps(doc))


def test_an_extra_member_that_inflates_hugely_is_never_decompressed(toy):
    """Issue 45: a 1.1 MB .npz with a compressible extra member cost 1.35 GB to load."""
    import tracemalloc
    import zipfile

    from piezo_narx_ros.ident.model_io import load_model
    model, _ = toy
    npz = model.with_suffix('.npz')
    with zipfile.ZipFile(npz, 'a', compression=zipfile.ZIP_DEFLATED) as z:
        with z.open('junk.npy', 'w', force_zip64=True) as member:
            n = 64 * 2**20 // 8
            np.lib.format.write_array_header_1_0(
                member, {'descr': '<f8', 'fortran_order': False, 'shape': (n,)})
            block = bytes(2**20)
            for _ in range(64):
                member.write(block)
    assert npz.stat().st_size < 2 * 2**20                  # 64 MiB of zeros, deflated
    _resign(model)
    tracemalloc.start()
    try:
        loaded = load_model(model)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert loaded.n_params > 0 and peak < 8 * 2**20, peak


def test_declared_weights_beyond_the_size_limit_are_refused_before_reading(toy, monkeypatch):
    from piezo_narx_ros.errors import ModelFileError
    from piezo_narx_ros.ident import model_io
    model, _ = toy
    monkeypatch.setattr(model_io, 'MAX_WEIGHT_BYTES', 2**20)
    doc = json.loads(model.read_text())
    big = np.zeros(200_000)                                 # 1.6 MB
    with np.load(model.with_suffix('.npz')) as z:
        arrays = {k: z[k] for k in z.files}
    np.savez_compressed(model.with_suffix('.npz'), **arrays, extra=big)
    doc['weights']['arrays']['extra'] = [200_000]
    model.write_text(json.dumps(doc))
    _resign(model)
    with pytest.raises(ModelFileError, match=r'its arrays declare more than 1048576 bytes'):
        model_io.load_model(model)


@pytest.mark.parametrize('edit, message', [
    (lambda text: text.replace('"fs": 2000.0', '"fs": 1' + '0' * 400), 'integer of 401 digits'),
    (lambda text: text.replace('"fs": 2000.0', '"fs": 1' + '0' * 400 + '.0'),
     'does not fit a double'),
    (lambda text: text.replace('"data": null', '"data": ' + '[' * 100_000 + ']' * 100_000),
     'nested too deeply'),
])
def test_absurd_numbers_and_nesting_are_one_line_refusals(toy, capsys, edit, message):
    model, rec = toy
    model.write_text(edit(model.read_text()))
    code, _, err = cli(['evaluate', str(model), str(rec)], capsys)
    assert code == 2 and one_error_line(err) and message in err, err
    assert 'this is a bug' not in err


def test_saving_a_model_follows_no_planted_temporary_name(tmp_path):
    from piezo_narx_ros.estimator.toy import toy_narx
    from piezo_narx_ros.ident.model_io import load_model, save_model
    victim, out = tmp_path / 'victim.txt', tmp_path / 'fit'
    plant(victim, out, ('model.json.tmp', 'model.npz.tmp'))
    path = save_model(toy_narx(fs=2000.0), out / 'model.json')
    assert victim.read_text() == 'precious' and load_model(path).n_params > 0


def test_a_constant_record_is_not_scored_minus_1e30_but_said_undefined(toy, tmp_path, capsys):
    """Issue 45: y = 1e-6 m throughout scored R² -3.9e30 (its mean is off by rounding)."""
    from piezo_narx_ros.errors import DataError
    from piezo_narx_ros.ident.selection.experiment import ExperimentConfig, run_experiment
    from piezo_narx_ros.ident.validation.metrics import r2
    from piezo_narx_ros.record import Record
    flat = np.full(4000, 1e-6)
    assert float(np.sum((flat - flat.mean()) ** 2)) > 0.0          # the rounding that did it
    with pytest.raises(DataError, match='R² undefined: the measured output is constant'):
        r2(flat, flat * 1.01)
    model, rec = toy
    u = np.random.default_rng(0).uniform(-100, 100, 4000)
    np.savez(tmp_path / 'flat.npz', u=u, y=flat, fs=2000.0)
    code, out, err = cli(['evaluate', str(model), str(tmp_path / 'flat.npz')], capsys)
    assert code == 2 and one_error_line(err) and 'R² is undefined against it' in err, err
    with np.load(rec) as z:
        est = Record(u=z['u'], y=z['y'], fs=2000.0, source='est')
    cfg = ExperimentConfig(narx=False, arx_na=(2,), arx_nb=(2,), noise_model='none', jobs=1)
    with pytest.raises(DataError, match='flat: the measured output is constant'):
        run_experiment([est], cfg, validation=[Record(u=u, y=flat, fs=2000.0, source='flat')])


# ----------------------------------------------------------- names derived from input names
def test_per_record_names_are_unique_and_stay_inside_out(tmp_path):
    """Issue 45: a/run, run-2, b/run were named run, run-2, run-2; a stem '..' escaped --out."""
    from piezo_narx_ros.ident.pipeline.fleet import recording_names
    assert recording_names(['a/run.npz', 'run-2.npz', 'b/run.npz']) == ['run', 'run-2', 'run-3']
    assert recording_names(['a/run.npz', 'b/run.npz', 'run-2.npz']) == ['run', 'run-3', 'run-2']
    hostile = ['x/...npz', 'y/..npz', '.npz', 'Run.npz', 'run.npz', 'a b/c d.csv',
               'rec\n.npz', 'e/../../f.npz', 'run.npz']
    names = recording_names(hostile)
    assert len({n.casefold() for n in names}) == len(hostile)
    out = tmp_path / 'out'
    for name in names:
        assert (out / name).resolve().parent == out.resolve() and not name.startswith('.')
