"""
Fault suite, bags.

A live recording is not repaired under the recorder's feet, the paired rate is the command rate
with dropped samples reported, an unreadable metadata.yaml is handled the same way by export and
repair, `bag info` counts every message, and `bag export --out` writes the file it names.

Covers issue 10 items 7-10 (item 6, SIGHUP, is in test_faults_nodes.py).
"""
import os
import subprocess
import sys

import numpy as np
import pytest

from piezo_narx_ros.bag.reader import bag_info, read_uy_report
from piezo_narx_ros.bag.repair import repair_bag
from piezo_narx_ros.bag.writer import JOINT_STATE, BagWriter, joint_state_cdr, write_uy_bag
from piezo_narx_ros.cli.main import main
from piezo_narx_ros.errors import BagError

T = 500_000  # ns, 2 kHz
T0 = 1_700_000_000_000_000_000


def cli(argv, capsys):
    with pytest.raises(SystemExit) as exc:
        main(argv)
    out = capsys.readouterr()
    return exc.value.code, out.out, out.err


def uy_bag(path, n, keep_deflection):
    """Command samples 0..n-1 and deflection only where keep_deflection(k)."""
    with BagWriter(path) as bag:
        c = bag.add_topic('piezo/voltage_command', JOINT_STATE)
        d = bag.add_topic('piezo/deflection', JOINT_STATE)
        for k in range(n):
            t = T0 + k * T
            bag.write(c, t + 1000, joint_state_cdr(t, ('x',), effort=(float(k),)))
            if keep_deflection(k):
                bag.write(d, t + 2000, joint_state_cdr(t, ('x',), position=(k * 1e-9,)))
    return path


# --------------------------------------------------------------------- live recording (item 7)
LIVE_WRITER = """
import sys, time
from piezo_narx_ros.bag.writer import JOINT_STATE, BagWriter, joint_state_cdr
bag = BagWriter(sys.argv[1], chunk_period_s=0.05)
c = bag.add_topic('piezo/voltage_command', JOINT_STATE)
for k in range(200):
    bag.write(c, k, joint_state_cdr(k, ('x',), effort=(1.0,)))
bag.flush()
print('recording', flush=True)
sys.stdin.readline()          # keeps recording until told to stop
bag.close()
"""


