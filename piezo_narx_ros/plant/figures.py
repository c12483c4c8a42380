"""
Measure the plant's behaviour and draw the figures of docs/plant.md.

    python -m piezo_narx_ros.plant.figures [OUTDIR]      (default docs/figures)

Prints the measured figures (loop widths, rate dependence, creep, resonance, noise) and writes
plant_hysteresis.png, plant_creep.png, plant_frequency_response.png, plant_multisine.png.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
from scipy import signal as sps

from piezo_narx_ros.plant import PiezoCantilever, generate, load_plant_params
from piezo_narx_ros.plant.piezo import linear_system

FS = 2000.0


def loop_width(u, y, bins=None):
    """
    Loop width of one sine period: max(descending - ascending branch) / peak-to-peak y.

    Branches are averaged in voltage bins (default min(80, samples/8)), ignoring the 5 % of the
    range at each end where they meet. Returns (width, bin centres V, ascending m, descending m).
    """
    bins = bins or min(80, u.size // 8)
    rising = np.gradient(u) > 0
    edges = np.linspace(u.min(), u.max(), bins + 1)
    edges = edges[bins // 20:bins + 1 - bins // 20]
    centre = 0.5 * (edges[:-1] + edges[1:])
    bins = list(zip(edges[:-1], edges[1:]))
    up = np.array([y[rising & (u >= a) & (u < b)].mean() for a, b in bins])
    down = np.array([y[~rising & (u >= a) & (u < b)].mean() for a, b in bins])
    return float(np.max(down - up) / np.ptp(y)), centre, up, down


def sine_period(params, amplitude, freq, cycles=2, seed=0):
    """(u V, y m, y_true m) over the last of `cycles` periods of a sine."""
    n = int(round(FS / freq))
    u = generate('sine', FS, cycles / freq, amplitude, freq=freq)
    res = PiezoCantilever(params, FS, seed=seed).run(u)
    return u[-n:], res.y[-n:], res.y_true[-n:]


def frf_from_chirp(params, amplitude=3.0, seconds=8.0, f0=100.0, f1=990.0, seed=2):
    """H1 estimate y/u (m/V) from a linear chirp; returns (f Hz, H complex) inside the sweep."""
    u = generate('chirp', FS, seconds, amplitude, f0=f0, f1=f1)
    y = PiezoCantilever(params, FS, seed=seed).run(u).y
    f, puu = sps.welch(u, FS, nperseg=2048)
    _, puy = sps.csd(u, y, FS, nperseg=2048)
    band = (f > 1.5 * f0) & (f < 0.91 * f1)
    return f[band], puy[band] / puu[band]


def measure(params=None) -> dict:
    """Return the figures quoted in docs/plant.md, measured on the simulated plant."""
    params = params or load_plant_params()
    out = {}
    for amp in (25.0, 50.0, 100.0, 200.0):
        u, y, _ = sine_period(params, amp, 0.1)
        out[f'width_{amp:g}V'], *_ = loop_width(u, y)
        out[f'stroke_{amp:g}V_um_per_V'] = 1e6 * np.ptp(y) / np.ptp(u)
    u_s, y_s, _ = sine_period(params, 100.0, 0.1)
    w_s, c_s, up_s, dn_s = loop_width(u_s, y_s)
    for freq in (1.0, 10.0):
        u_f, y_f, _ = sine_period(params, 100.0, freq)
        w_f, c_f, up_f, dn_f = loop_width(u_f, y_f)
        out[f'width_100V_{freq:g}Hz'] = w_f
        inner = (c_s >= c_f[0]) & (c_s <= c_f[-1])
        gap = max(np.max(np.abs(up_s[inner] - np.interp(c_s[inner], c_f, up_f))),
                  np.max(np.abs(dn_s[inner] - np.interp(c_s[inner], c_f, dn_f))))
        out[f'branch_gap_0.1_vs_{freq:g}Hz'] = float(gap / np.ptp(y_s))
    u = generate('steps', FS, 100.0, 50.0, levels=[1.0])
    res = PiezoCantilever(params, FS, seed=1).run(u)
    y50ms = res.y_true[int(0.05 * FS)]
    for t in (1.0, 10.0, 100.0):
        out[f'creep_0.05s_to_{t:g}s'] = float(res.y_true[int(t * FS) - 1] / y50ms - 1)
    f, h = frf_from_chirp(params)
    mag = np.abs(h)
    out['resonance_Hz'] = float(f[np.argmax(mag)])
    out['resonance_peak_over_200Hz_gain'] = float(mag.max()
                                                  / np.median(mag[(f > 150) & (f < 250)]))
    rest = PiezoCantilever(params, FS, seed=3).run(np.zeros(40000))
    out['noise_std_m'] = float(np.std(rest.y))
    u = generate('multisine', FS, 25.0, 100.0, seed=0)
    res = PiezoCantilever(params, FS, seed=0).run(u)
    out['multisine_y_std_um'] = 1e6 * float(np.std(res.y))
    out['multisine_r2_ceiling'] = float(1 - (params.noise_std / np.std(res.y)) ** 2)
    out['multisine_max_slew_V_per_s'] = float(np.max(np.abs(np.diff(u))) * FS)
    return out


def draw(outdir: Path, params=None) -> list[Path]:
    """Write the PNG figures into outdir; returns their paths."""
    import matplotlib
    matplotlib.use('Agg')
    import matplotlib.pyplot as plt

    params = params or load_plant_params()
    outdir.mkdir(parents=True, exist_ok=True)
    paths = []

    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 4.2))
    for amp in (25.0, 50.0, 100.0, 200.0):
        u, y, _ = sine_period(params, amp, 0.1)
        w, *_ = loop_width(u, y)
        ax1.plot(u, 1e6 * y, lw=0.8, label=f'±{amp:g} V: width {100 * w:.1f} %')
    ax1.set(xlabel='command u (V)', ylabel='measured deflection y (µm)',
            title='Sine 0.1 Hz, several amplitudes')
    ax1.legend(fontsize=8)
    for freq in (0.1, 1.0, 10.0):
        u, y, _ = sine_period(params, 100.0, freq)
        w, *_ = loop_width(u, y)
        ax2.plot(u, 1e6 * y, lw=0.8, label=f'{freq:g} Hz: width {100 * w:.1f} %')
    ax2.set(xlabel='command u (V)', ylabel='y (µm)', title='±100 V at 0.1, 1 and 10 Hz')
    ax2.legend(fontsize=8)
    for ax in (ax1, ax2):
        ax.grid(alpha=0.3)
    fig.tight_layout()
    paths.append(outdir / 'plant_hysteresis.png')
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)

    u = generate('steps', FS, 100.0, 50.0, levels=[1.0])
    res = PiezoCantilever(params, FS, seed=1).run(u)
    t = (np.arange(u.size) + 1) / FS
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(10, 4.2))
    ax1.plot(1e3 * t[:60], 1e6 * res.y[:60], '.-', ms=3, lw=0.8, label='measured y')
    ax1.plot(1e3 * t[:60], 1e6 * res.y_true[:60], lw=0.8, label='true y')
    ax1.set(xlabel='time after the step (ms)', ylabel='deflection (µm)',
            title='0 → 50 V step: first 30 ms')
    ax1.legend(fontsize=8)
    keep = t >= 0.05  # after the ring-down of the mode (1/(zeta*wn) = 10 ms)
    ax2.semilogx(t[keep], 1e6 * res.y[keep], lw=0.5, label='measured y')
    ax2.semilogx(t[keep], 1e6 * res.y_true[keep], lw=1.0, label='true y')
    ax2.set(xlabel='time after the step (s, log)', ylabel='deflection (µm)',
            title='Creep over 100 s')
    ax2.legend(fontsize=8)
    for ax in (ax1, ax2):
        ax.grid(alpha=0.3, which='both')
    fig.tight_layout()
    paths.append(outdir / 'plant_creep.png')
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)

    f, h = frf_from_chirp(params)
    a, b = linear_system(params)
    # Linearised model for reference: hysteresis replaced by its initial slope d_p*(1 - A).
    c = np.zeros(a.shape[0])
    c[-1] = 1.0
    w = 2 * np.pi * f
    h_lin = np.array([c @ np.linalg.solve(1j * wi * np.eye(a.shape[0]) - a, b) for wi in w])
    wa = 2 * np.pi * params.amp_bandwidth
    h_lin *= params.d_p * (1 - params.A) * wa / (1j * w + wa)
    # Sampled view: zero-order hold (sinc, half-period delay) and y[k] read one period after u[k].
    x = f / FS
    h_lin *= np.sinc(x) * np.exp(-1j * np.pi * x) * np.exp(2j * np.pi * x)
    fig, (ax1, ax2) = plt.subplots(2, 1, figsize=(8, 6), sharex=True)
    ax1.semilogy(f, 1e6 * np.abs(h), lw=0.8, label='from a ±3 V chirp (H1, measured y)')
    ax1.semilogy(f, 1e6 * np.abs(h_lin), '--', lw=0.8,
                 label='linearised model, ZOH-sampled (no aliasing)')
    ax1.axvline(params.mode_frequency, color='k', lw=0.5)
    ax1.set(ylabel='|y/u| (µm/V)',
            title=f'Frequency response: first mode at {params.mode_frequency:g} Hz, '
                  f'ζ = {params.mode_damping:g}')
    ax1.legend(fontsize=8)
    ax2.plot(f, np.degrees(np.unwrap(np.angle(h))), lw=0.8)
    ax2.plot(f, np.degrees(np.unwrap(np.angle(h_lin))), '--', lw=0.8)
    ax2.set(xlabel='frequency (Hz)', ylabel='phase (deg)')
    ax2.text(0.01, 0.05, 'y[k] is read one period after u[k] is applied: net half-sample lead',
             transform=ax2.transAxes, fontsize=8)
    for ax in (ax1, ax2):
        ax.grid(alpha=0.3, which='both')
    fig.tight_layout()
    paths.append(outdir / 'plant_frequency_response.png')
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)

    u = generate('multisine', FS, 25.0, 100.0, seed=0)
    res = PiezoCantilever(params, FS, seed=0).run(u)
    t = np.arange(u.size) / FS
    fig, (ax1, ax2, ax3) = plt.subplots(3, 1, figsize=(9, 7))
    ax1.plot(t, u, lw=0.3)
    ax1.set(ylabel='u (V)',
            title='Default identification record: multisine 0.1–100 Hz, peak 100 V, 25 s')
    ax2.plot(t, 1e6 * res.y, lw=0.3)
    ax2.set(ylabel='y (µm)', xlabel='time (s)')
    sel = slice(int(10 * FS), int(10.5 * FS))
    ax3.plot(1e3 * (t[sel] - 10), 1e6 * res.y[sel], '.', ms=2, label='measured y')
    ax3.plot(1e3 * (t[sel] - 10), 1e6 * res.y_true[sel], lw=0.8, label='true y')
    ax3.set(xlabel='time from 10 s (ms)', ylabel='y (µm)')
    ax3.legend(fontsize=8)
    for ax in (ax1, ax2, ax3):
        ax.grid(alpha=0.3)
    fig.tight_layout()
    paths.append(outdir / 'plant_multisine.png')
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)
    return paths


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    outdir = Path(argv[0]) if argv else Path('docs/figures')
    for key, value in measure().items():
        print(f'{key:40s} {value:.6g}')
    for path in draw(outdir):
        print('wrote', path)
    return 0


if __name__ == '__main__':
    sys.exit(main())
