"""docs/results.md from `make bench`: headline.py records figures, write_results.py the page."""
import json
import re
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
BENCH = REPO / 'bench'


def _run(code, env_file=None, tmp_path=None):
    import os
    env = {k: v for k, v in os.environ.items() if k != 'PNR_RESULTS'}
    if env_file is not None:
        env['PNR_RESULTS'] = str(env_file)
    script = tmp_path / 'bench_x.py'
    script.write_text(f'import sys\nsys.path.insert(0, {str(BENCH)!r})\n' + code)
    return subprocess.run([sys.executable, str(script)], env=env, capture_output=True,
                          text=True, timeout=60)


def test_a_figure_is_recorded_only_where_make_bench_asks(tmp_path):
    code = "from headline import headline\nheadline('fit | time', '1.5 s', '<= 2 s', 'x.md')\n"
    assert _run(code, None, tmp_path).returncode == 0
    assert not list(tmp_path.glob('*.jsonl'))
    results = tmp_path / 'r.jsonl'
    assert _run(code, results, tmp_path).returncode == 0
    assert _run(code, results, tmp_path).returncode == 0
    rows = [json.loads(line) for line in results.read_text().splitlines()]
    assert len(rows) == 2 and rows[0]['script'] == 'bench_x.py'
    first = rows[0]
    assert (first['what'], first['measured'], first['target']) == ('fit | time', '1.5 s', '<= 2 s')


def test_the_page_is_one_dated_table_with_the_machine(tmp_path):
    results = tmp_path / 'r.jsonl'
    results.write_text(json.dumps({'what': 'fit | time', 'measured': '1.5 s', 'target': '',
                                   'page': 'envelope.md', 'script': 'bench_a.py',
                                   'load': 0.5}) + '\n')
    out = tmp_path / 'results.md'
    proc = subprocess.run([sys.executable, str(BENCH / 'write_results.py'), str(results),
                           '--out', str(out)], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    page = out.read_text()
    assert re.search(r'Run of \d{4}-\d\d-\d\d \d\d:\d\d UTC on .+, \d+ cores', page)
    row = '| fit \\| time | 1.5 s |  | 0.5 | `bench/bench_a.py` | [envelope](envelope.md) |'
    assert row in page
    results.write_text('')
    proc = subprocess.run([sys.executable, str(BENCH / 'write_results.py'), str(results),
                           '--out', str(out)], capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and proc.stderr.count('\n') == 1
    assert out.read_text() == page          # kept


def test_every_benchmark_make_bench_runs_records_its_figures():
    text = (REPO / 'Makefile').read_text()
    recipe = text.split('\nbench:', 1)[1].split('\n\n', 1)[0]
    scripts = re.findall(r'bench/(bench_\w+\.py)', recipe)
    assert len(scripts) >= 10
    for name in scripts:
        assert 'headline(' in (BENCH / name).read_text(), name
    assert 'write_results.py' in recipe
