"""
What the demo measures on a live recording, ROS-free: free-run accuracy, latency and loss.

The input is a bag recorded by recorder_node with voltage_command, deflection and
deflection_estimate (JointState; stamps t_k shared by the three streams, receive times = the
recorder's wall clock). Everything here works on numpy arrays read from that bag.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from piezo_narx_ros.errors import DataError
from piezo_narx_ros.ident.validation import metrics

COMMAND = 'piezo/voltage_command'
DEFLECTION = 'piezo/deflection'
ESTIMATE = 'piezo/deflection_estimate'


@dataclass
class LiveRun:
    """
    Samples of one live run, paired by stamp (arrays (n,) in stamp order).

    t_s: seconds since the first command stamp; u: V; y: measured m; y_hat: estimated m;
    log_*_ns: the recorder's receive time of each message, ns (same clock for all three).
    first_estimate: index of the first sample with an estimate (samples before it were not
    estimated: the estimator waits for its first measured window).
    """

    stamps_ns: np.ndarray
    t_s: np.ndarray
    u: np.ndarray
    y: np.ndarray
    y_hat: np.ndarray
    log_command_ns: np.ndarray
    log_deflection_ns: np.ndarray
    log_estimate_ns: np.ndarray
    first_estimate: int
    lost: dict          # {stream: samples missing on it}, see load_live_run
    fs: float
    axes: tuple = ()    # several axes: the deflection's names (then y, y_hat are (n, axes))


def _unique(stamps: np.ndarray, *arrays: np.ndarray):
    """Sort by stamp and keep the first message of a repeated stamp."""
    order = np.argsort(stamps, kind='stable')
    s = stamps[order]
    keep = np.ones(s.size, dtype=bool)
    keep[1:] = s[1:] != s[:-1]
    return (s[keep],) + tuple(a[order][keep] for a in arrays)


def load_live_run(bag, expected: int | None = None, fs: float | None = None) -> LiveRun:
    """
    Read the three streams of a live run from `bag` and pair them by stamp.

    expected: samples the command node published (from its diagnostics); None = the number of
    distinct stamps seen on any stream. Lost samples per stream: expected minus distinct stamps
    received, except for the estimate, which is only expected from its first sample on.
    Raises DataError when a stream is empty.
    """
    from piezo_narx_ros.bag.reader import read_joint_series
    series = read_joint_series(bag, {COMMAND: 'effort', DEFLECTION: 'position',
                                     ESTIMATE: 'position'})
    streams = {}
    for topic, name in ((COMMAND, 'command'), (DEFLECTION, 'deflection'),
                        (ESTIMATE, 'estimate')):
        s = series[topic]
        if s.values.size == 0:
            raise DataError(f'{bag}: no samples on /{topic}')
        streams[name] = _unique(s.stamps_ns, s.values, s.log_ns)
    all_stamps = np.unique(np.concatenate([v[0] for v in streams.values()]))
    n_expected = int(expected) if expected is not None else all_stamps.size
    first_est = streams['estimate'][0][0]
    unseen = max(0, n_expected - all_stamps.size)   # missed by all three streams
    lost = {
        'command': n_expected - streams['command'][0].size,
        'deflection': n_expected - streams['deflection'][0].size,
        # Only stamps from the first estimate on were due (those before: initialisation).
        'estimate': int(np.count_nonzero(all_stamps >= first_est)) + unseen
        - streams['estimate'][0].size,
    }
    cs, cu, clog = streams['command']
    ds, dy, dlog = streams['deflection']
    es, ey, elog = streams['estimate']
    common = np.intersect1d(np.intersect1d(cs, ds), es)
    if common.size < 2:
        raise DataError(f'{bag}: fewer than 2 samples have command, deflection and estimate')
    ic = np.searchsorted(cs, common)
    idf = np.searchsorted(ds, common)
    ie = np.searchsorted(es, common)
    if fs is None:
        fs = 1e9 / float(np.median(np.diff(cs))) if cs.size > 1 else float('nan')
    return LiveRun(stamps_ns=common, t_s=(common - cs[0]) * 1e-9, u=cu[ic], y=dy[idf],
                   y_hat=ey[ie], log_command_ns=clog[ic], log_deflection_ns=dlog[idf],
                   log_estimate_ns=elog[ie],
                   first_estimate=int(np.count_nonzero(cs < first_est)),
                   lost={k: int(v) for k, v in lost.items()}, fs=float(fs),
                   axes=tuple(series[DEFLECTION].names) if dy.ndim == 2 else ())


def percentiles_us(delays_ns: np.ndarray) -> dict:
    """{'p50', 'p99', 'max', 'n'} of delays given in ns, reported in µs."""
    d = np.asarray(delays_ns, dtype=np.float64) / 1e3
    if d.size == 0:
        return {'p50': None, 'p99': None, 'max': None, 'n': 0}
    p50, p99, mx = np.percentile(d, [50, 99, 100])
    return {'p50': float(p50), 'p99': float(p99), 'max': float(mx), 'n': int(d.size)}


def _streaming(run: LiveRun, skip: int) -> np.ndarray:
    """
    Mask (n,) of the samples the estimator streamed, not held back for its initialisation.

    Held back: the measured window its state is set from (the first `skip` samples) and every
    later sample whose command the recorder had received before the first estimate arrived (the
    estimator computes the state, then publishes the waiting samples in one burst). Their delay
    is the window plus that computation, a start-up cost and not the per-sample latency.
    """
    index = np.arange(run.log_command_ns.size)
    waited = (index < skip) | ((index > 0) & (run.log_command_ns < run.log_estimate_ns.min()))
    return ~waited


def live_figures(run: LiveRun, skip: int = 0, input_range: tuple | None = None) -> dict:
    """
    Free-run accuracy and latency of a live run.

    skip: paired samples left out of R²/RMSE at the start (the measured window the estimator's
    state was fitted to, when it initialises from measurement). Returns a JSON-ready dict: r2,
    rmse_m,
    rmse_nm, max_abs_error_nm, n_scored, latency_us (estimate receive time minus command receive
    time, same stamp, both at the recorder), lateness_us (estimate receive time minus the stamp,
    i.e. including the command node's timer lateness), both over the streamed samples
    (`_streaming`), init_latency_us: the same for the samples that waited for the estimator's
    initialisation, lost samples. With input_range (V, the
    model's training range): how many scored commands lie outside it and the R²/RMSE of the
    samples inside it (a fresh excitation can reach voltages the model never saw).
    """
    if run.y.size - skip < 2:
        raise DataError(f'too few paired samples to score ({run.y.size}, skipping {skip})')
    y, y_hat = run.y[skip:], run.y_hat[skip:]
    err = y_hat - y
    streaming = _streaming(run, skip)
    # Several axes: pooled over them (docs/mimo.md), and each axis in `per_axis`.
    sc = metrics.channel_scores(y, y_hat, names=run.axes or None)
    out = {
        'n_paired': int(y.shape[0] + skip),
        'n_scored': int(y.shape[0]),
        'skipped_at_start': int(skip),
        'not_estimated_at_start': int(run.first_estimate),
        'r2': sc['r2'],
        'rmse_m': sc['rmse'],
        'rmse_nm': sc['rmse'] * 1e9,
        'max_abs_error_nm': float(np.max(np.abs(err)) * 1e9),
        'y_span_um': float(np.ptp(y) * 1e6),
        'latency_us': percentiles_us((run.log_estimate_ns - run.log_command_ns)[streaming]),
        'lateness_us': percentiles_us((run.log_estimate_ns - run.stamps_ns)[streaming]),
        'init_latency_us': percentiles_us((run.log_estimate_ns - run.log_command_ns)[~streaming]),
        'lost': dict(run.lost),
        'fs': run.fs,
    }
    if 'per_output' in sc:
        out['per_axis'] = [{'axis': r['name'], 'r2': r['r2'], 'rmse_nm': r['rmse'] * 1e9}
                           for r in sc['per_output']]
    if input_range is not None:
        lo, hi = (np.asarray(v, dtype=np.float64) for v in input_range)
        inside = (run.u[skip:] >= lo) & (run.u[skip:] <= hi)
        if inside.ndim == 2:       # a sample is inside when every axis is
            inside = inside.all(axis=1)
        out['input_range_V'] = [lo.tolist(), hi.tolist()]
        out['outside_input_range'] = int(np.count_nonzero(~inside))
        if np.count_nonzero(inside) >= 2:
            sc_in = metrics.channel_scores(y[inside], y_hat[inside])
            out['r2_inside_input_range'] = sc_in['r2']
            out['rmse_nm_inside_input_range'] = sc_in['rmse'] * 1e9
    return out


def offline_difference(run: LiveRun, model, init_samples: int) -> float | None:
    """
    Return the largest |live estimate - model.simulate| (m) over every estimated sample.

    init_samples > 0: the estimator started from the state its first init_samples measured
    samples set, so the offline run starts from model.estimate_state of the same window; 0: from
    rest. None when samples are missing in between (the live estimator then held the command,
    which the offline run cannot know).
    """
    if np.any(np.diff(run.stamps_ns) > 1.5e9 / run.fs):
        return None
    if init_samples:
        n = int(init_samples)
        sim = model.simulate(run.u, state=model.estimate_state(run.u[:n], run.y[:n]))
    else:
        sim = model.simulate(run.u)
    return float(np.max(np.abs(sim - run.y_hat)))


# ----------------------------------------------------------------------------------- figures
def _pyplot():
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt
    return plt


def plot_tracking(run: LiveRun, skip: int, zoom_s: float = 0.25):
    """Measured vs estimated deflection (µm), the error (nm), and a zoom of zoom_s seconds."""
    plt = _pyplot()
    t, y, yh = run.t_s[skip:], run.y[skip:] * 1e6, run.y_hat[skip:] * 1e6
    err_nm = (run.y_hat[skip:] - run.y[skip:]) * 1e9
    fig, ax = plt.subplots(3, 1, figsize=(10, 8), constrained_layout=True)
    ax[0].plot(t, y, lw=0.8, label='measured (deflection)')
    ax[0].plot(t, yh, lw=0.8, ls='--', label='estimated (deflection_estimate, free run)')
    ax[0].set_ylabel('deflection [µm]')
    ax[0].legend(loc='upper right')
    ax[0].set_title('live free-run estimate vs measurement')
    ax[1].plot(t, err_nm, lw=0.6, color='C3')
    ax[1].set_ylabel('estimate - measured [nm]')
    mid = t[0] + 0.5 * (t[-1] - t[0])
    sel = (t >= mid) & (t <= mid + zoom_s)
    ax[2].plot(t[sel], y[sel], '.-', ms=3, lw=0.8, label='measured')
    ax[2].plot(t[sel], yh[sel], '.--', ms=3, lw=0.8, label='estimated')
    ax[2].set_ylabel('deflection [µm]')
    ax[2].set_xlabel('time [s]')
    ax[2].set_title(f'zoom: {zoom_s * 1e3:.0f} ms')
    ax[2].legend(loc='upper right')
    return fig


def plot_hysteresis(run: LiveRun, skip: int, input_range: tuple | None = None):
    """
    Plot deflection against command voltage, measured and estimated.

    And the estimate's error against voltage (the model's training input range shaded).
    """
    plt = _pyplot()
    fig, ax = plt.subplots(1, 2, figsize=(12, 4.8), constrained_layout=True)
    u = run.u[skip:]
    ax[0].plot(u, run.y[skip:] * 1e6, lw=0.4, color='C0', label='measured')
    ax[0].plot(u, run.y_hat[skip:] * 1e6, lw=0.4, ls='--', color='C1',
               label='estimated (free run)')
    ax[0].set_xlabel('voltage command [V]')
    ax[0].set_ylabel('deflection [µm]')
    ax[0].set_title('hysteresis: deflection vs voltage')
    ax[0].legend(loc='upper left')
    ax[1].plot(u, (run.y_hat[skip:] - run.y[skip:]) * 1e9, '.', ms=1.5, color='C3')
    if input_range is not None and not np.ndim(input_range[0]):   # one axis: its range
        ax[1].axvspan(*input_range, color='0.9', zorder=0, label='training input range')
        ax[1].legend(loc='upper left')
    ax[1].set_xlabel('voltage command [V]')
    ax[1].set_ylabel('estimate - measured [nm]')
    ax[1].set_title('free-run error vs voltage')
    return fig


def plot_latency(run: LiveRun):
    """Histogram of estimate-minus-command receive times at the recorder (µs)."""
    plt = _pyplot()
    d = (run.log_estimate_ns - run.log_command_ns) / 1e3
    fig, ax = plt.subplots(figsize=(8, 4), constrained_layout=True)
    pos = d[d > 0]
    if pos.size:
        lo = max(pos.min(), 1.0)
        bins = np.logspace(np.log10(lo), np.log10(pos.max() * 1.01 + 1), 60)
        bins[0] = min(bins[0], lo)   # 10**log10(x) can round above x and drop the fastest sample
        ax.hist(pos, bins=bins, color='C2')
        ax.set_xscale('log')
    for q, ls in ((50, '--'), (99, ':')):
        v = float(np.percentile(d, q))
        ax.axvline(max(v, 1.0), color='k', ls=ls, label=f'p{q} = {v:.0f} µs')
    ax.set_xlabel('command -> estimate latency at the recorder [µs]')
    ax.set_ylabel('samples')
    ax.legend()
    return fig


def write_figures(run: LiveRun, skip: int, out_dir,
                  input_range: tuple | None = None) -> dict[str, Path]:
    """
    Save live_tracking.png, live_hysteresis.png, live_latency.png in out_dir.

    Returns {name: path}.
    """
    plt = _pyplot()
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = {}
    try:
        for name, fig in (('tracking', plot_tracking(run, skip)),
                          ('hysteresis', plot_hysteresis(run, skip, input_range)),
                          ('latency', plot_latency(run))):
            paths[name] = out_dir / f'live_{name}.png'
            fig.savefig(paths[name], dpi=110)
            plt.close(fig)
    finally:
        plt.close('all')
    return paths
