"""
A stable NARX network with random weights, for tests and benchmarks of the estimator path.

It is not an identified model: it has the structure and cost of one (same kernels as a fitted
NARXNetwork, piezo-like scales: ±100 V in, µm out) so the nodes can be exercised without training.
"""
from __future__ import annotations

import numpy as np


def toy_narx(nu: int = 4, ny: int = 4, hidden: int = 10, fs: float = 2000.0, seed: int = 0):
    """
    Return a NARXNetwork with random weights whose output feedback gain is < 0.5 (stable free run).

    Normalisation: u 0 ± 100 V, y 0 ± 1e-6 m. input_range ±150 V; output_range is set from a
    free run on a ±150 V random input, so a ±150 V command stays in range.
    """
    from piezo_narx_ros.ident.narx.model import NARXNetwork
    rng = np.random.default_rng(seed)
    d = nu + 1 + ny
    W1 = rng.normal(0.0, 1.0, (hidden, d))
    W1[:, nu + 1:] *= 0.5
    w2 = rng.normal(0.0, 1.0, hidden)
    # |dy(k)/dy(k-j)| <= 0.25 * sum_h |w2_h| |W1_hj|: keep the sum over j below 0.5.
    gain = 0.25 * np.abs(w2) @ np.abs(W1[:, nu + 1:]).sum(axis=1)
    w2 *= min(1.0, 0.5 / gain)
    model = NARXNetwork(nu=nu, ny=ny, hidden=hidden, seed=seed)
    model.set_weights(W1, rng.normal(0.0, 0.5, hidden), w2, 0.0, (0.0, 100.0, 0.0, 1e-6))
    model.fs = float(fs)
    model.input_range = (-150.0, 150.0)
    y = model.simulate(rng.uniform(-150.0, 150.0, 4000))
    model.output_range = (float(y.min()), float(y.max()))
    return model
