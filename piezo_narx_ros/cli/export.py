"""
`piezo-narx export MODEL --c DIR`: the model as C for a real-time target (docs/export.md).

Writes DIR/pnr_model.h and DIR/pnr_model.c (C99, no allocation, libm only, the weights as
constants): the free run (`pnr_step`, equal to the Python free run), the state-setting entry
points and the inverse of controller_node's `inverse` mode (`pnr_inverse_step`). A model file of
a kind the exporter does not know is refused with one line (exit 2).
"""
import argparse


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Register `export` (argparse only)."""
    p = subparsers.add_parser(
        'export', help='write a model as C (pnr_model.h / pnr_model.c) for a real-time target',
        description="Write the model's free run and inverse as C99 (no allocation, libm only): "
                    'DIR/pnr_model.h and DIR/pnr_model.c. docs/export.md shows how to build '
                    'them into Simulink, dSPACE or a microcontroller loop.')
    p.add_argument('model', metavar='MODEL', help='model .json written by piezo-narx fit')
    p.add_argument('--c', required=True, metavar='DIR', dest='c_dir',
                   help='directory for pnr_model.h and pnr_model.c (created if missing)')
    p.add_argument('--fs', type=float, metavar='HZ',
                   help='sample rate, Hz, for a model file without one')
    p.add_argument('--force', action='store_true',
                   help='overwrite pnr_model.h / pnr_model.c in DIR even when an earlier export '
                        'did not write them')
    return p


def run(args) -> int:
    """Load the model, write the C files and name them; returns 0."""
    from piezo_narx_ros.export.writer import write_c
    from piezo_narx_ros.ident.model_io import load_model

    model = load_model(args.model)
    header, source = write_c(model, args.c_dir, fs=args.fs, source=args.model, force=args.force)
    print(f'wrote {header} and {source} ({model.kind}, {model.n_params} parameters)')
    return 0
