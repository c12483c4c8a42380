"""
The fit's settings: a preset's built-in values < a settings file < explicit overrides.

One table of keys (`CONFIG_KEYS`, config/fit.yaml lists them with their defaults) serves the
command line, the demo's settings and the reference. `merge_settings` returns a plain mapping,
`experiment_config` the validated ExperimentConfig built from it.
"""
from __future__ import annotations

# Keys a --config YAML file may hold (config/fit.yaml lists them all with their defaults).
CONFIG_KEYS = ('preset', 'family', 'ny', 'nu', 'hidden', 'seed', 'n_seeds', 'hnarx', 'hnarx_grid',
               'narx_beside', 'without_increments', 'small_networks', 'small_hidden',
               'arx_na', 'arx_nb', 'arx', 'split', 'max_lag', 'max_outside_fraction', 'residuals',
               'noise_model', 'noise_order', 'selection', 'jobs', 'training', 'final_training',
               'init_seconds', 'init_past', 'ensemble', 'ensemble_margin', 'command_topic',
               'deflection_topic')
# Settings that belong to the command line, not to ExperimentConfig, with their defaults.
CLI_DEFAULTS = {'arx': True, 'command_topic': 'piezo/voltage_command',
                'deflection_topic': 'piezo/deflection'}
PRESET_NAMES = ('search', 'paper', 'envelope')
#: The keys an override (a command-line option) may set.
OVERRIDE_KEYS = ('ny', 'nu', 'hidden', 'seed', 'n_seeds', 'split', 'arx_na', 'arx_nb', 'max_lag',
                 'max_outside_fraction', 'residuals', 'noise_model', 'noise_order', 'jobs',
                 'command_topic', 'deflection_topic', 'init_past')


def parse_range(text, name: str) -> tuple:
    """'1-4' -> (1, 2, 3, 4); '3' -> (3,); '1,3' -> (1, 3); a list of ints passes through."""
    from piezo_narx_ros.errors import ConfigError
    if isinstance(text, (list, tuple)):
        items = list(text)
    elif isinstance(text, int) and not isinstance(text, bool):
        items = [text]
    else:
        items = []
        try:
            for part in str(text).split(','):
                part = part.strip()
                if '-' in part[1:]:
                    lo, hi = part.split('-', 1)
                    lo, hi = int(lo), int(hi)
                    if hi < lo:
                        raise ValueError
                    items += list(range(lo, hi + 1))
                else:
                    items.append(int(part))
        except ValueError:
            raise ConfigError(f'--{name.replace("_", "-")}: not a lag range: {text!r} '
                              f'(use e.g. 1-4, 2 or 1,3)') from None
    if not all(isinstance(i, int) and not isinstance(i, bool) for i in items):
        raise ConfigError(f'{name}: lag orders must be integers, got {text!r}')
    return tuple(sorted(set(items)))


def preset_settings(preset: str) -> dict:
    """
    Built-in settings of a preset.

    ExperimentConfig's defaults, the preset's changes (PRESETS), and the command line's own keys
    (CLI_DEFAULTS).
    """
    from dataclasses import fields

    from piezo_narx_ros.errors import ConfigError
    from piezo_narx_ros.ident.selection.experiment import PRESETS, ExperimentConfig
    if preset not in PRESET_NAMES:
        raise ConfigError(f'preset must be one of {", ".join(PRESET_NAMES)}, got {preset!r}')
    base = ExperimentConfig()
    out = {f.name: getattr(base, f.name) for f in fields(ExperimentConfig)
           if f.name in CONFIG_KEYS}
    out.update(CLI_DEFAULTS)
    # The search has no grid; the experiment's settings it reads (split, tests, past) are the
    # paper's, and its window the estimator's 0.5 s.
    out.update(PRESETS.get(preset, {'init_seconds': 0.5}))
    out['preset'] = preset
    return out


def merge_settings(preset: str | None = None, config_file=None, overrides: dict | None = None,
                   no_arx: bool = False) -> dict:
    """
    Merge the settings: preset < `config_file` (YAML) < `overrides` (None values are ignored).

    preset None: the file's, else 'search'. no_arx: leave the ARX baseline out.
    """
    from piezo_narx_ros.errors import ConfigError
    doc = {}
    if config_file:
        from piezo_narx_ros.settings import read_yaml_mapping
        doc = read_yaml_mapping(config_file, 'settings', known=CONFIG_KEYS)
    preset = preset or doc.get('preset') or 'search'
    settings = preset_settings(preset)
    settings.update(doc)
    settings['preset'] = preset
    for key, value in (overrides or {}).items():
        if key not in OVERRIDE_KEYS:
            raise ConfigError(f'{key}: not a setting an option can override')
        if value is not None:
            settings[key] = value
    if no_arx:
        settings['arx'] = False
    for key in ('training', 'final_training', 'hnarx'):
        if not isinstance(settings[key], dict):
            raise ConfigError(f'{key}: must be a mapping of training options')
    grid = settings['hnarx_grid']
    if not isinstance(grid, (list, tuple)) or not all(isinstance(g, dict) for g in grid):
        raise ConfigError('hnarx_grid: must be a list of mappings of HysteresisNARX options')
    return settings


def experiment_config(settings: dict, progress: bool):
    """Build the ExperimentConfig from merged settings (ConfigError on bad values)."""
    from piezo_narx_ros.errors import ConfigError
    from piezo_narx_ros.ident.selection.experiment import ExperimentConfig
    try:
        cfg = ExperimentConfig(
            ny=parse_range(settings['ny'], 'ny'), nu=parse_range(settings['nu'], 'nu'),
            hidden=int(settings['hidden']), seed=int(settings['seed']),
            n_seeds=int(settings['n_seeds']), family=str(settings['family']),
            hnarx=dict(settings['hnarx']), hnarx_grid=tuple(settings['hnarx_grid']),
            narx_beside=str(settings['narx_beside']),
            without_increments=str(settings['without_increments']),
            small_networks=str(settings['small_networks']),
            small_hidden=int(settings['small_hidden']),
            selection=str(settings['selection']),
            arx_na=parse_range(settings['arx_na'], 'arx_na') if settings['arx'] else (),
            arx_nb=parse_range(settings['arx_nb'], 'arx_nb') if settings['arx'] else (),
            split=float(settings['split']), max_lag=int(settings['max_lag']),
            max_outside_fraction=float(settings['max_outside_fraction']),
            residuals=str(settings['residuals']), noise_model=str(settings['noise_model']),
            noise_order=int(settings['noise_order']), jobs=int(settings['jobs']),
            progress=None if progress else False, training=dict(settings['training']),
            final_training=dict(settings['final_training']),
            init_seconds=float(settings['init_seconds']),
            init_past=str(settings['init_past']),
            ensemble=int(settings['ensemble']),
            ensemble_margin=float(settings['ensemble_margin']))
    except (TypeError, ValueError) as exc:
        raise ConfigError(f'invalid setting: {exc}') from None
    cfg.validate()
    return cfg
