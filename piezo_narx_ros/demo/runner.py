"""
The demo's phases.

Record (nodes over DDS), fit (`piezo-narx fit`), live (estimator over DDS), analysis. Processes are
started and stopped with the bringup machinery (cli/bringup.py): a ROS 2 YAML launch file per phase
is written to the output folder and loaded with `load_launch`, so every phase can be rerun by hand
with `piezo-narx bringup OUT/<phase>.launch.yaml` (or `ros2 launch` in a ROS install).
"""
from __future__ import annotations

import copy
import json
import os
import signal
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from piezo_narx_ros.cli.bringup import STOP_SIGNALS, Bringup, NodeSpec, load_launch
from piezo_narx_ros.errors import ConfigError, PiezoNarxError
from piezo_narx_ros.settings import check_known, read_yaml_mapping

DEFAULTS = {
    'namespace': 'piezo', 'fs': 2000.0, 'seconds': 25.0, 'seed': 0, 'kind': 'protocol',
    'amplitude': 100.0,
    'fit': {'preset': 'envelope', 'split': 0.5, 'jobs': 2},
    'validation_kind': 'multisine', 'validation_seconds': 10.0, 'validation_seed': None,
    'slow_kind': 'sine', 'slow_freq': 0.5, 'slow_seconds': 10.0,
    # Axes of the stage (one signal each, seed + i) and its plant file ('' = config/plant.yaml;
    # a file name alone is looked up in the package's config folder, e.g. plant_2axis.yaml).
    'axes': ['x'], 'plant_params': '',
    'startup_timeout_s': 60.0, 'settle_s': 3.0, 'sigint_timeout_s': 10.0,
    'sigterm_timeout_s': 3.0,
    # piezo-narx demo --control (demo/control.py): identification record and fit, then each
    # mode live for `seconds` on a position reference (command_node kinds; amplitude in m).
    'control': {'record_seconds': 25.0, 'fit': {'preset': 'envelope', 'jobs': 2},
                'modes': ['linear', 'inverse', 'inverse_feedback'], 'seconds': 20.0,
                'kind': 'sine', 'freq': 1.0, 'amplitude': 3e-5, 'seed': None,
                'plant_params': ''},
    'quick': {'seconds': 4.0, 'validation_seconds': 3.0, 'slow_seconds': 3.0,
              'fit': {'n_seeds': 1, 'hidden': 6, 'hnarx': {'n_plays': 8, 'max_iter': 15},
                      'hnarx_grid': [], 'arx_na': 2, 'arx_nb': 2, 'jobs': 1},
              'control': {'seconds': 3.0, 'record_seconds': 8.0,
                          'fit': {'n_seeds': 1, 'hnarx_grid': [], 'jobs': 1}}},
}
_POSITIVE = ('fs', 'seconds', 'validation_seconds', 'slow_seconds', 'slow_freq', 'amplitude',
             'startup_timeout_s', 'settle_s', 'sigint_timeout_s', 'sigterm_timeout_s')
_KINDS = ('kind', 'validation_kind', 'slow_kind')


class PhaseFailed(PiezoNarxError):
    """A demo phase could not complete (a node died, nothing recorded, fit failed)."""


class Interrupted(Exception):
    """SIGINT/SIGTERM arrived; carries the signal number."""

    def __init__(self, signum: int):
        super().__init__(signal.Signals(signum).name)
        self.signum = signum


def _merge(base: dict, over: dict) -> dict:
    out = copy.deepcopy(base)
    for k, v in over.items():
        if isinstance(v, dict) and isinstance(out.get(k), dict):
            out[k] = _merge(out[k], v)
        else:
            out[k] = v
    return out


