"""
docs/reference.md is what docs/gen_reference.py writes from the code (no DDS).

The page lists every node parameter (ParamSpec) and every command option (argparse); regenerating
it here and comparing with the committed file means a parameter or an option changed in the code
without the page fails the suite.
"""
import importlib.util
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def load_generator():
    spec = importlib.util.spec_from_file_location('gen_reference',
                                                  REPO / 'docs' / 'gen_reference.py')
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_committed_reference_is_the_generated_one():
    gen = load_generator()
    committed = (REPO / 'docs' / 'reference.md').read_text()
    assert committed == gen.render(), \
        'docs/reference.md is stale: run python docs/gen_reference.py'


def test_every_node_parameter_and_command_option_is_listed():
    gen = load_generator()
    text = gen.render()
    from piezo_narx_ros.cli.main import build_parser
    from piezo_narx_ros.nodes.estimator_node import EstimatorNode
    for spec in EstimatorNode.PARAMS:
        assert f'| `{spec.name}` |' in text
    fit = build_parser()._subparsers._group_actions[0].choices['fit']
    for action in fit._actions:
        for option in action.option_strings:
            if option not in ('-h', '--help'):
                assert f'`{option}' in text or f', {option}' in text, option
    # Every node the package installs has a section.
    setup = (REPO / 'setup.py').read_text()
    for module, _ in gen.NODES:
        assert f'{module} = piezo_narx_ros.nodes.{module}:main' in setup
        assert f'### {module}\n' in text


def test_check_mode_flags_a_stale_page(tmp_path, monkeypatch):
    gen = load_generator()
    stale = tmp_path / 'reference.md'
    stale.write_text('# an old page\n')
    monkeypatch.setattr(gen, 'OUT', stale)
    assert gen.main(['--check']) == 1
    assert gen.main([]) == 0
    assert gen.main(['--check']) == 0
    assert stale.read_text() == gen.render()
