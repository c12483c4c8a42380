"""
Pairing u and y by header stamp.

Gaps, duplicates, reordering, unmatched ends, irregular rate, both on arrays and through read_uy on
a bag with the same defects.
"""
import numpy as np
import pytest

from piezo_narx_ros.bag.pairing import (PairingReport, StreamCheck, clean_stream, pair_by_stamp,
                                        sample_clock)
from piezo_narx_ros.bag.reader import BagWarning, read_uy, read_uy_report
from piezo_narx_ros.bag.writer import JOINT_STATE, BagWriter, joint_state_cdr
from piezo_narx_ros.errors import BagError

T = 500_000  # ns, 2 kHz
T0 = 1_700_000_000_000_000_000


def _stamps(n):
    return T0 + T * np.arange(n, dtype=np.int64)


def test_clean_stream_sorts_and_drops_repeats_keeping_the_first():
    s = np.array([0, 2, 1, 3, 3, 3, 4]) * T
    v = np.array([0., 2., 1., 3., 3., 9., 4.])
    s2, v2, check = clean_stream(s, v)
    np.testing.assert_array_equal(s2, np.arange(5) * T)
    np.testing.assert_array_equal(v2, [0, 1, 2, 3, 4])
    assert (check.reordered, check.duplicates, check.conflicting) == (1, 2, 1)


def test_clean_stream_of_nothing_and_repeats_with_nan():
    s, v, check = clean_stream(np.array([], dtype=np.int64), np.array([]))
    assert s.size == v.size == 0 and check == StreamCheck()
    # A repeat is conflicting when its value differs from the kept one; NaN repeating NaN is the
    # same value, a number repeating NaN (or NaN a number) is not.
    s, v, check = clean_stream(np.array([1, 1, 2, 2, 3, 3]) * T,
                               np.array([np.nan, np.nan, np.nan, 5.0, 6.0, np.nan]))
    assert (check.duplicates, check.conflicting) == (3, 2)
    np.testing.assert_array_equal(v, [np.nan, np.nan, 6.0])


def test_sample_clock_rate_gaps_and_jitter():
    fs, gaps, jitter = sample_clock(np.array([0, 1000, 2100, 3000]))
    assert (fs, gaps) == (1e6, []) and jitter == pytest.approx(0.1)
    # exactly 1.5 periods is jitter; beyond, a gap of round(d / T) - 1 samples
    assert sample_clock(np.array([0, 1000, 2500, 3500]))[1:] == ([], 0.5)
    assert sample_clock(np.array([0, 1000, 3000, 4000]))[1] == [(pytest.approx(1e-6), 1)]
    # every period a gap of the given nominal one (every other sample lost): no jitter to measure
    assert sample_clock(np.array([0, 2, 4]), period_ns=1) == (1e9, [(0.0, 1), (2e-9, 1)], 0.0)
    with pytest.raises(BagError, match='at least 2 samples'):
        sample_clock(np.array([5]))
    with pytest.raises(BagError, match='do not increase'):
        sample_clock(np.array([7, 7, 7]))


def test_pairing_needs_two_matching_stamps_and_names_the_empty_stream():
    t, u, y, rep = pair_by_stamp(_stamps(2), [1.0, 2.0], _stamps(2), [3.0, 4.0])
    assert t.tolist() == _stamps(2).tolist() and rep.paired == 2 and rep.fs == 2000.0
    for tu, ty, match in ((_stamps(0), _stamps(5), 'no command samples'),
                          (_stamps(5), _stamps(0), 'no deflection samples'),
                          (_stamps(1), _stamps(5), 'only 1 command/deflection stamp')):
        with pytest.raises(BagError, match=match):
            pair_by_stamp(tu, np.ones(tu.size), ty, np.ones(ty.size))


