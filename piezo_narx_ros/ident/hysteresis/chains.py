"""
The envelope family on several axes coupled by the stage's mechanics: one actuator chain per axis.

A stage whose axes each have their own actuator (amplifier, piezo stack or bender with its own
hysteresis, creep and bending mode) and whose mechanics mix the actuators' motions: a two-axis
bender (plant/axes.py CoupledCantilever), an XY stage, a tip-tilt mount. Then

    z_j(k) = chain_j(u_j(0..k))      one one-axis HysteresisNARX per input (hysteresis/model.py)
    y(k)   = M z(k)                  M (n x n, 1 on its diagonal): the coupling

so y_i = z_i + sum_{j != i} M_ij z_j: driving axis j moves axis i by M_ij of chain j's motion, with
chain j's hysteresis, creep and dynamics. Every one-axis property carries over per chain (bounded
free run, operators frozen while an input holds, the quasi-static inverse of control/inverse.py),
and the coupling is inverted exactly by M^-1 (control/axes.py).

Why a second several-axes structure: the common-denominator one (hysteresis_mimo.py) fits the Fine
Steering Mirror's shared resonances, but a linear combination of operator features cannot hold a
Bouc-Wen actuator's minor loops and creep over slow moves (one axis: docs/envelope.md); on the
two-axis cantilever it left 1.7 um on its own estimation half and diverged to 1.2 mm on the
validation half (docs/mimo.md). The experiment fits both on records of several axes and selects
on the worst case, as for one axis.

Fit (`fit`): M first, then each chain on its decoupled output z_j = (M^-1 y)_j, alone, exactly as
a one-axis model is fitted, then M again on the chains' free runs (`refine_coupling`), and the
chains once more on the outputs that M decouples (CHAIN_PASSES). M is first found without the
chains, by reduced-rank least squares on a chain model linear in its parameters
(`coupling_matrix`): z_j ~ Phi_j(u_j) theta_j with Phi_j lags, plays and low-passes of u_j,
y = M [Phi_j theta_j], alternating theta (given M) and M (given theta) from the unconstrained
least squares. The rank constraint matters: an unconstrained
block of Phi_j per output, or an instrumental-variable estimate, absorbs the chains' unexplained
slow motion by chance correlation with the other inputs (0.05 came out as 0.39 on one 12.5 s
record).
"""
import math

import numpy as np
from numba import njit

from ...errors import DataError, ModelFileError
from ..data.checks import as_channels, input_vector
from ..data.filters import lfilter
from ..narx.kernels import step_rows
from .model import HysteresisNARX
from .model_file import LAYOUTS

#: Structure name in the model file (structure.layout) and the experiment (option 'structure').
CHAINS_LAYOUT = 'one-axis chain per input, mixed by a coupling matrix'
#: Features of the linear chain model that estimates M: input lags, play radii (fractions of
#: the largest |u|) with their lags, low-pass time constants (s).
COUPLING_LAGS = 16
COUPLING_RADII = tuple(float(r) for r in (np.arange(1, 13) / 12.0) ** 2 * 0.8)
COUPLING_PLAY_LAGS = 3
COUPLING_TAUS = (0.01, 0.05, 0.2, 1.0, 5.0)
COUPLING_ITER = 30
#: Chains fitted this many times, each on the outputs decoupled by the M the previous chains
#: refined (`refine_coupling`). Two-axis cantilever, seed 1: M[0, 1] 0.060 (linear chain model)
#: -> 0.056 -> 0.054 (stage 0.05); x's multisine 160 -> 147 -> 103 nm, slow sine 262 -> 118 nm.
CHAIN_PASSES = 2
#: Largest condition number of M accepted (its inverse decouples the outputs).
MAX_CONDITION = 1e3
#: The structure test before the chains are fitted: the linear chain model must explain this
#: share of the outputs' variance, and lose at most CHAINS_MAX_LOSS of it against a free linear
#: model over the same regressors (two-axis cantilever: 0.9989 and 0.0002; the Fine Steering
#: Mirror, whose resonances are the mirror's, shared by every actuator: 0.28 and 0.11).
CHAINS_MIN_R2 = 0.9
CHAINS_MAX_LOSS = 0.01


