"""
Test controller_node in a separate process over DDS (isolated domain, see conftest).

Checked:

- command_node (position mode) -> controller_node (inverse) -> simulator_node for 4 s at 2 kHz:
  every reference answered by one command with its stamp, the commands equal an offline
  PositionController on the same references, and the plant tracks the reference;
- bad references (NaN, out of range, backwards and far-future stamps, a malformed message)
  injected into a running controller: counted on /diagnostics, no command outside the limits,
  the node keeps running; ~/reset restarts the model from rest.
"""
import math
import time

import numpy as np
import pytest
from sensor_msgs.msg import JointState
from test_estimator_node import Collector, start_node, stop, wait_matched

from piezo_narx_ros.nodes.wire import make_joint_state
from piezo_narx_ros.nodes.qos import sample_qos

FS = 2000.0
P = 500_000  # ns


@pytest.fixture(scope='module')
def model_file(tmp_path_factory):
    """Return a small HysteresisNARX fitted on 8 s of the identification protocol, saved."""
    from piezo_narx_ros.ident.hysteresis.model import HysteresisNARX
    from piezo_narx_ros.ident.model_io import save_model
    from piezo_narx_ros.plant import PiezoCantilever, generate
    u = generate('protocol', FS, 8.0, 100.0, seed=3)
    y = PiezoCantilever(fs=FS, seed=3).run(u).y
    model = HysteresisNARX(hidden=6, n_plays=8, max_iter=25, seed=0).fit(u, y, fs=FS)
    path = tmp_path_factory.mktemp('model') / 'hnarx.json'
    save_model(model, path)
    return path


def offline(model_file, refs, **options):
    """Return the commands an offline PositionController gives for (stamp, reference) pairs."""
    from piezo_narx_ros.control.controller import PositionController
    from piezo_narx_ros.ident.model_io import load_model
    ctl = PositionController(load_model(model_file), slew_rate=1e5, **options)
    out = []
    for t, r in refs:
        out += ctl.on_reference(t, r)
    return out, ctl


def test_live_loop_answers_every_reference_and_tracks(model_file):
    seconds = 4.0
    n = int(seconds * FS)
    topics = ('position_reference', 'voltage_command', 'deflection')
    col = Collector('/ctl', topics)
    procs = [start_node('simulator_node', '-p', 'seed:=5', ns='/ctl'),
             start_node('controller_node', '-p', f'model:={model_file}', '-p', 'mode:=inverse',
                        '-p', 'wait_for_subscribers:=2', ns='/ctl')]   # simulator + collector
    try:
        # The controller subscribes to references only once its commands are heard.
        assert col.wait_for(lambda: all(s.get_publisher_count() >= 1 for s in col._subs[1:]),
                            40.0), 'simulator/controller did not come up'
        procs.append(start_node('command_node', '-p', 'output:=position', '-p', 'kind:=sine',
                                '-p', 'freq:=2.0', '-p', 'amplitude:=2.5e-05', '-p',
                                f'seconds:={seconds}', '-p', 'loop:=false', '-p',
                                'wait_for_subscribers:=2', ns='/ctl'))
        col.wait_for(lambda: all(len(col.data[t]) >= n for t in topics)
                     or any(p.poll() is not None for p in procs), 30.0 + seconds)
        time.sleep(0.3)
    finally:
        codes = stop(procs)
        col.close()
    errs = [p.stderr.read() for p in procs]
    assert codes == [0, 0, 0], errs[1]
    t_ref, r = col.arrays('position_reference')
    t_cmd, u = col.arrays('voltage_command')
    t_y, y = col.arrays('deflection')
    assert t_ref.size == n and np.all(np.diff(t_ref) == P)
    assert np.array_equal(t_cmd, t_ref) and np.array_equal(t_y, t_ref)   # nothing lost
    want, _ = offline(model_file, zip(t_ref.tolist(), r.tolist()), mode='inverse')
    assert np.array_equal(np.array([v for _, v in want]), u)   # the node is the offline logic
    # Tracking of the measured deflection (33 nm sensor noise), after the first period.
    assert np.sqrt(np.mean((y - r)[1000:] ** 2)) < 0.3e-6
    assert np.ptp(r) > 45e-6