def test_issue_lines_read_as_documented():
    # The lines `bag info`, `fit` and read_uy print: each finding with its figures.
    rep = PairingReport(command=StreamCheck(received=1000, malformed=2, reordered=3),
                        deflection=StreamCheck(received=990, duplicates=4, conflicting=1),
                        command_samples=1000, dropped_deflection=5, interior_unmatched=7,
                        head_trimmed=25, tail_trimmed=30, fs=2000.0,
                        gaps=[(0.25, 3), (0.5, 2)], jitter=0.0625)
    assert rep.issues() == [
        'command: 2 message(s) without the expected value, dropped',
        'command: 3 message(s) arrived out of stamp order, sorted',
        'deflection: 4 duplicate stamp(s) dropped (1 with a different value)',
        'deflection misses 5 of 1000 command samples inside the record (0.5 %); the record keeps '
        'the command rate 2000 Hz and has gaps there',
        '2 deflection sample(s) inside the record have no command with the same stamp, dropped',
        'deflection starts 0.0125 s (25 command samples) after the command stream: the record '
        'is trimmed to the paired part',
        'deflection ends 0.015 s (30 command samples) before the command stream: the record is '
        'trimmed to the paired part',
        '2 gap(s), 5 missing sample(s) in the paired record (first at t=0.25 s, 3 missing): '
        'lagged regressors across a gap join non-adjacent samples',
        'irregular sample rate: periods deviate by up to 6.25% from 1/fs (fs = 2000 Hz)']
    # at the limits nothing is said: 20 trimmed samples (or 1 % of the stream), jitter 5 %,
    # duplicates that repeat the same value say so without a count of conflicts
    quiet = PairingReport(deflection=StreamCheck(duplicates=2), command_samples=3000,
                          head_trimmed=30, tail_trimmed=20, fs=2000.0, jitter=0.05)
    assert quiet.issues() == ['deflection: 2 duplicate stamp(s) dropped']


def test_clean_pairing_has_no_issues():
    t = _stamps(100)
    tt, u, y, rep = pair_by_stamp(t, np.arange(100.), t, -np.arange(100.))
    assert rep.issues() == [] and rep.fs == 2000.0 and rep.paired == 100
    np.testing.assert_array_equal(y, -u)


def test_gap_is_reported_with_its_position_and_size():
    t = _stamps(100)
    keep = np.ones(100, bool)
    keep[40:43] = False  # the deflection lost 3 samples
    _, u, y, rep = pair_by_stamp(t, np.arange(100.), t[keep], np.arange(100.)[keep])
    assert rep.paired == 97 and rep.missing_samples == 3
    assert rep.gaps == [(pytest.approx(39 * T * 1e-9), 3)]
    np.testing.assert_array_equal(u, y)  # pairs stay aligned across the gap
    text = ' '.join(rep.issues())
    assert '1 gap(s), 3 missing' in text
    assert 'deflection misses 3 of 100 command samples inside the record' in text


def test_reordered_and_duplicated_deflection_still_pairs_exactly():
    t = _stamps(50)
    uy = np.arange(50.)
    order = np.arange(50)
    order[[10, 11]] = order[[11, 10]]             # swapped in transit
    ty = np.concatenate([t[order], t[[20]]])      # and one re-delivered
    yv = np.concatenate([uy[order], [uy[20]]])
    _, u, y, rep = pair_by_stamp(t, uy, ty, yv)
    np.testing.assert_array_equal(u, y)
    assert rep.deflection.reordered == 2 and rep.deflection.duplicates == 1
    assert rep.deflection.conflicting == 0 and rep.paired == 50 and not rep.gaps


def test_a_few_unmatched_samples_at_the_ends_are_trimmed_silently():
    t = _stamps(60)
    _, u, _, rep = pair_by_stamp(t, np.arange(60.), t[5:58], np.arange(5., 58.))
    assert rep.paired == 53 and rep.unmatched_command == 7 and rep.interior_unmatched == 0
    assert rep.issues() == []
    assert rep.t0_ns == t[5]


def test_irregular_rate_is_reported():
    rng = np.random.default_rng(0)
    t = _stamps(200) + rng.integers(-60_000, 60_000, 200)  # up to ~24 % jitter
    _, _, _, rep = pair_by_stamp(t, np.zeros(200), t, np.zeros(200))
    assert rep.jitter > 0.05
    assert any('irregular sample rate' in line for line in rep.issues())
    fs, gaps, jitter = sample_clock(_stamps(10))
    assert (fs, gaps, jitter) == (2000.0, [], 0.0)


def test_no_common_stamp_is_an_error():
    t = _stamps(20)
    with pytest.raises(BagError, match=r'only 0 command/deflection stamp\(s\) match'):
        pair_by_stamp(t, np.zeros(20), t + 1, np.zeros(20))


def _reference_stream(stamps, values):
    """clean_stream by its definition, one message at a time: {stamp: first value}, counts."""
    kept, counts = {}, {'reordered': 0, 'duplicates': 0, 'conflicting': 0}
    for i, (s, v) in enumerate(zip(stamps.tolist(), values.tolist())):
        counts['reordered'] += i > 0 and s < stamps[i - 1]
        if s in kept:
            counts['duplicates'] += 1
            counts['conflicting'] += not (v == kept[s] or (np.isnan(v) and np.isnan(kept[s])))
        else:
            kept[s] = v
    return kept, counts


