"""`piezo-narx bringup CONFIG.yaml`: start a set of nodes as processes (no ros2 launch here).

CONFIG (YAML):

    namespace: piezo                      # default namespace of every node
    nodes:
      - executable: simulator_node        # a node of this package (see NODES)
        name: simulator_node              # optional: log prefix and node name (__node remap)
        params_file: simulator_node.yaml  # optional, relative to CONFIG's folder
        parameters: {seed: 1}             # optional, override the file (-p name:=value)
        remap: {deflection: /other/deflection}   # optional, topic remaps (-r from:=to)

Each node is started as `python -m MODULE --ros-args -r __ns:=/NS --params-file F -p k:=v -r a:=b`,
its output is forwarded line by line with a `[name]` prefix, and all are stopped on Ctrl-C/SIGTERM
(SIGINT, then SIGTERM, then SIGKILL after timeouts). A node that exits while the others run is a
failure: the rest are stopped and bringup exits 1.
"""
from __future__ import annotations

import argparse
import os
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
    'driver_node': 'piezo_narx_ros.nodes.driver_node',
    'recorder_node': 'piezo_narx_ros.nodes.recorder_node',
    'player_node': 'piezo_narx_ros.nodes.player_node',
    'fake_rig': 'piezo_narx_ros.rig.fake_rig',
}
_KEYS = {'executable', 'name', 'params_file', 'parameters', 'remap', 'arguments'}


@dataclass
class NodeSpec:
    """One process to start: command line and log prefix."""
    name: str
    argv: list[str]
    env: dict = field(default_factory=dict)


def add_parser(subparsers) -> argparse.ArgumentParser:
    p = subparsers.add_parser('bringup', help='start a set of nodes (command, simulator, '
                              'estimator, ...) as processes and stop them together',
                              description=__doc__.split('\n\n')[0])
    p.add_argument('config', help='bringup YAML, e.g. config/bringup_sim.yaml')
    p.add_argument('--param', '-p', action='append', default=[], metavar='NODE.NAME=VALUE',
                   help='override a parameter of one node, e.g. estimator_node.model=m.json')
    p.add_argument('--duration', type=float, default=None, metavar='S',
                   help='stop everything after S seconds (default: run until Ctrl-C)')
    p.add_argument('--sigint-timeout', type=float, default=5.0, metavar='S',
                   help='time allowed after SIGINT before SIGTERM (default 5 s)')
    p.add_argument('--sigterm-timeout', type=float, default=3.0, metavar='S',
                   help='time allowed after SIGTERM before SIGKILL (default 3 s)')
    return p


def _yaml_scalar(value) -> str:
    """A value in ROS 2 `-p name:=value` syntax (YAML)."""
    import yaml
    text = yaml.safe_dump(value, default_flow_style=True).strip()
    return text[:-4].strip() if text.endswith('\n...') or text.endswith(' ...') else text


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


