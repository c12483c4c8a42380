"""Rig scenarios in the simulator: unknown history, session offset, 16-bit 10 kHz, rig signals."""
import json

import numpy as np
import pytest

from piezo_narx_ros.cli.main import main
from piezo_narx_ros.errors import ConfigError, DataError
from piezo_narx_ros.plant import (PiezoCantilever, adc_grid, generate, load_plant_params,
                                  random_history, session_offset)

FS = 2000.0
CONFIGS = ('config/plant.yaml', 'config/plant_preisach.yaml')


def quiet(cfg, **changes):
    """Return a plant config without sensor noise and quantisation (or with `changes`)."""
    return load_plant_params(cfg).replace(**{'noise_std': 0.0, 'quantisation': 0.0, **changes})


# --- unknown history ---------------------------------------------------------------------------

def test_history_ramps_from_rest_to_its_end_and_holds():
    h = random_history(FS, 5.0, 80.0, offset=10.0, seed=3, end=40.0, hold=0.5)
    assert np.array_equal(h, random_history(FS, 5.0, 80.0, offset=10.0, seed=3, end=40.0,
                                            hold=0.5))
    assert not np.allclose(h[:10000], random_history(FS, 5.0, 80.0, offset=10.0, seed=4,
                                                     end=40.0, hold=0.5)[:10000])
    assert h.size >= 11000 and np.all(h[-1000:] == 40.0)        # the hold, at `end`
    assert h.min() >= -70.0 - 1e-9 and h.max() <= 90.0 + 1e-9   # offset +- amplitude
    assert abs(h[0]) < 30.0 * 80.0 / FS + 1e-9                  # starts from 0 V at a ramp rate
    assert np.ptp(h[:10000]) > 80.0                              # it does move through the range


@pytest.mark.parametrize('cfg', CONFIGS)
def test_history_leaves_memory_and_creep_moving(cfg):
    params = quiet(cfg)
    u = np.zeros(2000)                                          # 1 s held at 0 V
    rest = PiezoCantilever(params, FS).run(u).y_true
    runs = [PiezoCantilever(params, FS).run(u, history=random_history(FS, 5.0, 100.0, seed=s,
                                                                      hold=0.5)).y_true
            for s in (0, 1)]
    assert np.max(np.abs(rest)) < 1e-12                         # at rest: nothing moves
    for y in runs:
        assert abs(y[0]) > 1e-6                                 # memory: 0 V is not 0 m
        assert abs(y[-1] - y[0]) > 5e-9                         # creep still moving
    assert abs(runs[0][0] - runs[1][0]) > 1e-6                  # the past input sets the memory


def test_history_draws_no_noise_and_equals_prime_then_run():
    params = load_plant_params().replace(quantisation=0.0)
    u = generate('sine', FS, 0.5, 50.0, freq=3.0)
    h1, h2 = (random_history(FS, 2.0, 100.0, seed=s) for s in (1, 2))

    def noise(history):
        noisy = PiezoCantilever(params, FS, seed=5).run(u, history=history).y
        clean = PiezoCantilever(params.replace(noise_std=0.0), FS, seed=5).run(
            u, history=history).y
        return noisy - clean
    assert np.allclose(noise(h1), noise(h2), rtol=0, atol=1e-15)
    assert np.allclose(noise(h1), noise(None), rtol=0, atol=1e-15)
    a = PiezoCantilever(params, FS, seed=5)
    a.prime(h1)
    stepped = np.array([a.step(x)[0] for x in u])
    assert np.array_equal(stepped, PiezoCantilever(params, FS, seed=5).run(u, history=h1).y)


def test_history_bad_input_raises_before_any_change():
    plant = PiezoCantilever(load_plant_params(), FS)
    with pytest.raises(DataError, match='history has a non-finite value at index 1'):
        plant.run(np.zeros(3), history=[0.0, np.nan])
    assert not plant.state.any()
    for kwargs, word in (({'seconds': 0.0}, 'seconds'), ({'amplitude': 0.0}, 'amplitude'),
                         ({'hold': -1.0}, 'hold'), ({'seed': -1}, 'seed')):
        args = {'fs': FS, 'seconds': 1.0, 'amplitude': 10.0, **kwargs}
        with pytest.raises(ConfigError, match=word):
            random_history(**args)


# --- sensor offset per session -----------------------------------------------------------------

