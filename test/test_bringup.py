"""
piezo-narx bringup.

ROS 2 YAML launch files (the subset it reads, the command lines launch_ros would build), prefixed
logs, clean stop on SIGTERM, failing node.
"""
import os
import re
import signal
import subprocess
import sys
import time

import pytest

from piezo_narx_ros.cli.bringup import Bringup, NodeSpec, load_launch
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


def test_launch_file_becomes_the_command_lines_launch_ros_builds(tmp_path):
    (tmp_path / 'sim.yaml').write_text('/**:\n  ros__parameters:\n    seed: 3\n')
    launch = tmp_path / 'b.launch.yaml'
    launch.write_text(
        'launch:\n'
        '- arg: {name: ns, default: rig2}\n'
        '- arg: {name: fs, default: "5000"}\n'
        '- arg: {name: with_cmd, default: "true"}\n'
        '- let: {name: out, value: $(var ns)_d}\n'
        '- node:\n'
        '    pkg: piezo_narx_ros\n'
        '    exec: simulator_node\n'
        '    namespace: $(var ns)\n'
        '    output: screen\n'
        '    param:\n'
        '    - from: $(dirname)/sim.yaml\n'
        '    - {name: axes, value: [x, y]}\n'
        '    - {name: fs, value: $(var fs)}\n'
        '    - {name: plant_params, value: ""}\n'
        '    remap: [{from: deflection, to: /$(var out)}]\n'
        '- node: {pkg: piezo_narx_ros, exec: command_node, name: cmd, if: $(var with_cmd),\n'
        '         env: [{name: PIEZO_NARX_EXECUTOR, value: single}]}\n'
        '- node: {pkg: piezo_narx_ros, exec: estimator_node, unless: $(var with_cmd)}\n'
        '- executable: {cmd: "$(exec-in-pkg fake_rig piezo_narx_ros) --port 5", name: rig}\n')
    specs = load_launch(launch, {'fs': '2000.0'}, {'cmd': {'kind': 'sine'}})
    assert [s.name for s in specs] == ['simulator_node', 'cmd', 'rig']
    a = specs[0].argv
    assert a[3] == 'piezo_narx_ros.nodes.simulator_node'
    assert a[4:] == ['--ros-args', '-r', '__ns:=/rig2',
                     '--params-file', str(tmp_path / 'sim.yaml'),
                     # y quoted: rcl reads a bare y as a boolean and refuses the list
                     '-p', "axes:=[x, 'y']", '-p', 'fs:=2000.0', '-p', "plant_params:=''",
                     '-r', 'deflection:=/rig2_d']
    b = specs[1].argv
    assert b[4:] == ['--ros-args', '-r', '__node:=cmd', '-p', 'kind:=sine']
    assert specs[1].env == {'PIEZO_NARX_EXECUTOR': 'single'}
    assert specs[2].argv[3:] == ['piezo_narx_ros.rig.fake_rig', '--port', '5']


def test_package_launch_files_are_found_by_name_and_take_arguments():
    specs = load_launch('estimate.launch.yaml', {'model': 'm.json', 'namespace': 'other'})
    assert [s.name for s in specs] == ['simulator_node', 'estimator_node', 'command_node']
    est = specs[1].argv
    assert '-p' in est and 'model:=m.json' in est and '__ns:=/other' in est
    assert any(a.endswith('config/estimator_node.yaml') for a in est)
    rig = load_launch('rig.launch.yaml', {'fake_rig': 'false', 'target_host': '10.1.2.3'})
    assert [s.name for s in rig] == ['driver_node', 'command_node']
    assert 'target_host:=10.1.2.3' in rig[0].argv
    ctl = load_launch('control.launch.yaml', {'model': 'm.json', 'mode': 'linear'})
    assert [s.name for s in ctl] == ['simulator_node', 'controller_node', 'command_node']
    assert 'model:=m.json' in ctl[1].argv and 'mode:=linear' in ctl[1].argv
    assert 'output:=position' in ctl[2].argv
    assert all(s.argv[0] == sys.executable for s in ctl)          # launch_prefix '' = none
    rt = load_launch('control.launch.yaml', {'model': 'm.json', 'launch_prefix': 'chrt -f 80'})
    assert all(s.argv[:4] == ['chrt', '-f', '80', sys.executable] for s in rt)


BASE = 'launch:\n- node: {pkg: piezo_narx_ros, exec: command_node}\n'