@njit(cache=True)
def _plays(x, radii):
    """Return play operators (N, len(radii)) of x (N,) from rest."""
    out = np.empty((x.size, radii.size))
    for r in range(radii.size):
        p = 0.0
        for k in range(x.size):
            if p < x[k] - radii[r]:
                p = x[k] - radii[r]
            elif p > x[k] + radii[r]:
                p = x[k] + radii[r]
            out[k, r] = p
    return out


def _lagged(x, lags):
    """Return [x(k), .., x(k - lags)] (N, lags + 1) of (N,) x, zeros before the record."""
    out = np.zeros((x.size, lags + 1))
    for lag in range(lags + 1):
        out[lag:, lag] = x[:x.size - lag]
    return out


def chain_features(x, fs):
    """Return the linear chain model's regressors (N, p) of one normalised input x (N,)."""
    cols = [_lagged(x, COUPLING_LAGS)]
    plays = _plays(np.ascontiguousarray(x, dtype=np.float64), np.array(COUPLING_RADII))
    cols += [_lagged(plays[:, r], COUPLING_PLAY_LAGS) for r in range(plays.shape[1])]
    for tau in COUPLING_TAUS:
        lam = math.exp(-1.0 / (tau * fs))
        cols.append(lfilter([1.0 - lam], [1.0, -lam], x)[:, None])
    return np.hstack(cols)


def coupling_matrix(us, ys, fs, iterations=COUPLING_ITER, ridge=1e-9):
    """
    Return the coupling M (n, n), unit diagonal, and {'structure_r2', 'free_r2'} of records us, ys.

    us (N_r, n) V, ys (N_r, n) m (module docstring). structure_r2 is the share of the outputs'
    variance the chain structure explains with the linear chain model, free_r2 the share an
    unconstrained linear model over the same regressors explains: close values say the outputs
    are a mix of one chain per input.
    """
    n = us[0].shape[1]
    scale = np.max(np.abs(np.vstack(us)), axis=0)
    if np.any(scale == 0):
        raise DataError('estimation data has a constant input channel; cannot fit its chain')
    F, Y = [], []
    for u, y in zip(us, ys):
        f = np.hstack([chain_features(u[:, j] / scale[j], fs) for j in range(n)])
        F.append(f - f.mean(axis=0))            # a constant per record and output: a nuisance
        Y.append(y - y.mean(axis=0))
    F, Y = np.vstack(F), np.vstack(Y)
    p = F.shape[1] // n
    blocks = [slice(j * p, (j + 1) * p) for j in range(n)]
    G, H = F.T @ F, F.T @ Y
    reg = ridge * np.trace(G) / G.shape[0] * np.eye(G.shape[0])
    sst = float(np.sum(Y * Y))

    def explained(T):       # share of the outputs' variance explained by F T (P, n)
        return 1.0 - float(np.sum(Y * Y) - 2 * np.sum(T * H) + np.sum(T * (G @ T))) / sst

    T = np.linalg.solve(G + reg, H)             # unconstrained: a block per input and output
    free_r2 = explained(T)
    M = np.eye(n)
    for j in range(n):
        b = blocks[j]
        vjj = T[b, j] @ G[b, b] @ T[b, j]
        for i in range(n):
            if i != j and vjj > 0:
                M[i, j] = T[b, i] @ G[b, b] @ T[b, j] / vjj
    theta = np.zeros((G.shape[0], n))           # block diagonal: chain j's weights in column j
    for _ in range(iterations):
        MtM = M.T @ M
        A = np.empty_like(G)
        rhs = np.empty(G.shape[0])
        for j, bj in enumerate(blocks):
            rhs[bj] = H[bj] @ M[:, j]
            for k, bk in enumerate(blocks):
                A[bj, bk] = MtM[j, k] * G[bj, bk]
        th = np.linalg.solve(A + reg, rhs)
        theta[:] = 0.0
        for j, b in enumerate(blocks):
            theta[b, j] = th[b]
        VV, VY = theta.T @ G @ theta, theta.T @ H
        for i in range(n):
            o = [j for j in range(n) if j != i]
            if o:
                M[i, o] = np.linalg.solve(VV[np.ix_(o, o)] + 1e-12 * np.trace(VV) * np.eye(
                    len(o)), VY[o, i] - VV[o, i])
    return M, {'structure_r2': explained(theta @ M.T), 'free_r2': free_r2}


