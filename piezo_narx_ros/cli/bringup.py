"""
`piezo-narx bringup LAUNCH [NAME:=VALUE ...]`: start a YAML launch file's nodes as processes.

ros2 launch does not exist here; in a ROS install `ros2 launch piezo_narx_ros LAUNCH` reads the
same file.

LAUNCH is a path, or the name of a launch file of this package (share/piezo_narx_ros/launch, e.g.
`sim.launch.yaml`). NAME:=VALUE sets launch arguments as with ros2 launch; `--param
NODE.NAME=VALUE` adds a parameter to one node. The subset of the format read is documented in
piezo_narx_ros/demo/launch_file.py. Each node is started as `python -m MODULE ARGS --ros-args ...`,
its output is forwarded line by line with a `[name]` prefix, and all are stopped on Ctrl-C/SIGTERM
(SIGINT, then SIGTERM, then SIGKILL after timeouts). A node that exits while the others run is a
failure: the rest are stopped and bringup exits 1.
"""
from __future__ import annotations

import argparse
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from piezo_narx_ros.errors import ConfigError

NODES = {
    'command_node': 'piezo_narx_ros.nodes.command_node',
    'simulator_node': 'piezo_narx_ros.nodes.simulator_node',
    'estimator_node': 'piezo_narx_ros.nodes.estimator_node',
    'controller_node': 'piezo_narx_ros.nodes.controller_node',
    'driver_node': 'piezo_narx_ros.nodes.driver_node',
    'recorder_node': 'piezo_narx_ros.nodes.recorder_node',
    'player_node': 'piezo_narx_ros.nodes.player_node',
    'fake_rig': 'piezo_narx_ros.rig.fake_rig',
}
_NOT_ROS = {'fake_rig'}   # plain command-line programs: an `executable` action, not a `node`


@dataclass
class NodeSpec:
    """One process to start: command line and log prefix."""

    name: str
    argv: list[str]
    env: dict = field(default_factory=dict)


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser('bringup', help='start the nodes of a ROS 2 YAML launch file as '
                              'processes and stop them together',
                              description=__doc__.strip().split('\n\n')[0])
    p.add_argument('launch', help='launch file: a path, or a name in share/piezo_narx_ros/launch '
                   '(sim.launch.yaml, rig.launch.yaml, record.launch.yaml, estimate.launch.yaml, '
                   'control.launch.yaml)')
    p.add_argument('arguments', nargs='*', metavar='NAME:=VALUE',
                   help='launch arguments, as with ros2 launch (e.g. model:=fit/model.json)')
    p.add_argument('--param', '-p', action='append', default=[], metavar='NODE.NAME=VALUE',
                   help='add a parameter to one node, e.g. command_node.amplitude=50.0')
    p.add_argument('--duration', type=float, default=None, metavar='S',
                   help='stop everything after S seconds (default: run until Ctrl-C)')
    p.add_argument('--sigint-timeout', type=float, default=5.0, metavar='S',
                   help='time allowed after SIGINT before SIGTERM (default 5 s)')
    p.add_argument('--sigterm-timeout', type=float, default=3.0, metavar='S',
                   help='time allowed after SIGTERM before SIGKILL (default 3 s)')
    return p


def _launch_arguments(items: list[str]) -> dict[str, str]:
    out = {}
    for item in items:
        name, sep, value = item.partition(':=')
        if not sep or not name:
            raise ConfigError(f'launch arguments look like NAME:=VALUE, got {item!r}')
        out[name] = value
    return out


def _overrides(items: list[str]) -> dict[str, dict]:
    import yaml
    out: dict[str, dict] = {}
    for item in items:
        key, sep, raw = item.partition('=')
        node, dot, name = key.partition('.')
        if not sep or not dot or not node or not name:
            raise ConfigError(f'--param must look like NODE.NAME=VALUE, got {item!r}')
        out.setdefault(node, {})[name] = yaml.safe_load(raw) if raw else ''
    return out


