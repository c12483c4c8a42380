"""Shared pytest fixtures.

DDS isolation: every test session gets its own ROS_DOMAIN_ID (derived from the process id, so that
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

os.environ.setdefault('ROS_DOMAIN_ID', str(1 + os.getpid() % 100))
os.environ['ROS_AUTOMATIC_DISCOVERY_RANGE'] = 'LOCALHOST'
os.environ.setdefault('MPLBACKEND', 'Agg')
# numpy's OpenBLAS spins one thread per core; on a busy 2-core box that made ARX fits 20x slower.
os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')


@pytest.fixture(scope='session')
def boucwen_dir():
    """Path of the Bouc-Wen benchmark data; skips the test when ../shared is absent."""
    if not (BOUCWEN / 'train.npz').is_file():
        pytest.skip(f'Bouc-Wen benchmark data not found at {BOUCWEN}')
    return BOUCWEN
