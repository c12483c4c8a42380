"""
Figures show what they claim.

The plotted data, axis ranges, marks and titles of the report (figures 6-9), the demo's live
figures and the control demo's figures, read back from the matplotlib Figure objects as they are
saved (a PNG that exists can still show the wrong curve).
"""
import json
from pathlib import Path

import numpy as np
import pytest
from matplotlib.collections import LineCollection
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle
from test_demo import _live_bag
from test_demo_control import _control_bag
from test_ident_experiment import arx_record

from piezo_narx_ros.demo.analysis import load_live_run, percentiles_us, write_figures
from piezo_narx_ros.demo.control import load_control_run, write_control_figures
from piezo_narx_ros.ident.validation.correlation import TEST_NAMES
from piezo_narx_ros.ident.selection.experiment import (ExperimentConfig, run_experiment,
                                                       split_records)
from piezo_narx_ros.ident.selection.scoring import free_run
from piezo_narx_ros.ident.validation.report import write_report


def _capture(monkeypatch) -> dict:
    """{file name: Figure} of every figure saved from now on (Figure.savefig wrapped)."""
    figures = {}
    original = Figure.savefig

    def savefig(fig, fname, *args, **kwargs):
        figures[Path(fname).name] = fig
        return original(fig, fname, *args, **kwargs)
    monkeypatch.setattr(Figure, 'savefig', savefig)
    return figures


@pytest.fixture
def saved_figures(monkeypatch):
    """{file name: Figure} of every figure saved while the test runs."""
    return _capture(monkeypatch)


def _line(ax, label):
    [line] = [ln for ln in ax.get_lines() if ln.get_label() == label]
    return line.get_xdata(), line.get_ydata()


def _data_axes(fig):
    """Axes that plot data (not colour bars, not the text panel switched off)."""
    return [ax for ax in fig.axes if ax.axison and ax.get_label() != '<colorbar>']


# ----------------------------------------------------------------------------- the report
@pytest.fixture(scope='module')
def report(tmp_path_factory):
    """Write one ARX-grid report once: (result, validation record, paths, figures)."""
    rec = arx_record(seed=1)
    cfg = ExperimentConfig(narx=False, arx_na=(1, 2), arx_nb=(0, 1, 2), jobs=1)
    result = run_experiment([rec], cfg)
    _, val = split_records([rec], cfg.split)
    with pytest.MonkeyPatch.context() as mp:
        figures = _capture(mp)
        paths = write_report(result, val, tmp_path_factory.mktemp('report'))
    return result, val[0], paths, figures


def test_report_figures_plot_the_selected_models_data(report):
    result, val, paths, saved_figures = report
    assert set(saved_figures) == {p.name for k, p in paths.items() if k != 'metrics'}
    model, n0 = result.best.model, result.best.model.n0
    _, sim = free_run(model, val)
    sim = sim[:, 0]   # free_run gives (N, n_out) columns; the figure plots the one output
    val_u, val_y = val.u[:, 0], val.y[:, 0]
    t = np.arange(val_u.size) / val.fs

    # Fig. 8: measured and free-run output in µm over the record, the residual after n0.
    top, resid, zoom = _data_axes(saved_figures['fig8_simulation.png'])
    x, y = _line(top, 'measured')
    np.testing.assert_array_equal(x, t)
    np.testing.assert_allclose(y, val_y * 1e6, rtol=1e-12)
    np.testing.assert_allclose(_line(top, 'simulated (free run)')[1], sim * 1e6, rtol=1e-12)
    assert top.get_xlim() == pytest.approx((t[0], t[-1]))
    [line] = resid.get_lines()
    np.testing.assert_array_equal(line.get_xdata(), t[n0:])
    np.testing.assert_allclose(line.get_ydata(), (val_y - sim)[n0:] * 1e6, rtol=1e-9)
    rms = np.sqrt(np.mean(((val_y - sim)[n0:] * 1e6) ** 2))
    assert f'RMS {rms:.4g} µm' in resid.get_title()
    zx, zy = _line(zoom, 'measured')
    assert n0 <= zx[0] * val.fs and zx.size >= 200 and zx[-1] < t[-1]
    np.testing.assert_allclose(zy, val_y[np.round(zx * val.fs).astype(int)] * 1e6, rtol=1e-12)

    # Fig. 9: y(u) loops, whole record after n0, measured and simulated.
    whole, _ = _data_axes(saved_figures['fig9_hysteresis.png'])
    x, y = _line(whole, 'measured')
    np.testing.assert_array_equal(x, val_u[n0:])
    np.testing.assert_allclose(y, val_y[n0:] * 1e6, rtol=1e-12)
    np.testing.assert_allclose(_line(whole, 'simulated (free run)')[1], sim[n0:] * 1e6,
                               rtol=1e-12)
    assert whole.get_xlabel() == 'input u (V)'