def test_sensor_offset_adds_a_constant_to_the_measurement_only():
    u = generate('multisine', FS, 0.5, 100.0, seed=2)
    params = load_plant_params().replace(quantisation=0.0)
    base = PiezoCantilever(params, FS, seed=1).run(u)
    shifted = PiezoCantilever(params, FS, seed=1, sensor_offset=3.2e-6).run(u)
    assert np.array_equal(base.y_true, shifted.y_true)
    assert np.allclose(shifted.y - base.y, 3.2e-6, rtol=0, atol=1e-18)
    q = load_plant_params()   # quantised: the offset is analogue, added before the converter
    d = (PiezoCantilever(q, FS, seed=1, sensor_offset=3.2e-6).run(u).y
         - PiezoCantilever(q, FS, seed=1).run(u).y)
    assert np.all(np.abs(d - 3.2e-6) <= q.quantisation * 1.0001)


def test_session_offsets_are_seeded_and_bounded():
    offsets = [session_offset(k, 2.5e-6) for k in range(50)]
    assert offsets == [session_offset(k, 2.5e-6) for k in range(50)]
    assert max(np.abs(offsets)) <= 2.5e-6 and len(set(offsets)) == 50
    assert np.ptp(offsets) > 4e-6                                # sessions differ by up to 5 um
    assert session_offset(3, 0.0) == 0.0
    with pytest.raises(ConfigError, match='session'):
        session_offset(-1, 1e-6)
    with pytest.raises(ConfigError, match='offset'):
        PiezoCantilever(load_plant_params(), FS, sensor_offset=float('nan'))


# --- 16-bit sensor at 10 kHz -------------------------------------------------------------------

def test_adc_grid_is_2_to_the_bits_codes_over_the_span():
    step, lo, hi = adc_grid(16, 2e-4)
    assert step == 2e-4 / 65536 and lo == -1e-4 and hi == pytest.approx(1e-4 - step)
    assert round((hi - lo) / step) + 1 == 65536
    for bits, span in ((0, 1e-4), (33, 1e-4), (16, 0.0), (16, float('inf'))):
        with pytest.raises(ConfigError):
            adc_grid(bits, span)
    with pytest.raises(ConfigError, match='together'):
        PiezoCantilever(load_plant_params(), FS, sensor_bits=16)


def test_16_bit_sensor_quantises_and_clips_at_10_khz():
    fs = 10000.0
    params = load_plant_params()
    u = generate('multisine', fs, 0.4, 100.0, seed=1, f_max=500.0)
    raw = PiezoCantilever(params.replace(quantisation=0.0), fs, seed=2).run(u).y
    span = 2e-4
    plant = PiezoCantilever(params, fs, seed=2, sensor_bits=16, sensor_span=span)
    y = plant.run(u).y
    step = span / 65536
    assert plant.sensor_quantisation == step
    codes = y / step
    assert np.allclose(codes, np.round(codes), rtol=0, atol=1e-6)          # on the grid
    assert np.all(np.abs(y - raw) <= step / 2 * (1 + 1e-9))                # nearest code
    assert np.unique(np.round(codes)).size > 2000                          # a fine grid, used
    # A 20 um span clips the +-40 um motion at its lowest and highest codes.
    small = PiezoCantilever(params, fs, seed=2, sensor_bits=16, sensor_span=2e-5).run(u).y
    lo, hi = adc_grid(16, 2e-5)[1:]
    assert small.min() == lo and small.max() == hi
    assert np.array_equal(small, np.clip(np.round(raw / (2e-5 / 65536)) * (2e-5 / 65536), lo, hi))


@pytest.mark.parametrize('cfg', CONFIGS)
def test_plant_at_10_khz_matches_2_khz_and_rings_at_its_mode(cfg):
    params = quiet(cfg)
    u2 = generate('multisine', FS, 0.5, 100.0, seed=3, f_max=200.0)
    y2 = PiezoCantilever(params, FS).run(u2).y_true
    # The same piecewise-constant input sampled 5x faster: the outputs must agree at t_k.
    y10 = PiezoCantilever(params, 5 * FS).run(np.repeat(u2, 5)).y_true[4::5]
    assert np.max(np.abs(y10 - y2)) < 2e-3 * np.ptp(y2)
    # A step at 10 kHz rings at the first mode, below the 5 kHz Nyquist frequency.
    fs = 10000.0
    y = PiezoCantilever(params, fs).run(np.full(500, 20.0)).y_true
    ring = (y - np.convolve(y, np.ones(50) / 50, 'same'))[50:-50]
    spec = np.abs(np.fft.rfft(ring * np.hanning(ring.size), 8 * ring.size))
    f_peak = np.fft.rfftfreq(8 * ring.size, 1 / fs)[np.argmax(spec)]
    assert f_peak == pytest.approx(params.mode_frequency, rel=0.03)


# --- rig signals -------------------------------------------------------------------------------

