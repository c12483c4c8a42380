"""
Batch fast paths (issue 21): the same numbers, counters and state as the one-sample calls.

RateMonitor.observe_run against received()+observe() per stamp; FreeRunEstimator.on_commands /
on_measurements against on_command / on_measurement per sample; PlantResponder.on_commands
against on_command per sample. Streams mix clean batches (the fast path) with gaps, outliers,
NaN, out-of-range commands, restarts and rate changes (the one-by-one fallback), so both paths
and the switches between them are exercised.
"""
import math

import numpy as np
import pytest

from piezo_narx_ros.command.stamps import RateMonitor
from piezo_narx_ros.estimator.free_run import FreeRunEstimator
from piezo_narx_ros.estimator.toy import toy_narx

PERIOD = 500_000          # ns, 2 kHz
T0 = 10**18


def _same(a, b):
    return a == b or (isinstance(a, float) and math.isnan(a) and math.isnan(b))


@pytest.mark.parametrize('window,single_writer', [(4, False), (50, True), (2000, False)])
def test_rate_monitor_observe_run_equals_one_by_one(window, single_writer):
    rng = np.random.default_rng(window)
    a, b = RateMonitor(PERIOD, 0.01, window), RateMonitor(PERIOD, 0.01, window)
    a.single_writer = b.single_writer = single_writer
    t = T0
    for _ in range(60):
        m = int(rng.integers(1, 40))
        steps = np.full(m, float(PERIOD))
        if rng.random() < 0.4:    # gaps, a faster and a slower stretch
            steps = rng.choice([PERIOD, 3 * PERIOD, 0.8 * PERIOD, 1.3 * PERIOD], m,
                               p=[0.7, 0.1, 0.1, 0.1])
        stamps = (t + np.cumsum(steps)).astype(np.int64)
        t = int(stamps[-1])
        if rng.random() < 0.05:
            a.reset()
            b.reset()
        expected = []
        for s in stamps.tolist():
            a.received()
            expected.append(a.observe(s))
        assert b.observe_run(stamps).tolist() == expected
        for name in ('off', 'episodes', 'ratio', 'arrival_ratio'):
            assert _same(getattr(a, name), getattr(b, name)), name
        assert (a._ring == b._ring).all() and (a._st == b._st).all()
    assert a.episodes > 0      # the off-rate stretches were seen


def test_pass_run_observed_is_pass_run_then_observe_run():
    from piezo_narx_ros.command import stamp_kernels as sk
    from piezo_narx_ros.command.stamps import StampGate, pass_run_observed
    rng = np.random.default_rng(4)
    pairs = [(StampGate(PERIOD, 100), RateMonitor(PERIOD, 0.01, 50)) for _ in range(2)]
    assert pass_run_observed(*pairs[1], np.array([T0], dtype=np.int64)) is None   # no stream
    for g, _ in pairs:
        g.push(T0)
    for _ in range(300):
        m = int(rng.integers(0, 30))
        steps = rng.choice([PERIOD, PERIOD, PERIOD, 3 * PERIOD, 0.7 * PERIOD], m)
        if rng.random() < 0.3:       # a stretch at another rate, on the gate's grid
            steps = np.full(m, 1.2 * PERIOD)
        (g1, r1), (g2, r2) = pairs
        stamps = (g1.last + np.cumsum(steps)).astype(np.int64)
        for _ in range(int(rng.integers(0, 3))):
            r1.received(g1.last + PERIOD)
            r2.received(g2.last + PERIOD)
        if rng.random() < 0.2:    # one sample alone, as the one-sample paths observe it
            for g, r in pairs:
                r.observe(g.last + PERIOD)
                g.push(g.last + PERIOD)
        if rng.random() < 0.02:
            for _, r in pairs:
                r.reset()
        ok = g1.pass_run(stamps)
        want = r1.observe_run(stamps) if ok else None
        got = pass_run_observed(g2, r2, stamps)
        assert (got is None) == (not ok) and g1.last == g2.last
        if ok:
            assert got[0].tolist() == want.tolist() and got[1] == int(want.sum())
        assert (r1._st == r2._st).all() and (r1._ring == r2._ring).all()
        assert _same(r1.ratio, r2.ratio) and r1._received == r2._received
        for r in (r1, r2):        # received(t) reads the last accepted stamp from Python
            assert r._last == (int(r._st[sk.I_LAST]) if r._st[sk.I_HAS_LAST] else None)
    assert pairs[1][1].episodes >= 1      # the other rate was seen


