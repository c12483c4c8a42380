"""
The one check that a loaded model can run at all: evaluate, estimator_node, controller_node.

A model file can be well formed, with finite weights of the right shapes, and still give NaN:
weights whose products overflow (issue 45: estimator_node published 100 % NaN estimates with
its status going WARN -> OK, controller_node reported "missed by up to 0 m", evaluate refused
the same file). `check_runs` drives the model's free run from rest over its own trained input
range, as every tool that runs it would, and refuses it when that is not finite.
"""
from __future__ import annotations

import numpy as np

from piezo_narx_ros.errors import ModelFileError

PROBE_S = 1.0          # s of sweep: a slow full-range sine and back, at the model's rate
PROBE_FS = 2000.0      # Hz, for a model file without a rate
FALLBACK_V = 100.0     # V, the sweep's amplitude for a model without a trained input range


def probe_input(model) -> np.ndarray:
    """Return a sweep over the model's trained input range: (N,) or (N, n_in) V."""
    from piezo_narx_ros.ident.base import channel_ranges
    fs = float(model.fs or PROBE_FS)
    n = max(int(round(PROBE_S * fs)), int(model.n0) + 10)
    n_in = int(getattr(model, 'n_in', 1) or 1)
    rng, _ = channel_ranges(model)
    if rng is None:
        rng = np.tile([-FALLBACK_V, FALLBACK_V], (n_in, 1))
    phase = 2 * np.pi * np.arange(n)[:, None] / n + np.arange(n_in)[None, :] * np.pi / 2
    u = rng[:, 0] + (rng[:, 1] - rng[:, 0]) * (0.5 - 0.5 * np.cos(phase))
    return u[:, 0] if n_in == 1 else u


def check_runs(model, name: str | None = None) -> None:
    """
    Raise ModelFileError (one line) when the model's free run on its trained inputs is NaN/inf.

    name: the model file, for the message (default: the model's `source`).
    """
    name = name or getattr(model, 'source', None) or repr(model)
    u = probe_input(model)
    with np.errstate(all='ignore'):
        y = np.asarray(model.simulate(u), dtype=np.float64)
    bad = ~np.isfinite(y.reshape(len(u), -1)).all(axis=1)
    if bad.any():
        k = int(np.argmax(bad))
        raise ModelFileError(f"{name}: the model's free run from rest is not finite (NaN or inf "
                             f'from sample {k} of a sweep over its trained input range): its '
                             'weights overflow, so it can neither estimate nor control; refit it')


def load_runnable(path):
    """Return load_model(path) once check_runs has vouched that it runs (the tools' loader)."""
    from piezo_narx_ros.ident.model_io import load_model
    with np.errstate(all='ignore'):     # overflowing weights: check_runs says so, in one line
        model = load_model(path)
    check_runs(model, str(path))
    return model
