"""
An ensemble: the mean output of several fitted models of one family (seeds of one structure).

Why (docs/real.md has the measurements): a record of a real actuator rarely covers what the model
is later asked to do. The micromanipulator's identification record is one full-range sine; its
test record fades in and out (minor loops) and holds. Every network seed fits the sine to R²
0.9998, and on the test they scatter from R² 0.85 to 0.99, because the sine does not decide how
a network behaves off the major loop: each seed extrapolates its own way. The mean of the seeds
that fit well averages those ways out (0.98-0.99 with four), where picking one seed is a lottery
that the identification record cannot referee.

Everything is the members': the free run is the mean of their free runs, the state is theirs side
by side (each with its own sensor offset from estimate_state), the Stepper steps each. The model
file nests the members' documents and prefixes their weight arrays (m0_W1, ...).
"""
from __future__ import annotations

import numpy as np

from ..errors import ConfigError, DataError, ModelFileError
from .base import DynamicModel, register_family
from .checks import as_signal


@register_family
class EnsembleModel(DynamicModel):
    """
    Mean of `members` (fitted models, or unfitted ones that fit() trains), all of one sample rate.

    Attributes as every model: nu, ny (the deepest member's), n_params (their sum), fs,
    input_range, output_range (the first member's), state_from_input (any member's).
    """

    kind = 'ensemble'
    file_format_version = 3     # the kind was added in format version 3
    _parameter_constraints: dict = {}

    def __init__(self, members=()):
        members = list(members)
        if len(members) < 2:
            raise ConfigError(f'an ensemble needs at least 2 members, got {len(members)}')
        for m in members:
            if not isinstance(m, DynamicModel) or isinstance(m, EnsembleModel):
                raise ConfigError(f'ensemble members must be models of a family (not '
                                  f'ensembles), got {type(m).__name__}')
        self.members = members
        self._sync()

    def _sync(self):
        first = self.members[0]
        self.fs = first.fs
        self.input_range, self.output_range = first.input_range, first.output_range
        self.state_from_input = any(m.state_from_input for m in self.members)

    @property
    def nu(self):
        """Input history the Stepper takes: the deepest member's, samples."""
        return max(m.nu for m in self.members)

    @property
    def ny(self):
        """Output history the Stepper takes: the deepest member's, samples."""
        return max(m.ny for m in self.members)

    @property
    def n_params(self):
        """Return the number of estimated parameters of all members."""
        return int(sum(m.n_params for m in self.members))

    def _is_fitted(self):
        return all(m._is_fitted() for m in self.members)

    def fit(self, u, y, fs=None):
        """Fit every member on u (V), y (m) (arrays, or lists for several records); self."""
        for m in self.members:
            m.fit(u, y, fs=fs)
        rates = {m.fs for m in self.members}
        if len(rates) > 1:
            raise DataError(f'ensemble members were fitted at different rates: {sorted(rates)}')
        self._sync()
        return self

    # ------------------------------------------------------------------ inference
    def _mean(self, outputs):
        return np.mean(np.vstack(outputs), axis=0)

    def predict(self, u, y):
        """One step ahead from measured past outputs: the mean of the members', (N,) m."""
        self._require_fitted()
        return self._mean([m.predict(u, y) for m in self.members])

    def simulate(self, u, y0=None, state=None):
        """
        Free run: the mean of the members' free runs, (N,) m.

        y0 and state as every model (state: estimate_state of this ensemble).
        """
        self._require_fitted()
        if state is not None:
            if y0 is not None:
                raise DataError('give y0 or state, not both')
            u = as_signal(u, 'u')
            return self._mean([m.simulate(u, state=s)
                               for m, s in zip(self.members, self._split(state))])
        if y0 is not None:
            y0 = as_signal(y0, 'y0', n=self.n0, min_len=0)
            return self._mean([m.simulate(u, None if y0 is None else y0[self.n0 - m.n0:])
                               for m in self.members])
        return self._mean([m.simulate(u) for m in self.members])

    def stepper(self, u_past=None, y_past=None, state=None):
        """A Stepper stepping every member and returning their mean (histories as simulate)."""
        self._require_fitted()
        if state is not None:
            if u_past is not None or y_past is not None:
                raise DataError('give u_past/y_past or state, not both')
            return EnsembleStepper([m.stepper(state=s)
                                    for m, s in zip(self.members, self._split(state))])
        return EnsembleStepper([m.stepper(*_tails(m, u_past, y_past)) for m in self.members])

    # ------------------------------------------------------------------ state
    @property
    def state_size(self):
        """Every member's state vector followed by its offset (m)."""
        return int(sum(m.state_size + 1 for m in self.members))

    def estimate_state(self, u, y, prior=None):
        """Each member's own estimate_state on the window, side by side (offset 0 overall)."""
        from .state import ModelState
        priors = self._split(prior) if prior is not None else [None] * len(self.members)
        states = [m.estimate_state(u, y, p) for m, p in zip(self.members, priors)]
        values = np.concatenate([np.r_[s.values, s.offset] for s in states])
        rms = [s.info.get('rms_m') for s in states]
        return ModelState(values, 0.0, {'members': [s.info for s in states],
                                        'window_samples': int(np.size(u)),
                                        'rms_m': float(np.mean(rms))})

    def _split(self, state):
        """The members' ModelStates from an ensemble ModelState."""
        from .state import ModelState
        values = self._check_state(state)
        out, k = [], 0
        for m in self.members:
            n = m.state_size
            out.append(ModelState(values[k:k + n], float(values[k + n]) + float(state.offset)))
            k += n + 1
        return out

    # ------------------------------------------------------------------ model file
    def file_document(self):
        """Return the ensemble's blocks: each member's document, its ranges, in a list."""
        docs = []
        for m in self.members:
            d = m.file_document()
            docs.append({**d, 'input_range': m.input_range, 'output_range': m.output_range})
        return {'structure': {'kind': self.kind, 'members': docs, 'n_params': self.n_params,
                              'nu': self.nu, 'ny': self.ny},
                'normalisation': None,
                'training': {'method': 'mean of the members (each trained on its own)'}}

    def file_weights(self):
        """Return every member's arrays, named m<i>_<name>."""
        return {f'm{i}_{name}': value for i, m in enumerate(self.members)
                for name, value in m.file_weights().items()}

    @classmethod
    def from_file_document(cls, doc, arrays, name, wpath, fs):
        """Return the EnsembleModel of a model file (see DynamicModel.from_file_document)."""
        from . import document
        from .families import family
        docs = document.get(doc, 'structure.members', name, (list,))
        if len(docs) < 2:
            raise ModelFileError(f'{name}: an ensemble needs at least 2 members, got {len(docs)}')
        members = []
        for i, mdoc in enumerate(docs):
            if not isinstance(mdoc, dict):
                raise ModelFileError(f'{name}: structure.members[{i}] must be an object')
            kind = document.get(mdoc, 'structure.kind', f'{name} member {i}', (str,))
            fam = family(kind)
            if fam is None or fam is cls:
                raise ModelFileError(f'{name}: member {i} has kind {kind!r}, not a model family')
            prefix = f'm{i}_'
            sub = {k[len(prefix):]: v for k, v in arrays.items() if k.startswith(prefix)}
            m = fam.from_file_document(mdoc, sub, f'{name} member {i}', wpath, fs)
            m.fs = float(fs) if fs is not None else None
            m.input_range = document.range_of(mdoc, 'input_range', name)
            m.output_range = document.range_of(mdoc, 'output_range', name)
            members.append(m)
        return cls(members)

    def c_emitter(self):
        """Ensembles are not exported to C yet: ExportError."""
        from ..export import ExportError
        raise ExportError('an ensemble model cannot be exported to C yet; export one of its '
                          'members')

    def __repr__(self):
        return f'EnsembleModel({", ".join(repr(m) for m in self.members)})'