def test_pass_run_checked_is_the_command_checks_then_pass_run_observed():
    # The commands' checks folded into the stamp kernel's call: the same verdicts and state as
    # the Python checks (finite, within the accepted range) before pass_run_observed.
    from piezo_narx_ros.command.stamps import (StampGate, checked_run_bounds, pass_run_checked,
                                               pass_run_observed)
    rng = np.random.default_rng(5)
    pairs = [(StampGate(PERIOD, 100), RateMonitor(PERIOD, 0.01, 50)) for _ in range(2)]
    bounds = checked_run_bounds((-200.0, 200.0), (-150.0, 150.0))
    for g, _ in pairs:
        g.push(T0)
    for _ in range(400):
        m = int(rng.integers(0, 25))
        steps = rng.choice([PERIOD, PERIOD, PERIOD, 3 * PERIOD], m)
        (g1, r1), (g2, r2) = pairs
        stamps = (g1.last + np.cumsum(steps)).astype(np.int64)
        v = rng.uniform(-140.0, 140.0, m)
        if m and rng.random() < 0.5:
            v[int(rng.integers(0, m))] = rng.choice([np.nan, np.inf, -np.inf, 200.0, -200.0,
                                                     200.5, 160.0, -150.0, -151.0])
        clean = m > 0 and bool(np.isfinite(v).all()) and -200.0 <= v.min() <= v.max() <= 200.0
        want = pass_run_observed(g1, r1, stamps) if clean else None
        got = pass_run_checked(g2, r2, stamps, v, bounds)
        assert (got is None) == (want is None) and g1.last == g2.last
        if want is not None:
            inside = bool(((v >= -150.0) & (v <= 150.0)).all())
            assert got[0].tolist() == want[0].tolist() and got[1:] == (want[1], inside)
        assert (r1._st == r2._st).all() and (r1._ring == r2._ring).all()
        assert r1._received == r2._received and r1._last == r2._last


def _command_stream(rng, n):
    """Stamps and volts of a stream with every kind of trouble in some of its stretches."""
    t = T0 + np.arange(n, dtype=np.int64) * PERIOD
    u = rng.uniform(-120.0, 120.0, n)
    for i, k in enumerate(np.sort(rng.choice(np.arange(200, n), 18, replace=False))):
        trouble = i % 6
        if trouble == 0:
            u[k] = np.nan
        elif trouble == 1:
            u[k] = 500.0                          # beyond u_max: rejected, held
        elif trouble == 2:
            u[k] = 190.0                          # beyond the trained input range: counted
        elif trouble == 3:
            t[k] += 7 * PERIOD // 2               # an outlier stamp
        elif trouble == 4:
            t[k:] += 5 * PERIOD                   # a gap of 5 samples
        else:
            t[k:] -= 800 * PERIOD                 # a jump back: a new stream
    return t, u


def _batches(rng, n):
    k = 0
    while k < n:
        m = int(rng.integers(1, 40))
        yield slice(k, min(n, k + m))
        k += m


def _twin_estimators(seed, init, n=6000):
    """rng, a troubled stream (stamps, volts), measurements and two identical estimators."""
    rng = np.random.default_rng(seed)
    t, u = _command_stream(rng, n)
    y_meas = rng.normal(0.0, 1e-7, n)
    # A narrowed range (negative margin): estimates and commands outside it, counted.
    model = toy_narx()
    twins = [FreeRunEstimator(model, init=init, window=300, init_window=0.02,
                              range_margin=-0.3) for _ in range(2)]
    return rng, t, u, y_meas, twins


