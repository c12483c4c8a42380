"""
An ensemble of fitted models: the mean of its members' outputs.

Issue 18 point 4 and issue 20: the envelope family's free run carries a constant loop-centre offset
whose sign changes with the network seed; the mean of several candidates' free runs may cancel
part of it. The members are fitted elsewhere (the experiment's candidates); the ensemble is not
fitted itself.

    y(k) = (1/K) sum_i member_i(u(0..k))

State (ident/state/ ModelState): the members' state vectors end to end, and one offset, the mean
of the members' offsets (the mean of member outputs with offsets o_i is the mean without them plus
mean(o_i): exact).
"""
import math

import numpy as np

from ...errors import DataError, ModelFileError
from ..base import DynamicModel, register_family, registered_families
from ..state.estimate import ModelState

#: The model-file format version whose readers know the kind (members nest their own documents).
ENSEMBLE_FORMAT_VERSION = 3


@register_family
class EnsembleModel(DynamicModel):
    """
    Mean of K fitted models with the same inputs and outputs.

    members : list of fitted DynamicModels (same n_in, n_out, fs).
    """

    kind = 'ensemble'
    file_format_version = ENSEMBLE_FORMAT_VERSION
    _parameter_constraints: dict = {}

    def __init__(self, members=None):
        self.members = list(members or [])
        if self.members:
            self._adopt()

    def _adopt(self):
        first = self.members[0]
        for m in self.members[1:]:
            if (m.n_in, m.n_out) != (first.n_in, first.n_out):
                raise DataError(f'ensemble members differ in channels: {first.n_in} x '
                                f'{first.n_out} and {m.n_in} x {m.n_out}')
        self.n_in, self.n_out = first.n_in, first.n_out
        self.output_2d_ = first.output_2d_
        self.fs = first.fs
        self.input_range, self.output_range = first.input_range, first.output_range
        self.state_from_input = any(m.state_from_input for m in self.members)
        self.inputs, self.outputs = first.inputs, first.outputs

    nu = property(lambda self: max(m.nu for m in self.members))
    ny = property(lambda self: max(m.ny for m in self.members))
    n_params = property(lambda self: sum(int(m.n_params) for m in self.members))
    state_size = property(lambda self: sum(int(m.state_size) for m in self.members))

    def _is_fitted(self) -> bool:
        return bool(self.members)

    def fit(self, u, y, fs=None):
        """Fit every member on u (V), y (m) as its own fit does; returns self."""
        self._require_fitted()
        for m in self.members:
            m.fit(u, y, fs=fs)
        self._adopt()
        return self

    def predict(self, u, y):
        """Mean of the members' one-step predictions, m."""
        self._require_fitted()
        return np.mean([m.predict(u, y) for m in self.members], axis=0)

    def simulate(self, u, y0=None, state=None):
        """Mean of the members' free runs (from y0's last rows each member needs, or `state`)."""
        self._require_fitted()
        if state is not None:
            parts, offset = self._member_states(state)
            runs = [m.simulate(u, state=s) for m, s in zip(self.members, parts)]
            return np.mean(runs, axis=0) + offset
        runs = [m.simulate(u, None if y0 is None else np.asarray(y0)[:m.n0])
                for m in self.members]
        return np.mean(runs, axis=0)

    def stepper(self, u_past=None, y_past=None, state=None):
        """Return an EnsembleStepper (each member's Stepper, outputs averaged)."""
        self._require_fitted()
        return EnsembleStepper(self, u_past, y_past, state)

    def estimate_state(self, u, y, prior=None, past='any'):
        """Each member's estimate on the window u (N,) V, y (N,) m; offsets averaged."""
        self._require_fitted()
        priors = [None] * len(self.members) if prior is None else self.as_member_states(prior)
        states = [m.estimate_state(u, y, prior=p, past=past)
                  for m, p in zip(self.members, priors)]
        return self.join_states(states)

    # ------------------------------------------------------------------ model file and export
    def file_document(self):
        """Return the model file's blocks: each member's own document, nested, with its ranges."""
        members = []
        for m in self.members:
            doc = m.file_document()
            doc['kind_version'] = int(m.file_format_version)
            doc['input_range'] = _plain(m.input_range)
            doc['output_range'] = _plain(m.output_range)
            doc['inputs'], doc['outputs'] = list(m.inputs), list(m.outputs)
            doc['output_2d'] = bool(m.output_2d_)
            members.append(doc)
        return {'structure': {'kind': self.kind, 'members': members, 'nu': self.nu,
                              'ny': self.ny, 'n_params': self.n_params},
                'normalisation': None,
                'training': {'method': "mean of the members' outputs (members fitted on their "
                                       'own; ident/ensemble/model.py)'}}

    def file_weights(self):
        """Return every member's weight arrays, named member<i>.<name>."""
        return {f'member{i}.{k}': v for i, m in enumerate(self.members)
                for k, v in m.file_weights().items()}

    @classmethod
    def from_file_document(cls, doc, arrays, name, wpath, fs):
        """Return the EnsembleModel of a model file: each member read by its own family."""
        # The registry (base), not ident.families: that module imports this one.
        families = registered_families()
        docs = doc['structure'].get('members')
        if not isinstance(docs, list) or len(docs) < 2 or \
                not all(isinstance(d, dict) for d in docs):
            raise ModelFileError(f'{name}: structure.members must list two or more models')
        members = []
        for i, d in enumerate(docs):
            where = f'{name} (member {i})'
            kind = (d.get('structure') or {}).get('kind')
            member_cls = families.get(kind)
            if member_cls is None or member_cls is cls:
                raise ModelFileError(f'{where}: unknown member kind {kind!r}')
            sub = {k[len(f'member{i}.'):]: v for k, v in arrays.items()
                   if k.startswith(f'member{i}.')}
            full = {**d, 'format_version': d.get('kind_version', 1), 'fs': fs}
            if d.get('output_2d'):
                full['structure'] = {**d['structure'], 'n_in': len(d.get('inputs') or ()),
                                     'n_out': len(d.get('outputs') or ())}
            m = member_cls.from_file_document(full, sub, where, wpath, fs)
            m.input_range = _range(d.get('input_range'), where, 'input_range')
            m.output_range = _range(d.get('output_range'), where, 'output_range')
            if d.get('output_2d'):
                m.inputs, m.outputs = d.get('inputs'), d.get('outputs')
                m.output_2d_ = True
            m.fs = None if fs is None else float(fs)
            members.append(m)
        return cls(members)

    def c_emitter(self):
        """Return the C emitter of this model (ensemble.export.EnsembleEmitter)."""
        from .export import EnsembleEmitter
        return EnsembleEmitter(self)

    def __repr__(self):
        return f'EnsembleModel({len(self.members)} members)'

    # ------------------------------------------------------------------ states
    def join_states(self, states) -> ModelState:
        """One ModelState from the members' ModelStates (values end to end, mean offset)."""
        values = np.concatenate([np.asarray(s.values, dtype=np.float64).ravel()
                                 for s in states])
        offsets = [np.asarray(s.offset, dtype=np.float64) for s in states]
        offset = np.mean(offsets, axis=0)
        offset = float(offset.reshape(-1)[0]) if self.n_out == 1 else offset.reshape(self.n_out)
        return ModelState(values, offset, {'members': [s.info for s in states]})

    def _member_states(self, state):
        """([member ModelState with offset 0, ...], the ensemble's offset) of a ModelState."""
        values = self._check_state(state)
        offset = self._check_offset(state)
        zero = 0.0 if self.n_out == 1 else np.zeros(self.n_out)
        cuts = np.cumsum([int(m.state_size) for m in self.members])[:-1]
        return [ModelState(v, zero) for v in np.split(values, cuts)], offset

    def _bracket_states(self, u0):
        """
        Return the two extreme pasts at u0 (V): every member from above, then from below.

        The ensemble is the mean of its members, so its runs from these bound what the unknown
        past can still change (estimator.memory; `evaluate --init-samples`).
        """
        pairs = [m._bracket_states(u0) for m in self.members]
        return [self.join_states([p[i] for p in pairs]) for i in range(2)]

    def as_member_states(self, state):
        """Member ModelStates carrying the ensemble's offset each (their mean is that offset)."""
        parts, offset = self._member_states(state)
        return [ModelState(p.values, offset) for p in parts]


