"""`piezo-narx bag info|repair|export`: inspect, fix and convert rosbag2 bags."""
from __future__ import annotations

import argparse
import sys


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Return the `bag` subcommand and its three actions (light imports only)."""
    parser = subparsers.add_parser(
        'bag', help='inspect, repair or export rosbag2 bags (MCAP or sqlite3)',
        description='Inspect, repair or export rosbag2 bags (a bag directory, .mcap or .db3).')
    actions = parser.add_subparsers(dest='bag_action', metavar='ACTION')
    actions.required = True

    info = actions.add_parser('info', help='topics, counts, duration, rate and gaps')
    info.add_argument('bag', help='bag directory, .mcap or .db3 file')

    repair = actions.add_parser(
        'repair', help='make an interrupted MCAP recording readable (summary, metadata.yaml)')
    repair.add_argument('bag', help='bag directory or .mcap file')
    repair.add_argument('--no-backup', action='store_true',
                        help='do not keep the damaged file as NAME.mcap.damaged')

    export = actions.add_parser('export', help='paired u (V), y (m), t (s), fs (Hz) to .npz')
    export.add_argument('bag', help='bag directory, .mcap or .db3 file')
    export.add_argument('--out', required=True,
                        help='output file: .npz (u, y, t, fs) or .csv (columns t,u,y)')
    export.add_argument('--command-topic', default='piezo/voltage_command')
    export.add_argument('--deflection-topic', default='piezo/deflection')
    export.add_argument('--force', action='store_true', help='overwrite --out if it exists')
    from piezo_narx_ros.cli.reading import add_reading_options
    add_reading_options(export, table=False)
    return parser


def run(args) -> int:
    """Run one bag action; BagError propagates to main (one line, exit 2)."""
    return {'info': _info, 'repair': _repair, 'export': _export}[args.bag_action](args)


def _info(args) -> int:
    from piezo_narx_ros.bag.reader import bag_info
    info = bag_info(args.bag)
    print(f'bag:       {info.path}')
    print(f'storage:   {info.storage}')
    print(f'messages:  {info.message_count}')
    print(f'duration:  {info.duration_s:.6g} s')
    width = max([len(t.name) for t in info.topics] + [5])
    print(f'{"topic":<{width}}  {"type":<36} {"count":>8} {"samples":>8} {"rate Hz":>10} '
          f'{"gaps":>5} {"missing":>8}  {"axes":<8}  stamps')
    for t in info.topics:
        if t.check is None:
            order = 'receive time'
        else:
            notes = [f'{n} {what}' for n, what in ((t.check.reordered, 'reordered'),
                                                   (t.check.duplicates, 'duplicate'))
                     if n]
            order = 'header' + (' (' + ', '.join(notes) + ')' if notes else '')
        axes = ','.join(t.names) or '-'
        print(f'{t.name:<{width}}  {t.msgtype:<36} {t.count:>8} {t.samples:>8} '
              f'{t.rate_hz:>10.6g} {t.gaps:>5} {t.missing:>8}  {axes:<8}  {order}')
    return 0


def _repair(args) -> int:
    from piezo_narx_ros.bag.repair import repair_bag
    rep = repair_bag(args.bag, backup=not args.no_backup)
    if rep.intact:
        print(f'{rep.bag} is intact ({rep.messages} messages): nothing to repair')
        return 0
    if rep.metadata_only:
        print(f'rebuilt {rep.bag}/metadata.yaml from {rep.mcap.name} ({rep.messages} messages, '
              f'file intact): {rep.metadata_problem}')
        return 0
    print(f'repaired {rep.bag}: {rep.messages} message(s) recovered'
          + (f', damaged original kept as {rep.backup}' if rep.backup else ''))
    for topic, n in rep.topics.items():
        print(f'  {topic}: {n}')
    if rep.stop_reason:
        print(f'  reading stopped at: {rep.stop_reason} ({rep.dropped_bytes} byte(s) dropped)')
    return 0


def _export(args) -> int:
    from pathlib import Path

    import numpy as np

    from piezo_narx_ros.bag.reader import read_uy_report
    from piezo_narx_ros.cli.reading import reading_options
    from piezo_narx_ros.errors import ConfigError
    from piezo_narx_ros.files import refuse_overwrite, write_atomic, write_npz
    from piezo_narx_ros.ident.data.records import checked
    out = Path(args.out)
    # np.savez appends .npz to any other name: 'e.csv' became 'e.csv.npz' while we said 'e.csv'.
    if out.suffix.lower() not in ('.npz', '.csv'):
        raise ConfigError(f'--out must end in .npz or .csv, got {out}')
    refuse_overwrite(out, args.force, '--out')
    reading = reading_options(args)
    rec, report = read_uy_report(args.bag, args.command_topic, args.deflection_topic,
                                 reading['axis'])
    for line in report.issues():
        print(f'piezo-narx: warning: {line}', file=sys.stderr)
    rec = checked(rec, reading['units'])
    from piezo_narx_ros.record import channels_arg
    one_axis = rec.n_in == 1 and rec.n_out == 1
    # Several axes: the channel names go with the data (npz keys inputs/outputs, CSV header).
    names = {} if one_axis else {'inputs': np.array(rec.inputs), 'outputs': np.array(rec.outputs)}
    if out.suffix.lower() == '.npz':
        write_npz(out, u=channels_arg(rec.u), y=channels_arg(rec.y), t=rec.t,
                  fs=np.float64(rec.fs), **names)
    else:   # what `fit` reads back: t,u,y with a header, exact to the last bit (%.17g)
        # Several axes: the bag's names, unless inputs and outputs share one (x commands, x
        # deflects): then u1.., y1.. in that order, which `fit` reads without options.
        cols = rec.inputs + rec.outputs
        if len(set(cols)) < len(cols) or any(c.lower() in ('t', 'u', 'y') for c in cols):
            cols = tuple(f'u{i + 1}' for i in range(rec.n_in)) + \
                tuple(f'y{i + 1}' for i in range(rec.n_out))
        header = 't,u,y' if one_axis else ','.join(('t',) + cols)
        with write_atomic(out, 'w', encoding='utf-8') as fh:
            np.savetxt(fh, np.column_stack([rec.t, rec.u, rec.y]), delimiter=',', fmt='%.17g',
                       header=header, comments='')
    print(f'wrote {out}: {len(rec)} samples at {rec.fs:.6g} Hz')
    return 0
