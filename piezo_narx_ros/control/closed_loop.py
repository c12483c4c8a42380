"""
A controller driving the simulated plant sample by sample, without DDS (bench and tests).

Sample k: the reference r(k) goes to the controller, its command u(k) to the plant, and the plant's
measured deflection for that command comes back to the controller before sample k+1, as over DDS
(the simulator answers each command before the next one is due).
"""
from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np


@dataclass
class LoopRun:
    """
    (N,) arrays of one closed-loop run.

    Reference r (m), command u (V), measured y (m), true deflection y_true (m), the controller's
    compute time per sample (ns).
    """

    r: np.ndarray
    u: np.ndarray
    y: np.ndarray
    y_true: np.ndarray
    compute_ns: np.ndarray

    def rmse(self, start: int = 0) -> float:
        """RMS of y_true - r from sample `start` on, m."""
        e = self.y_true[start:] - self.r[start:]
        return float(np.sqrt(np.mean(e * e)))


def run_loop(controller, plant, ref, measure: bool = True, t0_ns: int = 0) -> LoopRun:
    """
    Drive `plant` (PiezoCantilever) through `controller` (PositionController).

    References `ref` (N,) m, stamps t0 + k/fs. measure=False: no deflection goes back (no sensor).
    """
    ref = np.asarray(ref, dtype=float)
    n = ref.size
    u, y, yt, dt = np.empty(n), np.empty(n), np.empty(n), np.empty(n)
    period = 1e9 / controller.fs
    clock = time.perf_counter_ns
    on_ref, on_meas, step = controller.on_reference, controller.on_measurement, plant.step
    for k in range(n):
        t = t0_ns + int(round(k * period))
        c0 = clock()
        out = on_ref(t, ref[k])
        dt[k] = clock() - c0
        (_, u[k]), = out
        y[k], yt[k], _ = step(u[k])
        if measure:
            on_meas(t, y[k])
    return LoopRun(ref, u, y, yt, dt)
