"""
Hysteresis-operator NARX.

A sigmoid network over rate-independent operator states of the input, followed by learned creep and
linear output dynamics (the `--preset envelope` family).

    y(k) = -sum_j a_j y(k-j) + sum_i b_i z(k-i) + y_off                      (output lags: linear)
    z(k) = w(k) + sum_l g_l x_l(k),   x_l: first-order lags of w, time constants creep_taus (s)
    w(k) = f(phi(k)),  f: one hidden layer of sigmoid units plus a linear term, f = 0 at rest
    phi(k) = [play operators of v (n_plays radii), v increments over n_lags samples,
              learned Duhem states of v (n_duhem)]
    v(k) = v(k-1) + clip(u(k) - v(k-1), -rho, rho)   the drive, rho learned (amplifier slew)
    (with `amplifier`: the sampled output of a slew-limited first-order amplifier, its
    bandwidth learned too: hysteresis.kernels.amplifier)

Why this structure (docs/envelope.md has the measurements): the paper's network feeds its own
output back through a sigmoid layer. A rate-independent plant holding its input has a continuum of
equilibria (any point inside the loop); such a network has isolated ones, so on slow moves and
holds its free run drifts to them and can run away. Here the hysteresis memory lives in operators
of the input that are frozen while the input holds (plays: the Preisach class, any Preisach
operator is a sum of functions of plays; Duhem states: the Bouc-Wen / Duhem class, with learned
rates), the network is static in them, and only linear, stability-checked dynamics feed the
output back. The free run is therefore bounded for every bounded input (plays are bounded by the
input, Duhem states by |alpha|/BETA_MIN, sigmoids by 1, and the output dynamics are stable).

Inference is numpy + numba only; fitting too (no torch).
"""
import math

import numpy as np

from ...errors import DataError
from . import kernels as hk
from . import mimo as hm
from ..base import (DynamicModel, Interval, Options, Tuple, as_channel_lists, as_record_list,
                    check_parameters, register_family)
from ..state.estimate import PASTS
from .model_file import HysteresisFile
from .stepper import HysteresisStepper

#: Minor loops of the estimation input (reversals inside the previous loop) from which
#: monotone='auto' trusts the data to show the network its minor loops (coverage.inner_reversals):
#: a full-range sine and a sine of growing amplitude have none, the identification protocol about
#: 185 in 10 s. Measured (docs/real.md): on the
#: micromanipulator's one full-range sine the free network's seeds scatter from R² 0.85 to 0.99
#: on its test record and the monotone ones hold 0.998-0.9995; on the protocol the free network is
#: the more accurate (simulators, 0.19 against 0.27 um worst on slow full-range moves).
MINOR_LOOPS = 20

#: Seconds at the start of a record that estimate where it starts (HysteresisNARX start).
START_WINDOW_S = 2.0
#: Hold (s) at the record's first input after the estimated history, before the record.
START_HOLD_S = 1.0

#: Creep time constants (s): log-spaced from the mode's scale to the longest drift a record shows.
DEFAULT_CREEP_TAUS = (0.01, 0.03, 0.1, 0.3, 1.0, 3.0, 10.0, 30.0, 100.0)


