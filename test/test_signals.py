"""Excitation signals: shape, spectrum, determinism, amplifier limits, playback, bad parameters."""
import numpy as np
import pytest

from piezo_narx_ros.errors import ConfigError
from piezo_narx_ros.plant import KINDS, generate

FS = 2000.0


@pytest.mark.parametrize('kind', [k for k in KINDS if k != 'playback'])
def test_length_peak_offset_and_determinism(kind):
    u = generate(kind, FS, 2.0, 50.0, offset=10.0, seed=3)
    assert u.shape == (4000,) and u.dtype == np.float64
    assert np.max(np.abs(u - 10.0)) <= 50.0 + 1e-9
    assert np.max(np.abs(u - 10.0)) > 40.0  # the amplitude is used, not a fraction of it
    assert np.array_equal(u, generate(kind, FS, 2.0, 50.0, offset=10.0, seed=3))


@pytest.mark.parametrize('kind', ['multisine', 'aprbs'])
def test_seed_changes_random_signals(kind):
    assert not np.allclose(generate(kind, FS, 1.0, 1.0, seed=1),
                           generate(kind, FS, 1.0, 1.0, seed=2))


def test_sine_and_triangle_frequency():
    for kind in ('sine', 'triangle'):
        u = generate(kind, FS, 4.0, 1.0, freq=5.0)
        crossings = np.count_nonzero(np.diff(np.signbit(u)))
        assert crossings in (39, 40)  # 2 per period over 20 periods
        assert abs(u[0]) < 1e-12 and u[1] > 0  # both start at the offset, rising
    tri = generate('triangle', FS, 1.0, 1.0, freq=2.0)
    slopes = np.abs(np.diff(tri))
    # constant slope
    assert np.allclose(slopes[slopes > 0.5 * slopes.max()], 4 * 2.0 / FS, rtol=1e-6)


def test_multisine_lines_in_band_flat_and_periodic():
    u = generate('multisine', FS, 10.0, 1.0, seed=0, f_min=1.0, f_max=50.0, f_res=0.5)
    spec = np.abs(np.fft.rfft(u[:4000]))  # one period = 2 s = 4000 samples
    f = np.fft.rfftfreq(4000, 1 / FS)
    on = (f >= 1.0) & (f <= 50.0) & (np.abs(f / 0.5 - np.round(f / 0.5)) < 1e-9)
    assert np.count_nonzero(on) == 99
    # Off-band lines are empty; DC holds only the offset that span scaling adds.
    assert np.all(spec[~on & (f > 0)] < 1e-9 * spec.max())
    assert u.min() == pytest.approx(-1.0, abs=1e-12) and u.max() == pytest.approx(1.0, abs=1e-12)
    assert np.allclose(spec[on], spec[on].mean(), rtol=1e-9)  # flat
    assert np.allclose(u[:4000], u[4000:8000])  # periodic
    pink = generate('multisine', FS, 2.0, 1.0, f_min=1.0, f_max=100.0, spectrum='pink')
    ps = np.abs(np.fft.rfft(pink))
    fp = np.fft.rfftfreq(pink.size, 1 / FS)
    ratio = ps[np.argmin(np.abs(fp - 4.0))] / ps[np.argmin(np.abs(fp - 64.0))]
    assert ratio == pytest.approx(4.0, rel=1e-6)


def test_multisine_default_resolution_is_one_record():
    u = generate('multisine', FS, 25.0, 100.0, seed=1)
    spec = np.abs(np.fft.rfft(u))
    f = np.fft.rfftfreq(u.size, 1 / FS)
    on = (spec > 1e-6 * spec.max()) & (f > 0)  # DC: the span-scaling offset
    assert f[on].min() == pytest.approx(0.12) and f[on].max() == pytest.approx(100.0)


