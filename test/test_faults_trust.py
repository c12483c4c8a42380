"""
Issue 45, ROS-free: what a second axis, a model file or a message may smuggle past a node.

Axis names are unique wherever they are declared or carried; the controller's own safety window
bounds every command whatever the model file says; a model giving NaN is reported as such; a
message without the axis is reported as such; ~/reinitialize names the real window.
"""
import math

import numpy as np
import pytest

from piezo_narx_ros.axis_names import AXES_CHECK, distinct_names, repeated
from piezo_narx_ros.bag.reader import read_uy
from piezo_narx_ros.bag.writer import JOINT_STATE, BagWriter, joint_state_cdr
from piezo_narx_ros.control.controller import PositionController, input_limits, safety_bounded
from piezo_narx_ros.control.health import ControllerHealth
from piezo_narx_ros.errors import BagError, ConfigError, DataError
from piezo_narx_ros.estimator.free_run import FreeRunEstimator
from piezo_narx_ros.estimator.health import EstimatorHealth
from piezo_narx_ros.estimator.toy import toy_narx
from piezo_narx_ros.nodes.wire import (decode_joint_state, decode_joint_trajectory,
                                       encode_joint_state, encode_joint_trajectory,
                                       make_joint_state, parse_joint_state)
from piezo_narx_ros.nodes.params import ParamSpec
from piezo_narx_ros.plant.axes import make_axis_plants

P = 500_000


# ------------------------------------------------------------------------------ axis names
def test_an_axes_parameter_naming_one_axis_twice_is_refused():
    spec = ParamSpec('axes', ['x'], 'axis names', check=AXES_CHECK)
    assert spec.validate(['x', 'y']) is None
    assert spec.validate(['x', 'x']) == ('axes must be a non-empty list of distinct non-empty '
                                         "names, got ['x', 'x']")
    assert repeated(['x', 'y', 'x']) == 'x' and not distinct_names(['x', ' '])


def test_a_plant_of_two_axes_of_one_name_is_refused():
    with pytest.raises(ConfigError, match=r"distinct non-empty names, got \['x', 'x'\]"):
        make_axis_plants(['x', 'x'])
    assert make_axis_plants(['x', 'y']).n_axes == 2


@pytest.mark.parametrize('decode', [
    lambda names: decode_joint_state(encode_joint_state(10**9, names, effort=[1.0, 2.0])),
    lambda names: decode_joint_trajectory(encode_joint_trajectory([10**9], names,
                                                                  effort=np.ones((1, 2)))),
    lambda names: parse_joint_state(make_joint_state(10**9, names, effort=[1.0, 2.0])),
])
def test_a_message_naming_one_axis_twice_is_refused(decode):
    assert decode(['x', 'y']).names == ['x', 'y']
    with pytest.raises(DataError, match=r"message names axis 'x' twice \(names: \['x', 'x'\]\)"):
        decode(['x', 'x'])


def test_a_bag_whose_messages_name_one_axis_twice_is_refused(tmp_path):
    with BagWriter(tmp_path / 'b') as bag:
        c = bag.add_topic('piezo/voltage_command', JOINT_STATE)
        d = bag.add_topic('piezo/deflection', JOINT_STATE)
        for k in range(50):
            t = 10**18 + k * P
            bag.write(c, t, joint_state_cdr(t, names=('x', 'x'), effort=(k, -k)))
            bag.write(d, t, joint_state_cdr(t, position=(k * 1e-7,)))
    with pytest.raises(BagError, match=r'/piezo/voltage_command carries messages naming axis '
                       r"'x' twice \(x, x\)"):
        read_uy(tmp_path / 'b', axis='x')


# ---------------------------------------------------------------------- controller safety
def widened(lo=-5000.0, hi=5000.0):
    """Return a toy model whose file claims a trained input range of [lo, hi] V."""
    m = toy_narx()
    m.input_range = (lo, hi)
    return m


def test_the_safety_window_bounds_limits_from_a_hand_widened_model():
    limits, note = safety_bounded(input_limits(widened(), 0.05), -200.0, 200.0)
    assert limits == {'u_min': -200.0, 'u_max': 200.0}
    assert 'exceed the safety limits [-200, 200] V' in note
    same, quiet = safety_bounded({'u_min': -40.0, 'u_max': 60.0}, -200.0, 200.0)
    assert same == {'u_min': -40.0, 'u_max': 60.0} and quiet == ''
    per_axis, _ = safety_bounded({'u_min': np.array([-300.0, -10.0]),
                                  'u_max': np.array([300.0, 10.0])}, -200.0, 200.0)
    assert per_axis['u_min'].tolist() == [-200.0, -10.0]
    with pytest.raises(ConfigError, match='lie outside the safety limits'):
        safety_bounded({'u_min': 300.0, 'u_max': 400.0}, -200.0, 200.0)


def test_no_command_leaves_the_safety_window_whatever_the_model_claims():
    limits, _ = safety_bounded(input_limits(widened(), 0.05), -200.0, 200.0)
    ctl = PositionController(widened(), mode='inverse', **limits)
    out = []
    for k in range(400):      # references far beyond what 200 V reach
        out += ctl.on_reference(k * P, 1e-3 * math.sin(k / 20.0))
    u = np.array([v for _, v in out])
    assert len(u) == 400 and u.min() >= -200.0 and u.max() <= 200.0
    assert u.max() == 200.0 and u.min() == -200.0


def nan_model():
    """Return a model whose weights overflow: its free run is inf, then NaN."""
    m = toy_narx()
    w2 = m.w2.copy()
    w2[:2] = 1e308
    m.set_weights(m.W1, m.b1, w2, 0.0, (0.0, 100.0, 0.0, 1e300))
    return m