def test_bad_references_are_counted_limited_and_survived(model_file):
    col = Collector('/badref', ('voltage_command',), diagnostics=True)
    pub = col.node.create_publisher(JointState, 'position_reference', sample_qos(depth=1000))
    raw = col.node.create_publisher(JointState, 'position_reference', sample_qos(depth=10))
    ctl = start_node('controller_node', '-p', f'model:={model_file}', '-p', 'u_min:=-40.0',
                     '-p', 'u_max:=60.0', ns='/badref')
    from std_srvs.srv import Trigger
    reset = col.node.create_client(Trigger, '/badref/controller_node/reset')
    try:
        assert wait_matched(pub, col._data_subs, 1, 40.0)
        t0 = 10**18
        r = 20e-6 * np.sin(np.arange(600) / 40.0)
        sent = r.copy()
        sent[100], sent[101], sent[200], sent[300] = math.nan, math.inf, 1.0, -1.0
        sent[400:450] = 80e-6                  # needs more than u_max: unreachable
        given = []                             # what reached the controller's logic, in order
        for k in range(600):
            pub.publish(make_joint_state(t0 + k * P, ['x'], position=[sent[k]]))
            given.append((t0 + k * P, sent[k]))
            if k == 250:    # stamps backwards and an hour ahead: refused, no command
                for t in (t0 + 10 * P, t0 + 3600 * 10**9):
                    pub.publish(make_joint_state(t, ['x'], position=[0.0]))
                    given.append((t, 0.0))
            if k == 260:
                raw.publish(make_joint_state(t0 + 261 * P, ['y'], position=[0.0]))  # no axis x
            time.sleep(0.0005)
        assert col.wait_for(lambda: len(col.data['voltage_command']) >= 600, 20.0)
        assert col.wait_for(lambda: col.diag.get('/badref/controller_node', (0, '', {}))[2]
                            .get('references') == '602', 5.0)
        _, _, values = col.diag['/badref/controller_node']
        assert ctl.poll() is None                     # still running
        assert values['rejected_nonfinite'] == '2'    # NaN and inf
        assert values['refused_messages'] == '1'      # the message without x, said as such
        assert values['out_of_range'] == '52' and values['stamp_outliers'] == '2'
        assert int(values['voltage_limited']) >= 40
        t, u = col.arrays('voltage_command')
        assert np.array_equal(t, t0 + P * np.arange(600))
        assert u.min() >= -40.0 and u.max() <= 60.0 and np.max(np.abs(np.diff(u))) <= 50.0
        want, _ = offline(model_file, given, u_min=-40.0, u_max=60.0)
        assert np.array_equal(np.array([v for _, v in want]), u)
        assert reset.wait_for_service(timeout_sec=30.0)
        future = reset.call_async(Trigger.Request())
        assert col.wait_for(future.done, 10.0) and future.result().success
        assert col.wait_for(lambda: col.diag['/badref/controller_node'][2]
                            .get('requested_resets') == '1', 5.0)
    finally:
        codes = stop([ctl])
        col.close()
    assert codes == [0]


def test_bad_parameters_end_in_one_line(model_file, tmp_path):
    proc = start_node('controller_node', '-p', f'model:={model_file}', '-p', 'mode:=exact')
    assert proc.wait(60) == 2
    err = proc.stderr.read().strip().splitlines()
    assert len(err) == 1 and 'mode must be one of' in err[0]
    proc = start_node('controller_node', '-p', f'model:={tmp_path / "missing.json"}')
    assert proc.wait(60) == 2
    assert 'missing.json' in proc.stderr.read()
    proc = start_node('controller_node', '-p', f'model:={model_file}', '-p',
                      'mode:=inverse_feedback', '-p', 'use_deflection:=false')
    assert proc.wait(60) == 2
    assert 'needs use_deflection:=true' in proc.stderr.read()


def test_a_hand_widened_input_range_cannot_push_commands_past_the_safety_limits(
        model_file, tmp_path):
    """Issue 45: a model file claiming +-5000 V made the node command -3450 V."""
    import json
    import shutil
    doc = json.loads(model_file.read_text())
    doc['input_range'] = [-5000.0, 5000.0]
    wide = tmp_path / model_file.name
    wide.write_text(json.dumps(doc))
    shutil.copy(model_file.with_suffix('.npz'), tmp_path)
    col = Collector('/wide', ('voltage_command',), diagnostics=True)
    pub = col.node.create_publisher(JointState, 'position_reference', sample_qos(depth=1000))
    ctl = start_node('controller_node', '-p', f'model:={wide}', '-p', 'slew_rate:=0.0',
                     '-p', 'y_min:=-0.001', '-p', 'y_max:=0.001', ns='/wide')
    try:
        assert wait_matched(pub, col._data_subs, 1, 40.0)
        for k in range(400):        # far beyond what 200 V move the stage: up to the limits
            pub.publish(make_joint_state(10**18 + k * P, ['x'],
                                         position=[1e-3 * math.sin(k / 30.0)]))
            time.sleep(0.0005)
        assert col.wait_for(lambda: len(col.data['voltage_command']) >= 400, 20.0)
    finally:
        codes = stop([ctl])
        col.close()
    assert codes == [0]
    _, u = col.arrays('voltage_command')
    assert u.min() == -200.0 and u.max() == 200.0       # v_min / v_max, not the file's range
