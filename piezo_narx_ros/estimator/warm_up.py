"""A FreeRunEstimator's warm-up: what it runs on a stream compiled before the first sample."""
from __future__ import annotations

import numpy as np

from piezo_narx_ros.estimator.free_run import FreeRunEstimator


def warm_up(est: FreeRunEstimator, batch: int = 20) -> None:
    """
    Compile and load everything `est` runs on a stream, by running it on one: est is used up.

    Pass a throwaway estimator built like the one that will serve. A sine across the model's
    input range at est.fs, with the model's own free run as its measurement: one command and
    one measurement at a time through the initial window (from measurement when est waits for
    one), then batches of `batch`. Without it the first window's state estimate compiled its
    kernels on the live stream (0.5 s on a cold cache) while the commands queued.
    """
    n = est.init_samples + 4 * batch
    shape = (n, est.n_in) if est.vector else (n,)
    lo = np.maximum(np.broadcast_to(est.u_lo, shape[1:]), est.u_min)
    hi = np.minimum(np.broadcast_to(est.u_hi, shape[1:]), est.u_max)
    lo, hi = np.where(np.isfinite(lo), lo, -1.0), np.where(np.isfinite(hi), hi, 1.0)
    phase = np.sin(2.0 * np.pi * 5.0 * np.arange(n) / est.fs)
    u = (0.5 * (lo + hi) + 0.4 * (hi - lo) * (phase[:, None] if est.vector else phase))
    u = u.reshape(shape)
    with np.errstate(all='ignore'):
        y = np.asarray(est.model.simulate(u), dtype=np.float64)
    t = np.int64(10**18) + np.round(np.arange(n) * est.period_ns).astype(np.int64)
    est.start(True)
    k = est.init_samples + batch
    for i in range(k):
        est.on_measurement(int(t[i]), y[i] if est.vector else float(y[i]))
        est.on_command(int(t[i]), u[i] if est.vector else float(u[i]))
    for i in range(k, n, batch):
        est.on_commands(t[i:i + batch], u[i:i + batch])
        est.on_measurements(t[i:i + batch], y[i:i + batch])
    est.running_error()
