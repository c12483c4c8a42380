"""
simulator_node: the piezo plant answering each voltage_command with a deflection.

One PiezoCantilever per axis. Each command sample advances the plant one period and is answered
on deflection with the command's stamp (position = measured m, effort = volts applied). Missing
samples (stamp gaps) advance the plant with the held command, as a real amplifier would hold its
output; they are not published (no command, no answer). A command stream whose stamps step at
another rate than the plant's `fs` is not answered while it lasts (the plant would be stepped
1/fs per command, whatever the stamps say): ERROR on /diagnostics. The logic is in PlantResponder,
tested without DDS.
"""
from __future__ import annotations

import math

import numpy as np

from piezo_narx_ros.axis_names import AXES_CHECK
from piezo_narx_ros.command.stamps import (GRID_TOLERANCE, RATE_TOLERANCE, RESTART, RateMonitor,
                                           StampGate, pass_run_observed)
from piezo_narx_ros.counters import Since
from piezo_narx_ros.errors import DataError
from piezo_narx_ros.nodes.wire.batching import BATCH_PARAM, batch_topic, sample_type
from piezo_narx_ros.nodes.wire import (decode_joint_state, decode_joint_trajectory,
                                       encode_joint_state, encode_joint_trajectory)
from piezo_narx_ros.nodes.diagnostics import DIAG_ERROR, DIAG_OK, DIAG_WARN, Diagnostics
from piezo_narx_ros.nodes.graph import EpisodeLog, same_name_problem
from piezo_narx_ros.nodes.params import ParamSpec
from piezo_narx_ros.nodes.runtime import PiezoNode, main_for
from piezo_narx_ros.nodes.topics import TOPIC_COMMAND, TOPIC_DEFLECTION


