"""Imports inside the package flow one way: no module reaches itself through its imports."""
import ast
from pathlib import Path

from conftest import REPO


def _modules(root: Path, package: str) -> dict[str, Path]:
    """{dotted module name: file} of every module under root/package."""
    found = {}
    for path in sorted((root / package).rglob('*.py')):
        parts = list(path.relative_to(root).with_suffix('').parts)
        if parts[-1] == '__init__':
            parts.pop()
        found['.'.join(parts)] = path
    return found


def import_graph(root: Path, package: str) -> dict[str, set[str]]:
    """
    Return {module: modules of the package it imports}, lazy (in-function) imports included.

    `from P import name` points at module P.name when there is one, else at P itself. The parent
    packages Python imports implicitly are not edges: only what the code names.
    """
    modules = _modules(root, package)

    def owner(name):   # the module defining `name` (a module, or an attribute of one)
        while name and name not in modules:
            name = name.rpartition('.')[0]
        return name

    graph = {m: set() for m in modules}
    for module, path in modules.items():
        here = module.split('.') if path.name == '__init__.py' else module.split('.')[:-1]
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = (node.module or '') if not node.level else '.'.join(
                    here[:len(here) - node.level + 1] + ([node.module] if node.module else []))
                targets = [f'{base}.{a.name}' if f'{base}.{a.name}' in modules else base
                           for a in node.names]
            else:
                continue
            graph[module] |= {owner(t) for t in targets if owner(t) not in ('', module)}
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """Return one import cycle as [m1, m2, ..., m1], or None (depth-first search)."""
    state, stack = {}, []

    def visit(m):
        state[m] = 'open'
        stack.append(m)
        for n in sorted(graph[m]):
            if state.get(n) == 'open':
                return stack[stack.index(n):] + [n]
            if n not in state:
                found = visit(n)
                if found:
                    return found
        state[m] = 'done'
        stack.pop()
        return None

    for m in sorted(graph):
        if m not in state:
            found = visit(m)
            if found:
                return found
    return None


def test_no_import_cycle_inside_the_package():
    graph = import_graph(REPO, 'piezo_narx_ros')
    assert len(graph) > 50 and graph['piezo_narx_ros.ident.base']   # the walk saw the package
    cycle = find_cycle(graph)
    assert cycle is None, 'import cycle: ' + ' -> '.join(cycle)


def test_a_cycle_through_a_lazy_relative_import_is_found(tmp_path):
    pkg = tmp_path / 'pkg'
    (pkg / 'sub').mkdir(parents=True)
    (pkg / '__init__.py').write_text('')
    (pkg / 'sub' / '__init__.py').write_text('')
    (pkg / 'a.py').write_text('from pkg.sub import b\n')
    (pkg / 'sub' / 'b.py').write_text('from . import c\n')
    (pkg / 'sub' / 'c.py').write_text('def f():\n    from ..a import g\n')
    assert find_cycle(import_graph(tmp_path, 'pkg')) == ['pkg.a', 'pkg.sub.b', 'pkg.sub.c',
                                                         'pkg.a']
    (pkg / 'sub' / 'c.py').write_text('import numpy\n')   # outside the package: no edge
    assert find_cycle(import_graph(tmp_path, 'pkg')) is None
