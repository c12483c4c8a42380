"""
An installed (not editable) copy works: it finds its config in share/piezo_narx_ros.

The package is installed from a copy of its own files into a temporary prefix, the way colcon
(`setup.py install`, scripts in lib/piezo_narx_ros) and pip (`pip install --prefix`, scripts in
bin/) do, and the installed simulator_node and fake_rig are started from there with the source
tree out of reach (another working directory, PYTHONPATH on the prefix only).
"""
import os
import shutil
import signal
import subprocess
import sys
import sysconfig
import time

import pytest

from conftest import REPO

FILES = ('setup.py', 'setup.cfg', 'package.xml', 'resource', 'config', 'launch', 'piezo_narx_ros')


def _install(tmp_path, how):
    src, prefix = tmp_path / 'src', tmp_path / 'prefix'
    src.mkdir()
    for name in FILES:
        if (REPO / name).is_dir():
            shutil.copytree(REPO / name, src / name,
                            ignore=shutil.ignore_patterns('__pycache__', '*.pyc'))
        elif (REPO / name).exists():
            shutil.copy2(REPO / name, src / name)
    if how == 'setup.py':   # what colcon's ament_python build does
        cmd = [sys.executable, 'setup.py', '-q', 'install', '--prefix', str(prefix),
               '--single-version-externally-managed', '--record', str(tmp_path / 'files.txt')]
        scripts = prefix / 'lib' / 'piezo_narx_ros'
    else:
        cmd = [sys.executable, '-m', 'pip', 'install', '-q', '--prefix', str(prefix),
               '--ignore-installed', '--no-deps', '--no-build-isolation', '.']
        scripts = prefix / 'bin'
    done = subprocess.run(cmd, cwd=src, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stdout + done.stderr
    shutil.rmtree(src)   # nothing left to fall back on
    site = sysconfig.get_path('purelib', vars={'base': str(prefix), 'platbase': str(prefix)})
    env = dict(os.environ, PYTHONPATH=site, PYTHONUNBUFFERED='1')
    env.pop('AMENT_PREFIX_PATH', None)
    return prefix, scripts, env


def _run_until(argv, env, cwd, marker, timeout=60.0):
    """Start argv, wait for `marker` in its output, SIGINT it; returns (exit code, output)."""
    proc = subprocess.Popen(argv, env=env, cwd=cwd, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True)
    lines, deadline = [], time.monotonic() + timeout
    try:
        while time.monotonic() < deadline:
            line = proc.stdout.readline()
            if not line:
                break
            lines.append(line)
            if marker in line:
                break
        proc.send_signal(signal.SIGINT)
        out, _ = proc.communicate(timeout=30)
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.communicate()
    return proc.returncode, ''.join(lines) + out


@pytest.mark.parametrize('how', ['setup.py', 'pip'])
def test_installed_copy_finds_its_config_and_runs_simulator_and_fake_rig(tmp_path, how):
    prefix, scripts, env = _install(tmp_path, how)
    work = tmp_path / 'elsewhere'
    work.mkdir()
    where = subprocess.run(
        [sys.executable, '-c', 'import piezo_narx_ros.share as s; print(s.__file__); '
         'print(s.share_dir()); print(s.config_path("plant.yaml"))'],
        env=env, cwd=work, capture_output=True, text=True, timeout=60)
    assert where.returncode == 0, where.stderr
    module, share, plant = where.stdout.split()
    assert module.startswith(str(prefix)) and share == str(prefix / 'share' / 'piezo_narx_ros')
    assert plant == str(prefix / 'share' / 'piezo_narx_ros' / 'config' / 'plant.yaml')

    # launch files are installed too, and resolve $(find-pkg-share) to this prefix
    launch = subprocess.run(
        [sys.executable, '-c', 'from piezo_narx_ros.cli.bringup import load_launch; '
         'a = load_launch("sim.launch.yaml")[0].argv; print(a[a.index("--params-file") + 1])'],
        env=env, cwd=work, capture_output=True, text=True, timeout=60)
    assert launch.returncode == 0, launch.stderr
    assert launch.stdout.strip() == str(prefix / 'share' / 'piezo_narx_ros' / 'config' /
                                        'simulator_node.yaml')
    assert (prefix / 'share' / 'piezo_narx_ros' / 'launch' / 'rig.launch.yaml').is_file()
    assert (prefix / 'share' / 'piezo_narx_ros' / 'config' / 'fastdds.xml').is_file()

    code, out = _run_until([str(scripts / 'simulator_node'), '--ros-args', '-r',
                            f'__ns:=/install{os.getpid()}'], env, work, 'simulating')
    assert 'simulating' in out and code == 0, out
    code, out = _run_until([str(scripts / 'fake_rig'), '--port', '0'], env, work, 'listening')
    assert 'listening on 127.0.0.1:' in out and code == 0, out
    _console_scripts_are_installed(prefix, scripts, env, work)
    if how == 'pip':   # one install is enough to start them all (~10 s on the loaded box)
        _every_console_script_starts_its_own_program(scripts, env, work)


# Console scripts the design names (DESIGN.md: nodes runnable as `ros2 run piezo_narx_ros NAME`).
NODES = ('command_node', 'simulator_node', 'driver_node', 'estimator_node', 'controller_node',
         'recorder_node', 'player_node')
TOOLS = ('piezo-narx', 'fake_rig')


def _console_scripts_are_installed(prefix, scripts, env, work):
    """
    Check the console scripts as installed.

    The installed metadata lists exactly the design's scripts, each target loads (a misspelt module
    or function in setup.py fails here), and each script file is where it is run from.
    """
    listed = subprocess.run(
        [sys.executable, '-c', 'from importlib.metadata import distribution\n'
         'd = distribution("piezo_narx_ros")\n'
         'for e in [e for e in d.entry_points if e.group == "console_scripts"]:\n'
         '    assert callable(e.load()), e\n'
         '    print(e.name, d.locate_file(""))'],
        env=env, cwd=work, capture_output=True, text=True, timeout=60)
    assert listed.returncode == 0, listed.stderr
    names = sorted(line.split()[0] for line in listed.stdout.splitlines())
    assert names == sorted(NODES + TOOLS)
    assert all(line.split()[1].startswith(str(prefix)) for line in listed.stdout.splitlines())
    for name in names:
        assert os.access(scripts / name, os.X_OK), name


def _every_console_script_starts_its_own_program(scripts, env, work):
    """
    Each installed script reaches that program's own main.

    A node refuses a retired parameter with `NAME: error: ...` and exit 2 (so the line names the
    node the script started, not just any), the tools print their usage.
    """
    runs = {}
    # In parallel: each start imports rclpy and numba (~1-3 s). The nodes discover each other
    # while they refuse; the installed config/fastdds.xml keeps Fast DDS 3.2 from crashing in
    # that teardown (docs/nodes.md).
    for name in NODES:
        runs[name] = subprocess.Popen(
            [str(scripts / name), '--ros-args', '-r', f'__ns:=/inst{os.getpid()}', '-p',
             'qos_depth:=5'], env=env, cwd=work, stdout=subprocess.PIPE,
            stderr=subprocess.PIPE, text=True)
    for name in TOOLS:
        runs[name] = subprocess.Popen([str(scripts / name), '--help'], env=env, cwd=work,
                                      stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    for name, proc in runs.items():
        try:
            out, err = proc.communicate(timeout=120)
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.communicate()
        if name in NODES:
            assert proc.returncode == 2, (name, out, err)
            assert err.strip().splitlines()[-1].startswith(f'{name}: error: '), (name, err)
            assert 'Traceback' not in err
        else:
            assert proc.returncode == 0 and out.startswith(f'usage: {name} '), (name, out, err)


def test_ament_index_finds_the_installed_prefix(tmp_path):
    """
    With the prefix on AMENT_PREFIX_PATH, `ros2 run`'s lookup resolves the package there.

    As in a sourced workspace; share_dir() agrees.
    """
    prefix, scripts, env = _install(tmp_path, 'setup.py')
    env['AMENT_PREFIX_PATH'] = str(prefix)
    done = subprocess.run(
        [sys.executable, '-c', 'from ament_index_python.packages import get_package_prefix as p; '
         'import piezo_narx_ros.share as s; print(p("piezo_narx_ros")); print(s._ament_index())'],
        env=env, cwd=tmp_path, capture_output=True, text=True, timeout=60)
    assert done.returncode == 0, done.stderr
    assert done.stdout.split() == [str(prefix), str(prefix / 'share' / 'piezo_narx_ros')]
    assert (scripts / 'simulator_node').is_file()   # where `ros2 run` looks: lib/<package>
