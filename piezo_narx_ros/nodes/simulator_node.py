"""simulator_node: the piezo plant answering each voltage_command with a deflection.

One PiezoCantilever per axis. Each command sample advances the plant one period and is answered
on deflection with the command's stamp (position = measured m, effort = volts applied). Missing
samples (stamp gaps) advance the plant with the held command, as a real amplifier would hold its
output; they are not published (no command, no answer). The logic is in PlantResponder, tested
without DDS.
"""
from __future__ import annotations

import math

from piezo_narx_ros.errors import DataError
from piezo_narx_ros.nodes.common import (DIAG_OK, DIAG_WARN, TOPIC_COMMAND, TOPIC_DEFLECTION,
                                         Diagnostics, ParamSpec, PiezoNode,
                                         decode_joint_state, encode_joint_state, main_for)


class PlantResponder:
    """Plants (one per axis) driven by stamped commands; ROS-free.

    plants: {axis: PiezoCantilever}; fs: command rate, Hz; max_fill: longest gap (samples)
    bridged by holding the command (a longer one is not simulated: the plant just continues).
    """

    def __init__(self, plants: dict, fs: float, max_fill: int = 20000):
        self.plants = plants
        self.axes = list(plants)
        self.period_ns = 1e9 / fs
        self.max_fill = max_fill
        self.last_t: int | None = None
        self.last_u = {a: 0.0 for a in self.axes}
        self.answered = 0
        self.rejected = 0
        self.filled = 0
        self.gaps = 0
        self.out_of_order = 0

    def on_command(self, t_ns: int, volts: dict) -> tuple[list[float], list[float]] | None:
        """Apply {axis: V} at stamp t_ns; returns (y_meas m per axis, u_applied V per axis) in
        self.axes order, or None when the sample is refused (non-finite, missing axis, stale)."""
        try:
            u = [float(volts[a]) for a in self.axes]
        except KeyError as exc:
            self.rejected += 1
            raise DataError(f'command has no axis {exc.args[0]!r}') from None
        if not all(math.isfinite(x) for x in u):
            self.rejected += 1
            raise DataError(f'command is not finite: {u}')
        if self.last_t is not None:
            if t_ns <= self.last_t:
                self.out_of_order += 1
                raise DataError(f'command stamp {t_ns} ns is not after the previous one')
            missing = int(round((t_ns - self.last_t) / self.period_ns)) - 1
            if missing > 0:
                self.gaps += 1
                n = min(missing, self.max_fill)
                self.filled += n
                for a in self.axes:
                    plant, held = self.plants[a], self.last_u[a]
                    for _ in range(n):
                        plant.step(held)
        y_out, u_out = [], []
        for a, x in zip(self.axes, u):
            y_meas, _, u_app = self.plants[a].step(x)
            y_out.append(y_meas)
            u_out.append(u_app)
            self.last_u[a] = x
        self.last_t = t_ns
        self.answered += 1
        return y_out, u_out


class SimulatorNode(PiezoNode):
    """Thin wiring: voltage_command -> PlantResponder -> deflection."""

    NODE_NAME = 'simulator_node'
    PARAMS = (
        ParamSpec('fs', 2000.0, 'sample rate of the commands, Hz', low=1.0, high=100000.0,
                  read_only=True),
        ParamSpec('axes', ['x'], 'axes simulated (one plant each)', read_only=True,
                  check=(lambda v: len(v) > 0 and all(a.strip() for a in v),
                         'must be a non-empty list of non-empty names')),
        ParamSpec('plant_params', '', 'plant parameter YAML (empty: config/plant.yaml)',
                  read_only=True),
        ParamSpec('seed', 0, 'seed of the sensor noise (axis i uses seed + i)', low=0,
                  high=2**31 - 1, read_only=True),
        ParamSpec('max_fill', 20000, 'longest command gap bridged by holding the voltage, '
                  'samples', low=0, high=10**8, read_only=True),
    )

    def __init__(self, **kwargs):
        super().__init__(**kwargs)
        from piezo_narx_ros.plant import PiezoCantilever, load_plant_params
        p = self.params
        params = load_plant_params(p['plant_params'] or None)
        plants = {a: PiezoCantilever(params, fs=p['fs'], seed=p['seed'] + i)
                  for i, a in enumerate(p['axes'])}
        for plant in plants.values():
            plant.step(0.0)   # compile/load the numba kernel now, not on the first command
            plant.reset()
        self.responder = PlantResponder(plants, p['fs'], p['max_fill'])
        self.pub = self.sample_publisher(TOPIC_DEFLECTION)
        # Raw CDR bytes in and out (see common.decode_joint_state: 8x cheaper).
        self.sub = self.sample_subscription(TOPIC_COMMAND, self.on_command)
        self._names = list(p['axes'])
        self.diagnostics = Diagnostics(
            self, self.status, task='plant simulation',
            hardware_id=f"simulated cantilever (seed {p['seed']})")
        self.get_logger().info(f"simulating {p['axes']} at {p['fs']:g} Hz")

    def on_command(self, msg: bytes) -> None:
        try:
            sample = decode_joint_state(msg)
        except DataError as exc:
            self.responder.rejected += 1
            self.get_logger().warning(f'command refused: {exc}', throttle_duration_sec=1.0)
            return
        if sample.names:
            volts = dict(zip(sample.names, sample.effort))
        else:  # an unnamed message drives the first axis
            volts = {self.responder.axes[0]: sample.effort[0]} if sample.effort else {}
        try:
            y, u = self.responder.on_command(sample.t_ns, volts)
        except DataError as exc:
            self.get_logger().warning(f'command refused: {exc}', throttle_duration_sec=1.0)
            return
        self.pub.publish(encode_joint_state(sample.t_ns, self._names, y, u))

    def status(self):
        r = self.responder
        bad = r.rejected + r.out_of_order
        return (DIAG_WARN if bad else DIAG_OK, 'refusing commands' if bad else 'ok',
                {'answered': r.answered, 'rejected': r.rejected, 'gaps': r.gaps,
                 'filled': r.filled, 'out_of_order': r.out_of_order})


main = main_for(SimulatorNode)

if __name__ == '__main__':
    main()
