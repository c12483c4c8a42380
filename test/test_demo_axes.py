"""
The demo and the plant file of several axes (issue 20), without DDS.

Settings with axes and a plant file, the launch rendering of an axis named y (rcl reads a bare y
as a boolean), the live analysis pooled and per axis, and the stage file's checks.
"""
import numpy as np
import pytest

from piezo_narx_ros.demo.analysis import LiveRun, live_figures
from piezo_narx_ros.demo.launch_file import _yaml_flow
from piezo_narx_ros.demo.runner import load_settings, plant_file
from piezo_narx_ros.errors import ConfigError
from piezo_narx_ros.plant.axes import load_axes_config, make_axis_plants
from piezo_narx_ros.share import config_path


def test_two_axis_demo_settings_name_the_stage():
    s = load_settings(config_path('demo_2axis.yaml'))
    assert s['axes'] == ['x', 'y']
    assert s['seconds'] == 50.0         # two axes record twice one axis's 25 s (docs/mimo.md)
    assert load_settings(config_path('demo_2axis.yaml'), quick=True)['seconds'] < 10
    assert plant_file(s['plant_params']) == str(config_path('plant_2axis.yaml'))
    with pytest.raises(ConfigError, match='axes'):
        load_settings(None, axes=['x', 'x'])


def test_axis_names_yaml_reads_as_booleans_are_quoted():
    assert _yaml_flow(['x', 'y', 'z']) == "[x, 'y', z]"
    assert _yaml_flow('n') == "'n'" and _yaml_flow(2.5) == '2.5' and _yaml_flow(True) == 'true'


def test_live_figures_of_two_axes_are_pooled_and_per_axis():
    rng = np.random.default_rng(0)
    n = 500
    y = rng.normal(0.0, 1e-6, (n, 2))
    y_hat = y + rng.normal(0.0, [1e-8, 3e-8], (n, 2))
    t = np.arange(n, dtype=np.int64) * 500_000
    run = LiveRun(stamps_ns=t, t_s=t * 1e-9, u=rng.uniform(-90, 90, (n, 2)), y=y, y_hat=y_hat,
                  log_command_ns=t, log_deflection_ns=t, log_estimate_ns=t + 1000,
                  first_estimate=0, lost={}, fs=2000.0, axes=('x', 'y'))
    fig = live_figures(run, 0, (np.array([-80.0, -100.0]), np.array([80.0, 100.0])))
    per = {r['axis']: r for r in fig['per_axis']}
    assert per['y']['rmse_nm'] > 2 * per['x']['rmse_nm']
    sse = ((y_hat - y) ** 2).sum()
    sst = ((y - y.mean(axis=0)) ** 2).sum()
    assert fig['r2'] == pytest.approx(1 - sse / sst, rel=1e-12)
    assert fig['outside_input_range'] == int(np.count_nonzero((np.abs(run.u[:, 0]) > 80)))


def test_stage_file_checks(tmp_path):
    axes, params, c = load_axes_config(config_path('plant_2axis.yaml'))
    assert axes == ('x', 'y') and params[0] != params[1] and c[1, 0] == 0.12
    with pytest.raises(ConfigError, match='differ'):
        make_axis_plants(['a', 'b'], config_path('plant_2axis.yaml'))
    bad = tmp_path / 'bad.yaml'
    bad.write_text('axes: [x, y]\ncoupling: [[1.0, 0.1]]\n')
    with pytest.raises(ConfigError, match='coupling'):
        load_axes_config(bad)
    bad.write_text('axes: [x, y]\naxis_params: {z: {}}\n')
    with pytest.raises(ConfigError, match='axis_params'):
        load_axes_config(bad)
