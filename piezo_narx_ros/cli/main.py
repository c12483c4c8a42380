"""
`piezo-narx` entry point: dispatches to one module per subcommand.

Each subcommand module defines
    add_parser(subparsers) -> argparse.ArgumentParser   (must import nothing heavy)
    run(args) -> int                                     (exit code; heavy imports go here)
so that `piezo-narx evaluate` never pays for torch or rclpy.
"""
import argparse
import importlib
import os
import sys

from piezo_narx_ros.errors import PiezoNarxError   # imports nothing (numpy not loaded yet)

# Before numpy loads: OpenBLAS's per-core spinning threads fight the fit's own worker processes
# (measured: ARX(10,10) fit 427 ms with default threads vs 20 ms with one, on a busy 2-core box).
os.environ.setdefault('OPENBLAS_NUM_THREADS', '1')

# name -> module under piezo_narx_ros.cli; order is the order shown in --help.
SUBCOMMANDS = {
    'simulate': 'simulate',
    'fit': 'fit',
    'evaluate': 'evaluate',
    'export': 'export',
    'bag': 'bag',
    'bringup': 'bringup',
    'demo': 'demo',
}


def build_parser() -> argparse.ArgumentParser:
    """Parser with every subcommand whose module exists."""
    parser = argparse.ArgumentParser(
        prog='piezo-narx',
        description='NARX identification of piezo hysteresis and ROS 2 free-run estimation.')
    sub = parser.add_subparsers(dest='command', metavar='COMMAND')
    sub.required = True
    for name, module in SUBCOMMANDS.items():
        try:
            mod = importlib.import_module(f'piezo_narx_ros.cli.{module}')
        except ModuleNotFoundError as exc:
            if exc.name == f'piezo_narx_ros.cli.{module}':
                continue  # subcommand not built yet
            raise
        sub_parser = mod.add_parser(sub)
        sub_parser.set_defaults(_run=mod.run)
    return parser


def main(argv=None) -> int:
    """Run the command line; returns (and exits with) the process exit code."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        code = args._run(args)
    except PiezoNarxError as exc:
        print(f'piezo-narx: error: {exc}', file=sys.stderr)
        code = 2
    except FileNotFoundError as exc:
        print(f'piezo-narx: error: file not found: {exc.filename or exc}', file=sys.stderr)
        code = 2
    except KeyboardInterrupt:
        print('piezo-narx: interrupted', file=sys.stderr)
        code = 130
    except MemoryError:
        print('piezo-narx: error: out of memory (is an input or a length far too large?)',
              file=sys.stderr)
        code = 2
    except Exception as exc:  # noqa: BLE001 - last resort: a bug must still end in one line
        if os.environ.get('PIEZO_NARX_DEBUG'):
            raise
        text = ' '.join(str(exc).split())
        print(f'piezo-narx: error: unexpected {type(exc).__name__}: {text} (this is a bug; '
              'PIEZO_NARX_DEBUG=1 shows the traceback)', file=sys.stderr)
        code = 1
    sys.exit(code or 0)


if __name__ == '__main__':
    main()
