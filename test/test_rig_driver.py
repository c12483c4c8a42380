"""RigDriver without sockets or DDS: limits, watchdog ramp, reply matching and diagnostics."""
import numpy as np
import pytest

from piezo_narx_ros.errors import ConfigError, DataError
from piezo_narx_ros.rig import protocol as p
from piezo_narx_ros.rig.driver import (DIAG_ERROR, DIAG_OK, DIAG_WARN, DriverConfig, RigDriver,
                                       STATE_PARKED, STATE_RAMPING, STATE_STREAMING)
from piezo_narx_ros.rig.limits import SlewLimiter, Watchdog

FS = 1000.0


class Target:
    """Records what the driver sends and answers like a target would (position = volts * 1e-7)."""

    def __init__(self):
        self.sent = []

    def __call__(self, data):
        self.sent.append(p.unpack_command(data))

    def reply(self, cmd, flags=0):
        return p.pack_reply(p.Reply(cmd.seq, cmd.stamp_ns, tuple(v * 1e-7 for v in cmd.volts),
                                    cmd.volts, flags))


def make(**kw):
    cfg = {'sample_rate': FS, 'v_min': -100.0, 'v_max': 100.0, 'max_slew_rate': 1e4,
           'watchdog_timeout': 0.05, 'ramp_rate': 500.0, 'reply_timeout': 0.005}
    cfg.update(kw)
    target = Target()
    return RigDriver(DriverConfig(**cfg), target), target


def test_limiter_clamps_window_and_slew():
    lim = SlewLimiter(-10.0, 10.0, max_slew_rate=100.0)
    out, clamped, slewed = lim.apply([50.0], dt=0.01)     # 1 V allowed in 10 ms
    assert out.tolist() == [1.0] and clamped and slewed
    out, clamped, slewed = lim.apply([1.5], dt=0.01)
    assert out.tolist() == [1.5] and not clamped and not slewed
    for _ in range(20):
        out, _, _ = lim.apply([50.0], dt=0.01)
    assert out.tolist() == [10.0]


@pytest.mark.parametrize('args, reason', [
    ((5.0, -5.0, 1.0), 'v_min < v_max'),
    ((1.0, 5.0, 1.0), 'include 0 V'),
    ((-5.0, 5.0, 0.0), 'max_slew_rate'),
    ((-5.0, float('nan'), 1.0), 'finite'),
])
def test_limiter_refuses_bad_limits(args, reason):
    with pytest.raises(ConfigError, match=reason):
        SlewLimiter(*args)


@pytest.mark.parametrize('field, value', [('sample_rate', 0.0), ('reply_timeout', -1.0),
                                          ('watchdog_timeout', float('inf')), ('n_axes', 0),
                                          ('ramp_rate', float('nan'))])
def test_config_refuses_bad_values_naming_the_field(field, value):
    with pytest.raises(ConfigError, match=field):
        DriverConfig(**{field: value}).validate()


def test_watchdog_counts_each_trip_once():
    wd = Watchdog(0.1)
    assert not wd.expired(100.0)                  # never fed: output already at rest
    wd.feed(0.0)
    assert not wd.expired(0.1)
    assert wd.expired(0.11) and wd.expired(0.5) and wd.trips == 1
    wd.feed(1.0)
    assert not wd.expired(1.05) and wd.expired(1.2) and wd.trips == 2


def test_commands_within_limits_pass_unchanged_with_stamp_and_sequence():
    drv, target = make()
    u = 5.0 * np.sin(np.arange(50) / 10.0)        # at most 0.5 V per sample < 10 V allowed
    for k, v in enumerate(u):
        drv.command([v], stamp_ns=1000 * k, now=k / FS)
    assert [c.volts[0] for c in target.sent] == u.tolist()
    assert [c.stamp_ns for c in target.sent] == [1000 * k for k in range(50)]
    seqs = [c.seq for c in target.sent]
    assert seqs == list(range(seqs[0], seqs[0] + 50))
    assert drv.counts['commands_clamped'] == drv.counts['commands_slewed'] == 0


def test_commands_are_clamped_and_slew_limited_whatever_they_ask():
    drv, target = make()
    for k in range(30):
        drv.command([1e6], stamp_ns=k, now=k / FS)
    sent = np.array([c.volts[0] for c in target.sent])
    assert sent.max() == 100.0                                      # voltage window
    assert np.max(np.abs(np.diff(np.r_[0.0, sent]))) <= 1e4 / FS + 1e-12  # 10 V per sample
    assert sent[9] == pytest.approx(100.0) and sent[8] == pytest.approx(90.0)
    assert drv.counts['commands_clamped'] == 30 and drv.counts['commands_slewed'] == 9


def test_bad_commands_are_rejected_counted_and_survived():
    drv, target = make()
    with pytest.raises(DataError, match='not finite'):
        drv.command([float('nan')], 0, 0.0)
    with pytest.raises(DataError, match='1 axes'):
        drv.command([1.0, 2.0], 0, 0.0)
    drv.command([1.0], 0, 0.0)
    assert drv.counts['commands_rejected'] == 2 and len(target.sent) == 1