@pytest.mark.parametrize('method', ['linear', 'logarithmic'])
def test_chirp_sweeps_from_f0_to_f1(method):
    from scipy.signal import hilbert
    u = generate('chirp', FS, 4.0, 1.0, f0=5.0, f1=200.0, method=method)
    # instantaneous frequency, Hz
    inst = np.diff(np.unwrap(np.angle(hilbert(u)))) * FS / (2 * np.pi)
    duration = (u.size - 1) / FS
    for t in (0.5, 2.0, 3.5):
        expected = (5.0 + 195.0 * t / duration if method == 'linear'
                    else 5.0 * 40.0 ** (t / duration))
        k = int(t * FS)
        assert np.median(inst[k - 50:k + 50]) == pytest.approx(expected, rel=0.03), t


def test_aprbs_holds_and_levels():
    u = generate('aprbs', FS, 10.0, 80.0, seed=4, min_hold=0.02, max_hold=0.1)
    change = np.flatnonzero(np.diff(u)) + 1
    holds = np.diff(change) / FS
    assert holds.min() >= 0.02 - 1e-9 and holds.max() <= 0.1 + 1e-9
    levels = u[change]
    assert levels.min() < -50 and levels.max() > 50  # spread over the amplitude range


def test_steps_levels_and_hold():
    u = generate('steps', FS, 1.0, 100.0, offset=5.0, levels=[0, 1, -0.5], hold=0.2)
    assert np.array_equal(np.unique(u), [-45.0, 5.0, 105.0])
    assert np.all(u[:400] == 5.0) and np.all(u[400:800] == 105.0) and np.all(u[800:] == -45.0)
    assert np.array_equal(generate('steps', FS, 1.0, 2.0, levels='0,1'),
                          np.repeat([0.0, 2.0], 1000))


def test_limits_clamp_then_slew():
    u = generate('steps', FS, 0.1, 300.0, levels=[0, 1, -1], u_min=-150.0, u_max=120.0,
                 slew_rate=1e5)
    assert u.max() == 120.0 and u.min() == -150.0
    assert np.max(np.abs(np.diff(u))) == pytest.approx(1e5 / FS)
    assert u[0] == 0.0  # the slew limit starts from the first sample: no ramp-in


def test_playback_npz_csv_resample_and_loop(tmp_path):
    src = np.sin(np.linspace(0, 6, 500)) * 30.0
    np.savez(tmp_path / 'a.npz', u=src, fs=1000.0)
    with pytest.raises(ConfigError, match='recorded at 1000 Hz, not at fs = 2000 Hz'):
        generate('playback', FS, None, None, path=str(tmp_path / 'a.npz'))
    u = generate('playback', FS, None, None, path=str(tmp_path / 'a.npz'), resample=True)
    assert u.size == 999  # 0.499 s at 1 kHz resampled to 2 kHz
    assert np.allclose(u[::2], src, atol=1e-12)
    assert np.array_equal(generate('playback', 1000.0, None, None, path=str(tmp_path / 'a.npz')),
                          src)                                    # as recorded
    np.savetxt(tmp_path / 'b.csv', np.column_stack([np.arange(500) / FS, src]), delimiter=',',
               header='t,volts', comments='')
    with pytest.raises(ConfigError, match='ask for loop'):
        generate('playback', FS, 0.5, 10.0, path=str(tmp_path / 'b.csv'), column='volts')
    v = generate('playback', FS, 0.5, 10.0, offset=1.0, path=str(tmp_path / 'b.csv'),
                 column='volts', loop=True)
    assert v.size == 1000 and np.array_equal(v[:500], v[500:])  # looped
    assert np.max(np.abs(v - 1.0 - (src - src.mean()).mean())) == pytest.approx(10.0, rel=0.01)