class PlantResponder:
    """
    Plants (one per axis) driven by stamped commands; ROS-free.

    plants: a plant.axes.AxisPlants (or {axis: PiezoCantilever}, independent axes); fs: command
    rate, Hz; max_fill: longest gap (samples) bridged by holding the command. Stamps go through
    a `command.stamps.StampGate`: an isolated outlier stamp is refused (`stamp_outliers`) instead
    of making every later command look stale, and a new stream (a loop, a new run, a jump beyond
    max_fill) is followed: the plant just continues from its state, as a real one would
    (`stream_restarts`). A stream at another rate
    (`rate`, a command.stamps.RateMonitor) still drives the plants, but gets no answer
    (`rate_withheld`): deflections paired with those stamps would be wrong data.
    """

    def __init__(self, plants: dict, fs: float, max_fill: int = 20000,
                 rate_tolerance: float = RATE_TOLERANCE):
        from piezo_narx_ros.plant.axes import AxisPlants
        self.plants = plants if isinstance(plants, AxisPlants) else AxisPlants(plants)
        self.axes = list(self.plants.axes)
        self.fs = float(fs)
        self.period_ns = 1e9 / fs
        self.max_fill = max_fill
        self.gate = StampGate(self.period_ns, max_fill)
        self.rate = RateMonitor(self.period_ns, rate_tolerance)
        self.rate_withheld = 0
        self.last_t: int | None = None
        self.last_u = [0.0] * len(self.axes)
        self.received = 0
        self.answered = 0
        self.rejected = 0
        self.filled = 0
        self.gaps = 0

    @property
    def stamp_outliers(self) -> int:
        return self.gate.outliers

    @property
    def stream_restarts(self) -> int:
        return self.gate.restarts

    def on_command(self, t_ns: int, volts: dict) -> list[tuple[int, list[float], list[float]]]:
        """
        Apply {axis: V} at stamp t_ns.

        Returns the answers now due, [(stamp, y_meas m per axis, u_applied V per axis)] in
        self.axes order: usually one, none while the stamp is held (see StampGate), several when
        held commands are released. Raises DataError for a non-finite command or a missing axis
        (the plant is not touched).
        """
        self.received += 1
        self.rate.received(t_ns)
        try:
            u = [float(volts[a]) for a in self.axes]
        except KeyError as exc:
            self.rejected += 1
            raise DataError(f'command has no axis {exc.args[0]!r}') from None
        if not all(math.isfinite(x) for x in u):
            self.rejected += 1
            raise DataError(f'command is not finite: {u}')
        gate, last = self.gate, self.last_t
        if (last is not None and last == gate.last and not gate.holding
                and abs((t_ns - last) / self.period_ns - 1.0) <= GRID_TOLERANCE):
            # The running stream's next command (a 2 kHz stream's every command): what
            # gate.push and answer() do with it, without their checks.
            gate.last = t_ns
            off = self.rate.observe(t_ns)
            y_out, u_out = self.plants.step(u)
            self.last_u, self.last_t = u, t_ns
            if off:
                self.rate_withheld += 1
                return []
            self.answered += 1
            return [(t_ns, y_out, u_out)]
        return self.answer(gate.push(t_ns, u))

    def on_commands(self, t_ns, u) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """
        Answer a batch: stamps (n,) int64 ns, commands (n, n_axes) V in self.axes order.

        Returns the answers now due as arrays (stamps (m,), y_meas (m, n_axes) m, u_applied
        (m, n_axes) V): the same numbers, counters and plant state as n on_command() calls. A
        batch whose stamps each follow on the grid with every command finite takes the fast
        path (one plant run over the batch, the checks on arrays); anything else goes command by
        command.
        """
        t = np.ascontiguousarray(t_ns, dtype=np.int64).ravel()
        v = np.asarray(u, dtype=np.float64).reshape(t.shape[0], -1)
        # A finite sum holds no NaN or inf (one that overflows goes command by command); a
        # Python sum of a batch costs less than isfinite().all() in a node's cold caches.
        passed = None
        if v.shape[1] == len(self.axes) and math.isfinite(sum(v.ravel().tolist())):
            passed = pass_run_observed(self.gate, self.rate, t)    # stamp and rate checks
        if passed is not None:
            off, withheld = passed
            self.received += t.shape[0]
            y, ua = self.plants.run_checked(v)
            self.last_u = v[-1].tolist()
            self.last_t = int(t[-1])
            self.rate_withheld += withheld
            self.answered += t.shape[0] - withheld
            if withheld:
                return t[~off], y[~off], ua[~off]
            return t, y, ua
        answers = []
        for ti, ui in zip(t.tolist(), v.tolist()):
            try:
                answers += self.on_command(ti, dict(zip(self.axes, ui)))
            except DataError:
                pass           # counted in rejected; the node logs it
        return answers_as_arrays(answers, len(self.axes))

    def flush(self) -> list[tuple[int, list[float], list[float]]]:
        """Answers of held commands once commands have stopped (StampGate.flush)."""
        return self.answer(self.gate.flush())

    def answer(self, events) -> list[tuple[int, list[float], list[float]]]:
        """Step the plants for the commands the stamp gate let through."""
        out = []
        for kind, t_ns, u in events:
            if kind == RESTART:
                self.last_t = None      # no gap to bridge into a new stream
                self.rate.reset()
                continue
            self.rate.observe(t_ns)
            if self.last_t is not None:
                missing = int(round((t_ns - self.last_t) / self.period_ns)) - 1
                if missing > 0:
                    self.gaps += 1
                    self.filled += missing
                    self.plants.hold(self.last_u, missing)
            y_out, u_out = self.plants.step(u)
            self.last_u = list(u)
            self.last_t = t_ns
            if self.rate.off:
                self.rate_withheld += 1
                continue
            self.answered += 1
            out.append((t_ns, y_out, u_out))
        return out

    def rate_line(self) -> str:
        """Return the one line that says why deflections are withheld (the stream's rate)."""
        return (f'{self.rate.describe("command")}: deflections withheld, the plant is simulated '
                f'at {self.fs:g} Hz (start simulator_node with -p fs:= the stream rate)')


