"""flake8 as colcon test runs it for a ROS package (ament_flake8 and its configuration)."""
from pathlib import Path

import pytest
from ament_flake8.main import main_with_errors

PACKAGE = Path(__file__).resolve().parents[1]
# Trees of generated code, not the package's (mutmut's mutated copies, colcon's output).
GENERATED = ['mutants', 'build', 'install', 'log']


@pytest.mark.flake8
@pytest.mark.linter
def test_flake8(monkeypatch):
    # ament_flake8 checks the working directory (as colcon runs it: from the package).
    monkeypatch.chdir(PACKAGE)
    rc, errors = main_with_errors(argv=['--exclude', *GENERATED])
    assert rc == 0, f'{len(errors)} flake8 finding(s):\n' + '\n'.join(errors)
