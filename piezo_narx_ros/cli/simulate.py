"""
`piezo-narx simulate`: excite the simulated cantilever and write the record as .npz.

Writes u (commanded V), u_applied (V), y (measured m), y_true (m), t (s), fs (Hz) and meta (a JSON
string with the signal and plant parameters). Imports nothing heavy until run().
"""
import argparse

# Literal (importing plant.signals would load numba here); test_plant_cli checks it against KINDS.
KINDS = ('multisine', 'sine', 'triangle', 'chirp', 'aprbs', 'steps', 'playback', 'protocol',
         'growing_sine', 'holds')
PREAMBLES = ('none', 'fade-out')     # likewise plant.signals.PREAMBLES
# CLI flag -> generate() option name; None values are left to the generator's defaults.
SIGNAL_FLAGS = {
    'freq': 'freq', 'phase': 'phase', 'f_min': 'f_min', 'f_max': 'f_max', 'f_res': 'f_res',
    'spectrum': 'spectrum', 'f0': 'f0', 'f1': 'f1', 'method': 'method', 'min_hold': 'min_hold',
    'max_hold': 'max_hold', 'levels': 'levels', 'hold': 'hold', 'file': 'path', 'key': 'key',
    'column': 'column', 'file_fs': 'file_fs', 'u_min': 'u_min', 'u_max': 'u_max',
    'slew_rate': 'slew_rate', 'cycles': 'cycles', 'slow_freq': 'slow_freq',
    'resample': 'resample', 'loop': 'loop', 'growth': 'growth',
    'start_fraction': 'start_fraction', 'ramp': 'ramp',
}


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Register `simulate` (light imports only)."""
    p = subparsers.add_parser(
        'simulate',
        help='simulate the piezo cantilever under an excitation and write an .npz record',
        description='Simulate the piezo cantilever (config/plant.yaml) under an excitation signal '
                    'and write u, u_applied, y, y_true, t, fs to an .npz file. Units: V, m, s, '
                    'Hz.')
    p.add_argument('--signal', choices=KINDS, default='multisine',
                   help='excitation kind (default multisine; protocol: the identification '
                        'protocol covering fast, slow, step and hold moves, docs/envelope.md)')
    p.add_argument('--seconds', type=float, default=None,
                   help='duration, s (default 25; playback: the file length)')
    p.add_argument('--fs', type=float, default=None,
                   help="sample rate, Hz (default 2000; playback: the file's own rate)")
    p.add_argument('--amplitude', type=float, default=None,
                   help='peak deviation from the offset, V (default 100; playback: as recorded)')
    p.add_argument('--offset', type=float, default=0.0, help='offset, V (default 0)')
    p.add_argument('--seed', type=int, default=0,
                   help='seed of the signal and of the sensor noise')
    p.add_argument('--plant-config', default=None, help='plant YAML (default config/plant.yaml)')
    p.add_argument('--out', required=True, help='output file, .npz')
    p.add_argument('--force', action='store_true', help='overwrite --out if it exists')
    g = p.add_argument_group('signal options (defaults: piezo_narx_ros.plant.signals.OPTIONS)')
    g.add_argument('--freq', type=float, help='sine/triangle frequency, Hz (1)')
    g.add_argument('--phase', type=float, help='sine phase, rad (0)')
    g.add_argument('--f-min', type=float, help='multisine lowest line, Hz (0.1)')
    g.add_argument('--f-max', type=float, help='multisine highest line, Hz (100)')
    g.add_argument('--f-res', type=float, help='multisine line spacing, Hz (1/seconds)')
    g.add_argument('--spectrum', choices=('flat', 'pink', 'brown'),
                   help='multisine amplitude spectrum (flat)')
    g.add_argument('--f0', type=float, help='chirp start frequency, Hz (1)')
    g.add_argument('--f1', type=float, help='chirp end frequency, Hz (0.45*fs)')
    g.add_argument('--method', choices=('linear', 'logarithmic'), help='chirp sweep (linear)')
    g.add_argument('--min-hold', type=float, help='APRBS shortest hold, s (0.01)')
    g.add_argument('--max-hold', type=float, help='APRBS longest hold, s (0.5)')
    g.add_argument('--levels',
                   help='steps: comma-separated levels, in units of the amplitude (0,1,0,-1,0)')
    g.add_argument('--hold', type=float, help='steps: hold per level, s (even split)')
    g.add_argument('--file', help='playback: .npz (key --key), .mat (variable --column or --key) '
                                  'or a text table (column --column), played as recorded')
    g.add_argument('--key', help='playback .npz key or .mat variable (u)')
    g.add_argument('--column', help='playback table column: header name or 1-based number (the '
                                    'u column, as fit reads it); for a .mat, a variable name')
    g.add_argument('--file-fs', type=float,
                   help='playback file sample rate, Hz, for a file without fs or t')
    g.add_argument('--resample', action='store_const', const=True,
                   help='playback: resample a file at another rate than --fs (linear)')
    g.add_argument('--loop', action='store_const', const=True,
                   help='playback: repeat the file to fill --seconds')
    g.add_argument('--cycles', type=int, help='protocol: repeats of the section sequence (2)')
    g.add_argument('--slow-freq', type=float, help='protocol: slow-loop frequency, Hz (0.5)')
    g.add_argument('--growth', choices=('linear', 'exponential'),
                   help='growing_sine: how the amplitude grows (linear)')
    g.add_argument('--start-fraction', type=float,
                   help='growing_sine: amplitude when the sweep starts, fraction (0.05)')
    g.add_argument('--ramp', type=float, help='holds: ramp time between levels, s (0.01)')
    g.add_argument('--u-min', type=float, help='command clamp, V (-200)')
    g.add_argument('--u-max', type=float, help='command clamp, V (200)')
    g.add_argument('--slew-rate', type=float, help='command slew limit, V/s (none)')
    r = p.add_argument_group('a rig session (docs/real.md; all off by default)')
    r.add_argument('--history', type=float, default=0.0, metavar='SECONDS',
                   help='seconds of random past input before the record (0: the plant starts '
                        'at rest); it ends at the first command and holds there --history-hold s, '
                        'so the record starts with hysteresis memory set and creep moving')
    r.add_argument('--history-hold', type=float, default=1.0, metavar='SECONDS',
                   help='hold at the first command between the history and the record (1)')
    r.add_argument('--history-amplitude', type=float, metavar='V',
                   help="the history's peak deviation from --offset, V (the record's)")
    r.add_argument('--history-seed', type=int, metavar='N',
                   help='seed of the history (default --seed; its own stream either way)')
    r.add_argument('--sensor-offset', type=float, metavar='M',
                   help='constant added to the measured output, m (0; a negative value as '
                        '--sensor-offset=-2e-6)')
    r.add_argument('--session', type=int, metavar='K',
                   help='draw the sensor offset of session K, uniform in +-'
                        '--session-spread')
    r.add_argument('--session-spread', type=float, default=2.5e-6, metavar='M',
                   help='largest session offset, m (2.5e-6: sessions differ by up to 5 um)')
    r.add_argument('--sensor-bits', type=int, metavar='B',
                   help='a B-bit sensor over --sensor-span: its quantisation and full scale '
                        "replace the plant config's quantisation")
    r.add_argument('--sensor-span', type=float, metavar='M',
                   help='full scale of the --sensor-bits converter, m, centred on 0')
    r.add_argument('--preamble', choices=PREAMBLES, default='none',
                   help='moves played before the record, part of it (fade-out: sine cycles '
                        'about --offset fading from --amplitude to 0, so the memory the past '
                        'left is wiped; evaluate --init-samples over them sets the state)')
    r.add_argument('--preamble-seconds', type=float, default=2.0, metavar='SECONDS',
                   help='length of the preamble, s (2)')
    r.add_argument('--preamble-cycles', type=float, default=20.0, metavar='N',
                   help='sine cycles of the preamble (20)')
    return p


def session_settings(args, u, amplitude):
    """
    Check the rig-session settings: (history volts or None, sensor kwargs, meta).

    u: the record's commands (V); amplitude: its peak deviation from --offset (V).
    """
    from piezo_narx_ros.errors import ConfigError
    from piezo_narx_ros.plant import random_history, session_offset

    if not args.history >= 0.0:
        raise ConfigError(f'--history must be >= 0 s, got {args.history}')
    if args.sensor_offset is not None and args.session is not None:
        raise ConfigError('--sensor-offset and --session both set the sensor offset: give one')
    if (args.sensor_bits is None) != (args.sensor_span is None):
        raise ConfigError('--sensor-bits and --sensor-span go together: give both or neither')
    offset = args.sensor_offset or 0.0
    if args.session is not None:
        offset = session_offset(args.session, args.session_spread)
    sensor = {'sensor_offset': offset, 'sensor_bits': args.sensor_bits,
              'sensor_span': args.sensor_span}
    meta = {'sensor': {'offset_m': offset, 'session': args.session, 'bits': args.sensor_bits,
                       'span_m': args.sensor_span}}
    history = None
    if args.history > 0.0:
        seed = args.seed if args.history_seed is None else args.history_seed
        amp = amplitude if args.history_amplitude is None else args.history_amplitude
        history = random_history(args.fs, args.history, amp, offset=args.offset, seed=seed,
                                 end=float(u[0]), hold=args.history_hold)
        meta['history'] = {'seconds': args.history, 'hold_s': args.history_hold,
                           'amplitude_V': amp, 'seed': seed}
    return history, sensor, meta


def run(args) -> int:
    """Generate, simulate and write; returns 0. Problems raise PiezoNarxError subclasses."""
    import json
    from pathlib import Path

    import numpy as np

    from piezo_narx_ros.errors import ConfigError
    from piezo_narx_ros.files import refuse_overwrite, write_npz
    from piezo_narx_ros.plant import PiezoCantilever, generate, load_plant_params, preamble

    out = Path(args.out)
    if out.suffix != '.npz':
        raise ConfigError(f'--out must name an .npz file, got {args.out}')
    if not out.parent.is_dir():
        raise ConfigError(f'--out directory {out.parent} does not exist')
    refuse_overwrite(out, args.force, '--out')
    options = {name: getattr(args, flag) for flag, name in SIGNAL_FLAGS.items()
               if getattr(args, flag) is not None}
    playback = args.signal == 'playback'
    if args.fs is None:    # a recording plays at its own rate unless another is asked for
        args.fs = 2000.0
        if playback and args.file and args.file_fs is None:
            from piezo_narx_ros.ident.data.loaders import read_signal
            args.fs = read_signal(args.file, args.column, args.key or 'u').fs or 2000.0
    seconds = args.seconds if args.seconds is not None or playback else 25.0
    amplitude = args.amplitude if args.amplitude is not None or playback else 100.0
    if args.seed < 0:
        raise ConfigError(f'--seed must be a non-negative integer, got {args.seed}')
    from piezo_narx_ros.plant.axes import load_axes_config
    axes = load_axes_config(args.plant_config)[0] if args.plant_config else ()
    if axes:
        return _run_stage(args, axes, out, seconds, amplitude, options)
    params = load_plant_params(args.plant_config)
    u = generate(args.signal, args.fs, seconds, amplitude, offset=args.offset, seed=args.seed,
                 **options)
    # The record's peak deviation (a played file's as played): the preamble's and the history's.
    peak = amplitude if amplitude is not None else float(np.max(np.abs(u - args.offset)))
    lead = preamble(args.preamble, args.fs, args.preamble_seconds, peak, args.offset,
                    args.preamble_cycles)
    u = np.concatenate([lead, u])
    history, sensor, session_meta = session_settings(args, u, peak)
    plant = PiezoCantilever(params, fs=args.fs, seed=args.seed, **sensor)
    res = plant.run(u, history=history)
    meta = {'signal': args.signal, 'seconds': u.size / args.fs, 'amplitude_V': amplitude,
            'offset_V': args.offset, 'seed': args.seed, 'options': options,
            'plant': params.as_dict(), 'units': {'u': 'V', 'y': 'm', 't': 's', 'fs': 'Hz'}}
    session_on = history is not None or any(sensor.values())
    if session_on:
        meta.update(session_meta)   # only then: records without them keep their exact meta
    if lead.size:
        meta['preamble'] = {'kind': args.preamble, 'seconds': args.preamble_seconds,
                            'cycles': args.preamble_cycles, 'samples': int(lead.size)}
    write_npz(out, u=u, u_applied=res.u_applied, y=res.y, y_true=res.y_true,
              fs=np.float64(args.fs), t=np.arange(u.size) / args.fs,
              meta=np.str_(json.dumps(meta)))
    print(f'wrote {out}: {u.size} samples at {args.fs:g} Hz, u {u.min():.1f}..{u.max():.1f} V, '
          f'y {1e6 * np.ptp(res.y):.2f} um peak-to-peak')
    return 0


# Options that shape one cantilever's session (its past, its sensor): not defined for a stage.
_ONE_AXIS_ONLY = (('history', 0.0), ('sensor_offset', None), ('session', None),
                  ('sensor_bits', None), ('sensor_span', None), ('preamble', 'none'))


def _run_stage(args, axes, out, seconds, amplitude, options) -> int:
    """
    Simulate a stage file of several axes: one signal per axis (axis i seeded seed + i).

    Writes u, u_applied, y, y_true as (N, axes) arrays with the axis names (`inputs`,
    `outputs`), as command_node + simulator_node would stream them.
    """
    import json

    import numpy as np

    from piezo_narx_ros.errors import ConfigError
    from piezo_narx_ros.files import write_npz
    from piezo_narx_ros.plant import generate
    from piezo_narx_ros.plant.axes import make_axis_plants

    for name, default in _ONE_AXIS_ONLY:
        if getattr(args, name) != default:
            raise ConfigError(f'--{name.replace("_", "-")} shapes one cantilever\'s session; '
                              f'{args.plant_config} is a stage of {len(axes)} axes '
                              f'({", ".join(axes)})')
    u = np.column_stack([generate(args.signal, args.fs, seconds, amplitude, offset=args.offset,
                                  seed=args.seed + i, **options) for i in range(len(axes))])
    stage = make_axis_plants(axes, args.plant_config, fs=args.fs, seed=args.seed)
    y, u_applied, y_true = stage.run_with_truth(u)
    meta = {'signal': args.signal, 'seconds': u.shape[0] / args.fs, 'amplitude_V': amplitude,
            'offset_V': args.offset, 'seed': args.seed, 'options': options,
            'plant_config': str(args.plant_config), 'axes': list(axes),
            'units': {'u': 'V', 'y': 'm', 't': 's', 'fs': 'Hz'}}
    names = np.array(axes)
    write_npz(out, u=u, u_applied=u_applied, y=y, y_true=y_true, fs=np.float64(args.fs),
              t=np.arange(u.shape[0]) / args.fs, inputs=names, outputs=names,
              meta=np.str_(json.dumps(meta)))
    print(f'wrote {out}: {u.shape[0]} samples of {len(axes)} axes ({", ".join(axes)}) at '
          f'{args.fs:g} Hz, u {u.min():.1f}..{u.max():.1f} V, y '
          f'{1e6 * np.ptp(y, axis=0).max():.2f} um peak-to-peak at most')
    return 0