def test_watchdog_ramps_to_zero_at_slew_limit_and_keeps_talking():
    drv, target = make(max_slew_rate=1000.0)
    t = 0.0
    for k in range(200):                           # 1000 V/s = 1 V per sample: reach 100 V
        t = k / FS
        drv.command([100.0], k, t)
    assert target.sent[-1].volts == (100.0,)
    n_cmd = len(target.sent)
    # Commands stop; tick every 1 ms. Nothing before the 50 ms timeout, then 2 V per 2 ms datagram.
    times = t + np.arange(1, 400) * 1e-3
    for now in times:
        drv.tick(now, stamp_ns=int(now * 1e9))
    ramp = target.sent[n_cmd:]
    assert all(c.flags & p.FLAG_RAMP for c in ramp)
    volts = np.array([c.volts[0] for c in ramp])
    first_ramp_time = ramp[0].stamp_ns * 1e-9
    assert first_ramp_time - t == pytest.approx(0.051, abs=1.5e-3)
    assert volts[0] == pytest.approx(98.0)
    assert np.max(np.abs(np.diff(volts))) <= 1000.0 / 500.0 + 1e-9   # slew x ramp period
    assert volts[-1] == 0.0 and len(volts) == 50                       # 100 V / 2 V per datagram
    assert drv.state == STATE_PARKED and drv.counts['watchdog_trips'] == 1
    # Commands return: the output slews up again from 0 V, not jumps.
    drv.command([100.0], 0, times[-1] + 1e-3)
    assert target.sent[-1].volts == (1.0,) and drv.state == STATE_STREAMING


def test_late_ticks_do_not_exceed_the_slew_limit():
    drv, target = make(max_slew_rate=1000.0, v_max=100.0)
    drv.limiter.output[:] = 50.0
    drv.command([50.0], 0, 0.0)
    drv.tick(0.06)                                  # trips: one period's worth of slew (2 V)
    drv.tick(0.5)                                   # 440 ms late: still only 2 V
    assert [c.volts[0] for c in target.sent[1:]] == [48.0, 46.0]
    assert drv.state == STATE_RAMPING


def test_replies_matched_by_sequence_late_lost_duplicate_unknown_malformed():
    drv, target = make(reply_timeout=0.005)
    for k in range(5):
        drv.command([float(k)], stamp_ns=100 + k, now=0.0)
    c = target.sent
    s = drv.receive(target.reply(c[0]), now=0.001)
    assert s.stamp_ns == 100 and s.position_m == (0.0,) and not s.late
    assert drv.receive(target.reply(c[0]), now=0.002) is None            # duplicate
    assert drv.receive(target.reply(c[2]), now=0.003).stamp_ns == 102     # out of order is fine
    unknown = p.Command(c[-1].seq + 100, 0, (0.0,))
    assert drv.receive(target.reply(unknown), now=0.003) is None
    assert drv.receive(b'garbage', now=0.003) is None
    assert drv.receive(target.reply(c[0])[:-1], now=0.003) is None
    drv.tick(0.010)                                                       # 1, 3, 4 time out
    s = drv.receive(target.reply(c[3]), now=0.011)
    assert s.late and s.stamp_ns == 103                                   # late, still published
    s = drv.receive(target.reply(c[4]), now=0.012)
    assert s.late
    counts = drv.counts
    assert counts['replies'] == 2 and counts['replies_duplicate'] == 1
    assert counts['replies_unknown'] == 1 and counts['replies_malformed'] == 2
    assert counts['reply_timeouts'] == 3 and counts['replies_late'] == 2  # seq 1 lost


def test_ramp_replies_are_not_published():
    drv, target = make()
    drv.command([1.0], 0, 0.0)
    drv.tick(0.1)
    assert target.sent[-1].flags & p.FLAG_RAMP
    assert drv.receive(target.reply(target.sent[-1]), 0.1001) is None
    assert drv.counts['replies'] == 1


def test_diagnostics_report_timeouts_and_silent_target():
    drv, target = make()
    level, msg, values = drv.report(0.0)
    assert level == DIAG_OK and values['datagrams_sent'] == 0
    drv.command([1.0], 0, 0.0)
    drv.command([1.0], 1, 0.001)
    drv.receive(target.reply(target.sent[0]), 0.002)
    level, msg, values = drv.report(0.02)
    assert level == DIAG_WARN and 'reply timeout: 1' in msg and values['reply_timeouts'] == 1
    drv.command([1.0], 2, 0.03)
    level, msg, _ = drv.report(0.05)
    assert level == DIAG_ERROR and 'target not replying' in msg
    drv.receive(b'PZRG', 0.06)
    level, msg, values = drv.report(0.061)
    assert level == DIAG_WARN and 'malformed' in msg and values['replies_malformed'] == 1


