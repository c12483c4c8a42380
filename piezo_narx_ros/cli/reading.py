"""
The options that say how to read a recording, shared by `fit`, `evaluate` and `bag export`.

    --columns u=1,y=5[,t=N]   which columns of a text table (1-based numbers or header names),
                              or which variables of a .mat (names, rec.u for a struct field)
    --u-unit V|mV|kV          the unit u is recorded in (default V)
    --y-unit m|mm|um|nm       the unit y is recorded in (default m)
    --y-scale M               metres per recorded unit of y (sensor counts), instead of --y-unit
    --t-unit s|ms|us|ns       the unit of a time column (default s)
    --axis NAME               the joint of a bag whose command and deflection are paired
    --inputs A,B --outputs C,D  the input and output columns (or .mat variables) of several axes

Everything is converted to volts, metres and seconds on reading; an implausible magnitude with no
unit stated is refused with the option that fixes it (ident.data.units).
"""
from __future__ import annotations

Y_UNIT_CHOICES = ('m', 'mm', 'um', 'nm')
U_UNIT_CHOICES = ('V', 'mV', 'kV')
T_UNIT_CHOICES = ('s', 'ms', 'us', 'ns')


def add_reading_options(parser, table: bool = True, bag: bool = True) -> None:
    """Add the reading options to an argparse parser (table: --columns; bag: --axis)."""
    g = parser.add_argument_group('reading the data (units are converted to V, m, s)')
    if table:
        g.add_argument('--columns', metavar='SPEC',
                       help='columns of a text table (.csv, .tsv, .txt, .dat): ROLE=COLUMN '
                            'pairs, roles t, u, y, y_true, columns 1-based or header names, '
                            'e.g. u=1,y=5 (default: the header, or t,u,y / u,y by count); for '
                            'a .mat, variable names (case-insensitive, rec.u for a struct field) '
                            "or columns of the file's one matrix")
        g.add_argument('--t-unit', choices=T_UNIT_CHOICES,
                       help='unit of the time column (default s)')
        g.add_argument('--inputs', metavar='NAMES', dest='input_names',
                       help='several axes: the input columns of a text table by header name '
                            '(or vector variables of a .mat), in order, e.g. vx,vy (default: '
                            'header names u1, u2, ...)')
        g.add_argument('--outputs', metavar='NAMES', dest='output_names',
                       help='several axes: the output columns by header name, or .mat '
                            'variables (default y1, ...)')
    g.add_argument('--u-unit', choices=U_UNIT_CHOICES, help='unit u is recorded in (default V)')
    g.add_argument('--y-unit', choices=Y_UNIT_CHOICES,
                   help='unit y is recorded in (default m); stating it also accepts magnitudes '
                        'that look implausible for it')
    g.add_argument('--y-scale', type=float, metavar='M',
                   help="metres per recorded unit of y, e.g. a sensor's metres per count "
                        '(instead of --y-unit)')
    if bag:
        g.add_argument('--axis', metavar='NAME',
                       help='bag joint whose command (effort) and deflection (position) are '
                            "paired, by name in each message (default: the bag's one axis)")


def reading_options(args) -> dict:
    """Keyword arguments for ident.data.loaders.load_records from parsed options (absent: None)."""
    from piezo_narx_ros.ident.data.loaders import parse_columns
    from piezo_narx_ros.ident.data.units import Units
    units = Units.from_options(getattr(args, 'u_unit', None), getattr(args, 'y_unit', None),
                               getattr(args, 't_unit', None), getattr(args, 'y_scale', None))
    names = {key: [n.strip() for n in value.split(',') if n.strip()]
             for key, dest in (('inputs', 'input_names'), ('outputs', 'output_names'))
             if (value := getattr(args, dest, None)) is not None}
    return {'columns': parse_columns(getattr(args, 'columns', None)), 'units': units,
            'axis': getattr(args, 'axis', None), **names}