@pytest.mark.parametrize('kind, kwargs, name', [
    ('noise', {}, 'kind'),
    ('sine', {'freq': 1500.0}, 'freq'),
    ('sine', {'frequency': 2.0}, 'frequency'),
    ('multisine', {'f_min': 50.0, 'f_max': 10.0}, 'f_min'),
    ('multisine', {'spectrum': 'blue'}, 'spectrum'),
    ('chirp', {'method': 'cubic'}, 'method'),
    ('aprbs', {'min_hold': 0.5, 'max_hold': 0.1}, 'max_hold'),
    ('steps', {'levels': []}, 'levels'),
    ('sine', {'u_min': 10.0, 'u_max': -10.0}, 'u_min'),
    ('sine', {'slew_rate': -5.0}, 'slew_rate'),
    ('playback', {}, 'path'),
    ('playback', {'path': 'missing.npz'}, 'missing.npz'),
])
def test_bad_parameters_name_the_parameter(kind, kwargs, name):
    with pytest.raises(ConfigError, match=name):
        generate(kind, FS, 1.0, 1.0, **kwargs)


def test_bad_common_parameters():
    with pytest.raises(ConfigError, match='seconds'):
        generate('sine', FS, -1.0, 1.0)
    with pytest.raises(ConfigError, match='amplitude'):
        generate('sine', FS, 1.0, float('nan'))
    with pytest.raises(ConfigError, match='fs'):
        generate('sine', 0.0, 1.0, 1.0)
    with pytest.raises(ConfigError, match='seed'):
        generate('sine', FS, 1.0, 1.0, seed=-2)


def test_protocol_covers_the_envelope_in_each_half():
    # 25 s at 2 kHz, two cycles: each half of a 50/50 split holds every kind of move.
    u = generate('protocol', FS, 25.0, 100.0, seed=0)
    assert u.size == 50000 and np.all(np.abs(u) <= 100.0 + 1e-9)
    assert u[0] == 0.0
    for half in (u[:25000], u[25000:]):
        du = np.abs(np.diff(half))
        assert half.max() > 90.0 and half.min() < -90.0          # full range
        assert np.count_nonzero(du > 10.0) >= 5                   # steps (jumps > 10 V)
        held = np.convolve(du == 0.0, np.ones(400), 'valid') == 400
        assert np.count_nonzero(np.diff(held.astype(int)) == 1) >= 3   # holds >= 0.2 s
        # slow moves: long monotonic stretches below 0.5 V per sample (< 1000 V/s)
        slow = (du > 0) & (du < 0.5)
        assert np.count_nonzero(slow) > 2000
        spec = np.abs(np.fft.rfft(half))
        f = np.fft.rfftfreq(half.size, 1 / FS)
        assert spec[(f > 50) & (f < 100)].mean() > 20 * spec[(f > 200) & (f < 400)].mean()


def test_protocol_seeds_and_options():
    a = generate('protocol', FS, 4.0, 1.0, seed=1)
    assert not np.allclose(a, generate('protocol', FS, 4.0, 1.0, seed=2))
    one = generate('protocol', FS, 4.0, 1.0, seed=1, cycles=1)
    assert not np.allclose(a, one)
    with pytest.raises(ConfigError, match='cycles'):
        generate('protocol', FS, 4.0, 1.0, cycles=0)
    with pytest.raises(ConfigError, match='slow_freq'):
        generate('protocol', FS, 4.0, 1.0, slow_freq=5000.0)


def test_fade_out_preamble_fades_to_its_offset():
    from piezo_narx_ros.plant import preamble
    u = preamble('fade-out', 2000.0, 2.0, 80.0, offset=10.0, cycles=20)
    assert u.shape == (4000,)
    assert u[0] == pytest.approx(10.0) and abs(u[-1] - 10.0) < 0.1
    # Full amplitude in its first cycle, a tenth of it in the last tenth.
    assert np.max(np.abs(u[:200] - 10.0)) == pytest.approx(80.0, rel=0.02)
    assert np.max(np.abs(u[-400:] - 10.0)) < 8.0 + 1e-9
    assert preamble('none', 2000.0, 2.0, 80.0).size == 0
    with pytest.raises(ConfigError, match='preamble'):
        preamble('ramp', 2000.0, 2.0, 80.0)
    with pytest.raises(ConfigError, match='cycles'):
        preamble('fade-out', 2000.0, 2.0, 80.0, cycles=0)
