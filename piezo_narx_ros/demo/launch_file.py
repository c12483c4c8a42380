"""
Read a ROS 2 YAML launch file into the processes `piezo-narx bringup` starts (no ros2 launch here).

The same file serves `ros2 launch piezo_narx_ros NAME.launch.yaml` in a ROS install, so only the
launch_ros frontend's own schema is accepted (ros2/launch_ros, launch_ros/actions/node.py; launch,
launch/actions/execute_process.py), and anything outside the subset below is refused with one
line naming it, rather than ignored:

    launch:
      - arg: {name: N, default: D, description: ...}     # `N:=V` on the command line; no default
      - let: {name: N, value: V}                           #   = required
      - node:                                              # one process per node
          pkg: piezo_narx_ros                              # this package's executables only
          exec: simulator_node
          name: simulator_node                             # -r __node:=
          namespace: piezo                                 # -r __ns:=/piezo
          args: '--extra args'                             # before --ros-args
          ros_args: '-p a:=1'                              # after --ros-args
          param: [{from: FILE}, {name: N, value: V}]       # --params-file FILE, -p N:=V
          remap: [{from: A, to: B}]                        # -r A:=B
          env: [{name: N, value: V}]
          launch-prefix: chrt -f 80                        # a command the process runs under
          output: screen                                   # accepted; output is always shown
          if: $(var x)   /   unless: $(var x)              # on node and executable
      - executable:                                        # a non-ROS process (fake_rig)
          cmd: $(exec-in-pkg fake_rig piezo_narx_ros) --port 50000
          name: fake_rig

Substitutions: $(var N), $(env N [default]), $(find-pkg-share piezo_narx_ros), $(dirname),
$(exec-in-pkg EXE piezo_narx_ros) (first word of an executable's cmd). A parameter value that
contains a substitution is read as YAML after substitution (launch_ros does the same: `500`
becomes an integer, `''` an empty string). The command lines are those launch_ros builds:
EXE ARGS --ros-args -r __node:=NAME -r __ns:=NS --params-file F -p N:=V -r A:=B.
"""
from __future__ import annotations

import re
import shlex
from dataclasses import dataclass, field
from pathlib import Path

from piezo_narx_ros.errors import ConfigError

PACKAGE = 'piezo_narx_ros'
_SUBST = re.compile(r'\$\(([a-z][a-z-]*)((?:\s+[^\s()]+)*)\s*\)')
_NODE_KEYS = {'pkg', 'exec', 'name', 'namespace', 'args', 'ros_args', 'param', 'remap', 'env',
              'output', 'exec_name', 'if', 'unless', 'launch-prefix'}
_EXECUTABLE_KEYS = {'cmd', 'name', 'env', 'output', 'if', 'unless', 'launch-prefix'}


@dataclass
class Process:
    """
    One process of a launch file: the executable of this package, its arguments, environment.

    `argv` holds everything after the executable (command-line arguments, then --ros-args ...).
    `ros` is False for a plain executable (fake_rig). `prefix`: the launch-prefix's words (a
    command that runs the process, e.g. `chrt -f 80` for a real-time priority; empty: none).
    """

    name: str
    executable: str
    argv: list[str]
    env: dict = field(default_factory=dict)
    ros: bool = True
    prefix: list[str] = field(default_factory=list)