def _messy_stream(rng, t, values):
    """
    t/values as a recorder may receive them.

    Samples lost, some re-delivered (some with another value), neighbours swapped in transit.
    """
    keep = rng.random(t.size) > rng.uniform(0.0, 0.3)
    s, v = list(t[keep]), list(values[keep])
    for _ in range(rng.integers(0, 6)):
        i = int(rng.integers(0, len(s)))
        s.insert(i + 1, s[i])
        v.insert(i + 1, v[i] if rng.random() < 0.5 else v[i] + 1.0)
    for _ in range(rng.integers(0, 6)):
        i = int(rng.integers(0, len(s) - 1))
        s[i], s[i + 1], v[i], v[i + 1] = s[i + 1], s[i], v[i + 1], v[i]
    return np.array(s, dtype=np.int64), np.array(v)


def test_pairing_matches_a_message_by_message_reference_on_random_defects():
    """
    Every returned sample and count against a plain-Python pairing of the same messages.

    Lengths equal the number of common stamps, each pair carries the first value received for its
    stamp, and the trimmed, dropped and unmatched counts add up to the inputs.
    """
    rng = np.random.default_rng(8)
    for case in range(40):
        n = int(rng.integers(30, 300))
        t = _stamps(n)
        head, tail = int(rng.integers(0, 25)), int(rng.integers(0, 25))
        tu, u = _messy_stream(rng, t, rng.standard_normal(n))
        ty, y = _messy_stream(rng, t[head:n - tail], rng.standard_normal(n - head - tail))
        if case % 4 == 0:   # deflection stamps no command carries (another writer's clock)
            ty, y = np.r_[ty, t[n // 2] + 7], np.r_[y, 9.0]
        cu, count_u = _reference_stream(tu, u)
        cy, count_y = _reference_stream(ty, y)
        common = sorted(set(cu) & set(cy))
        if len(common) < 2:
            continue
        tt, uu, yy, rep = pair_by_stamp(tu, u, ty, y)
        assert tt.size == uu.size == yy.size == rep.paired == len(common)
        assert tt.tolist() == common
        assert uu.tolist() == [cu[k] for k in common] and yy.tolist() == [cy[k] for k in common]
        first, last = common[0], common[-1]
        inside_u = [k for k in cu if first < k < last and k not in cy]
        inside_y = [k for k in cy if first < k < last and k not in cu]
        assert rep.command_samples == len(cu)
        assert rep.unmatched_command == len(cu) - len(common)
        assert rep.unmatched_deflection == len(cy) - len(common)
        assert rep.head_trimmed == sum(k < first for k in cu)
        assert rep.tail_trimmed == sum(k > last for k in cu)
        assert rep.dropped_deflection == len(inside_u)
        assert rep.interior_unmatched == len(inside_u) + len(inside_y)
        assert rep.unmatched_command == rep.head_trimmed + rep.tail_trimmed + len(inside_u)
        for check, want in ((rep.command, count_u), (rep.deflection, count_y)):
            assert (check.reordered, check.duplicates, check.conflicting) == (
                want['reordered'], want['duplicates'], want['conflicting'])
            assert check.received == check.duplicates + (len(cu) if check is rep.command
                                                         else len(cy))
        assert rep.t0_ns == first and rep.fs == pytest.approx(2000.0)


def test_read_uy_warns_about_defects_in_a_bag(tmp_path):
    """A bag whose deflection lost a sample, got one twice and two out of order."""
    t = _stamps(80).tolist()
    arrivals = list(range(80))
    arrivals.remove(30)                            # lost
    arrivals.insert(50, 49)                        # duplicate of 49
    arrivals[60], arrivals[61] = arrivals[61], arrivals[60]   # reordered
    with BagWriter(tmp_path / 'b') as bag:
        c = bag.add_topic('piezo/voltage_command', JOINT_STATE)
        d = bag.add_topic('piezo/deflection', JOINT_STATE)
        for k in range(80):
            bag.write(c, t[k] + 1000, joint_state_cdr(t[k], ('x',), effort=(float(k),)))
        for i, k in enumerate(arrivals):
            bag.write(d, t[0] + i * T + 2000,
                      joint_state_cdr(t[k], ('x',), position=(k * 1e-6,)))
    with pytest.warns(BagWarning) as caught:
        rec = read_uy(tmp_path / 'b')
    text = ' | '.join(str(w.message) for w in caught)
    assert 'duplicate stamp' in text and 'out of stamp order' in text and 'gap' in text
    assert len(rec.u) == 79
    np.testing.assert_allclose(rec.y, rec.u * 1e-6)
    _, rep = read_uy_report(tmp_path / 'b')
    assert rep.missing_samples == 1 and rep.deflection.duplicates == 1
