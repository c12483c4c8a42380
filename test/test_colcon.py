"""
Build and test the way a ROS user does: `colcon build` and `colcon test` in a workspace.

A copy of this source tree is put in src/ of a temporary workspace and colcon (pinned in
requirements.txt, run from this interpreter's environment, no ROS sourced) builds and tests it.
`colcon test` runs pytest only if setup.py declares it as a test requirement; otherwise it runs
unittest, finds no test and reports success, which is the failure these tests catch.
"""
import ast
import os
import shutil
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

from conftest import REPO
from test_package import NO_ROSDEP_KEY, ROSDEP_KEY

COLCON = Path(sys.executable).parent / 'colcon'
# Not part of a clone: environments, build trees, caches, outputs (as .gitignore lists them).
NOT_IN_A_CLONE = shutil.ignore_patterns(
    '.git', '.venv*', 'build', 'install', 'log', 'mutants', 'reports', 'out', '__pycache__',
    '*.pyc', '*.egg-info', '.pytest_cache', '.mutmut.log', '.coverage')
# The subset `colcon test` runs here: two fast files without DDS or ../shared (~1 s).
SUBSET = ('test/test_package.py', 'test/test_ident_metrics.py')
# Test-only imports and their rosdep keys (the package's own imports: test_package.ROSDEP_KEY).
TEST_ROSDEP_KEY = {'pytest': 'python3-pytest', 'ament_flake8': 'ament_flake8',
                   'ament_pep257': 'ament_pep257', 'mcap_ros2': 'mcap-ros2-support'}


def _workspace(tmp_path):
    """Make a workspace with a clone-like copy of this package in src/; returns it and an env."""
    assert COLCON.is_file(), f'{COLCON} not found: colcon comes from requirements.txt'
    ws = tmp_path / 'ws'
    shutil.copytree(REPO, ws / 'src' / 'piezo_narx_ros', ignore=NOT_IN_A_CLONE)
    env = dict(os.environ, COLCON_HOME=str(tmp_path / 'colcon_home'))   # no user defaults
    # Nothing of an enclosing workspace or colcon run (this suite may itself run under colcon).
    for name in ('AMENT_PREFIX_PATH', 'CMAKE_PREFIX_PATH', 'COLCON_PREFIX_PATH', 'PYTHONPATH',
                 'PYTEST_ADDOPTS', 'COLCON_CURRENT_PREFIX'):
        env.pop(name, None)
    return ws, env


def _colcon(ws, env, *args):
    done = subprocess.run([str(COLCON), *args], cwd=ws, env=env, capture_output=True,
                          text=True, timeout=240)
    assert done.returncode == 0, f'colcon {" ".join(args)}:\n{done.stdout}\n{done.stderr}'
    return done.stdout


def test_colcon_test_runs_the_pytest_suite_and_it_passes(tmp_path):
    ws, env = _workspace(tmp_path)
    _colcon(ws, env, 'build')
    _colcon(ws, env, 'test', '--pytest-args', *SUBSET)
    result = ws / 'build' / 'piezo_narx_ros' / 'pytest.xml'
    assert result.is_file(), ('colcon test ran no pytest (no pytest.xml): does setup.py declare '
                              "extras_require={'test': ['pytest']}?")
    cases = ET.parse(result).getroot().findall('.//testcase')
    assert cases, result.read_text()
    files = {c.get('classname').split('.')[2] for c in cases}   # piezo_narx_ros.test.FILE
    assert files == {Path(f).stem for f in SUBSET}, files   # both files ran, nothing else
    failed = [c.get('name') for c in cases if c.find('failure') is not None
              or c.find('error') is not None]
    assert not failed, failed
    # What a user reads: every test listed, the summary counts them, exit 0 (non-zero on failure).
    shown = _colcon(ws, env, 'test-result', '--all', '--verbose')
    summary = shown.strip().splitlines()[-1]
    assert summary == f'Summary: {len(cases)} tests, 0 errors, 0 failures, 0 skipped', shown