def resolve_launch(name) -> Path:
    """Resolve a launch file: a path as given, or NAME in share/piezo_narx_ros/launch."""
    path = Path(name)
    if path.exists() or os.sep in str(name):
        return path
    from piezo_narx_ros.share import launch_path
    return launch_path(str(name))


def load_launch(path, arguments: dict[str, str] | None = None,
                overrides: dict[str, dict] | None = None) -> list[NodeSpec]:
    """
    Read a YAML launch file; returns the processes to start, in order.

    `arguments`: launch arguments {name: value}; `overrides`: {node name: {parameter: value}} added
    last (so they win). ConfigError (one line) on a bad file, argument or override.
    """
    from piezo_narx_ros.demo.launch_file import LaunchFile, _yaml_flow
    launch = LaunchFile(resolve_launch(path), arguments, NODES)
    overrides = dict(overrides or {})
    specs, names = [], set()
    for proc in launch.processes:
        if proc.name in names:
            raise ConfigError(f'{launch.path}: two processes named {proc.name!r} (set name)')
        names.add(proc.name)
        if proc.ros == (proc.executable in _NOT_ROS):
            raise ConfigError(f'{launch.path}: {proc.executable} must be started with '
                              f'{"an executable" if proc.ros else "a node"} action')
        argv = list(proc.argv)
        for k, v in overrides.pop(proc.name, {}).items():
            if not proc.ros:
                raise ConfigError(f'--param {proc.name}.{k}: {proc.name} takes no parameters')
            argv += ['-p', f'{k}:={_yaml_flow(v)}']
        if proc.prefix and shutil.which(proc.prefix[0]) is None:
            raise ConfigError(f'{launch.path}: launch-prefix of {proc.name}: no executable '
                              f'{proc.prefix[0]!r} on PATH')
        # python -m this module MODULE ...: see _child_main
        specs.append(NodeSpec(proc.name, [*proc.prefix, sys.executable, '-m', __name__,
                                          NODES[proc.executable], *argv], proc.env))
    if overrides:
        raise ConfigError(f'--param names node(s) not in {launch.path}: {", ".join(overrides)}')
    return specs


class Bringup:
    """Starts the processes, forwards their output, and stops them in order of escalation."""

    def __init__(self, specs: list[NodeSpec], out=None, sigint_timeout: float = 5.0,
                 sigterm_timeout: float = 3.0):
        self.specs = specs
        self.out = out or sys.stdout
        self.sigint_timeout = sigint_timeout
        self.sigterm_timeout = sigterm_timeout
        self.procs: dict[str, subprocess.Popen] = {}
        self._threads: list[threading.Thread] = []
        self._lock = threading.Lock()
        self.stop_requested = threading.Event()

    def log(self, name: str, line: str) -> None:
        with self._lock:
            self.out.write(f'[{name}] {line}\n')
            self.out.flush()

    def _forward(self, name: str, stream) -> None:
        for line in stream:
            self.log(name, line.rstrip('\n'))
        stream.close()

    def start(self) -> None:
        """
        Start every process.

        From the thread that will outlive them: the children's parent-death signal fires when the
        thread that forked them ends.
        """
        env = dict(os.environ, PYTHONUNBUFFERED='1', **{PARENT_PID_ENV: str(os.getpid())})
        for spec in self.specs:
            proc = subprocess.Popen(spec.argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                    stdin=subprocess.DEVNULL, text=True, env={**env, **spec.env})
            self.procs[spec.name] = proc
            self.log('bringup', f'started {spec.name} (pid {proc.pid})')
            t = threading.Thread(target=self._forward, args=(spec.name, proc.stdout), daemon=True)
            t.start()
            self._threads.append(t)

    def watch(self, duration: float | None = None) -> tuple[str, int] | None:
        """
        Wait for a stop request, the duration, or a node exiting.

        Returns (name, code) of a node that exited on its own, else None.
        """
        end = None if duration is None else time.monotonic() + duration
        while not self.stop_requested.is_set():
            for name, proc in self.procs.items():
                code = proc.poll()
                if code is not None:
                    return name, code
            if end is not None and time.monotonic() >= end:
                return None
            self.stop_requested.wait(0.1)
        return None

    def stop(self) -> dict[str, int]:
        """SIGINT all, then SIGTERM, then SIGKILL the ones still alive; returns exit codes."""
        for sig, timeout in ((signal.SIGINT, self.sigint_timeout),
                             (signal.SIGTERM, self.sigterm_timeout), (signal.SIGKILL, 5.0)):
            alive = [(n, p) for n, p in self.procs.items() if p.poll() is None]
            if not alive:
                break
            if sig != signal.SIGINT:
                self.log('bringup', f'{", ".join(n for n, _ in alive)} still running: '
                         f'{signal.Signals(sig).name}')
            for _, p in alive:
                try:
                    p.send_signal(sig)
                except ProcessLookupError:
                    pass
            end = time.monotonic() + timeout
            for _, p in alive:
                try:
                    p.wait(max(0.0, end - time.monotonic()))
                except subprocess.TimeoutExpired:
                    pass
        for t in self._threads:
            t.join(2.0)
        return {n: p.returncode for n, p in self.procs.items()}