def test_report_correlation_figure_shows_each_test_as_judged(report):
    result, val, paths, saved_figures = report
    doc = json.loads(paths['metrics'].read_text())
    corr = doc['selected_correlation'][result.config.residuals]
    band = 1.96 / np.sqrt(corr['n'])
    axes = saved_figures['fig7_correlation.png'].axes
    assert not axes[-1].axison                              # the sixth panel is the legend text
    assert f'±{band:.4f}' in axes[-1].texts[0].get_text()
    for ax, name in zip(axes, TEST_NAMES):
        test = corr['tests'][name]
        lags, values = np.array(test['lags']), np.array(test['values'], dtype=float)
        [stems] = [c for c in ax.collections if isinstance(c, LineCollection)]
        tops = np.array([seg[1] for seg in stems.get_segments()])
        np.testing.assert_array_equal(tops[:, 0], lags)
        np.testing.assert_allclose(tops[:, 1], values, rtol=1e-12)
        bands = sorted(ln.get_ydata()[0] for ln in ax.get_lines() if ln.get_linestyle() == '--')
        assert bands == pytest.approx([-band, band])
        tested = lags != 0
        low, high = ax.get_ylim()
        assert -low == high >= max(np.abs(values[tested]).max(), band)
        red = [ln for ln in ax.get_lines() if ln.get_color() == 'tab:red']
        outside = tested & (np.abs(values) > band)
        np.testing.assert_array_equal(red[0].get_xdata(), lags[outside])
        assert test['n_outside'] == outside.sum()
        assert ('pass' in ax.get_title()) == test['passed']
        assert ('FAIL' in ax.get_title()) != test['passed']


def test_report_r2_grid_colours_each_cell_by_its_candidate(report):
    result, val, paths, saved_figures = report
    fig = saved_figures['fig6_arx_r2_grid.png']
    axes = _data_axes(fig)
    assert len(axes) == 4
    best = result.best.spec
    for ax in axes:
        mode, data = ax.get_title().split(', ')
        image = np.asarray(ax.images[0].get_array())
        assert image.shape == (2, 3)                        # rows na = 1, 2; columns nb = 0..2
        assert [t.get_text() for t in ax.get_xticklabels()] == ['0', '1', '2']
        assert [t.get_text() for t in ax.get_yticklabels()] == ['1', '2']
        texts = {(round(t.get_position()[1]), round(t.get_position()[0])): t.get_text()
                 for t in ax.texts}
        for c in result.candidates:
            r2 = c.r2(data, mode)
            cell = (c.spec.ny - 1, c.spec.nu)
            assert image[cell] == pytest.approx(-np.log10(max(1.0 - r2, 1e-12)))
            decimals = len(texts[cell].split('.')[1])
            assert float(texts[cell]) == pytest.approx(r2, abs=0.51 * 10.0 ** -decimals)
            assert decimals >= 3
        [box] = [p for p in ax.patches if isinstance(p, Rectangle) and p.get_edgecolor()[0] == 1]
        assert box.get_xy() == (best.nu - 0.5, best.ny - 1 - 0.5)


