"""
Several axes over DDS (issue 20): command, two-axis simulator, estimator, recorder, controller.

command_node drives x and y (independent signals) in batches, simulator_node answers with the
coupled two-axis cantilever of config/plant_2axis.yaml (the offline plant's numbers), and
estimator_node runs a 2 x 2 model named x, y: every output axis is published, equal to the
model's offline free run on the commands; a command missing an axis is refused and counted; the
recorded bag reads back as a 2 x 2 record. controller_node inverts the 2 x 2 model.
"""
import time

import numpy as np
import pytest
from test_estimator_node import start_node, stop
from test_nodes_batch import BatchProbe

from piezo_narx_ros.ident.arx.model import ARXModel
from piezo_narx_ros.ident.model_io import save_model
from piezo_narx_ros.nodes.wire import encode_joint_trajectory
from piezo_narx_ros.plant.axes import make_axis_plants
from piezo_narx_ros.plant.signals import generate
from piezo_narx_ros.share import config_path

FS = 2000.0


def _model_file(tmp_path):
    plant = make_axis_plants([], config_path('plant_2axis.yaml'), fs=FS, seed=5)
    u = np.column_stack([generate('multisine', FS, 2.0, 80.0, seed=s) for s in (1, 2)])
    y, _ = plant.run(u)
    model = ARXModel(na=2, nb=2).fit(u, y, fs=FS)
    model.inputs = model.outputs = ('x', 'y')
    return model, save_model(model, tmp_path / 'arx2.json')


def test_two_axis_pipeline_publishes_every_axis_as_offline(tmp_path):
    model, path = _model_file(tmp_path)
    n, batch = 600, 10
    ns = '/axes2'
    probe = BatchProbe(ns, ('voltage_command_batch', 'deflection_batch',
                            'deflection_estimate_batch'), 'voltage_command_batch')
    stage = config_path('plant_2axis.yaml')
    procs = [start_node('simulator_node', '-p', f'fs:={FS}', '-p', f'batch:={batch}', '-p',
                        f'plant_params:={stage}', '-p', 'seed:=3', ns=ns),
             start_node('estimator_node', '-p', f'model:={path}', '-p', 'init:=rest', '-p',
                        f'batch:={batch}', ns=ns),
             start_node('recorder_node', '-p', f'output:={tmp_path / "bag"}', '-p',
                        f'batch:={batch}', ns=ns)]
    try:
        assert probe.wait_matched(3)
        # Matched on the probe's side is not yet matched on the readers' side: a volatile reader
        # that learns of the probe's writer after this sample skips it (the bag once lacked it).
        time.sleep(1.0)
        # A batch without the y axis, before the stream: refused whole and counted by the nodes;
        # recorded, it is the bag's first command and the reader still pairs x and y by name.
        probe.pub.publish(encode_joint_trajectory([10**18], ['x'], effort=[[1.0]]))
        assert probe.wait_for(lambda: probe.diag.get(f'{ns}/estimator_node', (0, {}))[1]
                              .get('refused_messages') == '1', 10.0)
        procs.append(start_node('command_node', '-p', f'fs:={FS}', '-p', f'batch:={batch}',
                                '-p', "axes:=['x','y']", '-p', 'loop:=false', '-p',
                                f'seconds:={n / FS}', '-p', 'wait_for_subscribers:=4', '-p',
                                'amplitude:=60.0', ns=ns))
        assert probe.wait_for(
            lambda: sum(map(len, probe.decoded('deflection_estimate_batch'))) >= n, 30.0)
        assert probe.wait_for(lambda: probe.diag.get(f'{ns}/estimator_node', (0, {}))[1]
                              .get('commands') == str(n), 5.0)
        values = probe.diag[f'{ns}/estimator_node'][1]
        sim = probe.wait_for(lambda: probe.diag.get(f'{ns}/simulator_node', (0, {}))[1]
                             .get('rejected') == '1', 5.0)
    finally:
        codes = stop(procs)
        probe.close()
    assert codes == [0, 0, 0, 0]
    cmd = [b for b in probe.decoded('voltage_command_batch') if len(b) and b.names == ['x', 'y']]
    u = np.concatenate([b.effort for b in cmd])
    t = np.concatenate([b.t_ns for b in cmd])
    assert u.shape == (n, 2) and not np.allclose(u[:, 0], u[:, 1])     # independent signals
    dfl = probe.decoded('deflection_batch')
    assert all(b.names == ['x', 'y'] for b in dfl)
    y = np.concatenate([b.position for b in dfl])
    ref, _ = make_axis_plants([], config_path('plant_2axis.yaml'), fs=FS, seed=3).run(u)
    assert np.array_equal(y, ref)
    est = probe.decoded('deflection_estimate_batch')
    assert all(b.names == ['x', 'y'] for b in est)
    assert np.concatenate([b.t_ns for b in est]).tolist() == t.tolist()
    y_hat = np.concatenate([b.position for b in est])
    assert np.allclose(y_hat, model.simulate(u), rtol=0, atol=1e-12 * np.ptp(y_hat))
    assert values['refused_messages'] == '1'            # the batch without y
    assert sim                                           # the simulator refused it too
    # The recorded bag reads back as one record of two inputs and two outputs, by name.
    from piezo_narx_ros.bag.reader import read_uy_report
    rec, report = read_uy_report(tmp_path / 'bag', command_topic=f'{ns[1:]}/voltage_command',
                                 deflection_topic=f'{ns[1:]}/deflection')
    assert rec.inputs == ('x', 'y') and rec.outputs == ('x', 'y')
    assert np.array_equal(rec.u, u) and np.array_equal(rec.y, y)
    assert report.command.missing_axes == {'y': 1}


