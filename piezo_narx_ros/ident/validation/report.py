"""
Report folder of an identification experiment: metrics.json and the paper-style figures.

    metrics.json               every candidate's scores and test verdicts, the selection, and the
                               selected model's correlation functions (values per lag)
    fig6_narx_r2_grid.png      R² over the NARX lag grid, prediction/simulation x
                               estimation/validation
    fig6_arx_r2_grid.png       the same for the ARX (na, nb) grid
    fig7_correlation.png       the five Billings tests of the selected model with the 95 % band
    fig8_simulation.png        measured vs free-run output on validation data, residual, and a zoom
    fig9_hysteresis.png        hysteresis loop y(u), measured and simulated

Outputs are plotted in µm (the files stay SI). Uses matplotlib's Agg backend (no display needed).
"""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from piezo_narx_ros.ident.validation.correlation import TEST_LABELS, TEST_NAMES
from piezo_narx_ros.record import Record
from piezo_narx_ros.ident.selection.experiment import ExperimentResult
from piezo_narx_ros.ident.selection.scoring import (free_run, outputs_by_record,
                                                    residual_correlations, scored_from)
from piezo_narx_ros.ident.validation.noise_model import noise_models_from_doc

UM = 1e6  # metres -> micrometres for plots


def _pyplot():
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    return plt


