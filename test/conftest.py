"""
Shared pytest fixtures.

DDS isolation: every test session gets its own ROS_DOMAIN_ID (claimed with a lock file, so that
parallel runs on one machine do not see each other) and discovery limited to localhost. Child
processes started by tests inherit these variables.
"""
import os
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
# The shared folder sits beside the repository (../shared); override with PIEZO_NARX_SHARED.
SHARED = Path(os.environ.get('PIEZO_NARX_SHARED', REPO.parent / 'shared'))
BOUCWEN = SHARED / 'data' / 'boucwen'


def _claim_domain_id() -> str:
    """
    Claim a ROS domain id no other test run on this machine holds (flock on a file per id).

    A pid-derived id collided between concurrent runs: one run's command node fed another's driver.
    The lock is held (file kept open) for the life of this pytest process and released by the OS.
    """
    import fcntl
    import tempfile
    for domain in range(1, 101):
        path = Path(tempfile.gettempdir()) / f'piezo_narx_ros_domain_{domain}.lock'
        handle = open(path, 'a')
        try:
            fcntl.flock(handle, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            handle.close()
            continue
        _claim_domain_id.handle = handle  # keep the lock for the whole session
        return str(domain)
    return str(1 + os.getpid() % 100)


# An xdist worker inherits the domain its controller claimed: it claims one of its own, so two
# workers' nodes never see each other (a domain the user set is kept).
if 'ROS_DOMAIN_ID' not in os.environ or (os.environ.get('PYTEST_XDIST_WORKER')
                                         and os.environ.get('PNR_TEST_DOMAIN_CLAIMED')):
    os.environ['ROS_DOMAIN_ID'] = _claim_domain_id()
    os.environ['PNR_TEST_DOMAIN_CLAIMED'] = '1'
os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
os.environ.setdefault('MPLBACKEND', 'Agg')
# numpy's OpenBLAS spins one thread per core; on a busy 2-core box that made ARX fits 20x slower.
os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')


# Test files that run alone, after the rest (`make test`): live DDS nodes and their timing, a
# live recorder's kill, the fake rig's UDP timing. Run beside a CPU-bound test on 2 cores
# they were slowed past their timing checks (the quick demo lost its latency pairs); the other
# files run on both cores at once (pytest-xdist).
# Each xdist worker has a ROS domain of its own, so process-lifecycle files without timing checks
# (bringup, the fake rig's CLI) run with the others.
SERIAL_FILES = frozenset({
    'test_command_node.py', 'test_controller_node.py', 'test_demo.py', 'test_demo_control.py',
    'test_driver_node.py', 'test_estimator_node.py', 'test_faults_bags.py', 'test_faults_nodes.py',
    'test_faults_replay.py', 'test_nodes_axes.py', 'test_nodes_batch.py', 'test_nodes_common.py',
    'test_player_node.py', 'test_recorder_node.py',
})


def pytest_ignore_collect(collection_path, config):
    """
    With `-m serial` or `-m 'not serial'` alone, leave the other group's files unimported.

    Importing every test module costs about 9 s per pytest run, and `make test` runs two.
    """
    if collection_path.suffix != '.py' or not collection_path.name.startswith('test_'):
        return None
    serial = collection_path.name in SERIAL_FILES
    wanted = {'serial': True, 'not serial': False}.get(config.getoption('markexpr', '').strip())
    return None if wanted is None or serial == wanted else True


def pytest_collection_modifyitems(config, items):
    """Mark the tests of SERIAL_FILES serial (make test: -n 2 -m "not serial", then -m serial)."""
    for item in items:
        if item.path.name in SERIAL_FILES:
            item.add_marker(pytest.mark.serial)


@pytest.fixture(scope='session')
def boucwen_dir():
    """Path of the Bouc-Wen benchmark data; skips the test when ../shared is absent."""
    if not (BOUCWEN / 'train.npz').is_file():
        pytest.skip(f'Bouc-Wen benchmark data not found at {BOUCWEN}')
    return BOUCWEN


@pytest.fixture(scope='session')
def stage_data():
    """Simulate 3 s at 2 kHz of independent multisines on both axes of plant_2axis: (u, y)."""
    import numpy as np

    from piezo_narx_ros.plant.axes import make_axis_plants
    from piezo_narx_ros.plant.signals import generate
    from piezo_narx_ros.share import config_path
    plant = make_axis_plants([], config_path('plant_2axis.yaml'), fs=2000.0, seed=1)
    u = np.column_stack([generate('multisine', 2000.0, 3.0, 100.0, seed=s) for s in (1, 2)])
    y, _ = plant.run(u)
    return u, y


@pytest.fixture(scope='session')
def arx2(stage_data):
    """Identify a 2 x 2 ARX (na = nb = 2) on `stage_data`: a small model of several axes."""
    from piezo_narx_ros.ident.arx.model import ARXModel
    u, y = stage_data
    return ARXModel(na=2, nb=2).fit(u, y, fs=2000.0)


@pytest.fixture(scope='session')
def chains2(stage_data):
    """Fit a small 2 x 2 envelope model of one chain per axis on `stage_data`."""
    from piezo_narx_ros.ident.hysteresis.chains import HysteresisChains
    u, y = stage_data
    model = HysteresisChains(hidden=4, n_plays=6, max_iter=15, seed=0).fit(u, y, fs=2000.0)
    model.inputs = model.outputs = ('x', 'y')
    return model
