"""
Headline figures of the benchmarks, collected for docs/results.md.

A benchmark calls `headline(what, measured, target, page)` beside the line it prints. When the
environment names a results file (PNR_RESULTS, as `make bench` sets it) the figure is appended
to it as one JSON line with the script's name; otherwise nothing happens. `bench/write_results.py`
then writes the page: one dated table, the machine stated.
"""
import json
import os
import sys
from pathlib import Path

ENV = 'PNR_RESULTS'


def headline(what: str, measured: str, target: str = '', page: str = '') -> None:
    """Record one figure: what was measured, the value as printed, its target, a docs page."""
    path = os.environ.get(ENV)
    if not path:
        return
    row = {'what': str(what), 'measured': str(measured), 'target': str(target),
           'page': str(page), 'script': Path(sys.argv[0]).name,
           'load': round(os.getloadavg()[0], 2)}
    with open(path, 'a') as f:
        f.write(json.dumps(row) + '\n')
