"""
Write docs/results.md from the figures the benchmarks recorded (bench/headline.py).

    python bench/write_results.py RESULTS.jsonl [--out docs/results.md]

`make bench` runs every benchmark with PNR_RESULTS=bench/out/results.jsonl and then this: one
dated table of every headline figure, in the order the scripts ran, with the machine (CPU model,
cores) and each figure's load average. A results file with no figure is refused (the page is kept).
"""
import argparse
import json
import os
import platform
import sys
from datetime import datetime, timezone
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def cpu_model() -> str:
    """Return the CPU's model name (Linux /proc/cpuinfo), else the platform's processor."""
    try:
        for line in Path('/proc/cpuinfo').read_text().splitlines():
            if line.lower().startswith('model name'):
                return line.split(':', 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def _cell(text: str) -> str:
    return str(text).replace('|', '\\|').replace('\n', ' ')


def render(rows: list, when: datetime, machine: str) -> str:
    """Return the page's Markdown for the recorded rows."""
    lines = [
        '# Results',
        '',
        'The headline figures of `make bench`, written by `bench/write_results.py` from what each',
        'benchmark measured in that run (do not edit by hand: run `make bench`). Accuracy figures',
        'are deterministic; times, CPU and latencies depend on the machine and its load (the load',
        'average when the figure was taken is beside it). The pages linked say how each is',
        'measured and what was tried.',
        '',
        f'Run of {when:%Y-%m-%d %H:%M} UTC on {machine}.',
        '',
        '| what | measured | target | load | script | page |',
        '|---|---|---|---|---|---|',
    ]
    for r in rows:
        page = r.get('page') or ''
        link = f'[{Path(page).stem}]({page})' if page else ''
        lines.append(f'| {_cell(r["what"])} | {_cell(r["measured"])} | '
                     f'{_cell(r.get("target", ""))} | {r.get("load", "")} | '
                     f'`bench/{_cell(r["script"])}` | {link} |')
    lines += [
        '',
        'Not in `make bench` (long runs, or data from ../shared): the FSM benchmark',
        '(`bench/bench_fsm_envelope.py`, [mimo](mimo.md)), Bouc-Wen (`bench/bench_boucwen.py`,',
        '[identification](identification.md)), the real records and the search on them',
        '(`bench/bench_real.py`, `bench/bench_search.py`, [real](real.md)), the demo',
        '(`make demo`, [demo](demo.md)) and the 10-minute soak (`make soak`,',
        '[reliability](reliability.md)):',
        'their pages give the figures with their dates.',
    ]
    return '\n'.join(lines) + '\n'


def main(argv=None) -> int:
    """Read the results file, write the page; exit 2 with one line when there is nothing."""
    p = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    p.add_argument('results', type=Path)
    p.add_argument('--out', type=Path, default=REPO / 'docs' / 'results.md')
    args = p.parse_args(argv)
    try:
        rows = [json.loads(line) for line in args.results.read_text().splitlines()
                if line.strip()]
    except (OSError, ValueError) as exc:
        print(f'write_results: {args.results}: {exc}', file=sys.stderr)
        return 2
    if not rows:
        print(f'write_results: {args.results} holds no figure; {args.out} kept', file=sys.stderr)
        return 2
    machine = f'{cpu_model()}, {os.cpu_count()} cores, Python {platform.python_version()}'
    page = render(rows, datetime.now(timezone.utc), machine)
    tmp = args.out.with_name(f'.{args.out.name}.{os.getpid()}.tmp')
    tmp.write_text(page)
    os.replace(tmp, args.out)
    print(f'wrote {args.out}: {len(rows)} figures')
    return 0


if __name__ == '__main__':
    sys.exit(main())