@pytest.mark.parametrize('family', ['arx', 'chains'])
def test_controller_node_inverts_a_model_of_two_axes(tmp_path, family, request):
    """The node's commands are AxesController's: the vector inverse, or a chain per axis."""
    from piezo_narx_ros.control.axes import AxesController
    if family == 'arx':
        model, path = _model_file(tmp_path)
    else:
        model = request.getfixturevalue('chains2')
        path = save_model(model, tmp_path / 'chains2.json')
    ns, batch, n = '/axes2c', 10, 200
    period = 500_000
    probe = BatchProbe(ns, ('voltage_command_batch',), 'position_reference_batch')
    ctl = start_node('controller_node', '-p', f'model:={path}', '-p', 'mode:=inverse', '-p',
                     f'batch:={batch}', '-p', 'use_deflection:=false', '-p', 'u_min:=-150.0',
                     '-p', 'u_max:=150.0', ns=ns)
    k = np.arange(n)
    ref = np.column_stack([8e-6 * np.sin(k / 12.0), -5e-6 * np.cos(k / 7.0)])
    t = 10**18 + k * period
    try:
        assert probe.wait_matched()
        for i in range(0, n, batch):
            probe.pub.publish(encode_joint_trajectory(t[i:i + batch], ['x', 'y'],
                                                      position=ref[i:i + batch]))
        assert probe.wait_for(
            lambda: sum(map(len, probe.decoded('voltage_command_batch'))) >= n, 20.0)
    finally:
        codes = stop([ctl])
        probe.close()
    assert codes == [0]
    got = probe.decoded('voltage_command_batch')
    assert all(b.names == ['x', 'y'] for b in got)
    u = np.concatenate([b.effort for b in got])
    offline = AxesController(model, mode='inverse', u_min=-150.0, u_max=150.0, slew_rate=1e5)
    want = np.array([offline.on_reference(int(s), r)[0][1] for s, r in zip(t, ref)])
    assert np.array_equal(u, want)
    if family == 'arx':
        assert np.max(np.abs(model.simulate(u) - ref)) < 1e-12      # both axes reached
    else:           # the quasi-static inverse of each chain: the fast dynamics pass
        assert np.sqrt(np.mean((model.simulate(u) - ref)[50:] ** 2)) < 0.05 * ref.std()