def run(args) -> int:
    specs = load_launch(args.launch, _launch_arguments(args.arguments), _overrides(args.param))
    if args.duration is not None and not args.duration > 0:
        raise ConfigError(f'--duration must be > 0 s, got {args.duration}')
    bringup = Bringup(specs, sigint_timeout=args.sigint_timeout,
                      sigterm_timeout=args.sigterm_timeout)

    def request_stop(signum, _frame):
        bringup.stop_requested.set()

    old = {s: signal.signal(s, request_stop) for s in STOP_SIGNALS}
    try:
        bringup.start()
        died = bringup.watch(args.duration)
    finally:
        # Children share our process group: a terminal Ctrl-C reaches them too, which is fine
        # (they stop cleanly); stop() then only waits, or escalates for the stragglers.
        codes = bringup.stop()
        for s, h in old.items():
            signal.signal(s, h)
    summary = ', '.join(f'{n}={c}' for n, c in codes.items())
    bringup.log('bringup', f'stopped ({summary})')
    if died is not None:
        name, code = died
        print(f'piezo-narx: error: {name} exited unexpectedly with code {code}', file=sys.stderr)
        return 1
    return 0


PARENT_PID_ENV = 'PIEZO_NARX_PARENT_PID'
# Signals that stop bringup (and its children) cleanly; SIGHUP: the terminal was closed.
STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)
_PR_SET_PDEATHSIG = 1   # linux/prctl.h


def die_with_parent(parent_pid: str | None) -> None:
    """
    Ask Linux to send this process SIGTERM when its parent dies (prctl PR_SET_PDEATHSIG).

    So that `kill -9` of bringup does not leave its nodes running; then exit at once if the parent
    (pid `parent_pid`, as a string) already died before the request. Elsewhere than Linux this does
    nothing.
    """
    if not sys.platform.startswith('linux'):
        return
    import ctypes
    libc = ctypes.CDLL(None, use_errno=True)
    if libc.prctl(_PR_SET_PDEATHSIG, int(signal.SIGTERM), 0, 0, 0) != 0:
        return   # not fatal: the node still stops on bringup's own signals
    if parent_pid and os.getppid() != int(parent_pid):
        sys.exit(143)   # orphaned between fork and prctl


def _child_main(argv: list[str]) -> None:
    """
    `python -m piezo_narx_ros.cli.bringup MODULE ARGS...`: run MODULE.main() with ARGS.

    Importing a node takes a second or two (rclpy, numba); a stop request in that window would
    print a KeyboardInterrupt traceback from the middle of an import. This exits quietly (130).
    The child first asks to be stopped (SIGTERM, a clean stop) when bringup dies, even by
    SIGKILL, which no handler of bringup's can see: see `die_with_parent`.
    """
    import importlib
    die_with_parent(os.environ.get(PARENT_PID_ENV))
    try:
        module = importlib.import_module(argv[0])
    except KeyboardInterrupt:
        sys.exit(130)
    sys.argv = [argv[0], *argv[1:]]
    module.main()


if __name__ == '__main__':
    _child_main(sys.argv[1:])