def check_coupling(M):
    """Return M (n, n) float64 when finite with a unit diagonal and invertible, else DataError."""
    M = np.array(M, dtype=np.float64)
    if M.ndim != 2 or M.shape[0] != M.shape[1] or not np.all(np.isfinite(M)) \
            or not np.allclose(np.diag(M), 1.0):
        raise DataError(f'coupling must be a finite square matrix with 1 on its diagonal, got '
                        f'{M.tolist()}')
    cond = np.linalg.cond(M)
    if not cond < MAX_CONDITION:
        raise DataError(f'coupling matrix is singular (condition number {cond:.3g}): the axes '
                        'cannot be told apart')
    return M


def decouple(y, M):
    """Return the chains' motion z = M^-1 y (N, n) of outputs y (N, n) m."""
    return np.linalg.solve(M, np.asarray(y, dtype=np.float64).T).T


def fit(model, us, ys, fs):
    """
    Fit `model` (a HysteresisChains) on records us (N_r, n) V, ys (N_r, n) m; returns info.

    M by `coupling_matrix` (DataError when the structure test fails: CHAINS_MIN_R2), then
    chain j as a one-axis HysteresisNARX with the model's options on (u_j, z_j) of every record.
    """
    import time
    t0 = time.perf_counter()
    M, info = coupling_matrix(us, ys, fs)
    if info['structure_r2'] < CHAINS_MIN_R2 or \
            info['free_r2'] - info['structure_r2'] > CHAINS_MAX_LOSS:
        raise DataError('the outputs are not a mix of one actuator chain per input: a linear '
                        f"chain model explains {info['structure_r2']:.3f} of their variance "
                        f"against {info['free_r2']:.3f} for a free linear model over the same "
                        f'regressors (needs >= {CHAINS_MIN_R2} and within {CHAINS_MAX_LOSS})')
    history = [check_coupling(M).tolist()]
    for _ in range(CHAIN_PASSES):
        zs = [decouple(y, M) for y in ys]
        chains = []
        for j in range(M.shape[0]):
            chain = model.chain_model()
            uj, zj = [u[:, j].copy() for u in us], [z[:, j].copy() for z in zs]
            chain.fit(uj, zj, fs=fs)
            chain.metadata = {'data': {'line': _line(np.concatenate(uj), np.concatenate(zj))}}
            chains.append(chain)
        M = check_coupling(refine_coupling(chains, us, ys, fs))
        history.append(M.tolist())
    model.coupling_, model.chains_ = M, chains
    return {**info, 'coupling': M.tolist(), 'coupling_passes': history,
            'fit_seconds': time.perf_counter() - t0,
            'chains': [c.training_info_ for c in chains]}