def test_send_errors_are_counted_not_raised():
    def refuse(_data):
        raise ConnectionRefusedError(111, 'refused')
    drv = RigDriver(DriverConfig(), refuse)
    drv.command([0.0], 0, 0.0)
    assert drv.counts['send_errors'] == 1 and drv.counts['datagrams_sent'] == 0
    level, msg, _ = drv.report(0.0)
    assert level == DIAG_ERROR and 'could not be sent' in msg


def test_target_fault_flag_is_reported():
    drv, target = make()
    drv.command([1.0], 0, 0.0)
    s = drv.receive(target.reply(target.sent[0], flags=p.FLAG_TARGET_FAULT), 0.001)
    assert s.target_fault
    level, msg, _ = drv.report(0.001)
    assert level == DIAG_ERROR and 'fault' in msg


def test_ping_reaches_the_target_without_moving_anything_and_is_not_published():
    drv, target = make()
    assert not drv.connected
    drv.ping(0.0, stamp_ns=5)
    ping = target.sent[-1]
    assert ping.flags == p.FLAG_PING and ping.volts == (0.0,)
    assert drv.receive(target.reply(ping), 0.001) is None
    assert drv.connected and drv.counts['replies'] == 1 and drv.state == 'idle'
    drv.tick(10.0)                                   # pings do not feed or trip the watchdog
    assert len(target.sent) == 1 and drv.counts['watchdog_trips'] == 0


def test_an_early_ramp_tick_still_moves_no_faster_than_the_slew_limit():
    drv, target = make(max_slew_rate=1000.0)          # ramp_rate 500 Hz: 2 V per 2 ms
    drv.limiter.output[:] = 50.0
    drv.command([50.0], 0, 0.0)
    drv.tick(0.06)
    drv.tick(0.0619)                                  # 1.9 ms later: sent, 1.9 V
    drv.tick(0.0629)                                  # 1.0 ms later: too early, skipped
    assert [c.volts[0] for c in target.sent[1:]] == pytest.approx([48.0, 46.1])


def test_a_reply_pairs_only_with_a_command_sent_and_only_once():
    drv, target = make()
    drv.command([1.0], stamp_ns=1000, now=0.0)
    cmd = target.sent[0]
    forged = p.Command(cmd.seq, 999_999, cmd.volts)          # right seq, a stamp never sent
    assert drv.receive(target.reply(forged), now=0.001) is None
    assert drv.counts['replies_mismatched'] == 1
    level, msg, _ = drv.report(0.001)
    assert level == DIAG_WARN and 'stamps are not those of their command' in msg
    s = drv.receive(target.reply(cmd), now=0.002)              # the real answer still pairs
    assert s.stamp_ns == 1000 and not s.late
    for _ in range(4):                                         # 5 replies to one command
        assert drv.receive(target.reply(cmd), now=0.003) is None
    assert drv.counts['samples_answered'] == 1 and drv.counts['replies_duplicate'] == 4


def test_a_batch_reply_must_echo_exactly_its_commands_stamps():
    drv, target = make()
    drv.command([1.0], stamp_ns=1000, now=0.0)
    cmd = target.sent[0]
    five = p.pack_reply_batch(p.ReplyBatch(cmd.seq, (1000, 2000, 3000, 4000, 5000),
                                           ((1e-7,),) * 5, ((1.0,),) * 5))
    assert drv.receive_batch(five, now=0.001) == []
    assert drv.counts['replies_mismatched'] == 1 and drv.counts['samples_answered'] == 0
    drv.tick(0.02)                                    # expired: a late reply must match too
    assert drv.receive_batch(five, now=0.021) == []
    assert drv.counts['replies_mismatched'] == 2
    one = p.pack_reply_batch(p.ReplyBatch(cmd.seq, (1000,), ((1e-7,),), ((1.0,),)))
    [s] = drv.receive_batch(one, now=0.022)
    assert s.stamp_ns == 1000 and s.late


def test_a_late_reply_to_a_ramp_datagram_is_not_published():
    drv, target = make()
    drv.command([1.0], 0, 0.0)
    drv.receive(target.reply(target.sent[0]), 0.0001)
    drv.tick(0.1)                                              # watchdog: a ramp datagram
    ramp = target.sent[-1]
    assert ramp.flags & p.FLAG_RAMP
    drv.tick(0.2)                                              # and it times out
    assert drv.receive(target.reply(ramp), 0.21) is None


def test_datagrams_from_elsewhere_are_a_warning_while_they_arrive():
    drv, _ = make()
    level, msg, values = drv.report(0.0, foreign=30_399)
    assert level == DIAG_WARN and "30399 datagrams from an address other than the target's" in msg
    assert values['datagrams_foreign'] == 30_399
    level, _, _ = drv.report(1.0, foreign=30_399)              # none since: OK again
    assert level == DIAG_OK