def load_settings(path=None, quick: bool = False, **overrides) -> dict:
    """
    Demo settings: DEFAULTS < YAML file < quick section (if quick) < non-None overrides.

    ConfigError names an unknown key or a bad value.
    """
    settings = copy.deepcopy(DEFAULTS)
    if path is not None:
        doc = read_yaml_mapping(path, 'demo settings', known=DEFAULTS)
        settings = _merge(settings, doc)
    if quick:
        settings = _merge(settings, settings.get('quick') or {})
    settings = _merge(settings, {k: v for k, v in overrides.items() if v is not None})
    for key in _POSITIVE:
        v = settings[key]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not v > 0:
            raise ConfigError(f'{key} must be a positive number, got {v!r}')
    for key in ('seed', 'validation_seed'):
        v = settings[key]
        if v is not None and (isinstance(v, bool) or not isinstance(v, int) or v < 0):
            raise ConfigError(f'{key} must be an integer >= 0, got {v!r}')
    if settings['validation_seed'] is None:
        settings['validation_seed'] = settings['seed'] + 1
    from piezo_narx_ros.cli.simulate import KINDS
    for key in _KINDS:
        if settings[key] not in KINDS:
            raise ConfigError(f'{key} must be one of {", ".join(KINDS)}, got {settings[key]!r}')
    if not isinstance(settings['fit'], dict):
        raise ConfigError('fit must be a mapping of `piezo-narx fit` settings')
    from piezo_narx_ros.ident.pipeline.settings import CONFIG_KEYS
    check_known(settings['fit'], CONFIG_KEYS, 'fit')
    if settings['fs'] * min(settings['seconds'], settings['validation_seconds'],
                            settings['slow_seconds']) < 500:
        raise ConfigError('seconds x fs must give at least 500 samples per phase')
    axes = settings['axes']
    if (not isinstance(axes, list) or not axes or len(set(axes)) != len(axes)
            or not all(isinstance(a, str) and a.strip() for a in axes)):
        raise ConfigError(f'axes must be a list of distinct non-empty names, got {axes!r}')
    if not isinstance(settings['plant_params'], str):
        raise ConfigError('plant_params must be a path or a file name of the config folder '
                          '(or empty)')
    check_control_settings(settings['control'])
    return settings


def plant_file(name: str) -> str:
    """Return a plant file setting as a path: a bare name is config/NAME ('' stays '')."""
    if not name or Path(name).exists() or '/' in name:
        return name
    from piezo_narx_ros.share import config_path
    return str(config_path(name))


def check_control_settings(c) -> None:
    """Raise ConfigError naming the first bad key of the demo's `control` settings."""
    from piezo_narx_ros.control.controller import MODES
    from piezo_narx_ros.plant.signals import KINDS
    if not isinstance(c, dict):
        raise ConfigError('control must be a mapping (demo --control settings)')
    check_known(c, DEFAULTS['control'], 'control')
    for key in ('record_seconds', 'seconds', 'freq', 'amplitude'):
        v = c[key]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not v > 0:
            raise ConfigError(f'control.{key} must be a positive number, got {v!r}')
    modes = c['modes']
    if not isinstance(modes, list) or not modes or any(m not in MODES for m in modes):
        raise ConfigError(f'control.modes must be a list of {list(MODES)}, got {modes!r}')
    if c['kind'] not in KINDS:
        raise ConfigError(f'control.kind must be one of {list(KINDS)}, got {c["kind"]!r}')
    if c['seed'] is not None and (isinstance(c['seed'], bool) or not isinstance(c['seed'], int)
                                  or c['seed'] < 0):
        raise ConfigError(f'control.seed must be an integer >= 0 or null, got {c["seed"]!r}')
    if not isinstance(c['fit'], dict) or not isinstance(c['plant_params'], str):
        raise ConfigError('control.fit must be a mapping of fit settings and '
                          'control.plant_params a path (or empty)')


class _Group(Bringup):
    """Bringup that writes its log to a file and keeps each process's last line (for errors)."""

    def __init__(self, specs, log_file, settings):
        super().__init__(specs, out=log_file, sigint_timeout=settings['sigint_timeout_s'],
                         sigterm_timeout=settings['sigterm_timeout_s'])
        self.last: dict[str, str] = {}

    def log(self, name: str, line: str) -> None:
        if line.strip():
            self.last[name] = line.strip()
        super().log(name, line)

    def exited(self) -> tuple[str, int] | None:
        """(name, code) of the first process that has exited, else None."""
        for name, proc in self.procs.items():
            code = proc.poll()
            if code is not None:
                return name, code
        return None