@pytest.mark.parametrize('text, args, fragment', [
    ('nodes: []', {}, 'one key `launch:`'),
    ('launch:\n- node: {pkg: piezo_narx_ros, exec: rm}', {}, 'exec must be one of'),
    ('launch:\n- node: {pkg: other_pkg, exec: talker}', {}, 'only piezo_narx_ros nodes'),
    ('launch:\n- node: {pkg: piezo_narx_ros, exec: command_node, colour: red}', {},
     'unknown attribute(s) colour'),
    ('launch:\n- include: {file: x.launch.yaml}', {}, "action 'include' is not supported"),
    ('launch:\n- node: {pkg: piezo_narx_ros, exec: command_node, param: [{from: none.yaml}]}',
     {}, 'parameter file not found'),
    ('launch:\n- node: {pkg: piezo_narx_ros, exec: command_node, namespace: $(var ns)}', {},
     '$(var ns) is not defined'),
    ('launch:\n- node: {pkg: piezo_narx_ros, exec: command_node, name: $(anon x)}', {},
     'substitution $(anon x) is not supported'),
    ('launch:\n- arg: {name: model}\n', {}, "launch argument 'model' is required"),
    (BASE, {'modle': 'x'}, 'no launch argument modle'),
    (BASE + BASE[8:], {}, 'two processes named'),
    ('launch:\n- node: {pkg: piezo_narx_ros, exec: fake_rig}', {}, 'executable action'),
    ('launch: [', {}, 'not valid YAML'),
    ('launch:\n- node: {pkg: piezo_narx_ros, exec: command_node, launch-prefix: no_such_cmd}',
     {}, "launch-prefix of command_node: no executable 'no_such_cmd' on PATH"),
])
def test_bad_launch_file_refused_with_one_line(tmp_path, text, args, fragment):
    launch = tmp_path / 'b.launch.yaml'
    launch.write_text(text)
    with pytest.raises(ConfigError) as info:
        load_launch(launch, args)
    assert fragment in str(info.value) and '\n' not in str(info.value)


def test_unknown_override_and_missing_file_exit_2():
    p = _bringup('sim.launch.yaml', '--param', 'nobody.x=1')
    _, err = p.communicate(timeout=60)
    assert p.returncode == 2 and 'nobody' in err and len(err.strip().splitlines()) == 1
    p = _bringup('/nonexistent/b.launch.yaml')
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


def _nice(pid):
    with open(f'/proc/{pid}/stat') as f:
        return int(f.read().rsplit(')', 1)[1].split()[16])     # field 19: nice


def test_sim_bringup_runs_prefixes_logs_and_stops_all_on_sigterm(tmp_path):
    from piezo_narx_ros.estimator.toy import toy_narx
    from piezo_narx_ros.ident.model_io import save_model
    model = save_model(toy_narx(), tmp_path / 'toy.json')
    # launch_prefix runs each node under a command (here nice; chrt -f for real-time priority):
    # the node is that command's process, so the stop below still reaches it.
    p = _bringup('estimate.launch.yaml', f'model:={model}', 'launch_prefix:=nice -n 5')
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
    running = [int(x) for x in re.findall(r'\(pid (\d+)\)', ''.join(lines))]
    niceness = [_nice(pid) for pid in running]
    p.send_signal(signal.SIGTERM)
    out, err = p.communicate(timeout=30)
    text = ''.join(lines) + out
    assert p.returncode == 0, err
    pids = [int(x) for x in re.findall(r'\(pid (\d+)\)', text)]
    assert len(pids) == 3 and not any(_alive(pid) for pid in pids)
    assert niceness == [_nice(os.getpid()) + 5] * 3
    assert 'stopped (simulator_node=0, estimator_node=0, command_node=0)' in text
    assert re.search(r'\[estimator_node\] \[INFO\] .*toy\.json', text)


def test_node_dying_stops_the_rest_and_exits_nonzero(tmp_path):
    p = _bringup('estimate.launch.yaml', f'model:={tmp_path / "missing.json"}', '--duration',
                 '60')
    out, err = p.communicate(timeout=90)
    assert p.returncode == 1
    assert 'estimator_node exited unexpectedly with code 2' in err
    assert re.search(r'\[estimator_node\] estimator_node: error: .*missing\.json', out)
    pids = [int(x) for x in re.findall(r'\(pid (\d+)\)', out)]
    assert len(pids) == 3 and not any(_alive(pid) for pid in pids)