@pytest.mark.parametrize('init', ['rest', 'measurement'])
def test_estimator_batch_path_equals_one_sample_path(init):
    n = 6000
    rng, t, u, y_meas, (one, many) = _twin_estimators(7, init, n)
    got_one, got_many = [], []
    for sl in _batches(rng, n):
        tl, ul = t[sl].tolist(), u[sl].tolist()
        # Measurements of the samples before this batch: the sensor lags the command a bit.
        lag = slice(max(0, sl.start - 3), max(0, sl.stop - 3))
        for s, y in zip(t[lag].tolist(), y_meas[lag].tolist()):
            got_one += one.on_measurement(s, y)
        ts, ys = many.on_measurements(t[lag], y_meas[lag])
        got_many += list(zip(ts.tolist(), ys.tolist()))
        for s, v in zip(tl, ul):
            got_one += one.on_command(s, v)
        ts, ys = many.on_commands(t[sl], u[sl])
        got_many += list(zip(ts.tolist(), ys.tolist()))
    assert len(got_one) > 0.9 * n
    assert got_many == got_one                 # bit for bit, stamps and values
    assert vars(many.stats) == vars(one.stats)
    st = one.stats
    assert st.stream_restarts and st.gaps and st.rejected_range and st.rejected_nonfinite
    assert st.stamp_outliers and st.input_out_of_range and st.out_of_range
    rms1, r21, n1 = one.running_error()
    rms2, r22, n2 = many.running_error()
    assert (rms1, r21, n1) == (rms2, r22, n2) and n1 == 300
    assert many.take_excursion() == one.take_excursion()
    assert many.take_input_excursion() == one.take_input_excursion()


@pytest.mark.parametrize('init', ['rest', 'measurement'])
def test_measurements_held_back_while_steady_change_nothing(init):
    """FreeRunEstimator.steady / handover: measurements handed in late, the same results."""
    n = 6000
    rng, t, u, y_meas, (now, late) = _twin_estimators(8, init, n)
    held, handed, out_now, out_late = [], [], [], []

    def hand_over():
        handed.append(len(held))
        while held:
            ts, ys = late.on_measurements(*held.pop(0))
            out_late.extend(zip(ts.tolist(), ys.tolist()))
    late.handover = hand_over
    for sl in _batches(rng, n):
        lag = slice(max(0, sl.start - 3), max(0, sl.stop - 3))
        ts, ys = now.on_measurements(t[lag], y_meas[lag])
        out_now += list(zip(ts.tolist(), ys.tolist()))
        if late.steady and len(held) < 7:
            held.append((t[lag], y_meas[lag]))
        else:
            hand_over()
            ts, ys = late.on_measurements(t[lag], y_meas[lag])
            out_late += list(zip(ts.tolist(), ys.tolist()))
        for est, out in ((now, out_now), (late, out_late)):
            ts, ys = est.on_commands(t[sl], u[sl])
            out += list(zip(ts.tolist(), ys.tolist()))
        if rng.random() < 0.01:
            now.flush()
            late.flush()
    assert now.running_error() == late.running_error() and now.running_error()[2] == 300
    assert sorted(out_late) == sorted(out_now) and len(out_now) > 0.9 * n
    assert vars(late.stats) == vars(now.stats)
    assert max(handed) > 3            # measurements were really held, several batches at once
    assert late.handover is hand_over  # restored after each hand-over


def test_held_batches_keep_the_batches_of_the_newest_samples():
    from piezo_narx_ros.nodes.wire import trajectory as codec
    from piezo_narx_ros.nodes.wire.batching import HeldBatches
    from piezo_narx_ros.nodes.wire import encode_joint_trajectory
    codec._SHAPES.clear()

    def batch(k, n=20):
        t = T0 + (k * 20 + np.arange(n, dtype=np.int64)) * PERIOD
        return encode_joint_trajectory(t, ['x'], position=np.full((n, 1), float(k)))
    held = HeldBatches(50, keep=70)
    assert held.push(batch(0))          # a shape not seen yet: taken at once, never dropped
    assert [len(b) for _, b in held.take()] == [20]
    for k in range(1, 30):
        assert not held.push(batch(k))
    assert held.push(batch(30, n=7))    # another shape: taken, with what is held
    got = [b for _, b in held.take()]
    # The 4 newest batches of 20 (80 samples >= 70; 3 would be 60), then the short one.
    assert [float(b.position[0, 0]) for b in got] == [26.0, 30.0]
    assert got[0].t_ns.size == 80 and held.dropped == 25 and len(held) == 0
    assert HeldBatches(3).push(b'') is False and HeldBatches(1).push(b'')


