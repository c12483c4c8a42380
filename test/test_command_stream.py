"""command/stream.py: drift-free sample clock, catch-up, limits, loop/stop, without DDS."""
import math

import numpy as np
import pytest

from piezo_narx_ros.command.stream import CommandStreamer, SampleClock, make_signal
from piezo_narx_ros.errors import ConfigError

NS = 10**9


def test_clock_stamps_are_exact_after_a_day_at_odd_rates():
    c = SampleClock(2000.0, t0_ns=5, mono0_ns=0)
    k = 2000 * 86400
    assert c.stamp_ns(k) == 5 + 86400 * NS
    c3 = SampleClock(3000.0, 0, 0)  # 1/3000 s is not a whole number of ns: no drift anyway
    assert c3.stamp_ns(3000 * 3600) == 3600 * NS
    assert c3.stamp_ns(1) == 333_333 and c3.stamp_ns(2) == 666_667
    with pytest.raises(ConfigError):
        SampleClock(0.0, 0, 0)


@pytest.mark.parametrize('fs', [2000.0, 20000.0, 3000.0, 2000.0 / 3.0, 12345.678])
def test_clock_stamps_of_a_batch_are_each_stamp(fs):
    c = SampleClock(fs, t0_ns=1_795_000_000_123_456_789, mono0_ns=0)
    for k in (0, 1, 999_983, 2000 * 86400 * 30, 10**11):     # a month at 2 kHz, years
        for n in (0, 1, 20, 10_000):
            assert c.stamps_ns(k, n).tolist() == [c.stamp_ns(k + i) for i in range(n)]
    assert c.stamps_ns(0, 3).dtype == np.int64
    far = SampleClock(fs, t0_ns=2**62, mono0_ns=0)      # beyond int64 arithmetic: exact anyway
    assert far.stamps_ns(5, 3).tolist() == [far.stamp_ns(5 + i) for i in range(3)]


def test_polls_read_the_signal_as_indexed_across_the_wrap():
    sig = np.arange(50.0).reshape(25, 2)
    s = CommandStreamer(sig, fs=1000.0, loop=True, lead=np.full((3, 2), -1.0))
    s.start(0, 0)
    got, now = [], 0
    for k in range(40):
        now += int(np.random.default_rng(k).integers(0, 9)) * 1_000_000
        got.append(s.poll(now)[1])
    u = np.concatenate(got)
    want = np.concatenate([np.full((3, 2), -1.0)] + [sig] * 20)[:u.shape[0]]
    assert u.shape[0] > 100 and np.array_equal(u, want)


def _hold_or_resume(k, holds, resumes, *streamers):
    """Hold the streamers at the k in `holds`, resume them at the k in `resumes`."""
    for s in streamers:
        if k in holds:
            s.hold()
        if k in resumes:
            s.resume()


def _assert_same_counters(a, b):
    for name in ('position', 'published', 'late_polls', 'max_batch', 'holding', 'finished'):
        assert getattr(a, name) == getattr(b, name), name
    assert np.array_equal(a._last, b._last)


@pytest.mark.parametrize('slew', [math.inf, 2000.0])
def test_poll_lists_is_poll_as_lists(slew):
    def streamer():
        return CommandStreamer(np.arange(30.0).reshape(15, 2), fs=1000.0, loop=True,
                               slew_rate=slew, max_burst=5, lead=np.full((4, 2), -3.0))
    a, b = streamer(), streamer()
    a.start(7 * NS, 0)
    b.start(7 * NS, 0)
    rng = np.random.default_rng(1)
    now, calls = 0, []
    for k in range(300):
        now += int(rng.choice([0, 1, 1, 1, 2, 9])) * 1_000_000
        _hold_or_resume(k, (100, 150), (120, 170), a, b)
        t, v = a.poll(now)
        got = b.poll_lists(now)
        assert got == (t.tolist(), v.tolist())
        calls.append(len(got[0]))
    assert calls.count(1) > 100 and max(calls) == 5
    _assert_same_counters(a, b)
    a.stop()
    b.stop()
    assert b.poll_lists(now) == ([], [])


@pytest.mark.parametrize('loop', [True, False])
def test_take_run_is_poll_where_it_answers(loop):
    def streamer(slew=math.inf):
        return CommandStreamer(np.arange(60.0).reshape(30, 2), fs=1000.0, loop=loop,
                               slew_rate=slew, max_burst=8, lead=np.full((4, 2), -3.0))
    a, b = streamer(), streamer()
    a.start(7 * NS, 0)
    b.start(7 * NS, 0)
    rng = np.random.default_rng(2)
    now, taken, refused = 0, 0, 0
    for k in range(400):
        now += int(rng.choice([0, 5, 5, 5, 6, 9])) * 1_000_000
        _hold_or_resume(k, (100, 250), (120, 270), a, b)
        t, v = a.poll(now)
        got = b.take_run(now, 5)
        if got is None:
            refused += 1
            got = b.poll(now)
        else:
            taken += 1
            assert len(t) == 5
        assert np.array_equal(got[0], t) and np.array_equal(got[1], v)
        _assert_same_counters(a, b)
    if loop:     # the holds, the wraps, the late and early polls
        assert taken > 50 and refused > 50
    else:        # the last run goes through poll, which says the signal finished
        assert taken >= 1 and a.finished and b.finished
    assert a.published == b.published > 0
    c = streamer(slew=2000.0)
    c.start(0, 0)
    assert c.take_run(5 * 1_000_000 - 1, 5) is None     # a slew limit: poll's general case
    c.stop()
    assert c.take_run(10 ** 9, 5) is None


