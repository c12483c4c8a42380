"""Rig datagrams version 2 (several samples each): codec, RigDriver, fake_rig; no DDS."""
import numpy as np
import pytest

from piezo_narx_ros.errors import ConfigError
from piezo_narx_ros.plant import PiezoCantilever, load_plant_params
from piezo_narx_ros.rig import protocol as p
from piezo_narx_ros.rig.driver import DriverConfig, RigDriver
from piezo_narx_ros.rig.fake_rig import FakeRig

T0 = 1_700_000_000_000_000_000
DT = 50_000          # 20 kHz


def test_version2_round_trips_every_stamp_and_value_and_has_the_documented_layout():
    stamps = (T0, T0 + DT, T0 + 3 * DT, T0 - 1)
    volts = ((12.5, -1.0), (13.0, 2.0), (-200.0, 0.0), (1e-9, 5.0))
    raw = p.pack_command_batch(p.CommandBatch(7, stamps, volts, p.FLAG_RAMP))
    assert len(raw) == 32 + 4 * (8 + 2 * 8)
    assert raw[:8] == b'PZRG\x02\x01\x02\x00' and raw[24:32] == b'\x04\x00' + bytes(6)
    assert int.from_bytes(raw[32:40], 'little', signed=True) == T0   # first sample's stamp
    assert p.unpack_command_batch(raw, n_axes=2) == p.CommandBatch(7, stamps, volts,
                                                                   p.FLAG_RAMP)
    assert p.datagram_version(raw) == 2
    pos = tuple(tuple(v * 1e-7 for v in row) for row in volts)
    reply = p.ReplyBatch(7, stamps, pos, volts, p.FLAG_TARGET_FAULT)
    assert p.unpack_reply_batch(p.pack_reply_batch(reply)) == reply


def test_version1_is_unchanged_and_refuses_version2_with_a_hint():
    v1 = p.pack_command(p.Command(7, 1_500_000_000, (12.5,)))
    assert v1.hex() == ('505a52470101010007000000000000000' '02f685900000000'
                        '0000000000002940')
    assert p.datagram_version(v1) == 1
    v2 = p.pack_command_batch(p.CommandBatch(7, (1_500_000_000,), ((12.5,),)))
    with pytest.raises(p.DatagramError, match='version 2 .*unpack_\\*_batch'):
        p.unpack_command(v2)
    with pytest.raises(p.DatagramError, match='version 1 where 2'):
        p.unpack_command_batch(v1 + bytes(8))


GOOD = p.pack_command_batch(p.CommandBatch(1, (T0, T0 + DT), ((1.0,), (2.0,))))


@pytest.mark.parametrize('data, reason', [
    (GOOD[:31], 'shorter than the 32-byte'),
    (GOOD[:-1], 'need exactly'),
    (GOOD + bytes(8), 'need exactly'),
    (GOOD[:24] + b'\x00\x00' + GOOD[26:], '0 samples'),
    (GOOD[:24] + (p.MAX_SAMPLES + 1).to_bytes(2, 'little') + GOOD[26:], 'samples; a version-2'),
    (GOOD[:16] + (T0 + 1).to_bytes(8, 'little') + GOOD[24:], 'header stamp'),
    (GOOD[:-8] + np.float64(np.nan).tobytes(), 'not finite'),
    (GOOD[:5] + b'\x02' + GOOD[6:], 'kind 2 where kind 1'),
])
def test_malformed_version2_datagrams_are_refused_with_a_reason(data, reason):
    with pytest.raises(p.DatagramError, match=reason):
        p.unpack_command_batch(data)


def test_packing_refuses_ragged_or_oversized_batches():
    with pytest.raises(p.DatagramError, match='axes in one datagram'):
        p.pack_command_batch(p.CommandBatch(1, (1, 2), ((1.0,), (1.0, 2.0))))
    with pytest.raises(p.DatagramError, match='samples; a version-2'):
        p.pack_command_batch(p.CommandBatch(1, tuple(range(p.MAX_SAMPLES + 1)),
                                            ((0.0,),) * (p.MAX_SAMPLES + 1)))
    with pytest.raises(p.DatagramError, match='2 stamps but 1'):
        p.pack_command_batch(p.CommandBatch(1, (1, 2), ((1.0,),)))


class Wire:
    """The driver's send(): keeps the datagrams it was given."""

    def __init__(self):
        self.sent = []

    def __call__(self, data):
        self.sent.append(data)


def make(version, **kw):
    cfg = {'sample_rate': 20000.0, 'max_slew_rate': 1e9, 'reply_timeout': 1.0,
           'protocol_version': version}
    cfg.update(kw)
    wire = Wire()
    return RigDriver(DriverConfig(**cfg), wire), wire


def test_protocol_version_is_checked():
    with pytest.raises(ConfigError, match='protocol_version must be one of'):
        DriverConfig(protocol_version=3).validate()


