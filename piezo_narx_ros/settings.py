"""
Settings files: one reader for every YAML mapping the project loads (fit, demo, plant).

yaml.safe_load builds plain data only, so reading a settings file never executes code from it.
"""
from __future__ import annotations

from pathlib import Path

from piezo_narx_ros.errors import ConfigError


def read_yaml_mapping(path, what: str = 'settings', known=None) -> dict:
    """
    Return the mapping stored in the YAML file `path` (empty file: {}).

    what: what the file holds, for messages ('settings', 'demo settings', ...); known: the allowed
    keys (None: any). Raises ConfigError with one line naming the file when it cannot be read, is
    not YAML, is not a mapping, or holds a key outside `known`.
    """
    import yaml
    try:
        doc = yaml.safe_load(Path(path).read_text(encoding='utf-8'))
    except OSError as exc:
        raise ConfigError(f'{path}: cannot read {what} ({exc.strerror or exc})') from None
    except UnicodeDecodeError as exc:
        raise ConfigError(f'{path}: {what} must be UTF-8 text (byte {exc.start} is not)') from None
    except yaml.YAMLError as exc:
        raise ConfigError(f'{path}: not valid YAML ({str(exc).splitlines()[0]})') from None
    doc = {} if doc is None else doc
    if not isinstance(doc, dict):
        raise ConfigError(f'{path}: {what} must be a mapping of key: value')
    if known is not None:
        check_known(doc, known, str(path))
    return doc


def check_known(doc: dict, known, where: str) -> None:
    """Raise ConfigError naming the keys of `doc` that are not in `known`."""
    unknown = sorted(set(doc) - set(known))
    if unknown:
        raise ConfigError(f'{where}: unknown setting(s) {", ".join(map(str, unknown))}; '
                          f'known: {", ".join(map(str, known))}')
