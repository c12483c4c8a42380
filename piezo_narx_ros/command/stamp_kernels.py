"""
Compiled stamp-rate bookkeeping (numba, cache=True) behind command.stamps.RateMonitor.

One kernel serves one sample (RateMonitor.observe) and a whole batch (RateMonitor.observe_run), so
both give the same verdicts to the last bit; for a batch of 20 it costs about what one Python
sample did.
"""
import numpy as np
from numba import njit

# Layout of the int64 state vector: cumulative steps, commands received, accepted samples seen
# (head), last stamp (ns), whether there is one, the verdict (0/1), episodes off rate; then the
# monitor's settings the kernels read there: min_steps, single_writer (0/1).
I_N, I_COUNT, I_HEAD, I_LAST, I_HAS_LAST, I_OFF, I_EPISODES, I_MIN_STEPS, I_SINGLE = range(9)
N_INT_STATE = 9
# Layout of the float64 state: stream period / node period, arrivals per node period; then the
# settings: the node's period (ns), the tolerance.
F_RATIO, F_ARRIVAL, F_PERIOD, F_TOLERANCE = range(4)
N_FLOAT_STATE = 4


@njit(cache=True)
def observe_run(t_ns, received, each, ring, st, fst, off_out):
    """
    Accept the samples t_ns (n,) int64 ns in order; off_out (n,) gets the verdict after each.

    received: commands received before the first sample, each: before each sample besides
    (RateMonitor.observe_run: the batch's own commands, 1), added to the count first, as
    RateMonitor.received() calls are. ring (window, 3) int64: stamp, cumulative steps, count at
    each accepted sample; st, fst: the state vectors above, updated in place, and the monitor's
    settings (period, tolerance, min_steps, single_writer) read from them: numba checks every
    argument on every call (nine took 1.3 us a sample, a quarter of the estimator's). The window
    is the last `window` accepted samples; the verdict needs min_steps periods of stamps.
    """
    period, tolerance = fst[F_PERIOD], fst[F_TOLERANCE]
    min_steps, single_writer = st[I_MIN_STEPS], st[I_SINGLE] != 0
    w = ring.shape[0]
    st[I_COUNT] += received
    for i in range(t_ns.shape[0]):
        st[I_COUNT] += each
        t = t_ns[i]
        if st[I_HAS_LAST]:
            k = np.int64(np.rint((t - st[I_LAST]) / period))
            st[I_N] += k if k > 1 else 1
        st[I_LAST] = t
        st[I_HAS_LAST] = 1
        h = st[I_HEAD]
        slot = h % w
        ring[slot, 0] = t
        ring[slot, 1] = st[I_N]
        ring[slot, 2] = st[I_COUNT]
        st[I_HEAD] = h + 1
        j = 0 if h < w else (h + 1) % w          # the oldest sample in the ring
        n = st[I_N] - ring[j, 1]
        if n >= min_steps:
            span = t - ring[j, 0]
            ratio = span / (n * period)
            fst[F_RATIO] = ratio
            arrived = st[I_COUNT] - ring[j, 2]
            if span > 0:
                fst[F_ARRIVAL] = arrived * period / span
            off = abs(ratio - 1.0) > tolerance + 0.5 / n or (
                # One writer sending more commands than grid points: a faster stream whose
                # in-between stamps the gate refuses (two writers interleave the same way).
                single_writer and arrived - 2 > n * (1.0 + tolerance))
            if off and not st[I_OFF]:
                st[I_EPISODES] += 1
            st[I_OFF] = 1 if off else 0
        off_out[i] = st[I_OFF] != 0
    return st[I_OFF] != 0


@njit(cache=True)
def observe_one(t, received, ring, st, fst):
    """
    observe_run for one sample t (int ns), its received count before it: returns the verdict.

    In one compiled call without the one-element arrays a caller would fill (RateMonitor.observe).
    """
    t_ns = np.empty(1, dtype=np.int64)
    t_ns[0] = t
    off = np.empty(1, dtype=np.bool_)
    return observe_run(t_ns, received, 0, ring, st, fst, off)


@njit(cache=True)
def on_grid_run(t_ns, last, period, tolerance):
    """Tell whether each stamp of t_ns (n,) ns is one period (± tolerance) after the one before."""
    prev = last
    for i in range(t_ns.shape[0]):
        d = (t_ns[i] - prev) / period
        if not abs(d - 1.0) <= tolerance:
            return False
        prev = t_ns[i]
    return True


@njit(cache=True)
def pass_and_observe(t_ns, last, grid_tolerance, received, ring, st, fst, off_out):
    """
    on_grid_run, then, when the batch passes, observe_run (each = 1): one call for both.

    Returns -1 when a stamp is off the grid (nothing changed), else how many samples are off
    rate (off_out filled as observe_run fills it).
    """
    if not on_grid_run(t_ns, last, fst[F_PERIOD], grid_tolerance):
        return -1
    observe_run(t_ns, received, 1, ring, st, fst, off_out)
    n_off = 0
    for i in range(off_out.shape[0]):
        if off_out[i]:
            n_off += 1
    return n_off


@njit(cache=True)
def check_pass_and_observe(t_ns, v, bounds, last, received, ring, st, fst, off_out):
    """
    pass_and_observe for a batch of commands v (n,) V that must each be finite and accepted.

    bounds (5,) float64: accepted lowest and highest command, trained lowest and highest (V),
    then the grid tolerance. Returns (-2, False) when a
    command is NaN, infinite or not accepted, (-1, False) when a stamp is off the grid (nothing
    changed either way), else (how many samples are off rate, whether every command is within
    the trained range): a batch's input, stamp and rate checks in one compiled call.
    """
    inside = True
    for i in range(v.shape[0]):
        x = v[i]
        if not (np.isfinite(x) and bounds[0] <= x <= bounds[1]):
            return -2, False
        if not bounds[2] <= x <= bounds[3]:
            inside = False
    n_off = pass_and_observe(t_ns, last, bounds[4], received, ring, st, fst, off_out)
    return n_off, inside and n_off >= 0
