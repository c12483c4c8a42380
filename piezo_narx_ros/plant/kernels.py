"""
Compiled per-sample kernels of the plant and of the amplifier limits (numba, cache=True).

One kernel per hysteresis model, `advance` (Bouc-Wen) and `advance_preisach` (Preisach), serves
both PiezoCantilever.run() (loop over N samples inside numba) and PiezoCantilever.step() (N = 1),
so both interfaces give bit-identical numbers.
"""
import math

import numpy as np
from numba import njit

# Layout of the `consts` vector passed to advance(). C_OFFSET (m): sensor offset added to the
# measured output; C_YMIN, C_YMAX (m): the sensor's full scale (-inf, inf: none).
(C_VMIN, C_VMAX, C_SLEW, C_AMP_W, C_H, C_DP, C_A, C_B, C_GAMMA, C_NOISE, C_QUANT, C_OFFSET, C_YMIN,
 C_YMAX) = range(14)
N_CONSTS = 14
# Layout of the `state` vector: amplifier output (V), Bouc-Wen state h (m), then the linear states
# [creep x_1..x_m (m), tip deflection y (m), tip velocity (m/s), sensor output (m)].
S_V, S_H, S_LIN = 0, 1, 2


@njit(cache=True)
def bouc_wen_increment(h, dv, a, b, gamma):
    """
    Bouc-Wen state after the input moves monotonically by dv (V); exact for exponent n = 1.

    Along the path length s = |v - v0| the model dh/dt = a*dv/dt - b*|dv/dt|*h - gamma*dv/dt*|h|
    becomes the linear ODE dh/ds = sv*a - (b + gamma*sv*sign(h))*h, solved in closed form on each
    piece where sign(h) is constant (at most two pieces: h can cross zero once). Depending on dv
    only, not on time, it is rate-independent by construction. a = A*d_p (m/V), b, gamma (1/V).
    """
    if dv == 0.0:
        return h
    sv = 1.0 if dv > 0.0 else -1.0
    s_rem = abs(dv)
    for _ in range(2):
        if h > 0.0:
            sh = 1.0
        elif h < 0.0:
            sh = -1.0
        else:
            sh = sv  # from h = 0 the state moves in the direction of sv*a (a >= 0)
        c = b + gamma * sv * sh
        if c > 1e-300:
            h_inf = sv * a / c
            h_end = h_inf + (h - h_inf) * math.exp(-c * s_rem)
        else:
            h_inf = 0.0
            h_end = h + sv * a * s_rem
        if h != 0.0 and h_end * h < 0.0:
            # Crosses zero inside the increment: stop there and continue with the other sign.
            if c > 1e-300:
                s0 = math.log((h_inf - h) / h_inf) / c
            else:
                s0 = -h / (sv * a)
            s_rem -= s0
            h = 0.0
            if s_rem <= 0.0:
                return 0.0
            continue
        return h_end
    return h


@njit(cache=True)
def amplifier_substep(v, target, w_a, slew, h):
    """
    Amplifier output after h s: exact solution of dv/dt = clip(w_a*(target - v), -slew, slew).

    v, target in V; w_a = 2*pi*bandwidth in rad/s; slew in V/s (inf: none). While the first-order
    rate exceeds the slew limit the output ramps at the limit; from |target - v| = slew/w_a on it
    follows the exponential.
    """
    e = target - v
    if w_a * abs(e) <= slew:
        return target - e * math.exp(-w_a * h)
    sign = 1.0 if e > 0.0 else -1.0
    t_ramp = (abs(e) - slew / w_a) / slew
    if t_ramp >= h:
        return v + sign * slew * h
    e_end = sign * slew / w_a  # remaining error when the ramp ends
    return target - e_end * math.exp(-w_a * (h - t_ramp))


