"""Interrupted recordings: a process killed with SIGKILL, a file cut mid-chunk, and the repair."""
import os
import signal
import subprocess
import sys

import numpy as np
import pytest

from piezo_narx_ros.bag.reader import bag_info, read_joint_series
from piezo_narx_ros.bag.repair import repair_bag
from piezo_narx_ros.bag.writer import JOINT_STATE, BagWriter, joint_state_cdr
from piezo_narx_ros.cli.main import main as cli_main
from piezo_narx_ros.errors import BagError

T0 = 1_700_000_000_000_000_000
TOPIC = '/piezo/voltage_command'

# A recording process: 1000 messages, wait until they are on disk, say so, then keep recording
# until killed.
RECORDER = r"""
import sys, time
from piezo_narx_ros.bag.recorder import BagRecorder
from piezo_narx_ros.bag.writer import joint_state_cdr
rec = BagRecorder(sys.argv[1], chunk_period_s=0.1)
topic = rec.add_topic('piezo/voltage_command', 'sensor_msgs/msg/JointState')
k = 0
def put():
    global k
    rec.put(topic, time.time_ns(), joint_state_cdr(%d + k * 500_000, effort=(k * 1e-3,)))
    k += 1
for _ in range(1000):
    put()
while rec.backlog or rec.stats.written < 1000:
    time.sleep(0.01)
time.sleep(0.4)  # > chunk period: the idle writer has flushed the chunk
print('checkpoint', flush=True)
while True:
    put()
    if k %% 200 == 0:
        time.sleep(0.02)
""" % T0


def _assert_exact_prefix(path, at_least):
    s = read_joint_series(path, {TOPIC: 'effort'})[TOPIC]
    n = s.values.size
    assert n >= at_least
    np.testing.assert_array_equal(s.stamps_ns, T0 + 500_000 * np.arange(n))
    np.testing.assert_allclose(s.values, 1e-3 * np.arange(n), rtol=0, atol=1e-15)
    return n


def test_sigkill_during_recording_then_repair(tmp_path):
    bag = tmp_path / 'killed'
    proc = subprocess.Popen([sys.executable, '-c', RECORDER, str(bag)], stdout=subprocess.PIPE,
                            text=True)
    try:
        assert proc.stdout.readline().strip() == 'checkpoint'
        try:
            proc.wait(0.3)  # keeps recording meanwhile
        except subprocess.TimeoutExpired:
            pass
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.kill()
        proc.wait(10)
    assert not (bag / 'metadata.yaml').exists()   # really killed before closing
    with pytest.raises(BagError, match='bag repair'):
        bag_info(bag)
    rep = repair_bag(bag)
    assert rep.backup.is_file() and (bag / 'metadata.yaml').is_file()
    n = _assert_exact_prefix(bag, at_least=1000)
    assert rep.messages == n == rep.topics[TOPIC]
    assert bag_info(bag).topics[0].count == n


def _multi_chunk_bag(path, n=3000):
    with BagWriter(path) as bag:
        t = bag.add_topic(TOPIC, JOINT_STATE)
        for k in range(n):
            bag.write(t, T0 + k * 500_000, joint_state_cdr(T0 + k * 500_000, effort=(k * 1e-3,)))
            if k % 500 == 499:
                bag.flush()  # one chunk per 500 messages
    return path


def test_file_cut_mid_chunk_is_repaired_via_cli(tmp_path, capsys):
    bag = _multi_chunk_bag(tmp_path / 'cut')
    mcap = bag / 'cut.mcap'
    data = mcap.read_bytes()
    mcap.write_bytes(data[:int(len(data) * 0.55)])  # inside the 4th chunk
    (bag / 'metadata.yaml').unlink()
    with pytest.raises(SystemExit) as code:
        cli_main(['bag', 'repair', str(bag), '--no-backup'])
    assert code.value.code == 0
    out = capsys.readouterr().out
    assert 'message(s) recovered' in out
    n = _assert_exact_prefix(bag, at_least=1000)
    assert n in (1500, 2000)  # whole chunks only
    assert not list(bag.glob('*.damaged'))


def test_repair_leaves_an_intact_bag_alone_and_refuses_non_mcap(tmp_path):
    bag = _multi_chunk_bag(tmp_path / 'ok', n=600)
    before = (bag / 'ok.mcap').read_bytes()
    rep = repair_bag(bag)
    assert rep.intact and rep.messages == 600
    assert (bag / 'ok.mcap').read_bytes() == before
    (tmp_path / 'x.mcap').write_bytes(b'not mcap at all')
    with pytest.raises(BagError, match='not an MCAP file'):
        repair_bag(tmp_path / 'x.mcap')
    header_only = tmp_path / 'h'
    header_only.mkdir()
    (header_only / 'h.mcap').write_bytes(before[:40])
    with pytest.raises(BagError, match='nothing to recover'):
        repair_bag(header_only)


def test_lone_mcap_file_is_repaired_in_place(tmp_path):
    bag = _multi_chunk_bag(tmp_path / 'src', n=1500)
    lone = tmp_path / 'lone.mcap'
    data = (bag / 'src.mcap').read_bytes()
    lone.write_bytes(data[:int(len(data) * 0.8)])
    rep = repair_bag(lone, backup=False)
    assert rep.messages == 1000 and not rep.intact
    assert _assert_exact_prefix(lone, at_least=1000) == 1000