def test_growing_sine_holds_then_grows_at_one_frequency():
    u = generate('growing_sine', FS, 10.0, 100.0, offset=20.0, freq=2.0, hold=1.0)
    assert np.all(u[:2000] == 20.0) and u[2001] > 20.0           # hold at the offset, then up
    peaks = np.abs(u[2000:] - 20.0).reshape(-1, 500).max(axis=1)  # per half period
    assert np.all(np.diff(peaks) > 0) and peaks[-1] > 98.0 and peaks[0] < 15.0
    swing = u[2000:] - 20.0
    zero_crossings = np.count_nonzero(np.diff(np.signbit(swing[swing != 0.0])))
    assert zero_crossings in (35, 36)                             # 2 per period, 18 periods
    exp = generate('growing_sine', FS, 4.0, 1.0, freq=5.0, growth='exponential',
                   start_fraction=0.1)
    per_s = np.abs(exp).reshape(4, -1).max(axis=1)
    assert np.allclose(per_s[1:] / per_s[:-1], 0.1 ** -0.25, rtol=0.05)  # equal ratios per s
    with pytest.raises(ConfigError, match='growth'):
        generate('growing_sine', FS, 1.0, 1.0, growth='cubic')
    with pytest.raises(ConfigError, match='start_fraction'):
        generate('growing_sine', FS, 1.0, 1.0, growth='exponential', start_fraction=0.0)


def test_holds_ramp_to_random_levels_and_hold_them():
    u = generate('holds', FS, 6.0, 50.0, seed=4, hold=1.0, ramp=0.05)
    assert abs(u[0]) <= 50.0 / 100 + 1e-9                         # ramps from the offset
    assert np.max(np.abs(u)) == pytest.approx(50.0)
    held = u[100:2100]                                            # after the first 0.05 s ramp
    assert np.all(held == held[0]) and abs(held[0]) > 0.0
    levels = u[2200::2100][:2]
    assert levels[0] != held[0] and np.all(u[2200:4200] == levels[0])
    assert not np.array_equal(u, generate('holds', FS, 6.0, 50.0, seed=5, hold=1.0, ramp=0.05))


# --- command line ------------------------------------------------------------------------------

def run_cli(argv):
    with pytest.raises(SystemExit) as exc:
        main(argv)
    return exc.value.code


def test_simulate_rig_session(tmp_path):
    common = ['simulate', '--signal', 'growing_sine', '--freq', '5', '--hold', '0.2',
              '--seconds', '0.6', '--fs', '10000', '--seed', '1']
    assert run_cli(common + ['--out', str(tmp_path / 'rest.npz')]) == 0
    assert run_cli(common + ['--history', '2', '--history-hold', '0.1', '--history-seed', '7',
                             '--session', '3', '--sensor-bits', '16', '--sensor-span', '2e-4',
                             '--out', str(tmp_path / 'rig.npz')]) == 0
    with np.load(tmp_path / 'rest.npz') as rest, np.load(tmp_path / 'rig.npz') as rig:
        meta = json.loads(str(rig['meta']))
        assert 'history' not in json.loads(str(rest['meta']))
        assert np.array_equal(rest['u'], rig['u'])
        assert abs(rest['y_true'][0]) < 1e-9 < abs(rig['y_true'][0])   # not at rest
        assert meta['history'] == {'seconds': 2.0, 'hold_s': 0.1, 'amplitude_V': 100.0,
                                   'seed': 7}
        assert meta['sensor']['offset_m'] == session_offset(3, 2.5e-6)
        codes = rig['y'] / (2e-4 / 65536)
        assert np.allclose(codes, np.round(codes), rtol=0, atol=1e-6)
        # Measured minus true deflection: the session's offset (noise averages out).
        gap = np.mean(rig['y'][:2000] - rig['y_true'][:2000])
        assert gap == pytest.approx(meta['sensor']['offset_m'], abs=0.05e-6)


@pytest.mark.parametrize('argv, words', [
    (['--sensor-bits', '16'], '--sensor-span'),
    (['--session', '1', '--sensor-offset', '1e-6'], '--session'),
    (['--history', '-1'], '--history'),
    (['--history', '1', '--history-seed', '-2'], 'history seed'),
    (['--sensor-bits', '40', '--sensor-span', '1e-4'], 'bits'),
    (['--signal', 'growing_sine', '--start-fraction', '2'], 'start_fraction'),
])
def test_simulate_bad_session_options_exit_2_with_one_line(tmp_path, capsys, argv, words):
    code = run_cli(['simulate', '--out', str(tmp_path / 'x.npz'), '--seconds', '0.1'] + argv)
    err = capsys.readouterr().err.strip()
    assert code == 2 and err.count('\n') == 0
    assert err.startswith('piezo-narx: error:') and words in err
    assert not (tmp_path / 'x.npz').exists()
