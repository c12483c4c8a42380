"""Package layout checks: the pieces `ros2 run` and colcon rely on are present and consistent."""
import ast
import re
import sys
import xml.etree.ElementTree as ET
from importlib.metadata import packages_distributions

from conftest import REPO

# rosdep key of every third-party module the package imports (keys from ros/rosdistro's
# rosdep/python.yaml; ROS packages are their own key). mcap has no key of its own: the
# mcap-ros2-support key installs it.
ROSDEP_KEY = {
    'rclpy': 'rclpy', 'rcl_interfaces': 'rcl_interfaces', 'sensor_msgs': 'sensor_msgs',
    'diagnostic_msgs': 'diagnostic_msgs', 'std_srvs': 'std_srvs',
    'trajectory_msgs': 'trajectory_msgs',
    'lifecycle_msgs': 'lifecycle_msgs', 'rosgraph_msgs': 'rosgraph_msgs',
    'ament_index_python': 'ament_index_python',
    'numpy': 'python3-numpy', 'scipy': 'python3-scipy', 'h5py': 'python3-h5py',
    'numba': 'python3-numba',
    'yaml': 'python3-yaml', 'matplotlib': 'python3-matplotlib', 'tqdm': 'python3-tqdm',
    'rosbags': 'python3-rosbags-pip', 'mcap': 'mcap-ros2-support', 'torch': 'python3-torch',
}
# Imported only by an optional feature, with no rosdep key to declare (pinned in requirements.txt
# all the same). ray: `fit --executor ray`; optuna: `fit --preset search`. ros/rosdistro's
# rosdep/python.yaml has no key for ray (checked 2026-11), none was found for optuna, and an
# unresolvable <exec_depend> would break `rosdep install`.
NO_ROSDEP_KEY = {'ray', 'optuna'}


def _third_party_imports() -> dict[str, str]:
    """{top-level module: first file importing it} over the installed package's sources."""
    found = {}
    for path in sorted((REPO / 'piezo_narx_ros').rglob('*.py')):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                names = [node.module]
            else:
                continue
            for name in names:
                top = name.split('.')[0]
                if top not in sys.stdlib_module_names and top != 'piezo_narx_ros':
                    found.setdefault(top, str(path.relative_to(REPO)))
    return found


def test_every_import_has_an_exec_depend_and_every_exec_depend_is_imported():
    root = ET.parse(REPO / 'package.xml').getroot()
    declared = {e.text for tag in ('exec_depend', 'depend') for e in root.findall(tag)}
    imports = {m: f for m, f in _third_party_imports().items() if m not in NO_ROSDEP_KEY}
    unmapped = {m: f for m, f in imports.items() if m not in ROSDEP_KEY}
    assert not unmapped, f'imports without a rosdep key (add to ROSDEP_KEY and package.xml): ' \
                         f'{unmapped}'
    missing = {ROSDEP_KEY[m]: f for m, f in imports.items() if ROSDEP_KEY[m] not in declared}
    assert not missing, f'package.xml lacks <exec_depend> for {missing}'
    stale = declared - {ROSDEP_KEY[m] for m in imports}
    assert not stale, f'package.xml declares {sorted(stale)} but nothing imports them'


def test_every_import_is_pinned_in_requirements():
    """A bare machine gets each imported module from the PyPI pin in requirements.txt."""
    pins = {}
    for line in (REPO / 'requirements.txt').read_text().splitlines():
        line = line.split('#')[0].strip()
        if line:
            name, _, version = line.partition('==')
            pins[re.sub(r'[-_.]+', '-', name).lower()] = version
    dists = packages_distributions()
    for module in _third_party_imports():
        names = [re.sub(r'[-_.]+', '-', d).lower() for d in dists.get(module, [])]
        assert names, f'{module} is imported but not installed'
        assert any(pins.get(n) for n in names), f'{module} ({names}) not pinned in requirements'


def test_package_xml_declares_runtime_dependencies():
    root = ET.parse(REPO / 'package.xml').getroot()
    assert root.get('format') == '3'
    assert root.findtext('name') == 'piezo_narx_ros'
    deps = {e.text for e in root.findall('exec_depend')}
    assert {'rclpy', 'sensor_msgs', 'diagnostic_msgs'} <= deps
    assert root.find('export/build_type').text == 'ament_python'


def test_setup_declares_every_node_entry_point():
    text = (REPO / 'setup.py').read_text()
    for name in ('command_node', 'simulator_node', 'driver_node', 'estimator_node',
                 'controller_node', 'recorder_node', 'player_node', 'piezo-narx'):
        assert re.search(rf"'{name} = piezo_narx_ros\.[\w.]+:main'", text), name
    assert (REPO / 'resource' / 'piezo_narx_ros').is_file()
    cfg = (REPO / 'setup.cfg').read_text()
    assert 'script_dir=$base/lib/piezo_narx_ros' in cfg
    assert 'install_scripts=$base/lib/piezo_narx_ros' in cfg