def test_repair_refuses_a_bag_that_is_being_recorded(tmp_path, capsys):
    path = tmp_path / 'live'
    proc = subprocess.Popen([sys.executable, '-c', LIVE_WRITER, str(path)],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    try:
        assert proc.stdout.readline().strip() == 'recording'
        before = sorted(p.name for p in path.iterdir())
        size = (path / 'live.mcap').stat().st_size
        code, _, err = cli(['bag', 'repair', str(path)], capsys)
        assert code == 2 and 'is being recorded right now' in err and err.count('\n') == 1
        assert sorted(p.name for p in path.iterdir()) == before    # nothing moved aside
        assert (path / 'live.mcap').stat().st_size == size
        code, _, err = cli(['bag', 'info', str(path)], capsys)
        assert code == 2 and 'being recorded right now' in err
        proc.stdin.write('stop\n')
        proc.stdin.flush()
        assert proc.wait(30) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    assert repair_bag(path).intact                       # closed: readable, nothing to do
    assert bag_info(path).message_count == 200


def test_lock_is_released_when_the_recorder_dies(tmp_path):
    path = tmp_path / 'killed'
    proc = subprocess.Popen([sys.executable, '-c', LIVE_WRITER, str(path)],
                            stdin=subprocess.PIPE, stdout=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == 'recording'
    proc.kill()
    proc.wait()
    rep = repair_bag(path)                               # SIGKILL: the OS dropped the lock
    assert not rep.intact and rep.messages == 200


# ----------------------------------------------------------- paired rate, drops (item 8)
def test_deflection_missing_every_other_sample_keeps_the_command_rate(tmp_path, capsys):
    bag = uy_bag(tmp_path / 'half', 2000, lambda k: k % 2 == 0)
    rec, report = read_uy_report(bag)
    assert rec.fs == 2000.0 and len(rec.u) == 1000           # not a 1000 Hz record
    assert report.dropped_deflection == 999
    text = ' | '.join(report.issues())
    assert 'deflection misses 999 of 2000 command samples' in text
    code, out, err = cli(['bag', 'export', str(bag), '--out', str(tmp_path / 'h.npz')], capsys)
    assert code == 0 and 'at 2000 Hz' in out and 'misses 999 of 2000' in err
    with np.load(tmp_path / 'h.npz') as z:
        assert float(z['fs']) == 2000.0


def test_deflection_stopping_halfway_is_reported(tmp_path):
    bag = uy_bag(tmp_path / 'stop', 2000, lambda k: k < 1000)
    rec, report = read_uy_report(bag)
    assert len(rec.u) == 1000 and report.tail_trimmed == 1000
    assert any('deflection ends 0.5 s (1000 command samples) before the command stream' in line
               for line in report.issues())


# ------------------------------------------------------------ metadata.yaml (item 9)
@pytest.mark.parametrize('text', [b'\x00\x01 not: [yaml\n', b'foo: 1\n', b'\xff\xfe\xfa'])
def test_unreadable_metadata_export_and_repair_agree(tmp_path, capsys, text):
    bag = write_uy_bag(tmp_path / 'b', np.arange(300.0), np.arange(300.0) * 1e-9, 2000.0)
    mcap_bytes = (bag / 'b.mcap').read_bytes()
    (bag / 'metadata.yaml').write_bytes(text)
    code, _, err = cli(['bag', 'export', str(bag), '--out', str(tmp_path / 'e.npz')], capsys)
    assert code == 2 and err.count('\n') == 1 and 'piezo-narx bag repair' in err
    code, out, _ = cli(['bag', 'repair', str(bag)], capsys)
    assert code == 0 and out.startswith(f'rebuilt {bag}/metadata.yaml') and 'intact' in out
    assert (bag / 'b.mcap').read_bytes() == mcap_bytes        # the complete file is untouched
    assert (bag / 'metadata.yaml.damaged').read_bytes() == text
    code, out, _ = cli(['bag', 'export', str(bag), '--out', str(tmp_path / 'e.npz')], capsys)
    assert code == 0 and 'wrote' in out and '300 samples' in out


# ---------------------------------------------------------- info counts, export name (item 10)
def test_info_counts_every_message_even_undecodable_ones(tmp_path):
    with BagWriter(tmp_path / 'odd') as bag:
        c = bag.add_topic('piezo/voltage_command', JOINT_STATE)
        for k in range(50):
            good = joint_state_cdr(T0 + k * T, ('x',), effort=(1.0,))
            bag.write(c, T0 + k * T, good if k != 20 else b'\x00\x01junk')
    [topic] = bag_info(tmp_path / 'odd').topics
    assert topic.count == 50 and topic.check is None     # counted, stamps from receive times


def test_export_writes_the_file_it_names(tmp_path, capsys):
    bag = write_uy_bag(tmp_path / 'b', np.sin(np.arange(400.0)), np.arange(400.0) * 1e-9, 2000.0)
    code, out, _ = cli(['bag', 'export', str(bag), '--out', str(tmp_path / 'e.csv')], capsys)
    assert code == 0 and out.startswith(f'wrote {tmp_path / "e.csv"}:')
    assert (tmp_path / 'e.csv').is_file() and not (tmp_path / 'e.csv.npz').exists()
    from piezo_narx_ros.ident.data.loaders import load_record
    rec = load_record(tmp_path / 'e.csv')
    assert rec.fs == pytest.approx(2000.0)
    assert np.array_equal(rec.u[:, 0], np.sin(np.arange(400.0)))
    code, _, err = cli(['bag', 'export', str(bag), '--out', str(tmp_path / 'e.txt')], capsys)
    assert code == 2 and '--out must end in .npz or .csv' in err
    assert not list(tmp_path.glob('e.txt*'))


def test_repair_of_a_non_bag_is_one_line(tmp_path):
    (tmp_path / 'x.mcap').write_bytes(b'not mcap at all')
    with pytest.raises(BagError, match='not an MCAP file'):
        repair_bag(tmp_path / 'x.mcap')


def test_recorder_on_a_full_disk_reports_the_error_and_leaves_a_repairable_bag(tmp_path):
    """
    A full disk: the recorder reports the error and leaves a repairable bag.

    The bag file cannot grow past 200 kB (RLIMIT_FSIZE; Python ignores SIGXFSZ, so writes fail with
    EFBIG as on a full disk). Before: the writer thread died with a traceback, /diagnostics went on
    saying 'recording' and SIGTERM ended silently. Now: ERROR on /diagnostics while it runs, one
    line at the end, and `bag repair` recovers what was written, in order. Chunks are cut every 50
    ms (about 30 kB at this rate), so several complete ones precede the failed write whatever the
    machine's load; at the default 0.5 s the first full chunk alone can exceed the limit and
    nothing but the first message is recoverable.
    """
    import resource

    from test_estimator_node import Collector, stop
    from test_recorder_node import P, T0, Publisher

    from piezo_narx_ros.bag.reader import iter_raw
    from piezo_narx_ros.bag.repair import repair_bag
    from piezo_narx_ros.nodes.wire import decode_joint_state
    from piezo_narx_ros.nodes.diagnostics import DIAG_ERROR

    def small_files():
        resource.setrlimit(resource.RLIMIT_FSIZE, (200_000, 200_000))
    bag, ns = tmp_path / 'full', '/fulldisk'
    proc = subprocess.Popen(
        [sys.executable, '-m', 'piezo_narx_ros.nodes.recorder_node', '--ros-args', '-r',
         f'__ns:={ns}', '-p', f'output:={bag}', '-p', 'chunk_period_s:=0.05'],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        text=True, preexec_fn=small_files, env=dict(os.environ, PYTHONUNBUFFERED='1'))
    pub, col = Publisher(ns), Collector(ns, (), diagnostics=True)
    try:
        assert pub.wait_matched(), 'recorder never subscribed'
        pub.publish_samples(0, 3000)               # ~600 kB of messages
        assert col.wait_for(lambda: col.diag.get(f'{ns}/recorder_node', (0,))[0]
                            == DIAG_ERROR, 15.0), col.diag
        level, message, values = col.diag[f'{ns}/recorder_node']
        assert message.startswith('writer stopped: ') and 'File too large' in message
        assert proc.poll() is None                  # still running, still answering
    finally:
        pub.close()
        col.close()
        codes = stop([proc])
    err = proc.stderr.read()
    assert codes == [0] and 'Traceback' not in err, err
    [line] = [ln for ln in err.splitlines() if 'error' in ln]
    assert line.startswith('recorder_node: error: writer stopped: [Errno 27] File too large')
    assert f'piezo-narx bag repair {bag}' in line
    repair_bag(bag)
    stamps = {}
    for topic, _, _, data in iter_raw(bag):
        stamps.setdefault(topic, []).append(decode_joint_state(data).t_ns)
    assert sum(map(len, stamps.values())) > 1000     # ~2,000 fit in 200 kB
    for got in stamps.values():     # each topic: the first samples sent, none missing
        assert got == [T0 + k * P for k in range(len(got))]
