"""Bad bags give one-line BagErrors naming the problem; foreign topics do not disturb reading."""
import shutil

import numpy as np
import pytest
from rosbags.rosbag2 import StoragePlugin, Writer

from piezo_narx_ros.bag.reader import bag_info, read_uy
from piezo_narx_ros.bag.writer import JOINT_STATE, BagWriter, joint_state_cdr, write_uy_bag
from piezo_narx_ros.errors import BagError

T0 = 1_700_000_000_000_000_000


def _one_line_error(exc_info):
    text = str(exc_info.value)
    assert '\n' not in text
    return text


@pytest.fixture(scope='module')
def good_bag(tmp_path_factory):
    path = tmp_path_factory.mktemp('err') / 'good'
    write_uy_bag(path, np.linspace(0, 1, 4000), np.linspace(0, 1e-6, 4000), 2000.0)
    return path


@pytest.mark.parametrize('make, expected', [
    (lambda d: d / 'nope', 'bag not found'),
    (lambda d: (d / 'empty').mkdir() or d / 'empty', 'not a rosbag2 bag'),
    (lambda d: (d / 'x.txt').write_text('hi') and d / 'x.txt', 'not a bag'),
    (lambda d: (d / 'junk.mcap').write_bytes(b'\x00' * 64) and d / 'junk.mcap', 'cannot read bag'),
])
def test_not_a_bag(tmp_path, make, expected):
    with pytest.raises(BagError, match=expected) as exc:
        read_uy(make(tmp_path))
    _one_line_error(exc)


def test_truncated_bag_points_to_repair(tmp_path, good_bag):
    bag = shutil.copytree(good_bag, tmp_path / 'cut')
    mcap = bag / 'cut.mcap'
    (bag / 'good.mcap').rename(mcap)
    meta = (bag / 'metadata.yaml').read_text().replace('good.mcap', 'cut.mcap')
    (bag / 'metadata.yaml').write_text(meta)
    data = mcap.read_bytes()
    mcap.write_bytes(data[:len(data) // 2])
    with pytest.raises(BagError, match='piezo-narx bag repair') as exc:
        read_uy(bag)
    _one_line_error(exc)


def test_wrong_topics_lists_what_is_there(good_bag):
    with pytest.raises(BagError, match=r'topic /rig/y not in bag .*topics: /piezo/deflection, '
                       r'/piezo/voltage_command\)') as exc:
        read_uy(good_bag, deflection_topic='rig/y')
    _one_line_error(exc)
    with pytest.raises(BagError, match='must differ'):
        read_uy(good_bag, 'piezo/deflection', '/piezo/deflection')


def test_wrong_type_and_foreign_definition(tmp_path):
    from rosbags.typesys import Stores, get_typestore
    store = get_typestore(Stores.ROS2_KILTED)
    f64 = store.types['std_msgs/msg/Float64']
    with Writer(tmp_path / 'b', version=9, storage_plugin=StoragePlugin.MCAP) as w:
        c = w.add_connection('/piezo/voltage_command', 'std_msgs/msg/Float64', typestore=store)
        d = w.add_connection('/piezo/deflection', JOINT_STATE, msgdef='float64 x\n',
                             rihs01='RIHS01_' + '1' * 64)
        foreign = w.add_connection('/lab/notes', 'my_pkg/msg/Note', msgdef='string text\n',
                                   rihs01='RIHS01_' + '2' * 64)
        w.write(c, T0, bytes(store.serialize_cdr(f64(data=1.0), 'std_msgs/msg/Float64')))
        w.write(d, T0, b'\x00\x01\x00\x00' + b'\x00' * 8)
        w.write(foreign, T0 + 1, b'\x00\x01\x00\x00\x03\x00\x00\x00hi\x00')
    with pytest.raises(BagError, match='/piezo/voltage_command .* has type std_msgs/msg/Float64,'
                       ' expected sensor_msgs/msg/JointState'):
        read_uy(tmp_path / 'b')
    with pytest.raises(BagError, match='/piezo/deflection .*definition differs'):
        read_uy(tmp_path / 'b', command_topic='/piezo/deflection', deflection_topic='/x')
    # info still describes the bag, foreign type included (counted, never decoded)
    by = {t.name: t for t in bag_info(tmp_path / 'b').topics}
    assert by['/lab/notes'].msgtype == 'my_pkg/msg/Note' and by['/lab/notes'].count == 1


def test_foreign_topic_beside_good_data_is_ignored(tmp_path):
    with Writer(tmp_path / 'b', version=9, storage_plugin=StoragePlugin.MCAP) as w:
        from piezo_narx_ros.bag.writer import typestore
        cu = w.add_connection('/piezo/voltage_command', JOINT_STATE, typestore=typestore())
        cy = w.add_connection('/piezo/deflection', JOINT_STATE, typestore=typestore())
        cf = w.add_connection('/lab/notes', 'my_pkg/msg/Note', msgdef='string text\n',
                              rihs01='RIHS01_' + '2' * 64)
        for k in range(10):
            t = T0 + k * 500_000
            w.write(cu, t, joint_state_cdr(t, effort=(k,)))
            w.write(cf, t, b'garbage')
            w.write(cy, t, joint_state_cdr(t, position=(k * 1e-6,)))
    rec = read_uy(tmp_path / 'b')
    np.testing.assert_allclose(rec.y, rec.u * 1e-6)


def test_empty_bag_and_messages_without_values(tmp_path):
    with BagWriter(tmp_path / 'empty') as bag:
        bag.add_topic('piezo/voltage_command', JOINT_STATE)
        bag.add_topic('piezo/deflection', JOINT_STATE)
    with pytest.raises(BagError, match='no command samples on /piezo/voltage_command'):
        read_uy(tmp_path / 'empty')
    with BagWriter(tmp_path / 'noeffort') as bag:
        c = bag.add_topic('piezo/voltage_command', JOINT_STATE)
        d = bag.add_topic('piezo/deflection', JOINT_STATE)
        for k in range(5):
            bag.write(c, T0 + k, joint_state_cdr(T0 + k, position=(1.0,)))   # effort missing
            bag.write(d, T0 + k, joint_state_cdr(T0 + k, position=(1.0,)))
    with pytest.raises(BagError, match=r'5 message\(s\) without effort of its axis'):
        read_uy(tmp_path / 'noeffort')


def test_undecodable_message_is_named(tmp_path):
    with BagWriter(tmp_path / 'b') as bag:
        c = bag.add_topic('piezo/voltage_command', JOINT_STATE)
        bag.add_topic('piezo/deflection', JOINT_STATE)
        bag.write(c, T0 + 5, b'\x00\x01\x00\x00\xff')
    with pytest.raises(BagError, match='cannot decode a sensor_msgs/msg/JointState message on '
                       '/piezo/voltage_command at log time') as exc:
        read_uy(tmp_path / 'b')
    _one_line_error(exc)
