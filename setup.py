"""
ament_python package definition for piezo_narx_ros.

Installs the same way under colcon (data_files land in share/, scripts in lib/piezo_narx_ros for
`ros2 run`) and with pip into a virtual environment (console scripts in bin/).
"""
from glob import glob

from setuptools import find_packages, setup

package_name = 'piezo_narx_ros'

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(include=[package_name, package_name + '.*']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        ('share/' + package_name + '/config', glob('config/*.yaml') + ['config/fastdds.xml']),
        ('share/' + package_name + '/launch', glob('launch/*.launch.yaml')),
    ],
    include_package_data=True,
    # Runtime libraries. The ROS 2 client libraries are not listed: in a ROS install they come from
    # the distribution; on a bare machine requirements.txt brings the PyPI wheels.
    install_requires=[
        'numpy', 'scipy', 'h5py', 'numba', 'pyyaml', 'matplotlib', 'tqdm',
        'rosbags', 'mcap', 'mcap-ros2-support', 'optuna',
    ],
    # 'test' is what makes `colcon test` run pytest (without it colcon falls back to unittest,
    # which finds none of these tests and reports success), as ament_python templates declare it.
    extras_require={'test': ['pytest'], 'train': ['torch']},
    zip_safe=True,
    maintainer='piezo_narx_ros developers',
    maintainer_email='dev@piezo-narx-ros.invalid',
    description=('NARX identification of piezo hysteresis and a ROS 2 free-run deflection '
                 'estimator'),
    license='Apache-2.0',
    entry_points={
        'console_scripts': [
            'piezo-narx = piezo_narx_ros.cli.main:main',
            'command_node = piezo_narx_ros.nodes.command_node:main',
            'simulator_node = piezo_narx_ros.nodes.simulator_node:main',
            'driver_node = piezo_narx_ros.nodes.driver_node:main',
            'estimator_node = piezo_narx_ros.nodes.estimator_node:main',
            'controller_node = piezo_narx_ros.nodes.controller_node:main',
            'recorder_node = piezo_narx_ros.nodes.recorder_node:main',
            'player_node = piezo_narx_ros.nodes.player_node:main',
            'fake_rig = piezo_narx_ros.rig.fake_rig:main',
        ],
    },
)
