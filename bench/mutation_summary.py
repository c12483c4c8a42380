"""
Kill rate per core module and the surviving mutants, from the results `mutmut run` left.

    python bench/mutation_summary.py [--diffs]       (after `make mutate`; docs/testing.md)

Reads mutants/<module>.py.meta (mutmut 3's per-file results: exit code of the tests per mutant)
for the modules `make mutate` mutates; for nodes/wire/joint_state.py only the JointState
codec counts.
A mutant is killed when the tests fail or time out on it; one that no test reaches counts as
surviving. --diffs prints each survivor's change (`mutmut show`).
"""
from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]

# module -> prefixes of the mutant names that count (mutmut names them module.x_function...).
MODULES = {
    'ident/narx/regressors.py': ('',),
    'ident/validation/correlation.py': ('',),
    'ident/validation/metrics.py': ('',),
    'ident/validation/noise_model.py': ('',),
    'ident/narx/model.py': ('',),
    'ident/model_io.py': ('',),
    'estimator/free_run.py': ('',),
    'bag/pairing.py': ('',),
    'nodes/wire/joint_state.py': ('x_decode_joint_state__', 'x_encode_joint_state__'),
}
# Killed: the tests fail, time out or crash (-6 abort, -9 kill, -11 segfault).
KILLED = {1, 3, 24, -24, 152, 255, 36, -6, -9, -11}
SURVIVED = {0, 5, 33}                               # tests pass, or no test reaches it


def module_results(module: str) -> dict[str, int | None]:
    """{mutant name: exit code (None = not run yet)} of one module's counted mutants."""
    meta = REPO / 'mutants' / 'piezo_narx_ros' / (module + '.meta')
    if not meta.is_file():
        return {}
    codes = json.loads(meta.read_text())['exit_code_by_key']
    base = 'piezo_narx_ros.' + module[:-3].replace('/', '.') + '.'
    prefixes = MODULES[module]
    return {k: v for k, v in codes.items()
            if any(k[len(base):].startswith(p) for p in prefixes)}


def main(argv: list[str]) -> int:
    diffs = '--diffs' in argv
    print(f"{'module':24} {'mutants':>7} {'killed':>6} {'survived':>8} {'not run':>7} "
          f"{'kill rate':>9}")
    survivors = []
    for module in MODULES:
        codes = module_results(module)
        killed = sum(c in KILLED for c in codes.values())
        survived = [k for k, c in codes.items() if c in SURVIVED]
        pending = sum(c is None for c in codes.values())
        judged = killed + len(survived)
        rate = f'{100.0 * killed / judged:.1f} %' if judged else '-'
        print(f'{module:24} {len(codes):7d} {killed:6d} {len(survived):8d} {pending:7d} '
              f'{rate:>9}')
        survivors += survived
    print(f'\nsurviving mutants ({len(survivors)}):')
    for name in survivors:
        print(' ', name)
        if diffs:
            shown = subprocess.run([str(Path(sys.executable).parent / 'mutmut'), 'show', name],
                                   cwd=REPO, capture_output=True, text=True)
            print('\n'.join('    ' + line for line in shown.stdout.splitlines()
                            if line.startswith(('+', '-'))
                            and not line.startswith(('+++', '---'))))
    return 0


if __name__ == '__main__':
    sys.exit(main(sys.argv[1:]))