def _plain(rng):
    """Return a range as nested lists of floats (JSON), None kept."""
    return None if rng is None else np.asarray(rng, dtype=np.float64).tolist()


def _range(value, where, key):
    """Return a member's range read back: (min, max) or per-channel tuples; ModelFileError."""
    try:
        arr = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        arr = np.array([math.nan])
    if arr.ndim not in (1, 2) or arr.shape[0] != 2 or not np.all(np.isfinite(arr)):
        raise ModelFileError(f'{where}: {key} must be [min, max] (per channel), got {value!r}')
    if arr.ndim == 1:
        return float(arr[0]), float(arr[1])
    return tuple(map(float, arr[0])), tuple(map(float, arr[1]))


class EnsembleStepper:
    """Stepper of an EnsembleModel: every member's Stepper stepped, the outputs averaged."""

    def __init__(self, model, u_past=None, y_past=None, state=None):
        self._model = model
        self.n_in, self.n_out = model.n_in, model.n_out
        self.nu, self.ny = model.nu, model.ny
        self._scale = 1.0 / len(model.members)
        self.offset = 0.0 if model.n_out == 1 else np.zeros(model.n_out)
        if state is not None:
            parts, self.offset = model._member_states(state)
            self._members = [m.stepper(state=s) for m, s in zip(model.members, parts)]
        else:
            self._members = [m.stepper() for m in model.members]
            self.reset(u_past, y_past)

    @property
    def members(self):
        """Return the members' Steppers (read, never step them)."""
        return tuple(self._members)

    def reset(self, u_past=None, y_past=None):
        """Restart every member from its last nu inputs / ny outputs of u_past, y_past."""
        for m, s in zip(self._model.members, self._members):
            s.reset(None if u_past is None else np.asarray(u_past)[len(u_past) - m.nu:],
                    None if y_past is None else np.asarray(y_past)[len(y_past) - m.ny:])
        self.offset = 0.0 if self.n_out == 1 else np.zeros(self.n_out)

    def set_state(self, state):
        """Continue from an ensemble ModelState."""
        parts, self.offset = self._model._member_states(state)
        for s, p in zip(self._members, parts):
            s.set_state(p)

    @property
    def state(self) -> ModelState:
        """Return the members' states joined (ModelState), offset included."""
        joined = self._model.join_states([s.state for s in self._members])
        return ModelState(joined.values, self.offset + joined.offset)

    def step(self, u_k):
        """Feed one input sample (V); returns the members' mean output (m)."""
        total = 0.0
        for s in self._members:
            total = total + s.step(u_k)
        return total * self._scale + self.offset

    def peek(self, u_k):
        """Return the output step(u_k) would give, without changing any member."""
        total = 0.0
        for s in self._members:
            total = total + s.peek(u_k)
        return total * self._scale + self.offset

    def step_many(self, u):
        """Feed input rows u (k,) or (k, n_in) V; returns the mean outputs (k,) / (k, n_out) m."""
        total = 0.0
        for s in self._members:
            total = total + s.step_many(u)
        return total * self._scale + self.offset