def refine_coupling(chains, us, ys, fs, skip_s=1.0):
    """
    Return M (n, n) refitted on the fitted chains' free runs z^ (least squares, unit diagonal).

    y_i - z^_i = sum_{j != i} M_ij z^_j + a constant per record, over each record after its
    first skip_s seconds (at most a quarter of it: a record that does not start at rest). The
    chains explain their motion far better than the linear chain model that gave the first M,
    so less of what they miss leaks into it: on the two-axis cantilever the first M's error
    (up to 0.01 on 0.05) added 0.01 of the other axis's motion to every free run.
    """
    n = len(chains)
    Z, Y, C = [], [], []
    for r, (u, y) in enumerate(zip(us, ys)):
        k0 = min(int(skip_s * fs), u.shape[0] // 4)
        z = np.column_stack([c.simulate(u[:, j]) for j, c in enumerate(chains)])[k0:]
        Z.append(z)
        Y.append(y[k0:])
        C.append(np.full(z.shape[0], r))
    Z, Y, C = np.vstack(Z), np.vstack(Y), np.concatenate(C)
    const = (C[:, None] == np.arange(len(us))[None, :]).astype(np.float64)
    M = np.eye(n)
    for i in range(n):
        o = [j for j in range(n) if j != i]
        coef = np.linalg.lstsq(np.column_stack([Z[:, o], const]), Y[:, i] - Z[:, i],
                               rcond=None)[0]
        M[i, o] = coef[:len(o)]
    return M


def _line(u, z):
    """Return the least-squares line of a chain's training data (as `fit` stores data.line)."""
    gain, offset = np.polyfit(u, z, 1)
    sst = float(np.sum((z - z.mean()) ** 2))
    r2 = 1.0 - float(np.sum((z - gain * u - offset) ** 2)) / sst if sst > 0 else math.nan
    return {'gain_m_per_v': float(gain), 'offset_m': float(offset), 'r2': r2}


class ChainsStepper:
    """
    Stepper of a HysteresisChains: step(u_k (n,) V) -> y_k (n,) m, one chain Stepper per axis.

    step and peek return a NEW (n,) array (M z + offset), the one allocation per step.
    """

    def __init__(self, model, u_past=None, y_past=None, state=None):
        self._model = model
        self.n_in = self.n_out = model.n_in
        self.nu, self.ny = model.nu, model.ny
        self._M = model.coupling_
        self._z = np.zeros(self.n_in)
        #: Added to every output (m, (n,)): the sensor offsets of a ModelState.
        self.offset = np.zeros(self.n_out)
        self._chains = [c.stepper() for c in model.chains_]
        if state is not None:
            self.set_state(state)
        else:
            self.reset(u_past, y_past)

    @property
    def chains(self):
        """Return the chains' one-axis Steppers (their state is the model's; read, never step)."""
        return tuple(self._chains)

    def reset(self, u_past=None, y_past=None):
        """Restart from rest, feed u_past (nu, n) V; y_past (ny, n) m is checked, not used."""
        up = None if u_past is None else as_channels(u_past, 'u_past', n=self.nu, width=self.n_in)
        if y_past is not None:
            as_channels(y_past, 'y_past', n=self.ny, width=self.n_out)
        for j, s in enumerate(self._chains):
            s.reset(None if up is None else up[:, j])
        self.offset = np.zeros(self.n_out)

    def set_state(self, state):
        """Continue from a ModelState (the chains' state vectors end to end, offsets m)."""
        values = self._model._check_state(state)
        offset = self._model._check_offset(state)
        for s, v in zip(self._chains, self._model.split_state(values)):
            s.set_state(_state(v, 0.0))
        self.offset = np.array(offset, dtype=np.float64)

    def step(self, u_k):
        """
        Feed one input sample u_k (n,) V; returns the free-run output y(k) (n,) m.

        A non-finite u_k raises DataError and leaves every chain untouched.
        """
        u = input_vector(u_k, self.n_in)
        if not np.all(np.isfinite(u)):
            raise DataError(f'stepper input must be finite voltages, got {u_k!r}')
        z = self._z
        for j, s in enumerate(self._chains):
            z[j] = s.step(u[j])
        return self._M @ z + self.offset

    def step_many(self, u):
        """
        Feed input rows u (k, n) V in order; returns the outputs (k, n) m.

        The same numbers as k step() calls: each chain's compiled step_many, mixed. A bad row
        raises DataError (kernels.step_rows' line) before any step.
        """
        try:
            a = np.asarray(u, dtype=np.float64)
        except (TypeError, ValueError):
            a = None
        if a is None or a.ndim != 2 or a.shape[1] != self.n_in or not np.isfinite(a).all():
            return step_rows(self, u)       # raises the one-line DataError, state untouched
        z = np.column_stack([s.step_many(a[:, j]) for j, s in enumerate(self._chains)])
        return z.reshape(a.shape[0], self.n_in) @ self._M.T + self.offset

    def peek(self, u_k):
        """Return the output step(u_k) would return (n,) m, without changing the state."""
        u = input_vector(u_k, self.n_in)
        if not np.all(np.isfinite(u)):
            raise DataError(f'stepper input must be finite voltages, got {u_k!r}')
        z = np.array([s.peek(u[j]) for j, s in enumerate(self._chains)])
        return self._M @ z + self.offset

    @property
    def state(self):
        """Return the current ModelState (the chains' state vectors end to end; offsets, m)."""
        from ..state.estimate import ModelState
        return ModelState(np.concatenate([s.state.values for s in self._chains]),
                          self.offset.copy())

    @property
    def u_past(self):
        """Copy of the last nu inputs (nu, n), V."""
        return np.column_stack([s.u_past for s in self._chains])

    @property
    def y_past(self):
        """Copy of the last ny outputs (ny, n), m (offset included)."""
        return np.column_stack([s.y_past for s in self._chains]) @ self._M.T + self.offset


def _state(values, offset, info=None):
    from ..state.estimate import ModelState
    return ModelState(np.asarray(values, dtype=np.float64), offset, info or {})


def chains_document(model):
    """Return the model file's blocks of a HysteresisChains (each chain's own, nested)."""
    chains = []
    for c in model.chains_:
        doc = c.file_document()
        doc['input_range'] = list(c.input_range)
        doc['output_range'] = list(c.output_range)
        doc['data'] = (getattr(c, 'metadata', None) or {}).get('data')
        chains.append(doc)
    return {'structure': {'kind': model.kind, 'layout': CHAINS_LAYOUT,
                          'coupling': model.coupling_.tolist(), 'chains': chains,
                          'nu': model.nu, 'ny': model.ny, 'n_params': model.n_params},
            'normalisation': None,
            'training': {'seed': model.seed, 'options': model.params_dict(),
                         'info': model.training_info_,
                         'method': 'coupling by reduced-rank least squares, then each chain as '
                                   'a one-axis model (output-error Levenberg-Marquardt)'}}


def chains_weights(model):
    """Return every chain's weight arrays, named chain<j>.<name>."""
    return {f'chain{j}.{k}': v for j, c in enumerate(model.chains_)
            for k, v in c.file_weights().items()}


def chains_from_document(cls, doc, arrays, name, wpath, fs):
    """Return the HysteresisChains of a model file (structure.layout CHAINS_LAYOUT)."""
    struct = doc['structure']
    docs = struct.get('chains')
    if not isinstance(docs, list) or len(docs) < 2 or \
            not all(isinstance(d, dict) for d in docs):
        raise ModelFileError(f'{name}: structure.chains must list one chain per axis')
    try:
        M = check_coupling(struct.get('coupling'))
    except (DataError, TypeError, ValueError) as exc:
        raise ModelFileError(f'{name}: structure.{exc}') from None
    if M.shape[0] != len(docs):
        raise ModelFileError(f'{name}: {len(docs)} chains but a {M.shape[0]} x {M.shape[0]} '
                             'coupling')
    chains = []
    for j, d in enumerate(docs):
        prefix = f'chain{j}.'
        sub = {k[len(prefix):]: v for k, v in arrays.items() if k.startswith(prefix)}
        chain = HysteresisNARX.from_file_document(d, sub, f'{name} (chain {j})', wpath, fs)
        for key in ('input_range', 'output_range'):
            rng = d.get(key)
            if not (isinstance(rng, list) and len(rng) == 2
                    and all(isinstance(v, (int, float)) and math.isfinite(v) for v in rng)):
                raise ModelFileError(f'{name}: structure.chains[{j}].{key} must be [min, max]')
            setattr(chain, key, (float(rng[0]), float(rng[1])))
        chain.fs = float(fs)
        chain.metadata = {'data': d.get('data')} if isinstance(d.get('data'), dict) else {}
        chains.append(chain)
    options = {k: v for k, v in chains[0].params_dict().items() if k in cls._parameter_constraints}
    model = cls(**options)
    model.coupling_, model.chains_ = M, chains
    model.n_in_ = model.n_out_ = M.shape[0]
    model.output_2d_ = True
    model.fs = float(fs)
    model.training_info_ = (doc.get('training') or {}).get('info') or {}
    return model


class HysteresisChains(HysteresisNARX):
    """
    A HysteresisNARX of n inputs and n outputs built as one one-axis chain per axis, mixed by M.

    Same constructor arguments as HysteresisNARX (each chain's; mimo_order unused). Fitted:
    `coupling_` (n, n) M, `chains_` (n one-axis HysteresisNARX, chain j driven by input j;
    each with its input/output range and its training data's line in `metadata`). simulate /
    predict / stepper / estimate_state take and return (N, n) arrays; the state vector is the
    chains' end to end (each chain's layout in hysteresis.kernels); a ModelState's offset is
    one per output (m).
    """

    #: Fitted: the coupling M (n, n) and the chains (module docstring).
    coupling_ = None
    chains_ = None

    def chain_model(self):
        """Return an unfitted one-axis HysteresisNARX with this model's options (one chain)."""
        return HysteresisNARX(**{k: v for k, v in self.params_dict().items()
                                 if k != 'mimo_order'})

    def params_dict(self):
        """
        Return the constructor arguments (mimo_order left out: it shapes no chain).

        amplifier only when not its default 'auto': each chain's own document says whether its
        drive has one, and files without it stay as they were.
        """
        return {name: getattr(self, name) for name in self._parameter_constraints
                if name != 'mimo_order' and (name != 'amplifier' or self.amplifier != 'auto')}

    @property
    def nu(self):
        """Input history the Stepper takes (each chain's), samples."""
        return self.n_lags

    @property
    def ny(self):
        """Output history the Stepper takes (each chain's), samples."""
        return self.na

    @property
    def n_params(self):
        """Return the chains' parameters plus the coupling's off-diagonal terms."""
        n = len(self.chains_) if self.chains_ else 0
        return int(sum(c.n_params for c in self.chains_ or ()) + n * (n - 1))

    def _is_fitted(self):
        return self.chains_ is not None

    @property
    def state_size(self):
        """Length of the state vector: every chain's, end to end."""
        return int(sum(c.state_size for c in self.chains_))

    def split_state(self, values):
        """Return the chains' state vectors of a state vector (views)."""
        bounds = np.cumsum([0] + [c.state_size for c in self.chains_])
        return [values[a:b] for a, b in zip(bounds[:-1], bounds[1:])]

    # ------------------------------------------------------------------ fitting
    def fit(self, u, y, fs=None):
        """
        Train on records of n inputs and n outputs, u (N, n) V, y (N, n) m (or lists of them).

        The coupling M, then chain j on (u_j, (M^-1 y)_j) as a one-axis model (module
        docstring). fs (Hz) is required. Returns self.
        """
        from ..base import as_channel_lists
        us, ys, _ = as_channel_lists(u, y, min_len=max(self.n0, 1) + 20)
        if fs is None:
            raise DataError('HysteresisChains.fit needs the sample rate fs (Hz)')
        fs = float(fs)
        if not np.isfinite(fs) or fs <= 0:
            raise DataError(f'sample rate fs must be a positive number of Hz, got {fs!r}')
        n_in, n_out = us[0].shape[1], ys[0].shape[1]
        if n_in != n_out or n_in < 2:
            raise DataError(f'a chain per axis needs as many inputs as outputs (2 or more), got '
                            f'{n_in} inputs and {n_out} outputs')
        self.n_in_, self.n_out_ = n_in, n_out
        self.output_2d_ = True
        self._inputs = self._outputs = None
        self.fs = fs
        self.training_info_ = fit(self, us, ys, fs)
        self.u_scale_ = float(max(c.u_scale_ for c in self.chains_))
        self.y_scale_ = float(max(c.y_scale_ for c in self.chains_))
        self._record_ranges(np.vstack(us), np.vstack(ys), fs)
        return self

    # ------------------------------------------------------------------ inference
    def _mix(self, z):
        return z @ self.coupling_.T

    def _signal2(self, x, name, n=None, min_len=1):
        return as_channels(x, name, n=n, width=self.n_in, min_len=min_len)

    def simulate(self, u, y0=None, state=None):
        """
        Free run: u (N, n) V -> (N, n) m, each chain from rest, or y0 (n0, n) m, or a ModelState.

        As HysteresisNARX.simulate, chain by chain on the decoupled y0 / state.
        """
        self._require_fitted()
        if state is not None:
            if y0 is not None:
                raise DataError('give y0 or state, not both')
            values = self._check_state(state)
            u = self._signal2(u, 'u')
            return self._run_from(values, u) + self._check_offset(state)
        if y0 is None:
            u = self._signal2(u, 'u')
            return self._mix(np.column_stack([c.simulate(u[:, j])
                                              for j, c in enumerate(self.chains_)]))
        u = self._signal2(u, 'u', min_len=self.n0)
        z0 = decouple(self._signal2(y0, 'y0', n=self.n0, min_len=0), self.coupling_)
        return self._mix(np.column_stack([c.simulate(u[:, j], z0[:, j])
                                          for j, c in enumerate(self.chains_)]))

    def predict(self, u, y):
        """One step ahead: each chain on its input and its decoupled measured output; (N, n) m."""
        self._require_fitted()
        u = self._signal2(u, 'u', min_len=self.n0 + 1)
        z = decouple(self._signal2(y, 'y', n=len(u)), self.coupling_)
        return self._mix(np.column_stack([c.predict(u[:, j], z[:, j])
                                          for j, c in enumerate(self.chains_)]))

    def stepper(self, u_past=None, y_past=None, state=None):
        """Per-sample free run: a ChainsStepper (rest, then u_past; or a ModelState)."""
        self._require_fitted()
        if state is not None and (u_past is not None or y_past is not None):
            raise DataError('give u_past/y_past or state, not both')
        return ChainsStepper(self, u_past, y_past, state)

    def _run_from(self, values, u):
        """Free run (m, without offset) of u (N, n) V from the state vector `values`."""
        u = self._signal2(u, 'u')
        return self._mix(np.column_stack([c._run_from(v, u[:, j]) for j, (c, v) in enumerate(
            zip(self.chains_, self.split_state(np.asarray(values, dtype=np.float64))))]))

    def estimate_state(self, u, y, prior=None, past='any'):
        """
        Return the ModelState at u[0] explaining a window u (N, n) V, y (N, n) m.

        Each chain's own estimate (HysteresisNARX.estimate_state, past as there) on its input and
        its decoupled output; offsets per output = M times the chains' offsets.
        """
        from ..state.estimate import MIN_WINDOW, ModelState
        self._require_fitted()
        u = self._signal2(u, 'u (state window)', min_len=MIN_WINDOW)
        z = decouple(self._signal2(y, 'y (state window)', n=len(u)), self.coupling_)
        priors = [None] * self.n_in
        if prior is not None:
            offs = decouple(self._check_offset(prior)[None, :], self.coupling_)[0]
            priors = [_state(v, float(o)) for v, o in zip(
                self.split_state(self._check_state(prior)), offs)]
        states = [c.estimate_state(u[:, j], z[:, j], priors[j], past)
                  for j, c in enumerate(self.chains_)]
        offset = self.coupling_ @ np.array([float(s.offset) for s in states])
        values = np.concatenate([s.values for s in states])
        fit_err = self._run_from(values, u) + offset - self._signal2(y, 'y', n=len(u))
        return ModelState(values, offset, {'chains': [s.info for s in states],
                                           'rms_m': float(np.sqrt(np.mean(fit_err ** 2))),
                                           'window_samples': int(len(u))})

    def _bracket_states(self, u0):
        """Return the two extreme pasts at u0 (n,) V: each chain's, paired in order."""
        u0 = np.broadcast_to(np.asarray(u0, dtype=np.float64), (self.n_in,))
        per = [c._bracket_states(float(u0[j])) for j, c in enumerate(self.chains_)]
        return [_state(np.concatenate([p[k].values for p in per]), np.zeros(self.n_out),
                       {'history': f'bracket {k}'}) for k in range(2)]

    # ------------------------------------------------------------------ model file and export
    def file_document(self):
        """Return the model file's blocks (the chains' own documents, nested; the coupling)."""
        return chains_document(self)

    def file_weights(self):
        """Return every chain's weight arrays, named chain<j>.<name>."""
        return chains_weights(self)

    @classmethod
    def from_file_document(cls, doc, arrays, name, wpath, fs):
        """Return the HysteresisChains of a model file (structure.layout CHAINS_LAYOUT)."""
        return chains_from_document(cls, doc, arrays, name, wpath, fs)

    def c_emitter(self):
        """Return the C emitter of this model (hysteresis.chains_export.ChainsEmitter)."""
        from .chains_export import ChainsEmitter
        return ChainsEmitter(self)

    def __repr__(self):
        return (f'HysteresisChains(hidden={self.hidden}, n_plays={self.n_plays}, '
                f'n_lags={self.n_lags}, seed={self.seed}, axes={self.n_in})')


LAYOUTS[CHAINS_LAYOUT] = HysteresisChains
