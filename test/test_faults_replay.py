"""
Fault suite, replays and pauses: issue 19 items 4, 5, 10 and 14.

command_node's playback plays a file as recorded (its volts, its rate, once), reads a headerless
t,u,y table as `fit` does, resamples a file at another rate only when asked, and a pause holds
the last command on the same clock so that the estimator does not restart from rest.
Each test fails on the code before issue 19.
"""
import numpy as np
import pytest

from piezo_narx_ros.command.playback import playback_signal
from piezo_narx_ros.command.stream import CommandStreamer
from piezo_narx_ros.errors import ConfigError

NS = 10**9


def recording(n=3000, fs=2000.0, seed=0):
    """Return a record's volts, -25..35 V, not centred (the issue's case)."""
    t = np.arange(n) / fs
    rng = np.random.default_rng(seed)
    u = 5.0 + 30.0 * np.sin(2 * np.pi * 1.3 * t) + rng.normal(0, 0.5, n)
    return np.clip(u, -25.0, 35.0)


@pytest.fixture
def files(tmp_path):
    u = recording()
    t = np.arange(u.size) / 2000.0
    np.savez(tmp_path / 'rec.npz', u=u, y=1e-7 * u, fs=2000.0)
    np.savetxt(tmp_path / 'tuy.csv', np.column_stack([t, u, 1e-7 * u]), delimiter=',',
               fmt='%.17g')                                          # headerless t,u,y
    np.savetxt(tmp_path / 'fast.csv', np.column_stack([np.arange(u.size) / 2500.0, u]),
               delimiter=',', header='t,u', comments='', fmt='%.17g')  # t column at 2.5 kHz
    return tmp_path, u


def test_playback_is_the_recording_unchanged(files):
    """Before: rescaled to +-100 V about its mean and looped to 25 s (-78.6..+82.8 V)."""
    d, u = files
    play = playback_signal(str(d / 'rec.npz'))
    assert play.fs == 2000.0 and not play.loop and play.notes == []
    assert play.signal.shape == (u.size, 1) and np.array_equal(play.signal[:, 0], u)
    # The playback parameters still change it, and say so.
    scaled = playback_signal(str(d / 'rec.npz'), scale=0.5, offset=1.0)
    assert np.array_equal(scaled.signal[:, 0], u * 0.5 + 1.0)
    assert any('u * 0.5 + 1' in n for n in scaled.notes)
    looped = playback_signal(str(d / 'rec.npz'), loop=True)
    assert looped.loop and any('jumps' in n for n in looped.notes)


def test_headerless_t_u_y_table_plays_u_not_the_time_column(files):
    """Before: the time column (0 .. 1.5 s) was streamed as volts."""
    d, u = files
    play = playback_signal(str(d / 'tuy.csv'))
    assert np.array_equal(play.signal[:, 0], u) and play.fs == pytest.approx(2000.0)


def test_playback_at_another_rate_plays_at_its_own_unless_resampling_is_asked(files):
    """Before: a 2.5 kHz CSV on a 2 kHz node was stretched by 25 % without a word."""
    d, u = files
    own = playback_signal(str(d / 'fast.csv'), fs=2000.0)
    assert own.fs == pytest.approx(2500.0) and np.array_equal(own.signal[:, 0], u)
    assert any('streamed at that rate, as recorded, not at fs 2000 Hz' in n for n in own.notes)
    with pytest.raises(ConfigError, match='needs path'):
        playback_signal('')
    res = playback_signal(str(d / 'fast.csv'), fs=2000.0, resample=True)
    assert res.signal.shape[0] == pytest.approx(u.size * 0.8, abs=1)
    assert any('resampled to 2000 Hz' in n for n in res.notes)


def test_playback_beyond_the_limits_is_clamped_and_said(files):
    d, u = files
    play = playback_signal(str(d / 'rec.npz'), u_min=-10.0, u_max=10.0)
    assert any('beyond [-10, 10] are clamped' in n for n in play.notes)


def test_command_node_replays_a_file_as_recorded(files):
    """
    Replay a file through the node as recorded.

    amplitude, seconds and loop (as a launch file's params file sets them) do not apply.
    """
    import rclpy
    from rclpy.parameter import Parameter

    from piezo_narx_ros.nodes.command_node import CommandNode
    d, u = files
    ctx = rclpy.Context()
    rclpy.init(context=ctx)
    try:
        node = CommandNode(context=ctx, parameter_overrides=[
            Parameter('kind', value='playback'), Parameter('path', value=str(d / 'fast.csv')),
            Parameter('amplitude', value=100.0), Parameter('seconds', value=25.0),
            Parameter('loop', value=True), Parameter('fs', value=2000.0),
            Parameter('running', value=False)])
        s = node.streamer
        assert s.fs == pytest.approx(2500.0) and not s.loop
        assert np.array_equal(s.signal[:, 0], u)
        node.destroy_node()
        node = CommandNode(context=ctx, parameter_overrides=[
            Parameter('kind', value='playback'), Parameter('path', value=str(d / 'fast.csv')),
            Parameter('resample', value=True), Parameter('playback_loop', value=True),
            Parameter('running', value=False)])
        assert node.streamer.fs == 2000.0 and node.streamer.loop
        node.destroy_node()
    finally:
        rclpy.try_shutdown(context=ctx)


def test_pause_holds_the_last_command_and_the_estimate_does_not_restart():
    """
    Hold a 2.3 s pause on the same clock: the estimate goes on.

    Before, the pause re-anchored the clock; the estimator took the resumed stream for a new one
    and restarted from rest while the plant held its voltage (26.7 um error for a second).
    """
    from piezo_narx_ros.estimator.free_run import FreeRunEstimator
    from piezo_narx_ros.estimator.toy import toy_narx
    fs = 2000.0
    sig = recording(4000, fs)
    s = CommandStreamer(sig, fs, loop=False)
    s.start(t0_ns=10**18, mono0_ns=0)
    stamps, volts = [], []

    def poll(until_s):
        t, v = s.poll(int(until_s * NS))
        stamps.extend(t.tolist())
        volts.extend(v[:, 0].tolist())
    poll(0.5)
    s.hold()
    poll(2.8)                                        # 2.3 s paused
    s.resume()
    poll(3.0)
    assert np.all(np.diff(stamps) == 500_000)        # one clock, no jump
    held = np.array(volts[1001:5601])
    assert np.all(held == sig[1000])                 # the last command, repeated
    assert volts[5601] == sig[1001]                  # the signal goes on where it stopped
    model = toy_narx(fs=fs)
    est = FreeRunEstimator(model, init='rest')
    out = []
    for t, u in zip(stamps, volts):
        out += est.on_command(t, u)
    assert est.stats.stream_restarts == 0 and est.stats.gaps == 0
    assert np.max(np.abs(np.array([y for _, y in out]) - model.simulate(np.array(volts)))) \
        <= 1e-12


def test_hold_before_the_first_sample_is_a_stop():
    s = CommandStreamer(np.zeros(10), 1000.0)
    s.start(0, 0)
    s.hold()                                   # nothing sent yet: nothing to hold
    assert not s.holding and not s.running