@njit(cache=True)
def _linear_substep(lin, tmp, phi, g0, g1, w0, w1):
    """
    Linear states lin after one sub-step (exact first-order hold of w from w0 to w1, m).

    Tmp: scratch of lin's size.
    """
    n_lin = lin.shape[0]
    for i in range(n_lin):
        acc = g0[i] * w0 + g1[i] * (w1 - w0)
        for j in range(n_lin):
            acc += phi[i, j] * lin[j]
        tmp[i] = acc
    for i in range(n_lin):
        lin[i] = tmp[i]


@njit(cache=True)
def _outputs(lin, noise, consts):
    """
    Return (true tip deflection m, measured m).

    Measured: the sensor state plus noise (m) plus the sensor offset, quantised, clipped to the
    sensor's full scale. The offset and the clip are skipped when off, so that the numbers
    without them stay bit-identical to the plant before they existed.
    """
    meas = lin[lin.shape[0] - 1] + noise
    offset = consts[C_OFFSET]
    if offset != 0.0:
        meas += offset
    quant = consts[C_QUANT]
    if quant > 0.0:
        meas = quant * math.floor(meas / quant + 0.5)
    if meas < consts[C_YMIN]:
        meas = consts[C_YMIN]
    elif meas > consts[C_YMAX]:
        meas = consts[C_YMAX]
    return lin[lin.shape[0] - 3], meas


@njit(cache=True)
def advance(u_cmd, noise, n_sub, consts, phi, g0, g1, state, work, y_meas, y_true, u_applied):
    """
    Advance the plant over len(u_cmd) samples; writes the three output arrays in place.

    u_cmd (N,) V is held (zero-order hold) over each sample period, which is split in n_sub
    sub-steps. Per sub-step: amplifier (clamp, then the exact slew-limited first-order response),
    Bouc-Wen (exact increment), then the linear creep/mode/sensor part with its exact
    first-order-hold discretisation (phi, g0, g1) on the hysteretic deflection w = d_p*v - h.
    Outputs are taken at the end of the sample period: y_meas (m, noisy and quantised sensor),
    y_true (m, tip), u_applied (V). noise (N,) holds standard normal draws. state is updated in
    place; work is scratch of phi's size (passed in so that a one-sample call allocates nothing).
    """
    vmin, vmax = consts[C_VMIN], consts[C_VMAX]
    slew, w_a, h = consts[C_SLEW], consts[C_AMP_W], consts[C_H]
    d_p, a_bw = consts[C_DP], consts[C_A] * consts[C_DP]
    b_bw, gamma = consts[C_B], consts[C_GAMMA]
    noise_std = consts[C_NOISE]
    lin = state[S_LIN:]
    tmp = work
    for k in range(u_cmd.shape[0]):
        target = min(max(u_cmd[k], vmin), vmax)
        for _ in range(n_sub):
            v0 = state[S_V]
            h0 = state[S_H]
            v1 = amplifier_substep(v0, target, w_a, slew, h)
            dv = v1 - v0
            h1 = bouc_wen_increment(h0, dv, a_bw, b_bw, gamma)
            w0 = d_p * v0 - h0
            w1 = d_p * v1 - h1
            _linear_substep(lin, tmp, phi, g0, g1, w0, w1)
            state[S_V] = v1
            state[S_H] = h1
        y_true[k], y_meas[k] = _outputs(lin, noise_std * noise[k], consts)
        u_applied[k] = state[S_V]


@njit(cache=True)
def advance_one(u_k, noise_k, n_sub, consts, phi, g0, g1, state, work):
    """
    `advance` over one sample (u_k V, noise_k a standard normal draw), in one compiled call.

    Returns (y_true m, y_meas m, u_applied V), the same numbers: the one-sample path of a
    simulator, which no longer fills and reads back arrays of one element from Python.
    """
    u = np.empty(1)
    u[0] = u_k
    noise = np.empty(1)
    noise[0] = noise_k
    y_meas, y_true, u_applied = np.empty(1), np.empty(1), np.empty(1)
    advance(u, noise, n_sub, consts, phi, g0, g1, state, work, y_meas, y_true, u_applied)
    return y_true[0], y_meas[0], u_applied[0]


