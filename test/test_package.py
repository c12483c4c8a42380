"""Package layout checks: the pieces `ros2 run` and colcon rely on are present and consistent."""
import re
import xml.etree.ElementTree as ET

from conftest import REPO


def test_package_xml_declares_runtime_dependencies():
    root = ET.parse(REPO / 'package.xml').getroot()
    assert root.get('format') == '3'
    assert root.findtext('name') == 'piezo_narx_ros'
    deps = {e.text for e in root.findall('exec_depend')}
    assert {'rclpy', 'std_msgs', 'sensor_msgs', 'diagnostic_msgs'} <= deps
    assert root.find('export/build_type').text == 'ament_python'


def test_setup_declares_every_node_entry_point():
    text = (REPO / 'setup.py').read_text()
    for name in ('command_node', 'simulator_node', 'driver_node', 'estimator_node',
                 'recorder_node', 'player_node', 'piezo-narx'):
        assert re.search(rf"'{name} = piezo_narx_ros\.[\w.]+:main'", text), name
    assert (REPO / 'resource' / 'piezo_narx_ros').is_file()
    cfg = (REPO / 'setup.cfg').read_text()
    assert 'script_dir=$base/lib/piezo_narx_ros' in cfg
    assert 'install_scripts=$base/lib/piezo_narx_ros' in cfg
