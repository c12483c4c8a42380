"""piezo-narx bringup: config parsing, prefixed logs, clean stop on SIGTERM, failing node."""
import os
import re
import signal
import subprocess
import sys
import time

import pytest

from conftest import REPO
from piezo_narx_ros.cli.bringup import Bringup, NodeSpec, load_config
from piezo_narx_ros.errors import ConfigError


def _bringup(*args):
    return subprocess.Popen([sys.executable, '-m', 'piezo_narx_ros.cli.main', 'bringup', *args],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            env=dict(os.environ, PYTHONUNBUFFERED='1'))


def _alive(pid):
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    with open(f'/proc/{pid}/stat') as f:      # a zombie is not running
        return f.read().split()[2] != 'Z'


def test_config_becomes_ros_arguments(tmp_path):
    (tmp_path / 'sim.yaml').write_text('/**:\n  ros__parameters:\n    seed: 3\n')
    cfg = tmp_path / 'b.yaml'
    cfg.write_text('namespace: rig2\nnodes:\n'
                   '  - {executable: simulator_node, params_file: sim.yaml,\n'
                   '     parameters: {axes: [x, y], fs: 5000.0}, remap: {deflection: /d}}\n'
                   '  - {executable: command_node, name: cmd}\n')
    specs = load_config(cfg, {'cmd': {'kind': 'sine'}})
    assert [s.name for s in specs] == ['simulator_node', 'cmd']
    a = specs[0].argv
    i = a.index('--ros-args')
    assert a[i + 1:] == ['-r', '__ns:=/rig2', '--params-file', str(tmp_path / 'sim.yaml'),
                         '-p', 'axes:=[x, y]', '-p', 'fs:=5000.0', '-r', 'deflection:=/d']
    b = specs[1].argv
    assert b[b.index('--ros-args') + 1:] == ['-r', '__ns:=/rig2', '-r', '__node:=cmd',
                                             '-p', 'kind:=sine']


@pytest.mark.parametrize('text, fragment', [
    ('nodes: []', 'non-empty list'),
    ('nodes:\n  - {executable: rm}', 'executable must be one of'),
    ('nodes:\n  - {executable: command_node, colour: red}', 'unknown key(s) colour'),
    ('nodes:\n  - {executable: command_node, params_file: none.yaml}', 'params_file not found'),
    ('nodes:\n  - {executable: command_node}\n  - {executable: command_node}', 'two nodes named'),
    ('nodes: [', 'not valid YAML'),
])
def test_bad_config_refused_with_one_line(tmp_path, text, fragment):
    cfg = tmp_path / 'b.yaml'
    cfg.write_text(text)
    with pytest.raises(ConfigError) as info:
        load_config(cfg)
    assert fragment in str(info.value) and '\n' not in str(info.value)


def test_unknown_override_and_missing_file_exit_2():
    p = _bringup(str(REPO / 'config' / 'bringup_sim.yaml'), '--param', 'nobody.x=1')
    _, err = p.communicate(timeout=60)
    assert p.returncode == 2 and 'nobody' in err and len(err.strip().splitlines()) == 1
    p = _bringup('/nonexistent/b.yaml')
    _, err = p.communicate(timeout=60)
    assert p.returncode == 2 and 'not found' in err


def test_escalates_to_sigkill_for_a_process_that_ignores_signals():
    stubborn = NodeSpec('stubborn', [sys.executable, '-c',
                                     'import signal, time\n'
                                     'signal.signal(signal.SIGINT, signal.SIG_IGN)\n'
                                     'signal.signal(signal.SIGTERM, signal.SIG_IGN)\n'
                                     'print("ready", flush=True)\n'
                                     'time.sleep(60)'])
    import io
    out = io.StringIO()
    b = Bringup([stubborn], out=out, sigint_timeout=0.5, sigterm_timeout=0.5)
    b.start()
    deadline = time.monotonic() + 20
    while 'ready' not in out.getvalue() and time.monotonic() < deadline:
        time.sleep(0.05)
    t = time.monotonic()
    codes = b.stop()
    assert codes == {'stubborn': -signal.SIGKILL}
    assert time.monotonic() - t < 5
    text = out.getvalue()
    assert '[stubborn] ready' in text and 'SIGTERM' in text and 'SIGKILL' in text


def test_sim_bringup_runs_prefixes_logs_and_stops_all_on_sigterm(tmp_path):
    from piezo_narx_ros.estimator.toy import toy_narx
    from piezo_narx_ros.ident.model_io import save_model
    model = save_model(toy_narx(), tmp_path / 'toy.json')
    p = _bringup(str(REPO / 'config' / 'bringup_sim.yaml'), '--param',
                 f'estimator_node.model={model}')
    lines = []
    deadline = time.monotonic() + 60
    while time.monotonic() < deadline:
        line = p.stdout.readline()
        if not line:
            break
        lines.append(line)
        text = ''.join(lines)
        if all(f'[{n}] [INFO]' in text for n in ('command_node', 'simulator_node',
                                                  'estimator_node')):
            break
    time.sleep(1.0)                                # let samples flow
    p.send_signal(signal.SIGTERM)
    out, err = p.communicate(timeout=30)
    text = ''.join(lines) + out
    assert p.returncode == 0, err
    pids = [int(x) for x in re.findall(r'\(pid (\d+)\)', text)]
    assert len(pids) == 3 and not any(_alive(pid) for pid in pids)
    assert 'stopped (simulator_node=0, estimator_node=0, command_node=0)' in text
    assert re.search(r'\[estimator_node\] \[INFO\] .*toy\.json', text)


def test_node_dying_stops_the_rest_and_exits_nonzero(tmp_path):
    p = _bringup(str(REPO / 'config' / 'bringup_sim.yaml'), '--param',
                 f'estimator_node.model={tmp_path / "missing.json"}', '--duration', '60')
    out, err = p.communicate(timeout=90)
    assert p.returncode == 1
    assert 'estimator_node exited unexpectedly with code 2' in err
    assert re.search(r'\[estimator_node\] estimator_node: error: .*missing\.json', out)
    pids = [int(x) for x in re.findall(r'\(pid (\d+)\)', out)]
    assert len(pids) == 3 and not any(_alive(pid) for pid in pids)
