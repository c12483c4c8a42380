"""
A controller's measured start: the model file's start policy applied to the first deflections.

A controller sends commands from its first reference on, before anything is measured, so its
model runs from rest while the start window fills. `MeasuredStart` keeps what was sent meanwhile
and the deflections that answer it; once the first `window` consecutive commands all have theirs,
it returns the state the policy takes from them (ident.state.start.window_state) and the
commands to step from that state to now, for the controller's inverse to continue from
(`start_from`). One class for the one-axis controller, the vector inverse and each chain.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from piezo_narx_ros.errors import ConfigError, DataError
from piezo_narx_ros.ident.state.window import FullWindow

#: Windows' worth of commands the start waits for its measured deflections before it gives up.
START_PATIENCE = 10
#: The start word of a controller whose window never gave a state: it stays on its run from rest.
NO_MEASUREMENT = 'rest (no measurement)'


def start_settings(model, policy, window) -> tuple[str, int]:
    """Return (start policy, window samples): given, else the model file's, else rest."""
    from piezo_narx_ros.ident.state.start import check_policy, min_window, model_start
    stored = model_start(model)
    policy = check_policy(policy if policy is not None else stored.get('policy', 'rest'),
                          'start_policy', ConfigError)
    if policy == 'rest':
        return policy, 0
    if window is None:
        window = stored.get('window_samples') or 0
    least = min_window(model, policy)
    if int(window) < least:
        if window:
            raise ConfigError(f'start_window must be at least {least} samples for start '
                              f'policy {policy!r} with this model, got {window}')
        window = least
    return policy, int(window)


@dataclass
class Start:
    """What a filled window gives: the state at u_run[0], the commands since, and the relag."""

    state: object              # ident.state.estimate.ModelState
    u_run: np.ndarray          # (n,) or (n, n_in) V: commands sent from the window's first on
    relag: tuple | None        # (u, y) whose last samples become the lags (relag_window)


class MeasuredStart:
    """
    The start window of one controller (module docstring).

    model: the controller's model; policy, window: from `start_settings`. `waiting` is True
    from construction (policy other than rest) until the window filled or the wait gave up.
    """

    def __init__(self, model, policy: str, window: int):
        self.model, self.policy, self.window = model, policy, int(window)
        self._log: list | None = [] if policy != 'rest' else None   # (t_ns, u V) sent
        self._meas: dict = {}                                       # t_ns -> y m
        # The window's first index in the log, found as commands and deflections come (a
        # rescan of the log on each deflection cost O(window) a sample while some were lost).
        self._full = FullWindow(max(1, self.window))
        self._first: int | None = None

    @property
    def waiting(self) -> bool:
        """Return True while commands and deflections are being kept for the window."""
        return self._log is not None

    def stop(self) -> None:
        """Stop waiting (a reset: the state is known, or the wait gave up)."""
        self._log = None
        self._meas = {}

    def sent(self, t_ns: int, u) -> bool:
        """Keep a command (stamp ns, V); return False when the wait gave up (START_PATIENCE)."""
        self._log.append((t_ns, u))
        first = self._full.command(t_ns, t_ns in self._meas)
        if first is not None and self._first is None:     # its deflection came first
            self._first = first
        if len(self._log) > START_PATIENCE * self.window:
            self.stop()
            return False
        return True

    def measured(self, t_ns: int, y) -> Start | None:
        """
        Keep a deflection (stamp of its command, m); the Start once the window is whole.

        The window is the first `window` consecutive commands that all have their measured
        deflection (usually the first ones: later ones when some were lost). DataError when no
        state explains it (the wait is over then too).
        """
        from piezo_narx_ros.ident.state.start import relag_window, window_state
        n, log, meas = self.window, self._log, self._meas
        meas[t_ns] = y
        first = self._full.measurement(t_ns)
        if self._first is not None:
            first = self._first
        if first is None:
            return None
        log = log[first:]
        u_win = np.array([u for _, u in log[:n]])
        y_win = np.array([meas[t] for t, _ in log[:n]])
        u_run = np.array([u for _, u in log])
        self.stop()
        state = window_state(self.model, u_win, y_win, self.policy)
        return Start(state, u_run, relag_window(self.model, self.policy, u_win, y_win))


def measured_start(start: MeasuredStart, inverse, t_ns: int, y, now: str) -> str:
    """
    Give `start` a deflection; once its window is whole the inverse continues from its state.

    Returns the controller's start word: `now` while waiting, 'measurement' once started, or
    NO_MEASUREMENT when no state explains the window (the model stays on its run from rest).
    """
    try:
        got = start.measured(t_ns, y)
    except DataError:
        return NO_MEASUREMENT
    if got is None:
        return now
    inverse.start_from(got.state, got.u_run, got.relag)
    return 'measurement'