def test_a_model_that_gives_nan_is_reported_as_such_not_as_a_zero_miss():
    with np.errstate(all='ignore'):
        ctl = PositionController(nan_model(), mode='inverse', u_min=-100.0, u_max=100.0)
        health = ControllerHealth(ctl)
        out = []
        for k in range(300):
            out += ctl.on_reference(k * P, 1e-6 * math.sin(k / 30.0))
    u = np.array([v for _, v in out])
    assert np.isfinite(u).all() and np.abs(u).max() <= 100.0
    level, msg, values = health.tick(1)
    assert level == 2 and msg.startswith("300 of 300 commands: the model's output is not finite")
    assert 'missed their target by up to 0 m' not in msg and values['model_nonfinite'] == 300


def test_a_vector_model_that_gives_nan_sends_finite_commands_and_says_why(arx2):
    from piezo_narx_ros.control.axes import AxesController
    from piezo_narx_ros.ident.arx.model import ARXModel
    m = ARXModel(na=2, nb=2).set_coefficients(a=arx2.a, b=arx2.b, c=np.array([1e308, -1e308]))
    m.fs, m.input_range, m.output_range = arx2.fs, arx2.input_range, arx2.output_range
    m.output_2d_ = True
    with np.errstate(all='ignore'):
        assert np.isnan(m.simulate(np.zeros((50, 2)))[-1]).all()
        ctl = AxesController(m, u_min=-100.0, u_max=100.0, y_min=[-1e-4] * 2, y_max=[1e-4] * 2)
        out = [u for k in range(100) for _, u in ctl.on_reference(k * P, [1e-6, 0.0])]
    u = np.array(out)
    assert u.shape == (100, 2) and np.isfinite(u).all() and np.abs(u).max() <= 100.0
    level, msg, values = ctl.status()
    assert level == 2 and "commands: the model's output is not finite" in msg
    assert values['model_nonfinite'] > 0


# ------------------------------------------------------------------- estimator messages
def test_a_message_without_the_axis_is_reported_as_such():
    est = FreeRunEstimator(toy_narx(), init='rest')
    health = EstimatorHealth(est)
    est.stats.refused_messages += 1
    est.stats.last_refusal = "command message: axis 'x' not in message (names: ['y'])"
    level, msg, values = health.tick()
    assert level == 1 and msg.startswith('1 message(s) refused (the last: command message: '
                                         "axis 'x' not in message")
    assert 'non-finite' not in msg and values['refused_messages'] == 1


def test_reinitialize_names_the_window_it_really_waits_for():
    est = FreeRunEstimator(toy_narx(), init='auto', init_window=0.5)
    said = est.request_restart(from_measurement=True)
    assert said.startswith(f'free run restarts from the next {est.init_samples} measured '
                           'samples (0.5 s;')
    assert est.init_samples == 1000
    assert est.request_restart(from_measurement=False) == \
        'free run restarts from rest at the next command'


# ------------------------------------------------------------ one check that a model runs
def test_the_shared_check_refuses_a_model_whose_free_run_overflows(tmp_path, capsys):
    from piezo_narx_ros.errors import ModelFileError
    from piezo_narx_ros.ident.model_io import save_model
    from piezo_narx_ros.ident.validation.usable import check_runs, load_runnable
    check_runs(toy_narx())                                   # a sane model passes
    path = save_model(nan_model(), tmp_path / 'nan.json')
    with pytest.raises(ModelFileError, match="nan.json: the model's free run from rest is not "
                       'finite .* it can neither estimate nor control'):
        load_runnable(path)
    from test_faults_cli import cli, one_error_line
    np.savez(tmp_path / 'r.npz', u=np.zeros(3000), y=np.zeros(3000) + 1e-9, fs=2000.0)
    code, _, err = cli(['evaluate', str(path), str(tmp_path / 'r.npz')], capsys)
    assert code == 2 and one_error_line(err) and 'free run from rest is not finite' in err


def test_an_estimator_whose_estimates_turn_nan_is_an_error_not_ok():
    with np.errstate(all='ignore'):
        est = FreeRunEstimator(nan_model(), init='rest')
        health = EstimatorHealth(est)
        for k in range(200):
            est.on_command(k * P, 10.0)
        level, msg, values = health.tick()
    assert level == 2 and msg.startswith('200 of 200 estimates are not finite (NaN/inf)')
    assert values['nonfinite_estimates'] == 200
    with np.errstate(all='ignore'):
        for k in range(200, 210):             # every later tick with estimates: ERROR again
            est.on_command(k * P, 10.0)
    assert health.tick()[0] == 2


# --------------------------------------------------------------- a write DDS refuses
def test_a_write_dds_refuses_loses_that_sample_not_the_node():
    """Issue 45 soak: `RCLError: Failed to publish: cannot publish data` ended command_node."""
    from rclpy._rclpy_pybind11 import RCLError

    from piezo_narx_ros.nodes.qos import PublishFailures

    class Writer:                       # what DDS does under load: refuses every third write
        topic_name = '/piezo/voltage_command'

        def __init__(self):
            self.sent = []

        def publish(self, msg):
            if len(self.sent) % 3 == 2:
                self.sent.append(None)
                raise RCLError('Failed to publish: cannot publish data, at rmw_publish.cpp:120')
            self.sent.append(msg)

    pub, failures = Writer(), PublishFailures()
    failures.guard(pub)
    for k in range(9):
        pub.publish(k)                  # never raises
    assert [m for m in pub.sent if m is not None] == [0, 1, 3, 4, 6, 7]
    phrase = failures.take()
    assert phrase.startswith('samples lost: DDS refused 3 on /piezo/voltage_command '
                             '(Failed to publish: cannot publish data')
    assert failures.take() == ''        # nothing new since