@register_family
class HysteresisNARX(HysteresisFile, DynamicModel):
    """
    Sigmoid network over hysteresis-operator states + creep + linear output dynamics.

    hidden : sigmoid units; n_plays : play operators (radii (i/n_plays)^2 of the input scale,
    i = 0..n_plays-1, denser where small reversals are); n_duhem : learned Duhem states;
    n_lags : input increments seen by the network (the drive's short-term dynamics, e.g. an
    amplifier's slew limit); na, nb : output dynamics orders; creep_taus : creep time constants, s;
    seed : initial hidden-layer seed. Training: max_iter LM iterations, val_fraction of each
    record held out for early stopping (0: none), max_fail, hessian_stride (see
    hysteresis.training). record_offsets: several records each get their own output offset
    after the first's (sensor zeros differ between sessions; training_info_['record_offsets_m']):
    'yes', 'no' (one zero for every record: records of one session), or 'auto' ('yes' for
    several records; the structure search tries both). start: how each
    estimation record starts: 'rest', or 'estimate' (a record that does not start at rest: after
    a fit from rest, each record's starting memory is estimated from its first seconds, prepended
    as an input history and the fit continued); 'auto': 'estimate' when a record's first input is
    away from 0 V, else 'rest'. past: how the estimation records' unlogged pasts ended, for
    that estimate (state.PASTS; 'fade-out' as `evaluate --past fade-out`). monotone:
    'yes' keeps the network increasing in every play operator (with the sign of the data's static
    gain), so the output moves with the input the way a Preisach actuator's does wherever the
    input goes, also inside loops the data never showed; 'no' leaves the network free; 'auto':
    'yes' unless the estimation input closes at least MINOR_LOOPS minor loops (reverses inside
    its previous loop: then the data show the network its minor loops, and the free network fits
    them better). amplifier: the drive also learns a first-order amplifier bandwidth beside its
    slew limit (the exact sampled output of a slew-limited first-order amplifier fed the held
    command: hysteresis.kernels.amplifier): 'yes', 'no', or 'auto': 'yes' when the command
    moves smoothly and fast enough to slew (hysteresis.training.drive_slews), else 'no'.
    Measured in docs/real.md ("The amplifier's bandwidth"): on a 0.1-1500 Hz multisine at
    5 kHz it finds the simulated amplifier's slew and bandwidth.
    creep: 'excited' keeps every creep weight >= 0 (a piezo creeps on in the direction it
    moved) and holds at 0 the weight of a filter the estimation input hardly moves
    (hysteresis.training.slow_creep: its weight would learn the output's slow drift, after an
    unknown past the past's; training_info_['creep_fixed_s'] lists them); 'free' fits every
    weight with either sign. Measured in docs/real.md ("Creep weights from what the records
    excite").

    Fitted attributes: u_scale_ (V), y_scale_ (m), radii_ (normalised), theta_ (all parameters,
    normalised units), amplifier_ (bool: the drive has a learned bandwidth), training_info_;
    fs, input_range, output_range as every model.
    """

    kind = 'hysteresis_narx'
    file_format_version = 2     # the kind was added in format version 2
    activation = 'logistic'
    state_from_input = True
    # Creep and output histories feed linear filters only (ident/state/ reuses one Jacobian).
    adjustable_state_linear = True
    _parameter_constraints = {
        'hidden': Interval(int, 1, 200),
        'n_plays': Interval(int, 1, 64),
        'n_duhem': Interval(int, 0, 8),
        'n_lags': Interval(int, 0, 50),
        'na': Interval(int, 0, 20),
        'nb': Interval(int, 0, 20),
        'creep_taus': Tuple(Interval(float, 1e-5, 1e6), min_len=0, max_len=32, increasing=True),
        'seed': Interval(int, 0, 2 ** 32 - 1),
        'max_iter': Interval(int, 0, 100000),
        'val_fraction': Interval(float, 0.0, 0.5),
        'max_fail': Interval(int, 1, 10000),
        'hessian_stride': Interval(int, 1, 64),
        'start': Options(('auto', 'rest', 'estimate')),
        'monotone': Options(('auto', 'yes', 'no')),
        'mimo_order': Interval(int, 1, 60),
        'amplifier': Options(('auto', 'no', 'yes')),
        'past': Options(PASTS),
        'creep': Options(('excited', 'free')),
        'record_offsets': Options(('auto', 'yes', 'no')),
    }

    def __init__(self, hidden=10, n_plays=12, n_duhem=1, n_lags=3, na=3, nb=3,
                 creep_taus=DEFAULT_CREEP_TAUS, seed=0, max_iter=60, val_fraction=0.0,
                 max_fail=8, hessian_stride=2, start='auto', monotone='auto', mimo_order=28,
                 amplifier='auto', past='any', creep='excited', record_offsets='auto'):
        values = check_parameters(type(self), {
            'hidden': hidden, 'n_plays': n_plays, 'n_duhem': n_duhem, 'n_lags': n_lags,
            'na': na, 'nb': nb, 'creep_taus': creep_taus, 'seed': seed, 'max_iter': max_iter,
            'val_fraction': val_fraction, 'max_fail': max_fail, 'hessian_stride': hessian_stride,
            'start': start, 'monotone': monotone, 'mimo_order': mimo_order,
            'amplifier': amplifier, 'past': past, 'creep': creep,
            'record_offsets': record_offsets})
        for name, value in values.items():
            setattr(self, name, value)
        self.theta_ = None
        self.mimo_ = None       # hysteresis.mimo.MimoParts when fitted on several axes
        self.amplifier_ = amplifier == 'yes'   # set by fit (auto) or the model file
        self.training_info_ = {}

    # ------------------------------------------------------------------ structure
    @property
    def nu(self):
        """Input history the Stepper takes: increments' depth (several axes: order), samples."""
        return self.mimo_order if self.mimo_ is not None else self.n_lags

    @property
    def ny(self):
        """Output history the Stepper takes: the output dynamics' order, samples."""
        return self.mimo_order if self.mimo_ is not None else self.na

    @property
    def n_inputs(self):
        """Network inputs d = n_plays + n_lags + n_duhem."""
        return self.n_plays + self.n_lags + self.n_duhem

    @property
    def n_params(self):
        """Return the number of estimated parameters."""
        if self.mimo_ is not None:
            return self.mimo_.n_params
        return self._layout()[1]

    def _layout(self):
        """Return hysteresis.kernels.layout of this structure (offsets, size)."""
        return hk.layout(self.hidden, self.n_inputs, self.n_duhem, len(self.creep_taus),
                         self.na, self.nb, 2 if self.amplifier_ else 1)

    def _is_fitted(self):
        return self.theta_ is not None or self.mimo_ is not None

    def params_dict(self):
        """Return the constructor arguments (for model files and reports)."""
        # mimo_order only shapes a several-axes model, amplifier a model that uses it, past a
        # fit told how its records' pasts ended, record_offsets a fit told whether its records
        # share a zero: other files stay as they were.
        return {name: getattr(self, name) for name in self._parameter_constraints
                if (name != 'mimo_order' or self.mimo_ is not None)
                and (name != 'amplifier' or self.amplifier_)
                and (name != 'past' or self.past != 'any')
                and (name != 'record_offsets' or self.record_offsets != 'auto')}

    # ------------------------------------------------------------------ fitting
    def fit(self, u, y, fs=None):
        """
        Train on one record (u V, y m: 1-D arrays) or several (lists of arrays).

        No state crosses records; fs (Hz) is required (creep time constants are in seconds). A
        record that does not start at rest is fitted from an estimated start (`start`). Returns
        self.
        """
        from .training import train
        if _several_axes(u, y):
            return self._fit_mimo(u, y, fs)
        us, ys = as_record_list(u, y, min_len=max(self.n0, 1) + 20)
        if fs is None:
            raise DataError('HysteresisNARX.fit needs the sample rate fs (Hz)')
        fs = float(fs)
        if not np.isfinite(fs) or fs <= 0:
            raise DataError(f'sample rate fs must be a positive number of Hz, got {fs!r}')
        u_all, y_all = np.concatenate(us), np.concatenate(ys)
        u_scale, y_scale = float(np.max(np.abs(u_all))), float(np.std(y_all))
        if u_scale == 0.0 or y_scale == 0.0:
            raise DataError('estimation data is constant (zero input or zero output variance); '
                            'cannot fit')
        self.u_scale_, self.y_scale_ = u_scale, y_scale
        self.radii_ = (np.arange(self.n_plays) / self.n_plays) ** 2
        self.fs = fs
        from ..data.coverage import inner_reversals
        loops = inner_reversals(us)
        monotone = self.monotone == 'yes' or (self.monotone == 'auto' and loops < MINOR_LOOPS)
        # The monotone network rises with the input; an actuator whose output falls with the
        # voltage is fitted on the negated output and the output layer negated after.
        sign = -1.0 if monotone and _gain_sign(us, ys) < 0 else 1.0
        from .training import drive_slews, slow_creep
        uns = [x / u_scale for x in us]
        self.amplifier_ = self.amplifier == 'yes' or (
            self.amplifier == 'auto' and drive_slews(uns))
        held = (slow_creep(self.creep_taus, uns, fs)
                if self.creep == 'excited' else [False] * len(self.creep_taus))

        def fit_on(prefixes, theta0):
            skip = [p.size for p in prefixes]
            theta, info = train(
                [np.r_[p, x] / u_scale for p, x in zip(prefixes, us)],
                [np.r_[np.zeros(p.size), sign * x] / y_scale for p, x in zip(prefixes, ys)],
                self.radii_, self.n_lags, self.hidden, self.n_duhem, self._lam(), self.na,
                self.nb, self.seed, self.max_iter, self.val_fraction, self.max_fail,
                self.hessian_stride,
                theta0=None if theta0 is None else self._signed(theta0, sign),
                skip=skip, record_offsets=len(us) > 1 and self.record_offsets != 'no',
                monotone=monotone, amplifier=self.amplifier_, creep_fixed=held,
                creep_nonneg=self.creep == 'excited')
            info['record_offsets'] = [sign * o for o in info['record_offsets']]
            return self._signed(theta, sign), info

        theta, info = fit_on([np.zeros(0)] * len(us), None)
        self.set_theta(theta)
        self._record_ranges(u_all, y_all, fs)
        start = self.start
        if start == 'auto':
            start = 'estimate' if any(abs(x[0]) > 0.01 * u_scale for x in us) else 'rest'
        if start == 'estimate':
            prefixes, starts = self._start_histories(us, ys)
            theta, more = fit_on(prefixes, theta)
            self.set_theta(theta)
            more['iterations_from_rest'] = info['iterations']
            more['record_starts'] = starts
            more['fit_seconds'] += info['fit_seconds']
            more['drive_starts'] = info['drive_starts']
            info = more
        # The drive limits tried as starts, in V/s (the training's are per normalised sample).
        info['drive_starts'] = [{**d, 'rho': d['rho'] * u_scale * fs}
                                for d in info['drive_starts']]
        info['record_offsets_m'] = [o * y_scale for o in info.pop('record_offsets')]
        info.update(monotone=bool(monotone), inner_reversals=loops,
                    creep_fixed_s=[t for t, h in zip(self.creep_taus, held) if h])
        if self.amplifier_:
            info['drive_bandwidth_hz'] = self.drive_bandwidth
        self.training_info_ = info
        return self

    def _fit_mimo(self, u, y, fs):
        """Fit the several-axes structure (hysteresis.mimo) on (N, n_in) / (N, n_out) records."""
        us, ys, flat = as_channel_lists(u, y, min_len=4 * self.mimo_order + 20)
        if fs is None:
            raise DataError('HysteresisNARX.fit needs the sample rate fs (Hz)')
        fs = float(fs)
        if not np.isfinite(fs) or fs <= 0:
            raise DataError(f'sample rate fs must be a positive number of Hz, got {fs!r}')
        self.theta_ = None
        self.n_in_, self.n_out_ = us[0].shape[1], ys[0].shape[1]
        self.output_2d_ = not flat
        self._inputs = self._outputs = None
        self.fs = fs
        parts, info = hm.fit(us, ys, fs, self.mimo_order)
        self.mimo_ = parts
        self.u_scale_ = float(np.max(parts.u_scale))
        self.y_scale_ = float(np.max(parts.y_scale))
        self._record_ranges(np.vstack(us), np.vstack(ys), fs)
        self.training_info_ = info
        return self

    def _mimo_signal(self, x, name, width, n=None, min_len=1):
        """Return a user array as (N, width) (several axes)."""
        from ..data.checks import as_channels
        return as_channels(x, name, n=n, width=width, min_len=min_len)

    # state.estimate_state reads windows of a several-axes model through _signal.
    _signal = _mimo_signal

    def _mimo_out(self, y):
        return self._as_output(y)

    def _mimo_initial_state(self, u_past=None, y_past=None):
        """State after rest then u_past (nu, n_in) V; y_past (ny, n_out) m sets the outputs."""
        st = np.zeros(self.mimo_.state_size)
        if u_past is not None:
            self.mimo_.simulate(self._mimo_signal(u_past, 'u_past', self.n_in, n=self.nu), st)
        if y_past is not None:
            yp = self._mimo_signal(y_past, 'y_past', self.n_out, n=self.ny)
            self.mimo_.set_output_history(st, yp[::-1] / self.mimo_.y_scale)
        return st

    def _signed(self, theta, sign):
        """Return theta with its output negated when sign < 0 (output layer, offset; a copy)."""
        theta = np.array(theta, dtype=np.float64)
        if sign < 0:
            lay, _ = self._layout()
            for name in ('w2', 'c', 'y_off'):
                lo, hi = lay[name]
                theta[lo:hi] = -theta[lo:hi]
        return theta

    def _start_histories(self, us, ys):
        """
        Per record, an input history (V) that puts the model where the record starts.

        From estimate_state on the record's first START_WINDOW_S seconds (told `past`): rest, a
        ramp through the estimated turning points to the record's first input, a hold of
        START_HOLD_S.
        Returns (histories, [{'turning_points_v', 'offset_m'}, ...]).
        """
        from ..state.estimate import ramp
        out, starts = [], []
        step = self.u_scale_ * min(0.02, 0.5 * self._kernel_args[3])
        for u, y in zip(us, ys):
            n = int(min(u.size, max(self.n0 + 20, round(START_WINDOW_S * self.fs))))
            state = self.estimate_state(u[:n], y[:n], past=self.past)
            pts = state.info['history_turning_points_v']
            if pts is None:   # from rest: nothing before the record
                out.append(np.zeros(0))
            else:
                hold = np.full(int(round(START_HOLD_S * self.fs)), float(u[0]))
                out.append(np.r_[ramp(tuple(pts) + (float(u[0]),), step), hold])
            starts.append({'turning_points_v': pts, 'offset_m': state.offset})
        return out, starts

    def _lam(self):
        return np.exp(-1.0 / (np.asarray(self.creep_taus, dtype=float) * self.fs))

    def set_theta(self, theta, u_scale=None, y_scale=None, radii=None, fs=None):
        """
        Set every parameter from the flat vector theta (normalised units).

        Layout in hysteresis.kernels; optionally also the scales (V, m), radii and fs (Hz).
        """
        if u_scale is not None:
            self.u_scale_, self.y_scale_ = float(u_scale), float(y_scale)
            self.radii_ = np.array(radii, dtype=np.float64)
            self.fs = float(fs)
        theta = np.array(theta, dtype=np.float64).ravel()
        if theta.size != self.n_params or not np.all(np.isfinite(theta)):
            raise DataError(f'theta must hold {self.n_params} finite values, got {theta.size}')
        if self.radii_.shape != (self.n_plays,) or not np.all(np.isfinite(self.radii_)):
            raise DataError(f'radii must hold {self.n_plays} finite values')
        if not (self.u_scale_ > 0 and self.y_scale_ > 0):
            raise DataError('u_scale and y_scale must be > 0')
        lay, _ = self._layout()
        part = {k: theta[lo:hi] for k, (lo, hi) in lay.items()}
        H, d = self.hidden, self.n_inputs
        W1 = np.ascontiguousarray(part['W1'].reshape(H, d))
        b1 = part['b1'].copy()
        w2 = part['w2'].copy()
        w_rest = float(np.sum(w2 / (1.0 + np.exp(-b1))))
        self.theta_ = theta
        self._kernel_args = (
            np.ascontiguousarray(self.radii_), int(self.n_lags),
            np.ascontiguousarray(part['duhem'].reshape(self.n_duhem, 6)),
            float(np.exp(part['drive'][0])),
            float(np.exp(part['drive'][1])) if self.amplifier_ else np.inf,
            W1, b1, w2, part['c'].copy(), w_rest,
            part['g'].copy(), self._lam(), part['a'].copy(), part['b'].copy(),
            float(part['y_off'][0]))
        return self

    def output_poles_mimo(self):
        """Roots of the several-axes model's common denominator A(q); inside the unit circle."""
        return self.mimo_.poles()

    @property
    def drive_slew_rate(self):
        """Learned slew-rate limit of the drive, V/s (inf when it never limits)."""
        return self._kernel_args[3] * self.u_scale_ * self.fs

    @property
    def drive_bandwidth(self):
        """Learned amplifier bandwidth of the drive, Hz (inf without `amplifier`)."""
        return self._kernel_args[4] * self.fs / (2.0 * math.pi)

    @property
    def output_poles(self):
        """Roots of the output dynamics' A(q) (z-plane); all inside the unit circle."""
        a = self._kernel_args[12]
        return np.roots(np.r_[1.0, a]) if a.size else np.zeros(0)

    # ------------------------------------------------------------------ inference
    def _state_size(self):
        return hk.state_size(self.n_plays, self.n_lags, self.n_duhem, len(self.creep_taus),
                             self.na, self.nb)

    def _initial_state(self, u_past, y_past):
        """
        Free-run state after rest, then the inputs u_past (V).

        y_past is not used: the operators' memory cannot be read from a few outputs, and
        writing measured outputs into the output dynamics' history alone gives a state that
        belongs to no input history. Measured on the demo's live multisine, which starts with a
        15 V jump that rings the plant's mode: doing so cost a 5.6 um transient (live R²
        0.99989 instead of 0.99994 from rest).
        """
        st = np.zeros(self._state_size())
        if u_past is not None and len(u_past):
            hk.simulate(np.asarray(u_past, dtype=np.float64) / self.u_scale_, st,
                        *self._kernel_args)
        return st

    def simulate(self, u, y0=None, state=None):
        """
        Free run from the input alone: u (N,) V -> (N,) m.

        y0=None starts from rest (every operator, creep state and past output 0). y0 (the first
        n0 measured outputs, m) is copied to the output for k < n0; the model then runs from rest
        fed with u[n0-nu:n0] (its state is a function of the input history; it cannot be read
        from n0 outputs). state: a ModelState at u[0] (estimate_state: memory, creep, output
        dynamics and sensor offset set from a measured window) instead of y0.
        """
        from ..narx.regressors import as_signal
        self._require_fitted()
        if self.mimo_ is not None:
            return self._mimo_simulate(u, y0, state)
        if state is not None:
            if y0 is not None:
                raise DataError('give y0 or state, not both')
            return self._run_from(self._check_state(state), as_signal(u, 'u')) + state.offset
        n0 = self.n0
        if y0 is None:
            u = as_signal(u, 'u')
            st = np.zeros(self._state_size())
            return hk.simulate(u / self.u_scale_, st, *self._kernel_args) * self.y_scale_
        u = as_signal(u, 'u', min_len=n0)
        y0 = as_signal(y0, 'y0', n=n0, min_len=0)
        st = self._initial_state(u[n0 - self.nu:n0], y0[n0 - self.ny:])
        out = np.empty(u.size)
        out[:n0] = y0
        out[n0:] = hk.simulate(u[n0:] / self.u_scale_, st, *self._kernel_args) * self.y_scale_
        return out

    def predict(self, u, y):
        """
        One step ahead: the operators free-run on u (V); the output lags are the measured y (m).

        Returns (N,) m with [:n0] = y[:n0].
        """
        from ..narx.regressors import as_signal
        self._require_fitted()
        if self.mimo_ is not None:
            u = self._mimo_signal(u, 'u', self.n_in, min_len=self.n0 + 1)
            y = self._mimo_signal(y, 'y', self.n_out, n=len(u))
            return self._mimo_out(self.mimo_.predict(u, y))
        u = as_signal(u, 'u', min_len=self.n0 + 1)
        y = as_signal(y, 'y', n=u.size)
        *chain, a, b, y_off = self._kernel_args
        z = hk.operator_chain(u / self.u_scale_, *chain)
        yl = y / self.y_scale_ - y_off
        n, n0 = u.size, self.n0
        pred = np.zeros(n - n0)
        for i in range(b.size):
            pred += b[i] * z[n0 - i:n - i]
        for j in range(1, a.size + 1):
            pred -= a[j - 1] * yl[n0 - j:n - j]
        out = y.copy()
        out[n0:] = (pred + y_off) * self.y_scale_
        return out

    def stepper(self, u_past=None, y_past=None, state=None):
        """
        Per-sample free run (the estimator's loop), started like simulate().

        Rest, then u_past (V, nu samples) through the model; y_past (m, ny samples) is checked and
        kept as `y_past` but does not set the state (see simulate). Or state: a ModelState
        (estimate_state), whose offset the Stepper adds to every output.
        """
        self._require_fitted()
        if self.mimo_ is not None:
            stepper = hm.MimoStepper(self)
            if state is not None:
                if u_past is not None or y_past is not None:
                    raise DataError('give u_past/y_past or state, not both')
                stepper.set_state(self._check_state(state), self._check_offset(state))
            else:
                stepper.reset(u_past, y_past)
            return stepper
        stepper = HysteresisStepper(self, u_past, y_past)
        if state is not None:
            if u_past is not None or y_past is not None:
                raise DataError('give u_past/y_past or state, not both')
            stepper.set_state(state)
        return stepper

    # ------------------------------------------------------------ state from measurement
    def estimate_state(self, u, y, prior=None, past='any'):
        """
        Return the ModelState at u[0] that best explains a window u, y (see DynamicModel).

        Several axes: the input held at u[0] (or prior's state), then the stage-1 and output
        histories and the offsets by their posterior mean given the window and the histories'
        distribution over the estimation records (hysteresis.mimo.estimate_state); past is
        checked but has no candidates to choose among there.
        """
        if self.mimo_ is None:
            return super().estimate_state(u, y, prior, past)
        from ..state.estimate import MIN_WINDOW, ModelState, check_past
        check_past(past)
        self._require_fitted()
        u = self._mimo_signal(u, 'u (state window)', self.n_in, min_len=MIN_WINDOW)
        y = self._mimo_signal(y, 'y (state window)', self.n_out, n=len(u))
        start = (self._mimo_held_state(u) if prior is None else
                 ModelState(self._check_state(prior), self._check_offset(prior),
                            {'history': 'given'}))
        values, offset, info = hm.estimate_state(self, self.mimo_, u, y, start.values)
        if not np.all(np.isfinite(values)):
            raise DataError('no initial state reproduces the window: the model diverges on it')
        return ModelState(values, np.asarray(offset, dtype=np.float64),
                          {**start.info, **info, 'window_samples': int(len(u))})

    @property
    def state_size(self):
        """Length of the state vector (layout in hysteresis.kernels or hysteresis.mimo)."""
        return self.mimo_.state_size if self.mimo_ is not None else self._state_size()

    def _mimo_simulate(self, u, y0, state):
        """simulate() of a several-axes model: (N, n_out) m (see simulate)."""
        if state is not None:
            if y0 is not None:
                raise DataError('give y0 or state, not both')
            values = self._check_state(state)
            u = self._mimo_signal(u, 'u', self.n_in)
            return self._mimo_out(self._run_from(values, u) + self._check_offset(state))
        if y0 is None:
            u = self._mimo_signal(u, 'u', self.n_in)
            return self._mimo_out(self.mimo_.simulate(u, np.zeros(self.mimo_.state_size)))
        n0 = self.n0
        u = self._mimo_signal(u, 'u', self.n_in, min_len=n0)
        y0 = self._mimo_signal(y0, 'y0', self.n_out, n=n0, min_len=0)
        st = self._mimo_initial_state(u[:n0], y0)
        out = np.empty((len(u), self.n_out))
        out[:n0] = y0
        out[n0:] = self.mimo_.simulate(u[n0:], st)
        return self._mimo_out(out)

    def _run_from(self, values, u):
        """Free run (m, without offset) of u (N,) V from the state vector values (normalised)."""
        if self.mimo_ is not None:
            return self.mimo_.simulate(self._mimo_signal(u, 'u', self.n_in),
                                       np.array(values, dtype=np.float64))
        st = np.array(values, dtype=np.float64)
        return hk.simulate(np.asarray(u, dtype=np.float64) / self.u_scale_, st,
                           *self._kernel_args) * self.y_scale_

    def _settled(self, st, u0):
        """
        Let st settle with the input held at u0 (V): creep at its equilibrium, output settled.

        The creep lags are made instantaneous for the hold (their equilibrium is w itself), so
        the hold lasts only as long as the output dynamics need.
        """
        args = self._kernel_args
        il = len(args) - 4          # the creep poles lam (then a, b, y_off)
        settle = args[:il] + (np.zeros_like(args[il]),) + args[il + 1:]
        poles = np.abs(self.output_poles)
        slowest = float(np.max(poles)) if poles.size else 0.0
        n = 20 if slowest <= 0 else int(min(20000, max(20, math.log(1e-9) / math.log(slowest))))
        hk.simulate(np.full(n, u0 / self.u_scale_), st, *settle)
        return st

    def _state_candidates(self, u, past='any'):
        """
        States after every input history of up to two turning points on 13 levels, settled at u0.

        With past='fade-out', also after a fade-out about u0 (the demagnetised memory, state.py
        step 5). The levels span the trained input range; a history ramps from rest through its
        turning points to u[0] (V) slower than the learned drive limit, so the operators see its
        path.
        """
        from ..state.estimate import ModelState, fade_out, ramp, turning_point_histories
        if self.mimo_ is not None:
            return [self._mimo_held_state(u)]
        lo, hi = self.input_range if self.input_range is not None \
            else (-self.u_scale_, self.u_scale_)
        u0 = float(u[0])
        step = self.u_scale_ * min(0.02, 0.5 * self._kernel_args[3])
        # Rest itself: a record whose first command is a jump from 0 V (the actuator idle at 0 V
        # when the recording started; the micromanipulator's records look like this).
        out = [ModelState(np.zeros(self._state_size()), 0.0, {'history_turning_points_v': None})]
        histories = [(pts, {}) for pts in turning_point_histories(min(lo, u0), max(hi, u0), u0)]
        if past == 'fade-out':   # a move ended by a fade-out, demagnetised about u0 (step 5)
            histories.append((fade_out(u0, min(lo, u0), max(hi, u0)), {'demagnetised': True}))
        for pts, tags in histories:
            st = np.zeros(self._state_size())
            self._run_from_inplace(st, ramp(pts + (u0,), step))
            out.append(ModelState(self._settled(st, u0), 0.0,
                                  {'history_turning_points_v': list(pts), **tags}))
        return out

    def _bracket_states(self, u0):
        """
        Return the two extreme pasts ending at u0 (V), settled there (estimator.memory).

        Down from the top of the trained input range, and up from its bottom.

        They differ only in the operators' memory: their creep and output states are cleared
        (as the estimate's from rest), so the spread bounds what the memory can change.
        """
        from ..state.estimate import ModelState, ramp
        if self.mimo_ is not None:
            u0 = np.asarray(u0, dtype=np.float64).reshape(1, self.n_in)
            return [ModelState(np.zeros(self.state_size), np.zeros(self.n_out),
                               {'history': 'rest'}), self._mimo_held_state(u0)]
        lo, hi = self.input_range if self.input_range is not None \
            else (-self.u_scale_, self.u_scale_)
        step = self.u_scale_ * min(0.02, 0.5 * self._kernel_args[3])
        out = []
        for extreme in (max(hi, u0), min(lo, u0)):
            st = np.zeros(self._state_size())
            self._run_from_inplace(st, ramp((extreme, u0), step))
            st = self._settled(st, u0)
            st[max(self.n_lags, 1) + self.n_plays + self.n_duhem:] = 0.0
            out.append(ModelState(st, 0.0, {'from_v': extreme}))
        return out

    def _mimo_held_state(self, u):
        """Return the ModelState of the input held at u[0] (V), amplitude from the window."""
        from ..state.estimate import ModelState
        u = self._mimo_signal(u, 'u (state window)', self.n_in)
        return ModelState(hm.held_state(self.mimo_, u), np.zeros(self.n_out),
                          {'history': 'input held at (' + ', '.join(f'{v:.6g}' for v in u[0])
                           + ') V'})

    def _run_from_inplace(self, st, u):
        hk.simulate(np.asarray(u, dtype=np.float64) / self.u_scale_, st, *self._kernel_args)

    def _adjustable_state(self, n_window):
        """
        Return the output dynamics' history and the creep states n_window samples observe.

        A creep state whose time constant exceeds a third of the window looks like an offset
        there: it keeps its settled value (normalised units, scale 1). So does the output
        dynamics' history when its slowest pole is that slow (fitted on one slow record, the
        output dynamics can take a creep-like pole, 2-4 s): the window would trade a decaying
        mode for the offset (measured: 13.8 um of offset on a 0.5 s multisine, docs/real.md).
        """
        if self.mimo_ is not None:
            # The stage-1 and output histories enter linearly: after `order` samples they span
            # every free response the unknown past input leaves.
            idx = hm.adjustable(self.mimo_)
            return idx.astype(int), np.ones(idx.size)
        i_x = max(self.n_lags, 1) + self.n_plays + self.n_duhem
        seen = np.flatnonzero(np.asarray(self.creep_taus) * self.fs <= n_window / 3.0)
        idx = i_x + seen
        pole = float(np.max(np.abs(self.output_poles), initial=0.0))
        if pole <= 0.0 or (pole < 1.0 and -1.0 / math.log(pole) <= n_window / 3.0):   # samples
            idx = np.r_[idx, np.arange(i_x + len(self.creep_taus), self._state_size())]
        return idx.astype(int), np.ones(idx.size)

    def c_emitter(self):
        """Return the C emitter of this model (piezo_narx_ros.ident.hysteresis.export)."""
        if self.mimo_ is not None:
            from .mimo_export import MimoEmitter
            return MimoEmitter(self)
        from .export import HysteresisEmitter
        return HysteresisEmitter(self)

    def __repr__(self):
        return (f'HysteresisNARX(hidden={self.hidden}, n_plays={self.n_plays}, '
                f'n_duhem={self.n_duhem}, n_lags={self.n_lags}, na={self.na}, nb={self.nb}, '
                f'seed={self.seed})')


def _gain_sign(us, ys) -> float:
    """Sign of the least-squares slope of output on input over the records (+1 when flat)."""
    u = np.concatenate([x - x.mean() for x in us])
    y = np.concatenate([x - x.mean() for x in ys])
    return -1.0 if float(u @ y) < 0 else 1.0


def _several_axes(u, y) -> bool:
    """Tell whether u, y (one record or lists) have more than one input or output channel."""
    us = u if isinstance(u, (list, tuple)) else [u]
    ys = y if isinstance(y, (list, tuple)) else [y]
    return any(np.ndim(x) == 2 and np.shape(x)[1] > 1 for x in list(us) + list(ys))