def test_measurements_beyond_the_error_window_dropped_unread_change_nothing():
    """The estimator node's held measurements (HeldBatches keep=window): the same results."""
    from piezo_narx_ros.nodes.wire.batching import HeldBatches
    from piezo_narx_ros.nodes.wire import encode_joint_trajectory
    n = 6000
    rng, t, u, y_meas, _ = _twin_estimators(9, 'rest', n)
    # Estimates kept for pairing well beyond the window, as the node requires for keep=window.
    now, late = (FreeRunEstimator(toy_narx(), init='rest', window=300, init_window=0.5,
                                  range_margin=-0.3) for _ in range(2))
    assert late.window + 40 <= late.pairing_horizon // 2
    # A sensor answers the samples the stream estimates (a simulator refuses outlier stamps
    # too), so every measurement pairs.
    whole = FreeRunEstimator(toy_narx(), init='rest', window=300, range_margin=-0.3)
    answered = set(whole.on_commands(t, u)[0].tolist())
    held = HeldBatches(50, keep=late.window)

    def hand_over():
        for _, batch in held.take():
            late.on_measurements(batch.t_ns, batch.position[:, 0])
    late.handover = hand_over
    errors = 0
    stops = np.cumsum(rng.choice([20, 20, 20, 13], n // 13))
    for sl in (slice(a, b) for a, b in zip(np.r_[0, stops], stops) if a < n):
        lag = slice(max(0, sl.start - 3), max(0, sl.stop - 3))
        keep = np.array([s in answered for s in t[lag].tolist()], dtype=bool)
        tm, ym = t[lag][keep], y_meas[lag][keep]
        now.on_measurements(tm, ym)
        if tm.size and late.steady:
            if held.push(encode_joint_trajectory(tm, ['x'], position=ym[:, None])):
                hand_over()
        elif tm.size:
            hand_over()
            late.on_measurements(tm, ym)
        for est in (now, late):
            est.on_commands(t[sl], u[sl])
        if rng.random() < 0.03:      # a diagnostics tick
            assert late.running_error() == now.running_error()
            errors += 1
    assert late.running_error() == now.running_error() and now.running_error()[2] == 300
    assert vars(late.stats) == vars(now.stats)
    assert errors > 3 and held.dropped > 50


def test_estimator_fast_path_is_taken_and_runs_at_the_model_rate():
    model = toy_narx()
    est = FreeRunEstimator(model, init='rest', bracket=False)
    t = T0 + np.arange(200, dtype=np.int64) * PERIOD
    u = np.linspace(-50.0, 50.0, 200)
    est.on_commands(t[:20], u[:20])          # the start goes one by one
    calls = []
    est.on_command = lambda *a: calls.append(a)   # the fast path must not fall back
    ts, ys = est.on_commands(t[20:], u[20:])
    assert calls == [] and ts.tolist() == t[20:].tolist()
    assert np.allclose(ys, model.simulate(u)[20:], rtol=0, atol=1e-12 * 1e-6)
    assert est.gate.last == t[-1] and est.stats.estimates == 200


def _stage(seed=0):
    from piezo_narx_ros.plant import load_plant_params
    from piezo_narx_ros.plant.axes import CoupledCantilever
    p = load_plant_params()
    return CoupledCantilever(('x', 'y'), [p, p.replace(d_p=4.2e-7, A=0.35, mode_frequency=690.0)],
                             [[1.0, 0.15], [-0.1, 1.0]], fs=2000.0, seed=seed)


@pytest.mark.parametrize('coupled', [False, True])
def test_plant_responder_batch_path_equals_one_sample_path(coupled):
    from piezo_narx_ros.nodes.simulator_node import PlantResponder
    from piezo_narx_ros.plant import PiezoCantilever

    def responder():
        plants = _stage() if coupled else {a: PiezoCantilever(fs=2000.0, seed=i)
                                           for i, a in enumerate(('x', 'y'))}
        return PlantResponder(plants, 2000.0)
    rng = np.random.default_rng(3)
    n = 4000
    t, u0 = _command_stream(rng, n)
    u = np.column_stack([u0, rng.uniform(-100.0, 100.0, n)])
    one, many = responder(), responder()
    got_one, got_many = [], []
    for sl in _batches(rng, n):
        for s, v in zip(t[sl].tolist(), u[sl].tolist()):
            try:
                got_one += [(a, list(y), list(ua)) for a, y, ua in
                            one.on_command(s, {'x': v[0], 'y': v[1]})]
            except Exception:     # noqa: BLE001 - refused and counted, as the node does
                pass
        ts, ys, uas = many.on_commands(t[sl], u[sl])
        got_many += list(zip(ts.tolist(), ys.tolist(), uas.tolist()))
    assert len(got_one) > 0.9 * n
    assert got_many == got_one
    for name in ('received', 'answered', 'rejected', 'filled', 'gaps', 'stamp_outliers',
                 'stream_restarts', 'rate_withheld', 'last_t', 'last_u'):
        assert getattr(many, name) == getattr(one, name), name
    assert one.rejected and one.gaps and one.stream_restarts


def test_one_sample_paths_give_the_offline_numbers():
    # The one-sample fast paths (a clean stream's every command) against the offline plant and
    # model, and a gap (the general path) on the way.
    from piezo_narx_ros.nodes.simulator_node import PlantResponder
    from piezo_narx_ros.plant import PiezoCantilever
    u = np.random.default_rng(2).uniform(-150.0, 150.0, 600)
    t = T0 + np.arange(600, dtype=np.int64) * PERIOD
    t[300:] += PERIOD                        # one sample missing: held by the plant, not answered
    held = np.insert(u, 300, u[299])
    r = PlantResponder({'x': PiezoCantilever(fs=2000.0, seed=3)}, 2000.0)
    got = [a for s, v in zip(t.tolist(), u.tolist()) for a in r.on_command(s, {'x': v})]
    want = PiezoCantilever(fs=2000.0, seed=3).run(held)
    keep = np.r_[0:300, 301:601]
    assert [g[1][0] for g in got] == want.y[keep].tolist()
    assert [g[2][0] for g in got] == want.u_applied[keep].tolist() and r.gaps == 1
    model = toy_narx()
    est = FreeRunEstimator(model, init='rest', bracket=False)
    ys = [y for s, v in zip(t.tolist(), u.tolist()) for _, y in est.on_command(s, v)]
    assert np.allclose(ys, model.simulate(held), rtol=0, atol=1e-12 * 1e-6)
    assert len(ys) == 601 and est.stats.filled == 1


@pytest.mark.parametrize('axes', [1, 2, 'coupled'])
def test_run_checked_equals_run(axes):
    # The simulator's batch path (commands known finite) gives run()'s numbers and state.
    from piezo_narx_ros.plant.axes import make_axis_plants

    def plants():
        return _stage(seed=2) if axes == 'coupled' else make_axis_plants(
            ['x', 'y'][:axes], fs=2000.0, seed=2)
    a, b = plants(), plants()
    u = np.random.default_rng(1).uniform(-150.0, 150.0, (3000, 1 if axes == 1 else 2))
    for k in range(0, 3000, 20):
        y_a, ua_a = a.run(u[k:k + 20])
        y_b, ua_b = b.run_checked(u[k:k + 20])
        assert y_b.tolist() == y_a.tolist() and ua_b.tolist() == ua_a.tolist()
    assert a.step(u[0])[0] == b.step(u[0])[0]


def test_coupled_cantilever_run_equals_steps_and_couples_the_axes():
    a, b = _stage(seed=4), _stage(seed=4)
    u = np.column_stack([100.0 * np.sin(np.arange(3000) / 40.0), np.zeros(3000)])
    y_run, ua_run = a.run(u)
    steps = [b.step(row) for row in u.tolist()]
    assert y_run.tolist() == [s[0] for s in steps]
    assert ua_run.tolist() == [s[1] for s in steps]
    # Only x is driven: y moves by -0.1 of x's deflection (within the sensor noise).
    slope = np.polyfit(y_run[500:, 0], y_run[500:, 1], 1)[0]
    assert slope == pytest.approx(-0.1 / (1.0 - 0.0), abs=0.01)
