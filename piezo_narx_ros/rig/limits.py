"""
Output safety for the rig driver: voltage window, slew-rate limit and a command watchdog.

The driver applies these itself, whatever the command says, because a controller or a replayed bag
may send anything; the target should still have its own hardware limits (docs/driver.md).
"""
from __future__ import annotations

import math

import numpy as np

from piezo_narx_ros.errors import ConfigError


class SlewLimiter:
    """
    Clamps each axis to [v_min, v_max] V and its change to max_slew_rate V/s x dt.

    The output starts at v0 (0 V: the amplifier's state at power-up) and moves only through apply()
    or toward(), so the slew limit also holds across a watchdog ramp and its recovery.
    """

    def __init__(self, v_min: float, v_max: float, max_slew_rate: float, n_axes: int = 1,
                 v0: float = 0.0):
        if not (math.isfinite(v_min) and math.isfinite(v_max)) or v_min >= v_max:
            raise ConfigError('voltage limits must be finite with v_min < v_max, '
                              f'got [{v_min}, {v_max}] V')
        if not v_min <= 0.0 <= v_max:
            # The watchdog parks the output at 0 V, so 0 V must be allowed.
            raise ConfigError(f'voltage limits [{v_min}, {v_max}] V must include 0 V')
        if not (math.isfinite(max_slew_rate) and max_slew_rate > 0):
            raise ConfigError(f'max_slew_rate must be a positive finite V/s, got {max_slew_rate}')
        self.v_min = float(v_min)
        self.v_max = float(v_max)
        self.max_slew_rate = float(max_slew_rate)
        self.output = np.full(n_axes, min(max(v0, v_min), v_max), dtype=float)

    def apply(self, v_cmd, dt: float) -> tuple[np.ndarray, bool, bool]:
        """
        Next output (V, shape (n_axes,)) for command v_cmd after dt s.

        Returns (output, clamped, slewed): whether the voltage window or the slew limit changed it.
        """
        v_cmd = np.asarray(v_cmd, dtype=float).reshape(self.output.shape)
        target = np.clip(v_cmd, self.v_min, self.v_max)
        clamped = bool(np.any(target != v_cmd))
        out = self._slew(target, dt)
        slewed = bool(np.any(out != target))
        self.output = out
        return out.copy(), clamped, slewed

    def toward(self, v_target: float, dt: float) -> np.ndarray:
        """Move every axis toward v_target V at the slew limit for dt s; returns the new output."""
        target = np.full(self.output.shape, min(max(v_target, self.v_min), self.v_max))
        self.output = self._slew(target, dt)
        return self.output.copy()

    def _slew(self, target: np.ndarray, dt: float) -> np.ndarray:
        step = self.max_slew_rate * max(dt, 0.0)
        out = np.clip(target, self.output - step, self.output + step)
        # A step short of the target only by rounding (dt from clock differences) lands on it,
        # instead of leaving a 1e-13 V residue for one more datagram.
        return np.where(np.abs(target - out) <= 1e-9 * step, target, out)


class Watchdog:
    """Trips when no command has been fed for longer than timeout s (monotonic clock)."""

    def __init__(self, timeout: float):
        if not (math.isfinite(timeout) and timeout > 0):
            raise ConfigError('watchdog_timeout must be a positive finite number of seconds, '
                              f'got {timeout}')
        self.timeout = float(timeout)
        self.last_feed: float | None = None
        self.trips = 0
        self._tripped = False

    def feed(self, now: float) -> None:
        """Note that a valid command arrived at time now (s)."""
        self.last_feed = now
        self._tripped = False

    def expired(self, now: float) -> bool:
        """
        Return True once commands have been missing for more than timeout s; counts each trip once.

        Before the first command it is not expired: the output is already at rest (0 V).
        """
        if self.last_feed is None:
            return False
        if now - self.last_feed > self.timeout:
            if not self._tripped:
                self._tripped = True
                self.trips += 1
            return True
        return False