def test_symlink_install_is_what_the_ament_index_finds(tmp_path):
    """
    `colcon build --symlink-install`, then the workspace sourced as a user does.

    The ament index (what `ros2 run` / `ros2 launch` use) resolves the package to the workspace;
    its config and launch files are the very files this code reads (symlinks to the source); the
    executables `ros2 run` looks for are in lib/piezo_narx_ros and run this workspace's code.
    """
    ws, env = _workspace(tmp_path)
    _colcon(ws, env, 'build', '--symlink-install')
    prefix = ws / 'install' / 'piezo_narx_ros'
    probe = (
        'from ament_index_python.packages import get_package_prefix, '
        'get_package_share_directory\n'
        'from pathlib import Path\n'
        'import piezo_narx_ros, piezo_narx_ros.share as s\n'
        'from piezo_narx_ros.cli.bringup import load_launch\n'
        'print(get_package_prefix("piezo_narx_ros"))\n'
        'share = Path(get_package_share_directory("piezo_narx_ros"))\n'
        'print(share)\n'
        'print(Path(piezo_narx_ros.__file__).resolve())\n'
        'for kind, find in (("config", s.config_path), ("launch", s.launch_path)):\n'
        '    names = sorted(p.name for p in (share / kind).iterdir())\n'
        '    assert names, kind\n'
        '    for n in names:\n'
        '        assert (share / kind / n).resolve() == find(n).resolve(), (kind, n)\n'
        'argv = load_launch("sim.launch.yaml")[0].argv\n'
        'params = Path(argv[argv.index("--params-file") + 1])\n'
        'assert params.resolve() == (share / "config" / params.name).resolve(), params\n')
    # `. install/setup.sh` as a user sources it (sh: no bash needed); this interpreter is the one
    # colcon built with, as `python3` is in a ROS install.
    run = subprocess.run(['sh', '-c', '. install/setup.sh && "$0" -c "$1" && '
                          '"$2"/lib/piezo_narx_ros/piezo-narx --help', sys.executable, probe,
                          str(prefix)],
                         cwd=ws, env=env, capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stdout + run.stderr
    found_prefix, share, module = run.stdout.splitlines()[:3]
    assert found_prefix == str(prefix)
    assert share == str(prefix / 'share' / 'piezo_narx_ros')
    assert module == str(ws / 'src' / 'piezo_narx_ros' / 'piezo_narx_ros' / '__init__.py')
    assert 'usage: piezo-narx ' in run.stdout
    scripts = sorted(p.name for p in (prefix / 'lib' / 'piezo_narx_ros').iterdir())
    from test_install import NODES, TOOLS
    assert scripts == sorted(NODES + TOOLS)
    assert all(os.access(prefix / 'lib' / 'piezo_narx_ros' / n, os.X_OK) for n in scripts)


def test_package_xml_declares_what_the_tests_import():
    """`rosdep install` (test_depend) brings everything test/ imports; colcon test needs it."""
    root = ET.parse(REPO / 'package.xml').getroot()
    declared = {e.text for tag in ('exec_depend', 'depend', 'test_depend')
                for e in root.findall(tag)}
    keys = {**ROSDEP_KEY, **TEST_ROSDEP_KEY}
    own = {p.stem for p in (REPO / 'test').glob('*.py')} | {'piezo_narx_ros'}
    missing = {}
    for path in sorted((REPO / 'test').glob('*.py')):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            else:
                continue
            for top in {n.split('.')[0] for n in names}:
                if top in sys.stdlib_module_names or top in own or top in NO_ROSDEP_KEY:
                    continue
                if keys.get(top) not in declared:
                    missing.setdefault(keys.get(top, f'{top} (no rosdep key known)'), path.name)
    assert not missing, f'package.xml lacks <test_depend> for {missing}'
