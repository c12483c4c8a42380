"""
The free-run estimator on a model of several axes (issue 20), without DDS.

A 2 x 2 ARX identified on the two-axis coupled cantilever (conftest.py `arx2`): the live
estimate equals the model's offline free run, the batch path equals the one-sample path, and every
check (NaN, range, gaps, init from measurement) holds per channel.
"""
import numpy as np
import pytest

from piezo_narx_ros.estimator.free_run import FreeRunEstimator

FS = 2000.0
PERIOD = 500_000
T0 = 10**18


def test_vector_estimates_equal_the_offline_free_run(arx2, stage_data):
    u, _ = stage_data
    est = FreeRunEstimator(arx2, init='rest')
    t = T0 + np.arange(len(u), dtype=np.int64) * PERIOD
    out = [e for s, row in zip(t.tolist(), u) for e in est.on_command(s, row)]
    y_hat = np.array([y for _, y in out])
    assert y_hat.shape == (len(u), 2)
    assert np.allclose(y_hat, arx2.simulate(u), rtol=0, atol=1e-12 * np.ptp(y_hat))


def test_vector_batch_path_equals_one_sample_path(arx2, stage_data):
    u, y = stage_data
    n = 3000
    u, y = u[:n].copy(), y[:n].copy()
    t = T0 + np.arange(n, dtype=np.int64) * PERIOD
    u[700, 1] = np.nan              # one channel not finite: the command is held
    u[900, 0] = 500.0               # one channel beyond u_max
    t[1200:] += 4 * PERIOD          # a gap
    y[1500, 0] = np.nan             # a measurement with a NaN channel is ignored
    one = FreeRunEstimator(arx2, init='measurement', init_window=0.01, window=200)
    many = FreeRunEstimator(arx2, init='measurement', init_window=0.01, window=200)
    got_one, got_many = [], []
    rng = np.random.default_rng(2)
    k = 0
    while k < n:
        sl = slice(k, min(n, k + int(rng.integers(1, 30))))
        k = sl.stop
        for s, row in zip(t[sl].tolist(), y[sl]):
            got_one += one.on_measurement(s, row)
        ts, ys = many.on_measurements(t[sl], y[sl])
        got_many += list(zip(ts.tolist(), ys.tolist()))
        for s, row in zip(t[sl].tolist(), u[sl]):
            got_one += one.on_command(s, row)
        ts, ys = many.on_commands(t[sl], u[sl])
        got_many += list(zip(ts.tolist(), ys.tolist()))
    assert got_many == [(s, e.tolist()) for s, e in got_one]
    assert vars(many.stats) == vars(one.stats)
    st = one.stats
    assert st.init == 'measurement' and st.rejected_nonfinite == 1 and st.rejected_range == 1
    assert st.gaps == 1 and st.filled == 4 + 2
    assert one.running_error() == many.running_error()
    rms, r2, _ = one.running_error()
    assert r2 > 0.9 and rms < 0.2 * np.nanstd(y)


def test_vector_range_checks_hold_per_channel(arx2):
    est = FreeRunEstimator(arx2, init='rest', range_margin=0.0)
    lo, hi = est.u_lo, est.u_hi
    assert lo.shape == hi.shape == (2,)
    est.on_command(T0, [0.0, 0.0])
    est.on_command(T0 + PERIOD, [0.0, hi[1] + 5.0])     # the second channel extrapolates
    assert est.stats.input_out_of_range == 1
    assert est.take_input_excursion() == pytest.approx(5.0)
