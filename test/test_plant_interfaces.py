"""
One plant, two interfaces: step() and run() agree.

Seeds reproduce; reset() returns to rest; bad commands and parameters raise one-line errors.
"""
import numpy as np
import pytest

from piezo_narx_ros.errors import ConfigError, DataError
from piezo_narx_ros.plant import PiezoCantilever, PlantParams, generate, load_plant_params

FS = 2000.0


@pytest.fixture(scope='module')
def params():
    return load_plant_params()


@pytest.fixture(scope='module')
def u_aprbs():
    # Steps exercise the slew limit, the mode and hysteresis reversals; 5000 samples > one noise
    # block.
    return generate('aprbs', FS, 2.5, 180.0, seed=7, min_hold=0.002, max_hold=0.05) + \
        generate('sine', FS, 2.5, 60.0, freq=3.0)


def test_step_and_run_agree(params, u_aprbs):
    a = PiezoCantilever(params, FS, seed=5).run(u_aprbs)
    b = PiezoCantilever(params, FS, seed=5)
    stepped = np.array([b.step(v) for v in u_aprbs])
    for col, arr in zip(stepped.T, (a.y, a.y_true, a.u_applied)):
        np.testing.assert_allclose(col, arr, rtol=0, atol=1e-12 * max(1.0, np.max(np.abs(arr))))
    assert np.array_equal(stepped[:, 0], a.y)  # in fact bit-identical: the same kernel


def test_mixed_run_and_step_continue_one_state(params, u_aprbs):
    whole = PiezoCantilever(params, FS, seed=9).run(u_aprbs)
    p = PiezoCantilever(params, FS, seed=9)
    first = p.run(u_aprbs[:1234])
    middle = [p.step(v)[0] for v in u_aprbs[1234:4500]]
    last = p.run(u_aprbs[4500:])
    assert np.array_equal(np.concatenate([first.y, middle, last.y]), whole.y)


def test_batches_of_any_size_continue_one_state(params, u_aprbs):
    # A node's batches (run_into, the simulator's fast path) cut the noise stream anywhere: small
    # draws refill the noise block, long ones take what they need, steps come in between.
    whole = PiezoCantilever(params, FS, seed=4).run(u_aprbs)
    p = PiezoCantilever(params, FS, seed=4)
    rng = np.random.default_rng(0)
    got, k = [], 0
    while k < u_aprbs.size:
        n = int(rng.choice([1, 7, 20, 4095, 4097]))
        part = np.ascontiguousarray(u_aprbs[k:k + n])
        kind = rng.integers(3)
        if kind == 0:
            got += p.run(part).y.tolist()
        elif kind == 1:
            y, ua = np.empty(part.size), np.empty(part.size)
            p.run_into(part, y, ua)
            got += y.tolist()
        else:
            got += [p.step(v)[0] for v in part]
        k += part.size
    assert np.array_equal(got, whole.y)


def test_seed_reproduces_and_changes_only_noise(params, u_aprbs):
    a = PiezoCantilever(params, FS, seed=1).run(u_aprbs)
    b = PiezoCantilever(params, FS, seed=1).run(u_aprbs)
    c = PiezoCantilever(params, FS, seed=2).run(u_aprbs)
    assert np.array_equal(a.y, b.y)
    assert not np.array_equal(a.y, c.y)
    assert np.array_equal(a.y_true, c.y_true)
    assert np.std(a.y - c.y) == pytest.approx(np.sqrt(2) * params.noise_std, rel=0.1)


def test_reset_returns_to_rest_and_reseeds(params, u_aprbs):
    p = PiezoCantilever(params, FS, seed=3)
    first = p.run(u_aprbs)
    assert np.any(p.state != 0)
    p.reset()
    assert np.all(p.state == 0) and p.u_applied == 0.0
    assert np.array_equal(p.run(u_aprbs).y, first.y)


def test_bad_command_raises_and_leaves_state(params):
    p = PiezoCantilever(params, FS)
    p.run(np.full(10, 20.0))
    before = p.state
    for bad in (float('nan'), float('inf'), 'ten volts', None):
        with pytest.raises(DataError, match='finite'):
            p.step(bad)
    with pytest.raises(DataError, match='index 2'):
        p.run([1.0, 2.0, float('nan')])
    with pytest.raises(DataError, match='numbers'):
        p.run(['a', 'b'])
    with pytest.raises(DataError, match='1-D'):
        p.run(np.zeros((3, 2)))
    assert np.array_equal(p.state, before)


@pytest.mark.parametrize('change, name', [
    ({'v_min': 300.0}, 'v_min'), ({'slew_rate': 0.0}, 'slew_rate'), ({'d_p': -1e-7}, 'd_p'),
    ({'B': 0.001, 'gamma': 0.01}, 'gamma'), ({'mode_damping': 0.0}, 'mode_damping'),
    ({'noise_std': -1.0}, 'noise_std'), ({'substeps': 0}, 'substeps'),
    ({'creep_gains': (0.1,)}, 'creep_time_constants'),
    ({'mode_frequency': float('nan')}, 'mode_frequency'),
])
def test_invalid_parameters_name_the_parameter(change, name):
    with pytest.raises(ConfigError, match=name):
        PlantParams(**change)


def test_constructor_checks_fs_and_seed(params):
    with pytest.raises(ConfigError, match='fs'):
        PiezoCantilever(params, fs=0.0)
    with pytest.raises(ConfigError, match='seed'):
        PiezoCantilever(params, seed=-1)


def test_yaml_defaults_match_code_and_errors_name_the_key(tmp_path):
    assert load_plant_params() == PlantParams()
    bad = tmp_path / 'bad.yaml'
    bad.write_text('plant:\n  mode_frequncy: 700\n')
    with pytest.raises(ConfigError, match='mode_frequncy'):
        load_plant_params(bad)
    bad.write_text('plant:\n  noise_std: loud\n')
    with pytest.raises(ConfigError, match='noise_std'):
        load_plant_params(bad)
    bad.write_text('plant: [1, 2\n')
    with pytest.raises(ConfigError, match='YAML'):
        load_plant_params(bad)
    with pytest.raises(ConfigError, match='cannot read'):
        load_plant_params(tmp_path / 'missing.yaml')
    good = tmp_path / 'good.yaml'
    good.write_text('plant:\n  mode_frequency: 700\n  slew_rate: .inf\n')
    p = load_plant_params(good)
    assert p.mode_frequency == 700.0 and p.slew_rate == float('inf') and p.d_p == PlantParams().d_p