class LaunchFile:
    """Parse `path` with launch arguments `args` ({name: value}); `processes` in file order."""

    def __init__(self, path, args: dict[str, str] | None = None, executables=()):
        import yaml
        self.path = Path(path)
        self.executables = set(executables)
        try:
            doc = yaml.safe_load(self.path.read_text(encoding='utf-8'))
        except FileNotFoundError:
            raise ConfigError(f'launch file not found: {self.path}') from None
        except OSError as exc:
            raise ConfigError(f'{self.path}: cannot read launch file '
                              f'({exc.strerror or exc})') from None
        except UnicodeDecodeError as exc:
            raise ConfigError(f'{self.path}: launch file must be UTF-8 text (byte {exc.start} '
                              'is not)') from None
        except yaml.YAMLError as exc:
            raise ConfigError(f'{self.path}: not valid YAML ({" ".join(str(exc).split())})') \
                from None
        if not isinstance(doc, dict) or set(doc) != {'launch'} or \
                not isinstance(doc['launch'], list):
            raise ConfigError(f'{self.path}: a YAML launch file is a mapping with one key '
                              '`launch:` holding a list of actions')
        self.given = {str(k): str(v) for k, v in (args or {}).items()}
        self.vars: dict[str, str] = {}
        self.declared: dict[str, str] = {}   # name -> description
        self.processes: list[Process] = []
        for i, item in enumerate(doc['launch']):
            where = f'{self.path}: launch[{i}]'
            if not isinstance(item, dict) or len(item) != 1:
                raise ConfigError(f'{where} must be a mapping with one action (arg, let, node, '
                                  'executable)')
            (kind, body), = item.items()
            if not isinstance(body, dict):
                raise ConfigError(f'{where}: {kind} needs a mapping of attributes')
            handler = {'arg': self._arg, 'let': self._let, 'node': self._node,
                       'executable': self._executable}.get(kind)
            if handler is None:
                raise ConfigError(f'{where}: action {kind!r} is not supported by bringup '
                                  '(arg, let, node, executable)')
            handler(body, f'{where} ({kind})')
        unknown = sorted(set(self.given) - set(self.declared))
        if unknown:
            raise ConfigError(f'{self.path}: no launch argument {", ".join(unknown)} '
                              f'(declared: {", ".join(self.declared) or "none"})')

    # -------------------------------------------------------------------------- substitutions
    def subst(self, text, where: str) -> str:
        """`text` with every $(...) substitution performed."""
        text = str(text)

        def one(m) -> str:
            name, words = m.group(1), m.group(2).split()
            if name == 'var' and len(words) == 1:
                if words[0] not in self.vars:
                    raise ConfigError(f'{where}: $(var {words[0]}) is not defined (declare it '
                                      'with arg or let, before use)')
                return self.vars[words[0]]
            if name == 'env' and len(words) in (1, 2):
                import os
                value = os.environ.get(words[0], words[1] if len(words) == 2 else None)
                if value is None:
                    raise ConfigError(f'{where}: environment variable {words[0]} is not set')
                return value
            if name == 'find-pkg-share' and len(words) == 1:
                return str(_package_share(words[0], where))
            if name == 'dirname' and not words:
                return str(self.path.resolve().parent)
            raise ConfigError(f'{where}: substitution $({m.group(0)[2:-1].strip()}) is not '
                              'supported by bringup (var, env, find-pkg-share, dirname, '
                              'exec-in-pkg)')

        out = _SUBST.sub(one, text)
        if '$(' in out:
            raise ConfigError(f'{where}: cannot read the substitution in {text!r}')
        return out

    def _value(self, value, where: str):
        """Return a parameter value: YAML-typed as written, or read as YAML after substitution."""
        import yaml
        if isinstance(value, list):
            return [self._value(v, where) for v in value]
        if not isinstance(value, str) or '$(' not in value:
            return value
        text = self.subst(value, where)
        try:
            parsed = yaml.safe_load(text) if text else ''
        except yaml.YAMLError:
            return text
        return parsed if isinstance(parsed, (bool, int, float, str, list)) else text

    def _condition(self, body: dict, where: str) -> bool:
        for key, want in (('if', True), ('unless', False)):
            if key in body:
                text = self.subst(body[key], where).strip().lower()
                if text not in ('true', 'false', '1', '0'):
                    raise ConfigError(f'{where}: {key} must be true or false, got {text!r}')
                if (text in ('true', '1')) != want:
                    return False
        return True

    # ------------------------------------------------------------------------------- actions
    def _arg(self, body: dict, where: str) -> None:
        _check_keys(body, {'name', 'default', 'description'}, where)
        name = str(body.get('name', ''))
        if not name:
            raise ConfigError(f'{where}: needs a name')
        self.declared[name] = str(body.get('description', ''))
        if name in self.given:
            self.vars[name] = self.given[name]
        elif 'default' in body:
            self.vars[name] = self.subst(_scalar_text(body['default']), where)
        else:
            raise ConfigError(f'{self.path}: launch argument {name!r} is required '
                              f'({self.declared[name] or "no description"}); pass {name}:=VALUE')

    def _let(self, body: dict, where: str) -> None:
        _check_keys(body, {'name', 'value'}, where)
        if 'name' not in body or 'value' not in body:
            raise ConfigError(f'{where}: needs name and value')
        self.vars[str(body['name'])] = self.subst(_scalar_text(body['value']), where)

    def _node(self, body: dict, where: str) -> None:
        _check_keys(body, _NODE_KEYS, where)
        if not self._condition(body, where):
            return
        pkg = self.subst(body.get('pkg', ''), where)
        exe = self.subst(body.get('exec', ''), where)
        if pkg != PACKAGE:
            raise ConfigError(f'{where}: bringup starts only {PACKAGE} nodes, got pkg {pkg!r}')
        self._check_executable(exe, where)
        name = self.subst(body['name'], where) if 'name' in body else None
        argv = shlex.split(self.subst(body.get('args', ''), where))
        argv.append('--ros-args')
        if 'ros_args' in body:
            argv += shlex.split(self.subst(body['ros_args'], where))
        if name is not None:
            argv += ['-r', f'__node:={name}']
        if 'namespace' in body:
            ns = self.subst(body['namespace'], where).strip('/')
            argv += ['-r', f'__ns:=/{ns}']
        for j, param in enumerate(_list(body.get('param'), f'{where}: param')):
            here = f'{where} param[{j}]'
            if not isinstance(param, dict):
                raise ConfigError(f'{here} must be {{from: FILE}} or {{name: N, value: V}}')
            if 'from' in param:
                _check_keys(param, {'from', 'allow_substs'}, here)
                path = Path(self.subst(param['from'], here))
                path = path if path.is_absolute() else self.path.parent / path
                if not path.is_file():
                    raise ConfigError(f'{here}: parameter file not found: {path}')
                argv += ['--params-file', str(path)]
            else:
                _check_keys(param, {'name', 'value'}, here)
                if 'name' not in param or 'value' not in param:
                    raise ConfigError(f'{here}: needs name and value (nested param groups are '
                                      'not supported by bringup)')
                argv += ['-p', f'{self.subst(param["name"], here)}:='
                         f'{_yaml_flow(self._value(param["value"], here))}']
        for j, remap in enumerate(_list(body.get('remap'), f'{where}: remap')):
            here = f'{where} remap[{j}]'
            if not isinstance(remap, dict) or set(remap) != {'from', 'to'}:
                raise ConfigError(f'{here} must be {{from: A, to: B}}')
            argv += ['-r', f'{self.subst(remap["from"], here)}:={self.subst(remap["to"], here)}']
        self.processes.append(Process(name or exe, exe, argv, self._env(body, where),
                                      prefix=self._prefix(body, where)))

    def _executable(self, body: dict, where: str) -> None:
        _check_keys(body, _EXECUTABLE_KEYS, where)
        if not self._condition(body, where):
            return
        cmd = str(body.get('cmd', '')).strip()
        m = re.match(r'\$\(exec-in-pkg\s+(\S+)\s+(\S+)\s*\)', cmd)
        if not m:
            raise ConfigError(f'{where}: cmd must start with $(exec-in-pkg EXECUTABLE '
                              f'{PACKAGE})')
        exe, pkg = self.subst(m.group(1), where), self.subst(m.group(2), where)
        if pkg != PACKAGE:
            raise ConfigError(f'{where}: bringup starts only {PACKAGE} executables, got {pkg!r}')
        self._check_executable(exe, where)
        argv = shlex.split(self.subst(cmd[m.end():], where))
        name = self.subst(body['name'], where) if 'name' in body else exe
        self.processes.append(Process(name, exe, argv, self._env(body, where), ros=False,
                                      prefix=self._prefix(body, where)))

    def _prefix(self, body: dict, where: str) -> list[str]:
        # As launch does: the substituted text split like a shell would; empty means none.
        return shlex.split(self.subst(_scalar_text(body.get('launch-prefix', '')), where))

    def _env(self, body: dict, where: str) -> dict:
        env = {}
        for j, item in enumerate(_list(body.get('env'), f'{where}: env')):
            if not isinstance(item, dict) or set(item) != {'name', 'value'}:
                raise ConfigError(f'{where} env[{j}] must be {{name: N, value: V}}')
            env[str(item['name'])] = self.subst(_scalar_text(item['value']), where)
        return env

    def _check_executable(self, exe: str, where: str) -> None:
        if exe not in self.executables:
            raise ConfigError(f'{where}: exec must be one of {", ".join(sorted(self.executables))}'
                              f', got {exe!r}')


