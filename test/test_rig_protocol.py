"""Datagram format: exact bytes, round trips, and rejection of malformed datagrams."""
import struct

import pytest

from piezo_narx_ros.errors import DataError
from piezo_narx_ros.rig import protocol as p


def test_command_bytes_are_the_documented_layout():
    data = p.pack_command(p.Command(seq=7, stamp_ns=1_500_000_000, volts=(12.5, -3.0), flags=1))
    assert len(data) == 24 + 16 == p.command_size(2)
    assert data[:4] == b'PZRG'
    assert data[4] == 1 and data[5] == 1                      # version, kind = command
    assert struct.unpack_from('<H', data, 6) == (2,)          # n_axes
    assert struct.unpack_from('<I', data, 8) == (7,)          # seq
    assert struct.unpack_from('<I', data, 12) == (1,)         # flags
    assert struct.unpack_from('<q', data, 16) == (1_500_000_000,)
    assert struct.unpack_from('<2d', data, 24) == (12.5, -3.0)


def test_reply_interleaves_metres_and_volts_per_axis():
    data = p.pack_reply(p.Reply(seq=9, stamp_ns=-5, position_m=(1e-6, 2e-6),
                                applied_volts=(10.0, 20.0)))
    assert len(data) == p.reply_size(2) == 24 + 32
    assert data[5] == 2
    assert struct.unpack_from('<4d', data, 24) == (1e-6, 10.0, 2e-6, 20.0)
    r = p.unpack_reply(data, n_axes=2)
    assert (r.seq, r.stamp_ns) == (9, -5)
    assert (r.position_m, r.applied_volts) == ((1e-6, 2e-6), (10.0, 20.0))


def test_round_trip_keeps_float64_exactly():
    volts = (0.1 + 0.2, -199.99999999999997)
    c = p.unpack_command(p.pack_command(p.Command((1 << 32) - 1, 2**62, volts)))
    assert c.volts == volts and c.seq == (1 << 32) - 1 and c.stamp_ns == 2**62


GOOD = p.pack_command(p.Command(1, 0, (1.0,)))


@pytest.mark.parametrize('data, reason', [
    (b'', 'shorter'),
    (GOOD[:23], 'shorter'),
    (b'XXXX' + GOOD[4:], 'magic'),
    (GOOD[:4] + b'\x02' + GOOD[5:], 'version'),
    (GOOD[:5] + b'\x02' + GOOD[6:], 'kind'),
    (GOOD + b'\x00', 'exactly'),
    (GOOD[:-1], 'exactly'),
    (GOOD[:6] + b'\x00\x00' + GOOD[8:], 'axes'),
    (GOOD[:24] + struct.pack('<d', float('nan')), 'not finite'),
])
def test_malformed_command_is_rejected_with_a_reason(data, reason):
    with pytest.raises(DataError, match=reason):
        p.unpack_command(data)


def test_axis_count_mismatch_and_reply_for_command_rejected():
    with pytest.raises(p.DatagramError, match='2 were expected'):
        p.unpack_command(GOOD, n_axes=2)
    with pytest.raises(p.DatagramError, match='kind'):
        p.unpack_reply(GOOD)


def test_pack_refuses_values_a_target_cannot_represent():
    with pytest.raises(p.DatagramError, match='uint32'):
        p.pack_command(p.Command(1 << 32, 0, (0.0,)))
    with pytest.raises(p.DatagramError, match='finite'):
        p.pack_command(p.Command(0, 0, (float('inf'),)))
    with pytest.raises(p.DatagramError, match='axes'):
        p.pack_command(p.Command(0, 0, ()))
    with pytest.raises(p.DatagramError, match='applied'):
        p.pack_reply(p.Reply(0, 0, (1.0,), ()))


def test_example_in_docs_driver_md_is_what_pack_produces():
    doc = (p.__file__.rsplit('/piezo_narx_ros/', 1)[0] + '/docs/driver.md')
    hex_line = next(line for line in open(doc) if line.startswith('50 5a 52 47'))
    assert bytes.fromhex(hex_line.replace(' ', '').strip()) == \
        p.pack_command(p.Command(7, 1_500_000_000, (12.5,)))
