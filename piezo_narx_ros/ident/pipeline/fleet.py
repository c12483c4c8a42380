"""
A fleet: each recording fitted on its own (`fit --per-record`).

DIR/NAME/ per recording and DIR/summary.csv, one row per recording. A recording that cannot
be loaded or fitted is a row with its error; the others complete.
"""
from __future__ import annotations

from dataclasses import dataclass

from piezo_narx_ros.errors import ConfigError, DataError, PiezoNarxError
from piezo_narx_ros.ident.pipeline.fit import (FitJob, load_estimation, warn_about_estimation,
                                               write_fit)

# Columns of DIR/summary.csv (--per-record): one row per recording. SI units.
SUMMARY_COLUMNS = ('recording', 'status', 'selected', 'n_params', 'validated',
                   'r2_validation_simulation', 'r2_worst_case', 'rmse_validation_simulation_m',
                   'samples', 'fs_hz', 'failed_candidates', 'source', 'error')


def recording_names(paths) -> list[str]:
    """
    Output folder name per input path: unique, and one plain name inside --out.

    The stem, with anything but letters, digits, '.', '-' and '_' made '_' and leading dots
    dropped (a stem '..' would have named the parent of --out); repeats get -2, -3, ..., never
    a name another input's own stem takes (a/run, run-2, b/run: run, run-2, run-3). Compared
    without case, for file systems that ignore it.
    """
    import re
    from pathlib import Path
    stems = [re.sub(r'[^\w.-]', '_', Path(path).stem).lstrip('.') or 'recording'
             for path in paths]
    reserved = {s.casefold() for s in stems}
    names, used = [], set()
    for stem in stems:
        name, k = stem, 1
        while name.casefold() in used or (k > 1 and name.casefold() in reserved):
            k += 1
            name = f'{stem}-{k}'
        used.add(name.casefold())
        names.append(name)
    return names


@dataclass
class FleetOutcome:
    """One row per recording (SUMMARY_COLUMNS) and the summary's path."""

    table: list
    summary_path: object

    def check(self) -> None:
        """Raise DataError in one line when some recording could not be fitted."""
        failed = [r for r in self.table if r['status'] != 'ok']
        if failed:
            raise DataError(f'{len(failed)} of {len(self.table)} recordings could not be fitted '
                            f'(see {self.summary_path}); {failed[0]["recording"]}: '
                            f'{failed[0]["error"]}')


def fit_fleet(job: FitJob, executor, announce=None) -> FleetOutcome:
    """
    One experiment per recording of job.inputs, all on one executor.

    announce(n): called with the number of recordings loaded, before the fits.
    """
    from piezo_narx_ros.ident.selection.experiment import run_experiments
    if job.validate:
        raise ConfigError('--validate serves one model; it cannot be combined with '
                          '--per-record')
    out = job.out
    names = recording_names(job.inputs)
    taken = [out / 'summary.csv'] + [out / n / 'model.json' for n in names]
    if any(p.exists() for p in taken) and not job.force:
        first = next(p for p in taken if p.exists())
        raise ConfigError(f'--out {out} already holds a fleet fit ({first}); choose another '
                          'directory or pass --force to overwrite it')
    loaded, rows = {}, {}
    for path, name in zip(job.inputs, names):
        try:
            loaded[name] = load_estimation(job, [path])
        except PiezoNarxError as exc:
            rows[name] = {'recording': name, 'status': 'failed', 'source': str(path),
                          'error': str(exc)}
    if announce is not None:
        announce(len(loaded))
    with executor:
        results = run_experiments(list(loaded.values()), job.config, executor)
    for (name, records), result in zip(loaded.items(), results):
        rows[name] = fleet_row(name, records[0], result)
        if not isinstance(result, PiezoNarxError):
            warn_about_estimation(records, job.config, name)
            write_fit(out / name, result, records, job.config, job.preset, job.report)
    table = [rows[n] for n in names]
    out.mkdir(parents=True, exist_ok=True)
    write_summary(table, out / 'summary.csv')
    return FleetOutcome(table, out / 'summary.csv')


def fleet_row(name, record, result) -> dict:
    """Return a recording's summary row from its experiment result (or its error)."""
    row = {'recording': name, 'source': record.source, 'samples': len(record),
           'fs_hz': record.fs}
    if isinstance(result, PiezoNarxError):
        return {**row, 'status': 'failed', 'error': str(result)}
    best = result.best
    sim = best.scores['validation']['simulation']
    return {**row, 'status': 'ok', 'selected': best.spec.label, 'n_params': best.n_params,
            'validated': result.validated, 'r2_validation_simulation': sim['r2'],
            'r2_worst_case': best.free_run_r2(), 'rmse_validation_simulation_m': sim['rmse'],
            'failed_candidates': sum(c.error is not None for c in result.candidates)}


def write_summary(table, path) -> None:
    """Write the rows as DIR/summary.csv (SUMMARY_COLUMNS; empty cells for None)."""
    import csv
    with open(path, 'w', newline='') as f:
        writer = csv.DictWriter(f, SUMMARY_COLUMNS, restval='')
        writer.writeheader()
        for row in table:
            writer.writerow({k: ('' if v is None else v) for k, v in row.items()})