def _package_share(package: str, where: str) -> Path:
    if package == PACKAGE:
        from piezo_narx_ros.share import share_dir
        return share_dir()
    try:
        from ament_index_python.packages import get_package_share_directory
        return Path(get_package_share_directory(package))
    except Exception:  # noqa: BLE001 - any lookup failure is the same answer for the user
        raise ConfigError(f'{where}: package {package!r} not found (ament index)') from None


def _check_keys(body: dict, known: set, where: str) -> None:
    unknown = sorted(set(body) - known)
    if unknown:
        raise ConfigError(f'{where}: unknown attribute(s) {", ".join(map(str, unknown))} '
                          f'(bringup reads: {", ".join(sorted(known))})')


def _list(value, where: str) -> list:
    if value is None:
        return []
    if not isinstance(value, list):
        raise ConfigError(f'{where} must be a list')
    return value


def _scalar_text(value) -> str:
    """Return a YAML scalar as launch reads it: booleans as true/false, numbers as written."""
    if isinstance(value, bool):
        return 'true' if value else 'false'
    return str(value)


# Words rcl's YAML parser reads as booleans (YAML 1.1) that PyYAML writes bare: an axis named y.
_BOOLISH = {'y', 'n', 'yes', 'no', 'on', 'off', 'true', 'false'}


def _yaml_flow(value) -> str:
    """Return a value in ROS 2 `-p name:=value` syntax (YAML flow)."""
    import yaml

    class Dumper(yaml.SafeDumper):

        def represent_str(self, data):
            style = "'" if data.lower() in _BOOLISH else None
            return self.represent_scalar('tag:yaml.org,2002:str', data, style=style)
    Dumper.add_representer(str, Dumper.represent_str)
    text = yaml.dump(value, Dumper=Dumper, default_flow_style=True).strip()
    return text[:-4].strip() if text.endswith('\n...') or text.endswith(' ...') else text
