"""`piezo-narx simulate`: writes a loadable record; bad input exits 2 with one line."""
import json

import numpy as np
import pytest

from piezo_narx_ros.cli.main import main


def run_cli(argv):
    with pytest.raises(SystemExit) as exc:
        main(argv)
    return exc.value.code


def test_simulate_writes_record(tmp_path, capsys):
    out = tmp_path / 'data.npz'
    code = run_cli(['simulate', '--signal', 'multisine', '--seconds', '0.5', '--fs', '2000',
                    '--amplitude', '80', '--f-max', '50', '--seed', '4', '--out', str(out)])
    assert code == 0
    assert 'wrote' in capsys.readouterr().out
    with np.load(out, allow_pickle=False) as d:
        assert set(d.files) >= {'u', 'u_applied', 'y', 'y_true', 'fs', 't'}
        assert d['u'].shape == d['y'].shape == d['y_true'].shape == d['u_applied'].shape == (1000,)
        assert float(d['fs']) == 2000.0 and d['t'][1] == pytest.approx(5e-4)
        assert np.max(np.abs(d['u'])) == pytest.approx(80.0)
        meta = json.loads(str(d['meta']))
        u, y = d['u'], d['y']
    assert meta['signal'] == 'multisine' and meta['options']['f_max'] == 50.0
    assert 10e-6 < np.ptp(y) < 80e-6  # ~0.4 um/V over a 160 V peak-to-peak command
    # Same seed, same numbers (signal and noise).
    out2 = tmp_path / 'again.npz'
    run_cli(['simulate', '--seconds', '0.5', '--amplitude', '80', '--f-max', '50', '--seed', '4',
             '--out', str(out2)])
    with np.load(out2, allow_pickle=False) as d2:
        assert np.array_equal(d2['u'], u) and np.array_equal(d2['y'], y)


def test_simulate_playback_and_plant_config(tmp_path):
    np.savez(tmp_path / 'src.npz', u=np.linspace(0, 50, 200))
    cfg = tmp_path / 'plant.yaml'
    cfg.write_text('plant:\n  noise_std: 0.0\n  quantisation: 0.0\n')
    out = tmp_path / 'p.npz'
    assert run_cli(['simulate', '--signal', 'playback', '--file', str(tmp_path / 'src.npz'),
                    '--plant-config', str(cfg), '--out', str(out)]) == 0
    with np.load(out, allow_pickle=False) as d:
        assert d['u'].size == 200 and np.all(np.diff(d['y']) >= 0)  # noise-free, monotone ramp


@pytest.mark.parametrize('argv, words', [
    (['--signal', 'sine', '--freq', '5000'], 'freq'),
    (['--signal', 'aprbs', '--min-hold', '-1'], 'min_hold'),
    (['--plant-config', 'nowhere.yaml'], 'nowhere.yaml'),
    (['--signal', 'playback'], 'path'),
    (['--seconds', '0'], 'seconds'),
    (['--preamble', 'fade-out', '--preamble-seconds', '0'], 'preamble seconds'),
])
def test_simulate_bad_input_exits_2_with_one_line(tmp_path, capsys, argv, words):
    code = run_cli(['simulate', '--out', str(tmp_path / 'x.npz'), '--seconds', '0.1'] + argv)
    err = capsys.readouterr().err.strip()
    assert code == 2 and err.count('\n') == 0
    assert err.startswith('piezo-narx: error:') and words in err
    assert not (tmp_path / 'x.npz').exists()


def test_simulate_out_must_be_npz(tmp_path, capsys):
    assert run_cli(['simulate', '--seconds', '0.1', '--out', str(tmp_path / 'x.csv')]) == 2
    assert '.npz' in capsys.readouterr().err


def test_cli_signal_kinds_match_the_generator():
    from piezo_narx_ros.cli.simulate import KINDS as CLI_KINDS, PREAMBLES as CLI_PREAMBLES
    from piezo_narx_ros.plant.signals import KINDS, PREAMBLES
    assert set(CLI_KINDS) == set(KINDS)
    assert set(CLI_PREAMBLES) == set(PREAMBLES)


def test_simulate_protocol(tmp_path):
    out = tmp_path / 'protocol.npz'
    assert run_cli(['simulate', '--signal', 'protocol', '--seconds', '5', '--cycles', '1',
                    '--out', str(out)]) == 0
    with np.load(out, allow_pickle=False) as d:
        assert d['u'].size == 10000 and np.max(np.abs(d['u'])) <= 100.0
        assert json.loads(str(d['meta']))['options']['cycles'] == 1


def test_simulate_preamble_wipes_what_the_unknown_past_left(tmp_path):
    # Two random pasts leave the plant about 1 um apart at the record's start; a 2 s fade-out
    # played before the record (part of it) brings them within a fifth of that (measured 13x).
    def start_gap(preamble):
        starts = []
        for seed in (1, 2):
            out = tmp_path / f'{preamble}_{seed}.npz'
            assert run_cli(['simulate', '--signal', 'sine', '--seconds', '1', '--history', '20',
                            '--history-seed', str(seed), '--preamble', preamble,
                            '--out', str(out)]) == 0
            with np.load(out, allow_pickle=False) as d:
                meta = json.loads(str(d['meta']))
                n = meta.get('preamble', {}).get('samples', 0)
                assert d['u'].size == n + 2000
                starts.append(float(d['y_true'][n]))
        return abs(starts[0] - starts[1]), meta, n

    gap_none, meta_none, n_none = start_gap('none')
    gap_fade, meta_fade, n_fade = start_gap('fade-out')
    assert n_none == 0 and 'preamble' not in meta_none
    assert n_fade == 4000 and meta_fade['preamble']['kind'] == 'fade-out'
    assert gap_none > 0.3e-6
    assert gap_fade < 0.2 * gap_none