@dataclass
class PhaseTimes:
    """Wall time of each phase, s."""

    seconds: dict = field(default_factory=dict)

    def add(self, name: str, t0: float) -> None:
        self.seconds[name] = round(time.monotonic() - t0, 3)


class Demo:
    """Runs the phases in `out` with `settings` (see load_settings); `say` prints progress."""

    def __init__(self, settings: dict, out: Path, say=print, work: Path | None = None):
        self.s = settings
        self.out = Path(out)
        self.work = Path(work) if work is not None else self.out   # launch files and the log
        self.say = say
        self.ns = str(settings['namespace']).strip('/')
        self.groups: list[_Group] = []
        self.stop_signal: int | None = None
        self.probe = None
        self.times = PhaseTimes()
        self._log = None

    # -------------------------------------------------------------------- signals and children
    def request_stop(self, signum, _frame=None) -> None:
        """Signal handler: remember the signal; the waiting loops raise Interrupted."""
        self.stop_signal = signum

    def check(self) -> None:
        """Raise Interrupted once a stop was requested."""
        if self.stop_signal is not None:
            raise Interrupted(self.stop_signal)

    def start_group(self, specs: list[NodeSpec]) -> _Group:
        """Start processes (output to the log file); stopped by stop_all."""
        self.check()
        group = _Group(specs, self._log, self.s)
        self.groups.append(group)
        group.start()
        return group

    def check_alive(self, phase: str) -> None:
        """Raise PhaseFailed when a process of a running group has exited."""
        for g in self.groups:
            died = g.exited()
            if died is not None:
                time.sleep(0.2)   # a terminal Ctrl-C reaches the children too: prefer that
                self.check()
                name, code = died
                why = g.last.get(name, 'no output')
                raise PhaseFailed(f'{phase}: {name} exited with code {code} ({why}); log: '
                                  f'{self._log.name}')

    def stop_all(self) -> dict[str, int]:
        """Stop every running group (SIGINT -> SIGTERM -> SIGKILL); returns exit codes."""
        codes = {}
        while self.groups:
            codes.update(self.groups.pop().stop())
        return codes

    def wait(self, seconds: float) -> None:
        """Spin the diagnostics probe (or sleep) for `seconds`, staying interruptible."""
        end = time.monotonic() + seconds
        while True:
            self.check()
            left = end - time.monotonic()
            if left <= 0:
                return
            if self.probe is not None:
                self.probe.spin(min(left, 0.1))
            else:
                time.sleep(min(left, 0.1))

    # ----------------------------------------------------------------------------- node phases
    def _launch_yaml(self, phase: str, nodes: list[dict]) -> Path:
        """Write the phase's nodes ({'executable', 'parameters'}) as a ROS 2 YAML launch file."""
        import yaml
        path = self.work / f'{phase}.launch.yaml'
        actions = [{'node': {'pkg': 'piezo_narx_ros', 'exec': n['executable'],
                             'name': n['executable'], 'namespace': self.ns, 'output': 'screen',
                             'param': [{'name': k, 'value': v}
                                       for k, v in n['parameters'].items()]}} for n in nodes]
        path.write_text(f'# Written by piezo-narx demo; rerun with: piezo-narx bringup {path}\n'
                        + yaml.safe_dump({'launch': actions}, sort_keys=False))
        return path

    def fq(self, name: str) -> str:
        """Fully qualified name of a node of this demo's namespace."""
        return f'/{self.ns}/{name}' if self.ns else f'/{name}'

    def stream(self, phase: str, bag: Path, seconds: float, seed: int, model: Path | None = None,
               kind: str | None = None, extra_command: dict | None = None,
               extra_simulator: dict | None = None) -> dict:
        """
        Run command -> simulator (-> estimator) -> recorder until the excitation has been recorded.

        Returns {'published': N, 'received': messages recorded, 'codes': exit codes}.
        """
        s = self.s
        topics = ['voltage_command', 'deflection'] + (['deflection_estimate'] if model else [])
        stage = {'axes': list(s['axes'])}
        plant = plant_file(s['plant_params'])
        listeners = [{'executable': 'simulator_node',
                      'parameters': {'fs': float(s['fs']), 'seed': int(seed), **stage,
                                     **({'plant_params': plant} if plant else {}),
                                     **(extra_simulator or {})}}]
        if model is not None:
            listeners.append({'executable': 'estimator_node',
                              'parameters': {'model': str(model), 'fs': float(s['fs'])}})
        listeners.append({'executable': 'recorder_node',
                          'parameters': {'output': str(bag), 'topics': topics}})
        command = {'executable': 'command_node', 'parameters': {
            'fs': float(s['fs']), 'kind': kind or s['kind'], 'amplitude': float(s['amplitude']),
            'seconds': float(seconds), 'seed': int(seed), 'loop': False, **stage,
            'wait_for_subscribers': len(listeners), **(extra_command or {})}}
        specs = load_launch(self._launch_yaml(phase, listeners + [command]))
        names = [n['executable'] for n in listeners]
        self.wait(0.3)
        self.probe.latest.clear()   # statuses of an earlier phase's nodes (same names) are stale
        self.start_group([sp for sp in specs if sp.name != 'command_node'])
        self._wait_up(phase, names)
        self.start_group([sp for sp in specs if sp.name == 'command_node'])
        result = self._wait_recorded(phase, seconds, estimator=model is not None)
        result['codes'] = self.stop_all()
        bad = {n: c for n, c in result['codes'].items() if c not in (0, None)}
        if 'recorder_node' in bad:   # the bag may be incomplete: the phase has failed
            raise PhaseFailed(f'{phase}: recorder_node exited with code {bad["recorder_node"]} '
                              f'while closing {bag}; log: {self._log.name}')
        if bad:   # data complete (checked from the bag later), but say it was not clean
            self.say(f'  {phase}: warning: stopped with escalation: '
                     + ', '.join(f'{n} exit {c}' for n, c in bad.items()))
        return result

    def _wait_up(self, phase: str, names: list[str]) -> None:
        """Until every listed node publishes diagnostics (it is constructed and spinning)."""
        t0 = time.monotonic()
        while not all(self.probe.status(self.fq(n)) for n in names):
            self.check_alive(phase)
            if time.monotonic() - t0 > self.s['startup_timeout_s']:
                missing = [n for n in names if not self.probe.status(self.fq(n))]
                raise PhaseFailed(f'{phase}: {", ".join(missing)} did not come up within '
                                  f'{self.s["startup_timeout_s"]:g} s')
            self.wait(0.2)
        if 'estimator_node' in names:
            # Its initial values are the first measured samples: under load the simulator's
            # deflection reached it only ~170 samples late when streaming started at once.
            est = self.fq('estimator_node')
            while self.probe.value(est, 'measurement_publishers') < 1:
                self.check_alive(phase)
                if time.monotonic() - t0 > self.s['startup_timeout_s']:
                    raise PhaseFailed(f'{phase}: estimator_node never matched a deflection '
                                      f'publisher within {self.s["startup_timeout_s"]:g} s')
                self.wait(0.2)
        self.wait(0.5)   # discovery of the subscriptions among the nodes

    def _wait_recorded(self, phase: str, seconds: float, estimator: bool) -> dict:
        """
        Wait until the command node has finished and the recorder has everything.

        Or until nothing new arrived for settle_s. Prints a progress line every few seconds.
        """
        fs, n_total = self.s['fs'], int(round(seconds * self.s['fs']))
        cmd, sim, est, rec = (self.fq(n) for n in ('command_node', 'simulator_node',
                                                   'estimator_node', 'recorder_node'))
        limit = self.s['startup_timeout_s'] + 3 * seconds + 30
        deadline = time.monotonic() + limit
        last_line = last_change = time.monotonic()
        last_received = -1
        while True:
            self.check_alive(phase)
            now = time.monotonic()
            published = self.probe.value(cmd, 'published')
            received = self.probe.value(rec, 'received')
            if now > deadline:
                raise PhaseFailed(f'{phase}: excitation not recorded within {limit:.0f} s '
                                  f'({published} samples sent, {received} messages recorded)')
            st = self.probe.status(cmd)
            if received != last_received:
                last_received, last_change = received, now
            # 'finished' is the command node's state; the count is the fallback if that changes
            finished = (st is not None and st[0] == 'finished') or published >= n_total
            if now - last_line >= 3.0:
                last_line = now
                self.say(f'  {phase}: {published / fs:5.1f} of {seconds:g} s sent '
                         f'({published} samples), {received} messages recorded')
            if finished:
                answered = self.probe.value(sim, 'answered')
                target = published + answered
                done = answered >= published
                if estimator:
                    target += self.probe.value(est, 'estimates')
                    done = done and self.probe.value(est, 'commands') >= published
                if (done and received >= target) or now - last_change > self.s['settle_s']:
                    self.wait(0.3)
                    self.say(f'  {phase}: {published} samples sent, '
                             f'{self.probe.value(rec, "received")} messages recorded')
                    return {'published': published, 'expected': n_total,
                            'received': self.probe.value(rec, 'received')}
            self.wait(0.1)

    # ------------------------------------------------------------------------------- fit phase
    def fit(self, bag: Path, out: Path, no_report: bool = False) -> dict:
        """`piezo-narx fit BAG --out OUT --config OUT/../fit_settings.yaml` as a child process."""
        import yaml
        settings_path = self.work / f'{out.name}_settings.yaml'
        settings_path.write_text('# piezo-narx fit settings written by piezo-narx demo\n'
                                 + yaml.safe_dump(dict(self.s['fit']), sort_keys=False))
        # Through bringup's child entry point, like the nodes: the fit dies with the demo.
        argv = [sys.executable, '-m', 'piezo_narx_ros.cli.bringup', 'piezo_narx_ros.cli.main',
                'fit', str(bag), '--out', str(out), '--config', str(settings_path)]
        argv += ['--no-report'] if no_report else []
        group = self.start_group([NodeSpec('fit', argv)])
        t0 = last = time.monotonic()
        while group.exited() is None:
            if time.monotonic() - last >= 10.0:
                last = time.monotonic()
                self.say(f'  fit: running for {last - t0:.0f} s')
            self.wait(0.2)
        name, code = group.exited()
        self.groups.remove(group)
        group.stop()   # joins the output thread
        if code != 0:
            raise PhaseFailed(f'fit: piezo-narx fit exited with code {code} '
                              f'({group.last.get(name, "no output")}); log: {self._log.name}')
        return json.loads((out / 'model.json').read_text())

    # ----------------------------------------------------------------------------- orchestration
    def __enter__(self) -> 'Demo':
        from piezo_narx_ros.demo.probe import DiagnosticsProbe
        self.out.mkdir(parents=True, exist_ok=True)
        self.work.mkdir(parents=True, exist_ok=True)
        self._log = open(self.work / 'demo.log', 'a', buffering=1)
        self.probe = DiagnosticsProbe()
        return self

    def __exit__(self, *exc) -> bool:
        try:
            self.stop_all()
        finally:
            if self.probe is not None:
                self.probe.close()
                self.probe = None
            if self._log is not None:
                self._log.close()
        return False


def install_signal_handlers(demo: Demo) -> dict:
    """Route SIGINT/SIGTERM/SIGHUP to demo.request_stop; returns the previous handlers."""
    return {s: signal.signal(s, demo.request_stop) for s in STOP_SIGNALS}


def restore_signal_handlers(old: dict) -> None:
    """Put back the handlers returned by install_signal_handlers."""
    for s, h in old.items():
        signal.signal(s, h)


def stream_counts(bag: Path, topics: dict[str, str]) -> dict[str, int]:
    """Distinct stamps recorded per topic ({topic: 'effort'|'position'} -> {topic: count})."""
    from piezo_narx_ros.bag.reader import read_joint_series
    series = read_joint_series(bag, topics)
    return {t: int(np.unique(v.stamps_ns).size) for t, v in series.items()}


def child_environment() -> None:
    """Children discover only on this host unless the caller chose otherwise."""
    os.environ.setdefault('ROS_AUTOMATIC_DISCOVERY_RANGE', 'LOCALHOST')
    os.environ.setdefault('MPLBACKEND', 'Agg')
