"""`piezo-narx bag info|export` output and exit codes."""
import numpy as np
import pytest

from piezo_narx_ros.bag.writer import write_uy_bag
from piezo_narx_ros.cli.main import main as cli_main


def _run(argv):
    with pytest.raises(SystemExit) as code:
        cli_main(argv)
    return code.value.code


def test_info_and_export(tmp_path, capsys):
    u = np.sin(np.arange(1000) / 30.0)
    y = 1e-6 * np.cos(np.arange(1000) / 30.0)
    bag = write_uy_bag(tmp_path / 'rec', u, y, 1000.0)
    assert _run(['bag', 'info', str(bag)]) == 0
    out = capsys.readouterr().out
    assert 'messages:  2000' in out
    line = next(s for s in out.splitlines() if s.startswith('/piezo/deflection'))
    assert line.split()[1:7] == ['sensor_msgs/msg/JointState', '1000', '1000', '1000', '0', '0']

    assert _run(['bag', 'export', str(bag), '--out', str(tmp_path / 'd.npz')]) == 0
    with np.load(tmp_path / 'd.npz', allow_pickle=False) as d:
        np.testing.assert_array_equal(d['u'], u)
        np.testing.assert_array_equal(d['y'], y)
        assert float(d['fs']) == 1000.0 and d['t'][-1] == pytest.approx(0.999)


def test_errors_are_one_line_exit_2(tmp_path, capsys):
    bag = write_uy_bag(tmp_path / 'rec', np.zeros(10), np.zeros(10), 1000.0)
    assert _run(['bag', 'export', str(bag), '--out', str(tmp_path / 'd.npz'),
                 '--deflection-topic', 'nope']) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith('piezo-narx: error: topic /nope not in bag') and '\n' not in err
    assert _run(['bag', 'info', str(tmp_path / 'missing')]) == 2
    assert 'bag not found' in capsys.readouterr().err
