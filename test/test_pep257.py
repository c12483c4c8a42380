"""Docstring conventions as colcon test checks them for a ROS package (ament_pep257)."""
from pathlib import Path

import pytest
from ament_pep257.main import main

PACKAGE = Path(__file__).resolve().parents[1]
GENERATED = ['mutants', 'build', 'install', 'log']   # see test_flake8.py


@pytest.mark.linter
@pytest.mark.pep257
def test_pep257(monkeypatch, capsys):
    monkeypatch.chdir(PACKAGE)
    rc = main(argv=['.', '--exclude', *GENERATED])
    findings = [ln for ln in capsys.readouterr().err.splitlines() if ': D' in ln]
    assert rc == 0, f'{len(findings)} pep257 finding(s):\n' + '\n'.join(findings)
