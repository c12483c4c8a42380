"""
`piezo-narx demo --make-sample-bags DIR`: record the sample bags and fit their model.

The repository's sample bags, recorded through the real nodes (command_node -> simulator_node ->
recorder_node over DDS), and the model fitted from them. Short on purpose: MCAP chunks are written
uncompressed (about 0.2 MB per second of one 2 kHz JointState stream), and the bags live in git.

    DIR/estimation   multisine, seed 0       -> `piezo-narx fit` (its own 50/50 split selects)
    DIR/validation   multisine, seed 1       -> held out: `piezo-narx evaluate` only
    DIR/sine         sine 0.5 Hz, one period -> the hysteresis loop
    DIR/model.json + model.npz               -> fitted from DIR/estimation alone
"""
from __future__ import annotations

import json
import shutil
import tempfile
import time
from pathlib import Path

from piezo_narx_ros.demo.runner import (Demo, PhaseFailed, install_signal_handlers,
                                        restore_signal_handlers, stream_counts)
from piezo_narx_ros.errors import ConfigError

# (bag name, seconds, seed, command_node kind, extra command parameters)
SAMPLE_BAGS = (
    ('estimation', 6.0, 0, 'multisine', {}),
    ('validation', 2.0, 1, 'multisine', {}),
    ('sine', 2.0, 2, 'sine', {'freq': 0.5}),
)
TOPICS_UY = {'piezo/voltage_command': 'effort', 'piezo/deflection': 'position'}


def make_sample_bags(settings: dict, dest: Path, bags=SAMPLE_BAGS) -> int:
    """
    Record `bags` into dest, fit dest/model.json from dest/estimation, score it on dest/validation.

    Prints what it did. Returns 0; PhaseFailed/Interrupted propagate.
    """
    dest = Path(dest)
    taken = [name for name, *_ in bags if (dest / name).exists()]
    if taken or (dest / 'model.json').exists():
        raise ConfigError(f'{dest}: already holds {", ".join(taken) or "model.json"}; '
                          'remove the old sample bags first')
    work = Path(tempfile.mkdtemp(prefix='piezo-sample-bags-'))
    demo = Demo(settings, dest, say=print, work=work)
    old = install_signal_handlers(demo)
    t0 = time.monotonic()
    try:
        with demo:
            for name, seconds, seed, kind, extra in bags:
                print(f'== recording {dest / name}: {kind} {seconds:g} s, seed {seed}', flush=True)
                run = demo.stream(name, dest / name, seconds, seed, kind=kind,
                                  extra_command=extra)
                counts = stream_counts(dest / name, TOPICS_UY)
                lost = {t: run['published'] - c for t, c in counts.items()}
                if any(lost.values()):
                    raise PhaseFailed(f'{name}: samples lost while recording ({lost}); '
                                      'run again on a quieter machine')
            print(f'== fitting {dest / "model.json"} from {dest / "estimation"}', flush=True)
            demo.fit(dest / 'estimation', work / 'fit', no_report=True)
            for suffix in ('.json', '.npz'):
                shutil.copy(work / 'fit' / f'model{suffix}', dest / f'model{suffix}')
        score = evaluate(dest / 'model.json', dest / 'validation')
        sine_loop_figure(dest / 'model.json', dest / 'sine', dest / 'sine_loop.png')
        print(f'model on {dest / "validation"} (held out): free-run R² '
              f'{score["simulation"]["r2"]:.6f}, RMSE {score["simulation"]["rmse"] * 1e9:.1f} '
              f'nm; done in {time.monotonic() - t0:.0f} s', flush=True)
    finally:
        restore_signal_handlers(old)
    shutil.rmtree(work, ignore_errors=True)   # kept after a failure: the error names its log
    return 0


def evaluate(model_path: Path, bag: Path) -> dict:
    """
    Return `piezo-narx evaluate`'s scores of a model file on one bag.

    Whole record, free run from the first n0 measured outputs.
    """
    from piezo_narx_ros.cli.evaluate import evaluate as evaluate_model
    from piezo_narx_ros.ident.data.loaders import load_records
    from piezo_narx_ros.ident.model_io import load_model
    return json.loads(json.dumps(evaluate_model(load_model(model_path),
                                                load_records([bag])), default=float))


def sine_loop_figure(model_path: Path, bag: Path, png: Path) -> Path:
    """
    Plot the sine bag's hysteresis loop, measured and the model's free run; saved to png.

    The free run starts from the first n0 measured outputs; the error is shown in nm.
    """
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    from piezo_narx_ros.bag.reader import read_uy
    from piezo_narx_ros.ident.model_io import load_model
    model = load_model(model_path)
    rec = read_uy(bag)
    sim = model.simulate(rec.u, rec.y[:model.n0])
    fig, ax = plt.subplots(1, 2, figsize=(11, 4.5), constrained_layout=True)
    ax[0].plot(rec.u, rec.y * 1e6, lw=1.0, label='measured (simulator_node)')
    ax[0].plot(rec.u, sim * 1e6, lw=1.0, ls='--', label=f'model free run ({model_path.name})')
    ax[0].set_xlabel('voltage command [V]')
    ax[0].set_ylabel('deflection [µm]')
    ax[0].set_title(f'{bag.name}: one period of a 0.5 Hz sine')
    ax[0].legend(loc='upper left')
    ax[1].plot(rec.t, (sim - rec.y) * 1e9, lw=0.5, color='C3')
    ax[1].set_xlabel('time [s]')
    ax[1].set_ylabel('free run - measured [nm]')
    ax[1].set_title('error')
    fig.savefig(png, dpi=100)
    plt.close(fig)
    return Path(png)