def json_safe(obj):
    """Replace non-finite floats (not valid JSON) by None, recursively."""
    if isinstance(obj, dict):
        return {k: json_safe(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [json_safe(v) for v in obj]
    if isinstance(obj, (float, np.floating)):
        return float(obj) if np.isfinite(obj) else None
    if isinstance(obj, np.integer):
        return int(obj)
    return obj


def write_json(obj, path) -> Path:
    """Write obj as indented JSON (non-finite numbers as null); returns the path."""
    from piezo_narx_ros.files import write_text_atomic
    path = Path(path)
    write_text_atomic(path, json.dumps(json_safe(obj), indent=1) + '\n')
    return path


def selected_correlations(result: ExperimentResult, validation: list[Record]) -> dict:
    """
    Compute the correlation functions of the selected model on the validation data.

    Per residual kind, whitened by the same noise model as the verdicts (so Fig. 7 shows what was
    judged).
    """
    parts = outputs_by_record(result.best.model, validation)
    cfg = result.config
    corr = {}
    for mode in ('prediction', 'simulation'):
        doc = result.best.tests.get(mode, {}).get('noise_model')
        noise = noise_models_from_doc(doc) if doc else None
        c = residual_correlations(parts, mode, cfg.max_lag, cfg.max_outside_fraction, noise)
        if c is not None:
            corr[mode] = (c, noise)
    return corr


MAX_RECORD_FIGURES = 4


def write_report(result: ExperimentResult, validation: list[Record], out_dir) -> dict[str, Path]:
    """
    Write metrics.json and the figures for `result` into out_dir (created); returns the paths.

    `validation` are the validation halves the experiment scored (figures 7-9 use the selected
    model on them; figures 8-9 show each record, the first as fig8_simulation.png /
    fig9_hysteresis.png, the next ones with a _r<i> suffix, at most MAX_RECORD_FIGURES).
    """
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    corr = selected_correlations(result, validation)
    summary = result.to_dict()
    summary['selected_correlation'] = {
        mode: {**c.to_dict(), 'noise_model': (None if not noise else
                                              [n.to_dict() for n in noise]
                                              if isinstance(noise, list) else noise.to_dict())}
        for mode, (c, noise) in corr.items()}
    paths = {'metrics': write_json(summary, out_dir / 'metrics.json')}
    plt = _pyplot()
    try:
        for kind, name in (('narx', 'fig6_narx_r2_grid.png'), ('arx', 'fig6_arx_r2_grid.png')):
            fig = plot_r2_grid(result, kind)
            if fig is not None:
                paths[f'r2_grid_{kind}'] = _save(fig, out_dir / name)
        mode = result.config.residuals
        if mode in corr:
            c, noise = corr[mode]
            paths['correlation'] = _save(plot_correlation(c, result.best.spec.label, mode, noise),
                                         out_dir / 'fig7_correlation.png')
        model = result.best.model
        label = result.best.spec.label
        for i, rec in enumerate(validation[:MAX_RECORD_FIGURES]):
            _, sim = free_run(model, rec)
            if not np.all(np.isfinite(sim)):
                continue
            first = scored_from(model, rec)
            for one, sim_j, axis in _per_output(rec, sim):
                tag = ('' if i == 0 else f'_r{i}') + axis
                title = label if len(validation) == 1 else f'{label}, {rec.source}'
                title += f' (output {one.outputs[0]})' if axis else ''
                paths['simulation' + tag] = _save(plot_simulation(one, sim_j, title, first),
                                                  out_dir / f'fig8_simulation{tag}.png')
                paths['hysteresis' + tag] = _save(plot_hysteresis(one, sim_j, title, first),
                                                  out_dir / f'fig9_hysteresis{tag}.png')
    finally:
        plt.close('all')
    return paths


def _per_output(rec: Record, sim: np.ndarray):
    """
    Yield (one-output record, its free run (N,), file tag) for each output of a record.

    One output: the record itself and tag ''. Several: output j beside input j (the last input
    when there are fewer), tag '_<name>', so each figure shows one axis.
    """
    sim = sim.reshape(len(rec), -1)
    if rec.n_out == 1:
        yield rec, sim[:, 0], ''
        return
    for j, name in enumerate(rec.outputs):
        i = min(j, rec.n_in - 1)
        one = Record(u=rec.u[:, i], y=rec.y[:, j], fs=rec.fs, source=rec.source,
                     inputs=(rec.inputs[i],), outputs=(name,))
        yield one, sim[:, j], f'_{name}'


def _save(fig, path: Path) -> Path:
    fig.savefig(path, dpi=110)
    _pyplot().close(fig)
    return path


def _grid(result: ExperimentResult, kind: str):
    """(rows = output lags, cols = input lags, {(data, mode): 2-D R² array}) for one model kind."""
    cands = [c for c in result.candidates if c.spec.kind == kind]
    if not cands:
        return None
    rows = sorted({c.spec.ny for c in cands})
    cols = sorted({c.spec.nu for c in cands})
    grids = {}
    for data in ('estimation', 'validation'):
        for mode in ('prediction', 'simulation'):
            g = np.full((len(rows), len(cols)), np.nan)
            for c in cands:
                v = c.r2(data, mode)
                g[rows.index(c.spec.ny), cols.index(c.spec.nu)] = v if np.isfinite(v) else np.nan
            grids[(data, mode)] = g
    return rows, cols, grids


def plot_r2_grid(result: ExperimentResult, kind: str = 'narx'):
    """
    Fig. 6: R² heat maps over the lag grid; colour = -log10(1 - R²) ("nines"), text = R².

    Returns a matplotlib Figure, or None when the experiment has no candidate of `kind`.
    """
    found = _grid(result, kind)
    if found is None:
        return None
    rows, cols, grids = found
    plt = _pyplot()
    big = max(len(rows), len(cols)) > 5
    fig, axes = plt.subplots(2, 2, figsize=(12, 9.5) if big else (9, 7.4), constrained_layout=True)
    nines = {k: -np.log10(np.clip(1.0 - g, 1e-12, None)) for k, g in grids.items()}
    finite = np.concatenate([v[np.isfinite(v)] for v in nines.values()])
    vmin, vmax = (float(finite.min()), float(finite.max())) if finite.size else (0.0, 1.0)
    if vmax - vmin < 1e-6:
        vmax = vmin + 1.0
    # Enough decimals that the best cells do not all print as 1.000.
    decimals = int(np.clip(np.ceil(vmax) + 1, 3, 4 if big else 6))
    ylab, xlab = ('output lag ny', 'input lag nu') if kind == 'narx' else ('na', 'nb')
    image = None
    for i, mode in enumerate(('prediction', 'simulation')):
        for j, data in enumerate(('estimation', 'validation')):
            ax = axes[i, j]
            image = ax.imshow(nines[(data, mode)], origin='lower', cmap='viridis', vmin=vmin,
                              vmax=vmax, aspect='auto')
            ax.set_xticks(range(len(cols)), [str(c) for c in cols])
            ax.set_yticks(range(len(rows)), [str(r) for r in rows])
            ax.set_xlabel(xlab)
            ax.set_ylabel(ylab)
            ax.set_title(f'{mode}, {data}')
            g = grids[(data, mode)]
            for r in range(len(rows)):
                for c in range(len(cols)):
                    v = g[r, c]
                    text = 'diverged' if not np.isfinite(v) else f'{v:.{decimals}f}'
                    shade = nines[(data, mode)][r, c]
                    dark = np.isfinite(shade) and shade < vmin + 0.6 * (vmax - vmin)
                    ax.text(c, r, text, ha='center', va='center', fontsize=6.5 if big else 9,
                            color='white' if dark else 'black')
    best = result.best.spec
    if best.kind == kind:
        for i in range(2):
            for j in range(2):
                axes[i, j].add_patch(plt.Rectangle(
                    (cols.index(best.nu) - 0.5, rows.index(best.ny) - 0.5), 1, 1, fill=False,
                    edgecolor='red', linewidth=2))
    bar = fig.colorbar(image, ax=axes, shrink=0.8)
    bar.set_label(r'$-\log_{10}(1-R^2)$  (number of nines)')
    name = 'NARX network' if kind == 'narx' else 'ARX'
    fig.suptitle(f'{name} R² over the lag grid (text: R²; red: selected model)')
    return fig


def plot_correlation(corr, label: str, mode: str, noise=None):
    """
    Fig. 7: the five correlation functions with the ±1.96/sqrt(N) band; returns the Figure.

    `noise` is the AR noise model that whitened the residuals (None: raw residuals).
    """
    plt = _pyplot()
    fig, axes = plt.subplots(3, 2, figsize=(10, 8.4), constrained_layout=True)
    flat = axes.ravel()
    for ax, name in zip(flat, TEST_NAMES):
        test = corr.tests[name]
        lags, vals = test.lags, np.nan_to_num(test.values)
        tested = lags != 0
        ax.vlines(lags, 0, vals, color='tab:blue', linewidth=1.2)
        outside = tested & (np.abs(vals) > corr.band)
        ax.plot(lags[tested & ~outside], vals[tested & ~outside], 'o', color='tab:blue', ms=3)
        ax.plot(lags[outside], vals[outside], 'o', color='tab:red', ms=4)
        ax.plot(lags[~tested], vals[~tested], 'o', color='0.6', ms=3)
        ax.axhline(corr.band, color='k', linestyle='--', linewidth=0.8)
        ax.axhline(-corr.band, color='k', linestyle='--', linewidth=0.8)
        ax.axhline(0, color='k', linewidth=0.5)
        span = max(0.1, 1.2 * float(np.max(np.abs(vals[tested]))) if tested.any() else 0.1,
                   2 * corr.band)
        ax.set_ylim(-span, span)
        verdict = 'pass' if test.passed else f'FAIL ({test.n_outside}/{test.n_tested} outside)'
        ax.set_title(f'{TEST_LABELS[name]}: {verdict}',
                     color='black' if test.passed else 'tab:red')
        ax.set_xlabel('lag τ (samples)')
    flat[-1].axis('off')
    if isinstance(noise, list):   # several outputs: the pair the tests judged
        noise = noise[(corr.pair or {}).get('output', 0)]
    whitening = (f'after the AR({noise.order}) noise model' if noise is not None and noise.order
                 else 'raw (no noise model)')
    flat[-1].text(0.02, 0.5,
                  f'{label}\n{mode} residuals, validation data\n{whitening}\nN = {corr.n}, '
                  f'band ±1.96/√N = ±{corr.band:.4f}\nlag 0 (grey) not tested\n'
                  f'overall: {"PASS" if corr.passed else "FAIL"}',
                  va='center', fontsize=10, transform=flat[-1].transAxes)
    fig.suptitle('Residual correlation tests (Billings)')
    return fig


def plot_simulation(rec: Record, sim: np.ndarray, label: str, n0: int):
    """Fig. 8: measured and free-run output (µm) over time, the residual, and a zoom."""
    plt = _pyplot()
    y = rec.y[:, 0]   # one output (write_report splits several)
    sim = np.reshape(sim, -1)
    t = np.arange(len(rec)) / rec.fs
    fig, axes = plt.subplots(3, 1, figsize=(10, 8), constrained_layout=True)
    axes[0].plot(t, y * UM, color='tab:blue', linewidth=0.8, label='measured')
    axes[0].plot(t, sim * UM, color='tab:orange', linewidth=0.8, linestyle='--',
                 label='simulated (free run)')
    axes[0].set_ylabel('deflection (µm)')
    axes[0].legend(loc='upper right')
    axes[0].set_title(f'{label}: validation data, free-run simulation from u alone')
    resid = (y - sim)[n0:] * UM
    axes[1].plot(t[n0:], resid, color='tab:red', linewidth=0.6)
    axes[1].set_ylabel('residual (µm)')
    rms = float(np.sqrt(np.mean(resid ** 2)))
    axes[1].set_title(f'residual y - ŷ (RMS {rms:.4g} µm)')
    cut = _zoom_window(len(rec), n0)
    axes[2].plot(t[cut], y[cut] * UM, color='tab:blue', linewidth=1.2, label='measured')
    axes[2].plot(t[cut], sim[cut] * UM, color='tab:orange', linewidth=1.2, linestyle='--',
                 label='simulated')
    axes[2].set_ylabel('deflection (µm)')
    axes[2].set_xlabel('time (s)')
    axes[2].legend(loc='upper right')
    axes[2].set_title('zoom')
    for ax in axes[:2]:
        ax.set_xlim(t[0], t[-1])
    return fig


def _zoom_window(n: int, n0: int) -> slice:
    """About 5 % of a record (at least 200 samples) around its middle, after the first n0."""
    width = min(n, max(200, n // 20))
    start = max(n0, n // 2 - width // 2)
    return slice(start, min(n, start + width))


def plot_hysteresis(rec: Record, sim: np.ndarray, label: str, n0: int):
    """
    Fig. 9: hysteresis loop, deflection (µm) against input (V), measured and simulated.

    The whole validation record and, to see single loops, the zoom window of Fig. 8.
    """
    plt = _pyplot()
    u, y = rec.u[:, 0], rec.y[:, 0]   # one output (write_report splits several)
    sim = np.reshape(sim, -1)
    fig, axes = plt.subplots(1, 2, figsize=(11, 5), constrained_layout=True)
    for ax, cut, title in ((axes[0], slice(n0, None), 'whole validation record'),
                           (axes[1], _zoom_window(len(rec), n0), 'zoom (as Fig. 8)')):
        ax.plot(u[cut], y[cut] * UM, color='tab:blue', linewidth=0.8, label='measured')
        ax.plot(u[cut], sim[cut] * UM, color='tab:orange', linewidth=0.8, linestyle='--',
                alpha=0.8, label='simulated (free run)')
        ax.set_xlabel('input u (V)')
        ax.set_ylabel('deflection y (µm)')
        ax.set_title(title)
        ax.legend(loc='upper left')
        ax.grid(alpha=0.3)
    fig.suptitle(f'Hysteresis loop y(u): {label}')
    return fig