@njit(cache=True)
def preisach_output(plays, weights, centres, spread):
    """
    Irreversible Preisach deflection (m) from the play outputs (V) of every radius.

    A relay of half-width r and centre c is up exactly when the play of radius r is above c, so a
    Preisach operator is a sum over radii of a function of that radius' play (Krejci's
    representation). With relay centres normally distributed (mean centres[i] V, std spread V)
    and total weight weights[i] m per radius, that function is
    weights[i] * erf((p - c) / (s*sqrt2)).
    """
    acc = 0.0
    k = 1.0 / (spread * math.sqrt(2.0))
    for i in range(plays.shape[0]):
        acc += weights[i] * math.erf((plays[i] - centres[i]) * k)
    return acc


@njit(cache=True)
def advance_preisach(u_cmd, noise, n_sub, consts, phi, g0, g1, state, work, y_meas, y_true,
                     u_applied, radii, weights, centres, creep_gains, creep_decay):
    """
    Like `advance`, with a Preisach operator instead of Bouc-Wen and creep on the voltage.

    The hysteresis input is the creeping drive v_c = v + sum_i creep_gains[i]*(x_i - v), where
    x_i follow v through first-order lags (creep_decay[i] = exp(-h/tau_i) per sub-step): a voltage
    step creeps on through the hysteresis nonlinearity instead of adding a linear drift after it.
    Deflection w = d_rev*v_c + preisach_output(plays of v_c) - (its value at rest).
    State: [v, x_1..x_m, plays (len(radii)), linear states (phi's size)]; consts as `advance`, with
    C_DP = d_rev (m/V), C_A = rest offset (m), C_B = relay-centre spread (V).
    """
    n_cr = creep_gains.shape[0]
    n_r = radii.shape[0]
    vmin, vmax = consts[C_VMIN], consts[C_VMAX]
    slew, w_a, h = consts[C_SLEW], consts[C_AMP_W], consts[C_H]
    d_rev, rest, spread = consts[C_DP], consts[C_A], consts[C_B]
    noise_std = consts[C_NOISE]
    xs = state[1:1 + n_cr]
    plays = state[1 + n_cr:1 + n_cr + n_r]
    lin = state[1 + n_cr + n_r:]
    tmp = work
    v_c0 = state[0]
    for i in range(n_cr):
        v_c0 += creep_gains[i] * (xs[i] - state[0])
    w0 = d_rev * v_c0 + preisach_output(plays, weights, centres, spread) - rest
    for k in range(u_cmd.shape[0]):
        target = min(max(u_cmd[k], vmin), vmax)
        for _ in range(n_sub):
            v1 = amplifier_substep(state[0], target, w_a, slew, h)
            v_c = v1
            for i in range(n_cr):
                xs[i] = v1 + (xs[i] - v1) * creep_decay[i]
                v_c += creep_gains[i] * (xs[i] - v1)
            for i in range(n_r):
                lo = v_c - radii[i]
                hi = v_c + radii[i]
                if plays[i] < lo:
                    plays[i] = lo
                elif plays[i] > hi:
                    plays[i] = hi
            w1 = d_rev * v_c + preisach_output(plays, weights, centres, spread) - rest
            _linear_substep(lin, tmp, phi, g0, g1, w0, w1)
            state[0] = v1
            w0 = w1
        y_true[k], y_meas[k] = _outputs(lin, noise_std * noise[k], consts)
        u_applied[k] = state[0]


@njit(cache=True)
def slew_limit(u, max_step, u0):
    """Return u (V) limited to sample-to-sample changes of max_step (V), starting from u0 (V)."""
    out = np.empty_like(u)
    prev = u0
    for k in range(u.shape[0]):
        d = u[k] - prev
        if d > max_step:
            d = max_step
        elif d < -max_step:
            d = -max_step
        prev = prev + d
        out[k] = prev
    return out