def load_config(path, overrides: dict[str, dict] | None = None) -> list[NodeSpec]:
    """Read a bringup YAML; returns the processes to start, in order. ConfigError on a bad file."""
    import yaml
    path = Path(path)
    try:
        doc = yaml.safe_load(path.read_text(encoding='utf-8'))
    except FileNotFoundError:
        raise ConfigError(f'bringup file not found: {path}') from None
    except OSError as exc:
        raise ConfigError(f'{path}: cannot read bringup file ({exc.strerror or exc})') from None
    except UnicodeDecodeError as exc:
        raise ConfigError(f'{path}: bringup file must be UTF-8 text (byte {exc.start} is '
                          'not)') from None
    except yaml.YAMLError as exc:
        raise ConfigError(f'{path}: not valid YAML ({" ".join(str(exc).split())})') from None
    if not isinstance(doc, dict) or not isinstance(doc.get('nodes'), list) or not doc['nodes']:
        raise ConfigError(f'{path}: needs a non-empty list `nodes`')
    ns = str(doc.get('namespace', 'piezo')).strip('/')
    overrides = dict(overrides or {})
    specs, names = [], set()
    for i, entry in enumerate(doc['nodes']):
        where = f'{path}: nodes[{i}]'
        if not isinstance(entry, dict):
            raise ConfigError(f'{where} must be a mapping')
        unknown = set(entry) - _KEYS
        if unknown:
            raise ConfigError(f'{where}: unknown key(s) {", ".join(sorted(unknown))}')
        exe = entry.get('executable')
        if exe not in NODES:
            raise ConfigError(f'{where}: executable must be one of {", ".join(NODES)}, got {exe!r}')
        name = str(entry.get('name', exe))
        if name in names:
            raise ConfigError(f'{where}: two nodes named {name!r} (set `name`)')
        names.add(name)
        argv = [sys.executable, '-m', __name__, NODES[exe]]   # see _child_main
        argv += [str(a) for a in entry.get('arguments', [])]
        if exe == 'fake_rig':   # not a ROS node: plain command-line arguments only
            specs.append(NodeSpec(name, argv))
            continue
        argv += ['--ros-args', '-r', f'__ns:=/{ns}' if ns else '__ns:=/']
        if 'name' in entry:
            argv += ['-r', f'__node:={name}']
        if entry.get('params_file'):
            pf = Path(entry['params_file'])
            pf = pf if pf.is_absolute() else path.parent / pf
            if not pf.is_file():
                raise ConfigError(f'{where}: params_file not found: {pf}')
            argv += ['--params-file', str(pf)]
        params = dict(entry.get('parameters') or {})
        params.update(overrides.pop(name, {}))
        for k, v in params.items():
            argv += ['-p', f'{k}:={_yaml_scalar(v)}']
        remap = entry.get('remap') or {}
        if not isinstance(remap, dict):
            raise ConfigError(f'{where}: remap must be a mapping from:to')
        for a, b in remap.items():
            argv += ['-r', f'{a}:={b}']
        specs.append(NodeSpec(name, argv))
    if overrides:
        raise ConfigError(f'--param names node(s) not in {path}: {", ".join(overrides)}')
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
        env = dict(os.environ, PYTHONUNBUFFERED='1')
        for spec in self.specs:
            proc = subprocess.Popen(spec.argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                    stdin=subprocess.DEVNULL, text=True, env={**env, **spec.env})
            self.procs[spec.name] = proc
            self.log('bringup', f'started {spec.name} (pid {proc.pid})')
            t = threading.Thread(target=self._forward, args=(spec.name, proc.stdout), daemon=True)
            t.start()
            self._threads.append(t)

    def watch(self, duration: float | None = None) -> tuple[str, int] | None:
        """Wait for a stop request, the duration, or a node exiting; returns (name, code) of a
        node that exited on its own, else None."""
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
    specs = load_config(args.config, _overrides(args.param))
    if args.duration is not None and not args.duration > 0:
        raise ConfigError(f'--duration must be > 0 s, got {args.duration}')
    bringup = Bringup(specs, sigint_timeout=args.sigint_timeout,
                      sigterm_timeout=args.sigterm_timeout)

    def request_stop(signum, _frame):
        bringup.stop_requested.set()

    old = {s: signal.signal(s, request_stop) for s in (signal.SIGINT, signal.SIGTERM)}
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


def _child_main(argv: list[str]) -> None:
    """`python -m piezo_narx_ros.cli.bringup MODULE ARGS...`: run MODULE.main() with ARGS.

    Importing a node takes a second or two (rclpy, numba); a stop request in that window would
    print a KeyboardInterrupt traceback from the middle of an import. This exits quietly (130).
    """
    import importlib
    try:
        module = importlib.import_module(argv[0])
    except KeyboardInterrupt:
        sys.exit(130)
    sys.argv = [argv[0], *argv[1:]]
    module.main()


if __name__ == '__main__':
    _child_main(sys.argv[1:])