def _tails(model, u_past, y_past):
    """The last nu / ny samples of the ensemble's histories that `model` takes."""
    up = None if u_past is None else np.asarray(u_past, dtype=np.float64)
    yp = None if y_past is None else np.asarray(y_past, dtype=np.float64)
    return (None if up is None else up[up.size - model.nu:] if model.nu else None,
            None if yp is None else yp[yp.size - model.ny:] if model.ny else None)


class EnsembleStepper:
    """Steps every member's Stepper; step(u_k V) -> the mean of their outputs (m)."""

    def __init__(self, steppers):
        self._steppers = list(steppers)
        self._n = float(len(self._steppers))

    def step(self, u_k):
        """Feed one input sample u_k (V) to every member; returns the mean output (m)."""
        total = 0.0
        for s in self._steppers:
            total += s.step(u_k)
        return total / self._n

    def peek(self, u_k):
        """Return the output step(u_k) would return (m), without changing any state."""
        total = 0.0
        for s in self._steppers:
            total += s.peek(u_k)
        return total / self._n

    def reset(self, u_past=None, y_past=None):
        """Restart every member from the given histories (as their reset)."""
        for s in self._steppers:
            s.reset(*_tails(s, u_past, y_past))

    @property
    def state(self):
        """The current ModelState: the members' states and offsets side by side."""
        from .state import ModelState
        return ModelState(np.concatenate([np.r_[s.state.values, s.state.offset]
                                          for s in self._steppers]), 0.0)