# ------------------------------------------------------------------------- the demo's figures
def test_live_figures_plot_the_paired_samples_and_the_measured_latency(tmp_path, saved_figures):
    u, y, y_hat = _live_bag(tmp_path / 'b', n=400, drop_defl=(20,), delay_ns=300_000)
    run = load_live_run(tmp_path / 'b', expected=400)
    skip = 3
    write_figures(run, skip, tmp_path / 'fig', input_range=(-40.0, 40.0))
    top, err, zoom = saved_figures['live_tracking.png'].axes
    x, ym = _line(top, 'measured (deflection)')
    np.testing.assert_array_equal(x, run.t_s[skip:])
    np.testing.assert_allclose(ym, run.y[skip:] * 1e6, rtol=1e-12)
    np.testing.assert_allclose(_line(top, 'estimated (deflection_estimate, free run)')[1],
                               run.y_hat[skip:] * 1e6, rtol=1e-12)
    [line] = err.get_lines()
    np.testing.assert_allclose(line.get_ydata(), (run.y_hat - run.y)[skip:] * 1e9, rtol=1e-9)
    t = run.t_s[skip:]
    mid = t[0] + 0.5 * (t[-1] - t[0])                         # 0.25 s from the middle
    np.testing.assert_array_equal(_line(zoom, 'measured')[0], t[(t >= mid) & (t <= mid + 0.25)])

    loop, error_vs_u = saved_figures['live_hysteresis.png'].axes
    x, ym = _line(loop, 'measured')
    np.testing.assert_array_equal(x, run.u[skip:])
    np.testing.assert_allclose(ym, run.y[skip:] * 1e6, rtol=1e-12)
    [shade] = error_vs_u.patches                               # the training input range
    corners = shade.get_patch_transform().transform(shade.get_path().vertices)
    assert (corners[:, 0].min(), corners[:, 0].max()) == (-40.0, 40.0)
    np.testing.assert_allclose(error_vs_u.get_lines()[0].get_ydata(),
                               (run.y_hat - run.y)[skip:] * 1e9, rtol=1e-9)

    [ax] = saved_figures['live_latency.png'].axes
    delays = (run.log_estimate_ns - run.log_command_ns) / 1e3
    bars = [p for p in ax.patches if isinstance(p, Rectangle)]
    assert sum(b.get_height() for b in bars) == np.count_nonzero(delays > 0)
    p = percentiles_us(run.log_estimate_ns - run.log_command_ns)
    marks = {ln.get_label(): ln.get_xdata()[0] for ln in ax.get_lines()}
    assert marks == {f"p50 = {p['p50']:.0f} µs": pytest.approx(300.0),
                     f"p99 = {p['p99']:.0f} µs": pytest.approx(300.0)}


def test_control_figures_plot_reference_deflection_error_and_latency(tmp_path, saved_figures):
    r = _control_bag(tmp_path / 'b', n=6000, drop={}, delay_ns=250_000)
    run = load_control_run(tmp_path / 'b', 'piezo', expected=6000)
    write_control_figures({'inverse': run}, tmp_path / 'fig', skip_s=1.0)
    over_time, error, y_vs_r = saved_figures['control_tracking.png'].axes
    x, ref = _line(over_time, 'reference')
    assert x[0] == pytest.approx(1.0) and x[-1] == pytest.approx(1.0 + 2.0, abs=1e-3)
    np.testing.assert_allclose(ref, r[np.round(x * 2000).astype(int)] * 1e6, rtol=1e-12)
    _, e = _line(error, 'inverse')
    np.testing.assert_allclose(e, 0.05, rtol=1e-6)           # the bag's deflection is r + 50 nm
    x, y = _line(y_vs_r, 'inverse')
    np.testing.assert_allclose(y - x, 0.05, rtol=1e-6)
    [ax] = saved_figures['control_latency.png'].axes
    assert ax.get_legend().get_texts()[0].get_text() == 'inverse: p99 250 µs'
    bars = [p for p in ax.patches if isinstance(p, Rectangle)]
    assert sum(b.get_height() for b in bars) == run.t_s.size
