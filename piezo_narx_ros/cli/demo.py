"""
`piezo-narx demo`: the whole method end to end, with real node processes over DDS.

    1 record    command_node (multisine, 25 s at 2 kHz, no loop) -> simulator_node -> recorder_node
    2 fit       `piezo-narx fit` on that bag: NARX ny,nu 1..4 x 10 units, ARX 1..10 x 1..10, 50/50
    3 live      the selected model in estimator_node on a fresh excitation (another seed), recorded
                with the measurement
    4 analysis  live free-run R², RMSE, latency and lost samples from that bag;
                figures; summary.json

Writes everything to --out (default reports/demo-YYYYmmdd-HHMMSS). Every child process is stopped
on success, on error and on Ctrl-C/SIGTERM (SIGINT, then SIGTERM, then SIGKILL).
`--make-sample-bags DIR` records the repository's sample bags instead (bags/README.md).
`--control` runs sensorless position control instead (docs/control.md): identification record and
envelope fit (or `--model`), then controller_node live in each mode on a position reference.
"""


def add_parser(subparsers):
    """Register the `demo` subcommand (argparse only; heavy imports wait for run)."""
    p = subparsers.add_parser(
        'demo', help='record, identify and run the estimator live on the simulated piezo; '
                     'prints a summary and writes a report folder',
        description=__doc__.strip().split('\n\n')[0])
    p.add_argument('--out', metavar='DIR', help='report folder (default '
                   'reports/demo-YYYYmmdd-HHMMSS); must not hold an earlier demo')
    p.add_argument('--config', metavar='YAML', help='settings file (default: built-in, the same '
                   'as config/demo.yaml)')
    p.add_argument('--seconds', type=float, metavar='S',
                   help='identification record length, s (default 25)')
    p.add_argument('--validation-seconds', type=float, metavar='S',
                   help='live validation length, s (default 10)')
    p.add_argument('--fs', type=float, metavar='HZ', help='sample rate, Hz (default 2000)')
    p.add_argument('--seed', type=int, help='excitation seed of the record (default 0; the live '
                   'phase uses seed + 1)')
    p.add_argument('--quick', action='store_true',
                   help='tiny run for tests: 4 s + 3 s, NARX(4,4) and four ARX models')
    p.add_argument('--control', action='store_true',
                   help='sensorless position control end to end: record + envelope fit (or '
                        '--model), then controller_node live in each mode (docs/control.md)')
    p.add_argument('--model', metavar='JSON',
                   help='with --control: use this model file instead of identifying one')
    p.add_argument('--control-seconds', type=float, metavar='S',
                   help='with --control: seconds per mode (default 20)')
    p.add_argument('--make-sample-bags', metavar='DIR',
                   help='record the sample bags (estimation, validation, sine) and their model '
                        'into DIR instead of running the demo')
    return p


def run(args) -> int:
    """Run the demo (or --make-sample-bags); exit code 0, 130/143 when interrupted."""
    import signal
    import sys
    from datetime import datetime
    from pathlib import Path

    from piezo_narx_ros.demo.runner import Interrupted, child_environment, load_settings

    from piezo_narx_ros.errors import ConfigError
    if (args.model or args.control_seconds) and not args.control:
        raise ConfigError('--model and --control-seconds go with --control')
    settings = load_settings(args.config, quick=args.quick, seconds=args.seconds,
                             validation_seconds=args.validation_seconds, fs=args.fs,
                             seed=args.seed, control=(
                                 {'seconds': args.control_seconds} if args.control_seconds
                                 else None))
    child_environment()
    try:
        if args.control:
            from piezo_narx_ros.demo.control import run_control_demo
            out = Path(args.out or datetime.now().strftime('reports/control-%Y%m%d-%H%M%S'))
            return run_control_demo(settings, out, Path(args.model) if args.model else None)
        if args.make_sample_bags:
            from piezo_narx_ros.demo.sample_bags import make_sample_bags
            return make_sample_bags(settings, Path(args.make_sample_bags))
        out = Path(args.out or datetime.now().strftime('reports/demo-%Y%m%d-%H%M%S'))
        from piezo_narx_ros.demo.main import run_demo
        return run_demo(settings, out)
    except Interrupted as exc:
        print(f'piezo-narx: interrupted ({exc}); all child processes stopped', file=sys.stderr)
        return 128 + exc.signum if exc.signum != signal.SIGINT else 130