def test_due_count_follows_monotonic_time():
    c = SampleClock(1000.0, 0, mono0_ns=10 * NS)
    assert c.due_count(10 * NS - 1) == 0
    assert c.due_count(10 * NS) == 1
    assert c.due_count(10 * NS + 999_999) == 1
    assert c.due_count(10 * NS + 1_000_000) == 2
    assert c.due_count(11 * NS) == 1001


def test_late_poll_catches_up_every_sample_with_exact_stamps():
    s = CommandStreamer(np.arange(10.0), fs=1000.0, loop=True, max_burst=4)
    s.start(t0_ns=7 * NS, mono0_ns=0)
    t, u = s.poll(0)
    assert t.tolist() == [7 * NS] and u[:, 0].tolist() == [0.0]
    t, u = s.poll(1_000_000)                  # on time: one sample
    assert t.tolist() == [7 * NS + 1_000_000]
    t1, u1 = s.poll(12_500_000)               # 11 samples due: burst-limited to 4 ...
    t2, u2 = s.poll(12_500_000)
    t3, u3 = s.poll(12_500_000)
    t4, _ = s.poll(12_500_000)                # ... and nothing dropped or duplicated
    stamps = np.concatenate([t1, t2, t3])
    assert len(stamps) == 11 and t4.size == 0
    assert np.array_equal(np.diff(stamps), np.full(10, 1_000_000))
    assert stamps[0] == 7 * NS + 2_000_000
    volts = np.concatenate([u1, u2, u3])[:, 0]
    assert volts.tolist() == [2, 3, 4, 5, 6, 7, 8, 9, 0, 1, 2]   # looped
    assert s.late_polls == 3 and s.max_batch == 4 and s.published == 13


def test_non_looping_signal_finishes_and_stop_resumes_position():
    s = CommandStreamer([1.0, 2.0, 3.0], fs=100.0, loop=False)
    s.start(0, 0)
    assert s.poll(10_000_000)[1][:, 0].tolist() == [1.0, 2.0]
    s.stop()
    assert s.poll(10**12)[0].size == 0 and not s.running
    s.start(5 * NS, 10**12)
    t, u = s.poll(10**12 + 10**9)
    assert t.tolist() == [5 * NS] and u[:, 0].tolist() == [3.0]
    assert s.finished and not s.running


def test_clamp_and_slew_limit_apply_across_the_loop_wrap():
    s = CommandStreamer([0.0, 100.0, 300.0, -300.0], fs=10.0, u_min=-150.0, u_max=150.0,
                        slew_rate=500.0)   # 50 V per sample
    s.start(0, 0)
    _, u = s.poll(int(0.75 * NS))          # 8 samples: two periods
    assert u[:, 0].tolist() == [0.0, 50.0, 100.0, 50.0, 0.0, 50.0, 100.0, 50.0]
    assert np.all(np.abs(np.diff(u[:, 0])) <= 50.0 + 1e-12)


def test_streamer_refuses_bad_configuration():
    with pytest.raises(ConfigError, match='NaN'):
        CommandStreamer([0.0, math.nan], fs=10.0)
    with pytest.raises(ConfigError, match='u_min'):
        CommandStreamer([0.0], fs=10.0, u_min=5.0, u_max=1.0)
    with pytest.raises(ConfigError, match='fs'):
        CommandStreamer([0.0], fs=-1.0)


def test_make_signal_ignores_options_of_other_kinds_and_seeds_axes():
    u = make_signal('aprbs', 1000.0, 0.5, 10.0, n_axes=2, freq=3.0, min_hold=0.01, max_hold=0.05,
                    u_min=-5.0, u_max=5.0)
    assert u.shape == (500, 2) and np.abs(u).max() <= 5.0
    assert not np.array_equal(u[:, 0], u[:, 1])
    with pytest.raises(ConfigError, match='kind'):
        make_signal('noise', 1000.0, 1.0, 1.0)


def test_due_ns_is_the_first_instant_a_sample_is_due():
    for fs in (2000.0, 3000.0, 7.0):
        c = SampleClock(fs, 0, mono0_ns=123)
        for k in (0, 1, 2, 999, 10**6 + 7):
            t = c.due_ns(k)
            assert c.due_count(t) == k + 1 and c.due_count(t - 1) == k, (fs, k)


def test_next_due_follows_the_polls_and_is_none_when_not_running():
    s = CommandStreamer(np.zeros(10), 1000.0, loop=False)
    assert s.next_due_ns() is None
    s.start(0, mono0_ns=NS)
    assert s.next_due_ns() == NS
    s.poll(NS + 2_500_000)                     # samples 0, 1, 2 due
    assert s.next_due_ns() == NS + 3_000_000
    s.poll(NS + 10**9)
    assert s.finished and s.next_due_ns() is None


def test_preamble_streams_once_before_the_signal_and_the_loop_skips_it():
    s = CommandStreamer([1.0, 2.0], fs=100.0, loop=True, lead=[-5.0, -6.0, -7.0])
    s.start(0, 0)
    _, v = s.poll(int(7.5e7))       # 8 samples due at t = 75 ms
    assert v[:, 0].tolist() == [-5.0, -6.0, -7.0, 1.0, 2.0, 1.0, 2.0, 1.0]
    once = CommandStreamer(np.zeros((2, 2)), fs=100.0, loop=False, lead=[3.0])
    once.start(0, 0)
    _, v = once.poll(int(1e9))
    assert v.tolist() == [[3.0, 3.0], [0.0, 0.0], [0.0, 0.0]] and once.finished
    with pytest.raises(ConfigError, match='preamble'):
        CommandStreamer(np.zeros((2, 2)), fs=100.0, lead=np.zeros((3, 3)))