def _columns(names: list, axes: list, width: int) -> list[int] | None:
    """Columns of `axes` in a message of joint `names` (unnamed: one axis), None if one lacks."""
    if not names:
        return [0] if len(axes) == 1 and width >= 1 else None
    try:
        return [names.index(a) for a in axes]
    except ValueError:
        return None


def answers_as_arrays(answers: list, n_axes: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """[(t_ns, y per axis, u per axis), ...] -> (stamps (m,), y (m, n_axes), u (m, n_axes))."""
    if not answers:
        return np.empty(0, dtype=np.int64), np.empty((0, n_axes)), np.empty((0, n_axes))
    t, y, u = zip(*answers)
    return np.array(t, dtype=np.int64), np.array(y, dtype=np.float64), np.array(u, np.float64)


class SimulatorNode(PiezoNode):
    """Thin wiring: voltage_command -> PlantResponder -> deflection."""

    NODE_NAME = 'simulator_node'
    PARAMS = (
        ParamSpec('fs', 2000.0, 'sample rate of the commands, Hz', low=1.0, high=100000.0,
                  read_only=True),
        ParamSpec('axes', ['x'], 'axes simulated (one plant each)', read_only=True,
                  check=AXES_CHECK),
        ParamSpec('plant_params', '', 'plant parameter YAML (empty: config/plant.yaml)',
                  read_only=True),
        ParamSpec('seed', 0, 'seed of the sensor noise (axis i uses seed + i)', low=0,
                  high=2**31 - 1, read_only=True),
        ParamSpec('max_fill', 20000, 'longest command gap bridged by holding the voltage, '
                  'samples', low=0, high=10**8, read_only=True),
        ParamSpec('rate_tolerance', RATE_TOLERANCE, 'relative difference between the command '
                  "stream's stamp rate and fs beyond which no deflection is published (ERROR)",
                  low=1e-6, high=0.5, read_only=True),
        BATCH_PARAM,
    )

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        from piezo_narx_ros.plant.axes import make_axis_plants
        p = self.params
        plants = make_axis_plants(p['axes'], p['plant_params'] or None, fs=p['fs'],
                                  seed=p['seed'])
        plants.warm_up()   # compile/load the numba kernels now, not on the first command
        self.responder = PlantResponder(plants, p['fs'], p['max_fill'], p['rate_tolerance'])
        self._error_log = EpisodeLog(self.get_logger())
        b = self.batch = p['batch']
        self.pub = self.sample_publisher(batch_topic(TOPIC_DEFLECTION, b), sample_type(b))
        # Raw CDR bytes in and out (see nodes.codec.decode_joint_state: 8x cheaper).
        self.sub = self.sample_subscription(
            batch_topic(TOPIC_COMMAND, b), self.on_command_batch if b > 1 else self.on_command,
            sample_type(b))
        self._names = list(self.responder.axes)
        # A stream's batch layout (names, effort width) -> its columns, and whether they are
        # the axes in order (then the effort array is used as it is, not copied by a fancy index).
        self._layout = (None, -1, None, False)
        self._seen = 0
        self.flush_timer = self.create_timer(0.2, self.on_idle_check)
        r = self.responder
        self._since = Since(lambda: {'rejected': r.rejected, 'stamp_outliers': r.stamp_outliers,
                                     'stream_restarts': r.stream_restarts,
                                     'rate_withheld': r.rate_withheld},
                            ('rejected', 'stamp_outliers', 'stream_restarts', 'rate_withheld'))
        self.diagnostics = Diagnostics(
            self, self.status, task='plant simulation',
            hardware_id=f"simulated cantilever (seed {p['seed']})")
        self.get_logger().info(f"simulating {self._names} at {p['fs']:g} Hz")

    def on_command(self, msg: bytes) -> None:
        try:
            sample = decode_joint_state(msg)
        except DataError as exc:
            self.responder.rejected += 1
            self.get_logger().warning(f'command refused: {exc}', throttle_duration_sec=1.0)
            return
        self.publish(self._command(sample.t_ns, sample.names, sample.effort))

    def _command(self, t_ns: int, names, effort) -> list:
        if names:
            volts = dict(zip(names, effort))
        else:  # an unnamed message drives the first axis
            volts = {self.responder.axes[0]: effort[0]} if len(effort) else {}
        try:
            return self.responder.on_command(t_ns, volts)
        except DataError as exc:
            self.get_logger().warning(f'command refused: {exc}', throttle_duration_sec=1.0)
            return []

    def on_command_batch(self, msg: bytes) -> None:
        """Feed a batch sample by sample through the one-sample call; answer with one batch."""
        try:
            batch = decode_joint_trajectory(msg)
        except DataError as exc:
            self.responder.rejected += 1
            self.get_logger().warning(f'command batch refused: {exc}', throttle_duration_sec=1.0)
            return
        names, r = batch.names, self.responder
        width = batch.effort.shape[1]
        if self._layout[0] != names or self._layout[1] != width:   # a stream's first batch
            columns = _columns(names, r.axes, width)
            self._layout = (names, width, columns,
                            columns is not None and columns == list(range(width)))
        columns, in_order = self._layout[2:]
        if columns is None:     # an axis is missing: every command refused, as one by one
            self.publish([a for t, u in zip(batch.t_ns.tolist(), batch.effort.tolist())
                          for a in self._command(t, names, u)])
            return
        rejected = r.rejected
        t, y, ua = r.on_commands(batch.t_ns, batch.effort if in_order else
                                 batch.effort[:, columns])
        if r.rejected > rejected:
            self.get_logger().warning(f'command batch: {r.rejected - rejected} command(s) '
                                      'refused (not finite)', throttle_duration_sec=1.0)
        if t.shape[0]:
            self.pub.publish(encode_joint_trajectory(t, self._names, y, ua))

    def publish(self, answers) -> None:
        if self.batch > 1:
            if answers:
                self.pub.publish(encode_joint_trajectory(
                    [a[0] for a in answers], self._names, [a[1] for a in answers],
                    [a[2] for a in answers]))
            return
        for t_ns, y, u in answers:
            self.pub.publish(encode_joint_state(t_ns, self._names, y, u))

    def on_idle_check(self) -> None:
        """Commands stopped while one was held back for its stamp: decide on it now."""
        n = self.responder.received
        if n == self._seen and self.responder.gate.holding:
            self.publish(self.responder.flush())
        # One writer: more commands than grid points are a faster stream (RateMonitor).
        self.responder.rate.single_writer = self.sub.get_publisher_count() == 1
        self._seen = n

    def status(self):
        """Log an ERROR status once per episode (see `_status`)."""
        level, message, values = self._status()
        self._error_log.status(level[0], message)
        return level, message, values

    def _status(self):
        """WARN when commands were refused since the previous tick (not forever after one)."""
        r = self.responder
        d = self._since.tick()
        problems = [f'{n} {what}' for n, what in (
            (d['rejected'], 'command(s) refused (not finite or missing axis)'),
            (d['stamp_outliers'], 'command stamp(s) refused as outliers'),
            (d['stream_restarts'], 'command stream restart(s) followed')) if n]
        values = {'answered': r.answered, 'rejected': r.rejected, 'gaps': r.gaps,
                  'filled': r.filled, 'stamp_outliers': r.stamp_outliers,
                  'stream_restarts': r.stream_restarts, 'holding': r.gate.holding,
                  'rate_withheld': r.rate_withheld}
        clash = same_name_problem(self, TOPIC_DEFLECTION)
        if clash:
            return DIAG_ERROR, clash, values
        if r.rate.off or d['rate_withheld']:
            return DIAG_ERROR, (f'{r.rate_line()} ({d["rate_withheld"]} withheld since the '
                                'last report)'
                                + ('; ' + '; '.join(problems) if problems else '')), values
        if problems:
            return DIAG_WARN, '; '.join(problems) + ' since the last report', values
        return DIAG_OK, 'ok', values


main = main_for(SimulatorNode)

if __name__ == '__main__':
    main()