def test_a_batch_goes_out_in_one_version2_datagram_and_comes_back_sample_by_sample():
    driver, wire = make(2)
    volts = np.array([[1.0], [np.nan], [3.0], [2000.0]])     # a NaN and one beyond v_max
    stamps = [T0, T0 + DT, T0 + 2 * DT, T0 + 5 * DT]         # and a stamp gap
    sent = driver.command_batch(volts, stamps, now=0.0)
    assert sent[:, 0].tolist() == [1.0, 3.0, 200.0]
    assert driver.counts['commands_rejected'] == 1 and driver.counts['commands_clamped'] == 1
    assert len(wire.sent) == 1
    cmd = p.unpack_command_batch(wire.sent[0])
    assert cmd.stamps_ns == (T0, T0 + 2 * DT, T0 + 5 * DT)
    rig = FakeRig(port=0, seed=3, fs=20000.0)
    try:
        samples = driver.receive_batch(rig.handle(wire.sent[0]), now=0.001)
    finally:
        rig.close()
    assert [s.stamp_ns for s in samples] == list(cmd.stamps_ns)
    assert cmd.volts == ((1.0,), (3.0,), (200.0,)) and rig.commands == 3 and rig.filled == 3
    assert driver.counts['replies'] == 1 and driver.counts['samples_answered'] == 3
    # A repeated reply (same seq) is a duplicate, as in version 1: nothing published twice.
    again = p.pack_reply_batch(p.ReplyBatch(cmd.seq, cmd.stamps_ns,
                                            tuple((0.0,) for _ in cmd.stamps_ns), cmd.volts))
    assert driver.receive_batch(again, 0.002) == []
    assert driver.counts['replies_duplicate'] == 1


def test_version1_driver_sends_one_datagram_per_sample_of_a_batch():
    driver, wire = make(1)
    driver.command_batch(np.array([[1.0], [2.0], [3.0]]), [T0, T0 + DT, T0 + 2 * DT], 0.0)
    assert [p.unpack_command(d).volts for d in wire.sent] == [(1.0,), (2.0,), (3.0,)]


def test_batches_larger_than_a_datagram_are_split():
    driver, wire = make(2)
    n = p.MAX_SAMPLES + 10
    driver.command_batch(np.zeros((n, 1)), [T0 + k * DT for k in range(n)], 0.0)
    counts = [len(p.unpack_command_batch(d).stamps_ns) for d in wire.sent]
    assert counts == [p.MAX_SAMPLES, 10]


def test_pings_of_both_versions_negotiate_what_the_target_speaks():
    for rig_speaks_2, expected in ((True, {1, 2}), (False, {1})):
        driver, wire = make(1)
        driver.ping(0.0, T0, version=2)
        driver.ping(0.0, T0, version=1)
        rig = FakeRig(port=0, seed=0)
        try:
            for data in wire.sent:
                if not rig_speaks_2 and p.datagram_version(data) == 2:
                    continue             # a version-1 target drops what it cannot read
                driver.receive_batch(rig.handle(data), 0.001)
        finally:
            rig.close()
        assert driver.versions_seen == expected
        driver.use_version(max(driver.versions_seen))
        assert driver.version == max(expected)
        # The unanswered version-2 ping is no reply timeout: the target just does not speak it.
        driver.tick(10.0)
        assert driver.counts['reply_timeouts'] == 0


def test_fake_rig_answers_version2_exactly_as_version1_including_a_gap():
    """The same commands, one datagram each or in batches: the same plant outputs, bit for bit."""
    rng = np.random.default_rng(1)
    u = rng.uniform(-100, 100, 60)
    keep = [k for k in range(60) if not 20 <= k < 27]          # 7 samples lost upstream
    stamps = [T0 + k * DT for k in keep]
    one, batched = FakeRig(port=0, seed=5, fs=20000.0), FakeRig(port=0, seed=5, fs=20000.0)
    try:
        v1 = [p.unpack_reply(one.handle(p.pack_command(p.Command(i, t, (u[k],)))))
              for i, (k, t) in enumerate(zip(keep, stamps))]
        v2 = []
        for i in range(0, len(keep), 8):
            raw = batched.handle(p.pack_command_batch(p.CommandBatch(
                i, tuple(stamps[i:i + 8]), tuple((u[k],) for k in keep[i:i + 8]))))
            v2.append(p.unpack_reply_batch(raw))
        ping = p.unpack_reply_batch(batched.handle(p.pack_command_batch(p.CommandBatch(
            999, (T0,), ((0.0,),), p.FLAG_PING))))
    finally:
        one.close()
        batched.close()
    assert [r.stamp_ns for r in v1] == [t for r in v2 for t in r.stamps_ns] == stamps
    assert [r.position_m for r in v1] == [pos for r in v2 for pos in r.position_m]
    assert one.filled == batched.filled == 7 and batched.commands == len(keep)
    assert ping.position_m[0] == v1[-1].position_m                  # a ping steps nothing
    plant = PiezoCantilever(load_plant_params(), fs=20000.0, seed=5)
    ref = [plant.step(u[k] if k in keep else u[19])[0] for k in range(60)]
    assert [r.position_m[0] for r in v1] == [ref[k] for k in keep]
