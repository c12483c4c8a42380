"""
Where this copy's installed data lives: share/piezo_narx_ros (config/, launch/, package.xml).

setup.py installs config/*.yaml and launch/*.launch.yaml under PREFIX/share/piezo_narx_ros, as
colcon and ROS packages do; the Python package itself lands in PREFIX/lib/.../site-packages. The
share directory is looked up, in order:

1. beside this copy's own install prefix (PREFIX/share/piezo_narx_ros above the package folder):
   `pip install .`, `pip install --prefix P`, `setup.py install`, colcon, a Debian package;
2. the source tree this module sits in (a clone, or `pip install -e .`): it has package.xml;
3. the ament index (AMENT_PREFIX_PATH, set by a sourced ROS workspace), for any other layout.

The first two belong to this very copy of the code, so a sourced workspace holding another
version never hands this code that version's files; the ament index is the general fallback.
"""
from __future__ import annotations

import os
from functools import lru_cache
from pathlib import Path

from piezo_narx_ros.errors import ConfigError

PACKAGE = 'piezo_narx_ros'
_HERE = Path(__file__).resolve().parent   # the piezo_narx_ros package folder


def _own_prefix_share(package_dir: Path) -> Path | None:
    for parent in package_dir.parents:
        candidate = parent / 'share' / PACKAGE
        if (candidate / 'package.xml').is_file():
            return candidate
    return None


def _source_tree(package_dir: Path) -> Path | None:
    root = package_dir.parent
    if (root / 'package.xml').is_file() and (root / 'setup.py').is_file():
        return root
    return None


def _ament_index() -> Path | None:
    if not os.environ.get('AMENT_PREFIX_PATH'):
        return None
    try:
        from ament_index_python.packages import (PackageNotFoundError,
                                                 get_package_share_directory)
    except ImportError:
        return None
    try:
        return Path(get_package_share_directory(PACKAGE))
    except (PackageNotFoundError, OSError, ValueError):
        return None


@lru_cache(maxsize=None)
def share_dir() -> Path:
    """
    Return the folder holding config/ and launch/ for this copy (see the module docstring).

    Raises ConfigError (one line) when no copy can be found, e.g. a wheel installed without its
    data files.
    """
    for find in (lambda: _own_prefix_share(_HERE), lambda: _source_tree(_HERE), _ament_index):
        found = find()
        if found is not None:
            return found
    raise ConfigError(f'cannot find share/{PACKAGE} (config/, launch/): not beside the install '
                      f'prefix of {_HERE}, not a source tree, not in the ament index '
                      '(AMENT_PREFIX_PATH)')


def config_path(name: str) -> Path:
    """Path of config/NAME of this copy (e.g. 'plant.yaml'); ConfigError when it is missing."""
    path = share_dir() / 'config' / name
    if not path.is_file():
        raise ConfigError(f'config file {name} not found in {path.parent}')
    return path


def launch_path(name: str) -> Path:
    """Path of launch/NAME of this copy (e.g. 'sim.launch.yaml'); ConfigError when missing."""
    folder = share_dir() / 'launch'
    path = folder / name
    if not path.is_file():
        known = sorted(p.name for p in folder.glob('*.launch.yaml')) if folder.is_dir() else []
        raise ConfigError(f'launch file {name} not found in {folder}'
                          + (f' (there: {", ".join(known)})' if known else ''))
    return path
