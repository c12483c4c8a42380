"""
Control of several axes (control/axes.py), without DDS.

A 2 x 2 ARX identified on the coupled two-axis cantilever: the vector inverse reaches its own
model's output on both axes at once (the coupling compensated: holding y at 0 while x moves
takes a y command), keeps every axis within its own limits and counts what it cannot reach; the
per-axis linear baseline ignores the coupling and misses by it.
"""
import numpy as np
import pytest

from piezo_narx_ros.control.axes import AxesController, VectorInverse, static_gains
from piezo_narx_ros.errors import ConfigError

FS = 2000.0
T0 = 10**15


def test_static_gains_show_the_coupling_of_the_stage(arx2):
    gains, _ = static_gains(arx2)
    # config/plant_2axis.yaml: y moves by 0.12 of x's chain, x by 0.05 of y's.
    assert gains[1, 0] / gains[0, 0] == pytest.approx(0.12, abs=0.03)
    assert gains[0, 1] / gains[1, 1] == pytest.approx(0.05, abs=0.03)


def test_inverse_reaches_both_axes_and_compensates_the_coupling(arx2):
    inv = VectorInverse(arx2)
    for k in range(200):
        r = np.array([10e-6 * np.sin(k / 20.0), 0.0])      # move x, hold y still
        sol = inv.solve(r)
        assert sol.limit == 'reached'
        assert np.max(np.abs(inv.commit(sol.u) - r)) < 1e-15
    assert abs(sol.u[1]) > 1.0          # y is driven (V) to cancel what x does to it


def test_limits_per_axis_are_kept_and_misses_counted(arx2):
    ctl = AxesController(arx2, u_min=[-200.0, -5.0], u_max=[200.0, 5.0],
                         y_min=[-1e-4, -1e-4], y_max=[1e-4, 1e-4])
    out = [ctl.on_reference(T0 + k * 500_000, [0.0, 20e-6])[0][1] for k in range(50)]
    u = np.array(out)
    assert (u[:, 1] <= 5.0).all() and (u[:, 1] >= -5.0).all()
    assert ctl.stats.voltage_limited > 0 and ctl.stats.unreachable == ctl.stats.voltage_limited
    ctl.on_reference(T0 + 50 * 500_000, [np.nan, 0.0])      # a NaN axis: previous one held
    assert ctl.stats.rejected_nonfinite == 1


def test_inverse_tracks_its_model_and_the_linear_baseline_misses_the_coupling(arx2):
    n = 400
    ref = np.column_stack([10e-6 * np.sin(np.arange(n) / 15.0), 5e-6 * np.cos(np.arange(n) / 9.0)])
    miss = {}
    for mode in ('inverse', 'linear'):
        ctl = AxesController(arx2, mode=mode)
        u = np.array([ctl.on_reference(T0 + k * 500_000, ref[k])[0][1] for k in range(n)])
        y = arx2.simulate(u)                 # the model as the plant: sensorless, exact
        miss[mode] = np.sqrt(np.mean((y[100:] - ref[100:]) ** 2))
    assert miss['inverse'] < 1e-12
    assert miss['linear'] > 1e-7


def test_feedback_mode_is_refused_for_several_axes(arx2):
    with pytest.raises(ConfigError, match='several axes'):
        AxesController(arx2, mode='inverse_feedback')
