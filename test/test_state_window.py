"""FullWindow: the first n consecutive measured commands, found while they arrive."""
import numpy as np
import pytest

from piezo_narx_ros.ident.state.window import FullWindow
from piezo_narx_ros.ident.state.start import first_full_window


def _arrivals(rng, count: int, lost: float, late: int):
    """Commands 0..count-1 in order; each measurement lost, or up to `late` events away."""
    events = [(2.0 * k, 'c', k) for k in range(count)]
    for k in range(count):
        if rng.random() >= lost:
            events.append((2.0 * k + rng.integers(-late, late + 1) + 0.5, 'm', k))
    return [(kind, k) for _, kind, k in sorted(events)]


@pytest.mark.parametrize('seed', range(40))
def test_the_window_found_as_things_arrive_is_the_first_full_one_of_the_list(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(1, 12))
    finder, measured, commands = FullWindow(n), set(), []
    found = None
    for kind, k in _arrivals(rng, 200, lost=rng.uniform(0.0, 0.3), late=int(rng.integers(0, 6))):
        if kind == 'm':
            measured.add(k)
            got = finder.measurement(k) if k in commands else None
        else:
            commands.append(k)
            got = finder.command(k, k in measured)
        if found is None:
            # The list's answer at the same moment: None until the finder reports it.
            want = first_full_window(commands, measured, n)
            assert got == want, (kind, k)
            found = got


def test_a_skipped_window_is_not_offered_again_and_the_next_one_is_after_it():
    finder = FullWindow(3)
    assert [finder.command(t, True) for t in range(3)] == [None, None, 0]
    assert finder.skip(0) is None                  # nothing after it yet
    assert [finder.command(t, True) for t in range(3, 6)] == [None, None, 3]
    # A late measurement completes a long run at once; skipping its first window offers the next.
    finder = FullWindow(2)
    assert finder.command(0, False) is None
    assert [finder.command(t, True) for t in (1,)] == [None]
    assert finder.command(2, False) is None
    assert [finder.command(t, True) for t in (3,)] == [None]
    assert finder.measurement(2) == 1              # 1, 2, 3 measured: the first window at 1
    assert finder.skip(1) is None                  # 3 alone is too short
    assert finder.measurement(0) == 0              # 0, 1: a window not tried, 2 is out now


def test_window_size_must_be_positive():
    with pytest.raises(ValueError, match='n must be >= 1'):
        FullWindow(0)


@pytest.mark.parametrize('family', ['toy', 'arx2'])
def test_warm_up_runs_the_estimator_through_its_measured_start_and_both_paths(family, request):
    from piezo_narx_ros.estimator.free_run import FreeRunEstimator
    from piezo_narx_ros.estimator.warm_up import warm_up
    from piezo_narx_ros.estimator.toy import toy_narx
    model = toy_narx(fs=2000.0) if family == 'toy' else request.getfixturevalue('arx2')
    est = FreeRunEstimator(model, fs=2000.0, init='measurement', init_window=0.05)
    warm_up(est, batch=8)
    # Started from the window of measurements and estimated every command after it: what the
    # live stream will run was run, one sample and batch by batch.
    assert est.stats.init == 'measurement' and est.stats.unestimated == 0
    assert est.stats.estimates == est.stats.commands == est.init_samples + 32
    rmse, r2, n = est.running_error()
    assert n > 0 and r2 > 0.999     # measured: the model's own free run, estimated again


def test_a_controller_start_waits_past_lost_deflections_to_the_first_full_window():
    from piezo_narx_ros.control.start import MeasuredStart
    from piezo_narx_ros.estimator.toy import toy_narx
    model = toy_narx(fs=2000.0)
    u = np.random.default_rng(0).uniform(-100.0, 100.0, 60)
    y = model.simulate(u)
    start = MeasuredStart(model, 'state', 20)
    lost, got = {5, 30}, None
    for k in range(60):
        assert start.sent(k, u[k])
        if k not in lost:
            got = start.measured(k, y[k])
            if got is not None:
                break
    # Commands 6 .. 25 are the first 20 in a row with their deflection: the window ends at 25.
    assert k == 25 and not start.waiting
    assert np.array_equal(got.u_run, u[6:26])
