"""
What every model family implements, and the parameter-rule table their constructors check.

Every family (ARX, the paper's NARX network, the hysteresis-operator NARX) is a `DynamicModel`:
fit / predict / simulate on numpy arrays in SI units (V in, m out), a `Stepper` for the estimator's
per-sample loop, and the attributes the estimator, the experiment and the model files read.

Constructor arguments are checked against the class's `_parameter_constraints` table (as
scikit-learn does): the same table gives the CLI its defaults and ranges, and the tests iterate
over it, so a rule is written once.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..errors import ConfigError, DataError
from ..record import default_names
from .data.checks import as_channels, as_signal


@dataclass(frozen=True)
class Interval:
    """A number of `kind` (int or float) in [low, high] (None: unbounded on that side)."""

    kind: type
    low: float | None = None
    high: float | None = None

    def check(self, name: str, value):
        """`value` converted to `kind`; ConfigError naming `name` and the rule otherwise."""
        ok = (not isinstance(value, bool) and isinstance(value, (int, float, np.integer,
                                                                 np.floating)))
        if ok and self.kind is int:
            ok = float(value).is_integer()
        if ok:
            value = self.kind(value)
            ok = math.isfinite(value) and (self.low is None or value >= self.low) and \
                (self.high is None or value <= self.high)
        if not ok:
            raise ConfigError(f'{name} must be {self.describe()}, got {value!r}')
        return value

    def describe(self) -> str:
        """Return the rule in words, e.g. 'an integer in [1, 200]'."""
        what = 'an integer' if self.kind is int else 'a number'
        lo = '-inf' if self.low is None else f'{self.low:g}'
        hi = 'inf' if self.high is None else f'{self.high:g}'
        return f'{what} in [{lo}, {hi}]'


@dataclass(frozen=True)
class Tuple:
    """A non-empty tuple of numbers, each satisfying `item`, strictly increasing if asked."""

    item: Interval
    min_len: int = 1
    max_len: int = 64
    increasing: bool = False

    def check(self, name: str, value):
        """`value` as a tuple; ConfigError naming `name` otherwise."""
        try:
            items = tuple(value)
        except TypeError:
            raise ConfigError(f'{name} must be {self.describe()}, got {value!r}') from None
        if not self.min_len <= len(items) <= self.max_len:
            raise ConfigError(f'{name} must be {self.describe()}, got {len(items)} values')
        items = tuple(self.item.check(f'{name}[{i}]', v) for i, v in enumerate(items))
        if self.increasing and any(b <= a for a, b in zip(items, items[1:])):
            raise ConfigError(f'{name} must be strictly increasing, got {list(items)}')
        return items

    def describe(self) -> str:
        """Return the rule in words."""
        return (f'{self.min_len}-{self.max_len} values, each {self.item.describe()}'
                + (', increasing' if self.increasing else ''))


@dataclass(frozen=True)
class Options:
    """One of a fixed set of strings."""

    values: tuple

    def check(self, name: str, value):
        """`value` if it is one of `values`; ConfigError naming `name` otherwise."""
        if not isinstance(value, str) or value not in self.values:
            raise ConfigError(f'{name} must be {self.describe()}, got {value!r}')
        return value

    def describe(self) -> str:
        """Return the rule in words."""
        return 'one of ' + ', '.join(self.values)


def check_parameters(cls, values: dict) -> dict:
    """
    Every constructor value checked against `cls._parameter_constraints`; returns them converted.

    ConfigError on the first bad one (its name, the rule and the value).
    """
    rules = cls._parameter_constraints
    unknown = set(values) - set(rules)
    if unknown:
        raise ConfigError(f'{cls.__name__}: unknown parameter(s) {", ".join(sorted(unknown))}')
    return {name: rules[name].check(name, value) for name, value in values.items()}


class DynamicModel:
    """
    Base class of every model family: the interface the rest of the package relies on.

    Attributes (set by fit or by model_io.load_model):
      kind : str, the model file's structure.kind;
      nu, ny : input / output history the Stepper takes (samples); n0 = max(nu, ny);
      n_params : number of estimated parameters;
      fs : sample rate the model was fitted at, Hz (None when unknown);
      input_range, output_range : (min, max) seen in the estimation data, V and m; for several
        channels ((min per channel...), (max per channel...)) (`channel_ranges` reads both);
      n_in_, n_out_ : input / output channels (the n_in / n_out properties return them; 1 until
        fitted); inputs, outputs : their names (default u1.. / y1.., ('u',) / ('y',) for one);
      output_2d_ : True when predict/simulate return (N, n_out) (fitted on a 2-D y, or loaded
        from a several-axes model file); False: (N,), the one-axis case;
      state_from_input : True when the model's internal state is a function of the whole input
        history (hysteresis operators, creep) and cannot be set from n0 measured outputs: such a
        model is scored on part of a record by free-running from the record's start.
    Methods: fit(u, y, fs=None) -> self with u (N,) or (N, n_in) V, y (N,) or (N, n_out) m, or
      lists of such for several records; predict(u, y) and simulate(u, y0=None, state=None) ->
      (N,) m for a model fitted on a 1-D y, else (N, n_out) (y0 then (n0, n_out));
      stepper(u_past=None, y_past=None) -> a Stepper with step(u_k) -> y_k and reset(): u_k a
      float (V) returning a float (m) for a one-input one-output model, else an (n_in,) array
      returning an (n_out,) array. ModelState.offset (m) is a float for one output, else (n_out,).

    What a family owns besides its math (a new family implements these and registers itself with
    `register_family`; model_io and the C export find it by `kind`, nothing else changes):
      file_document() / file_weights() / from_file_document(...): its part of the model file
        (model_io keeps the envelope: format, version, units, ranges, checksum, atomic write);
      file_format_version: the model-file format_version its documents are written with (the
        oldest reader that knows the kind);
      c_emitter(): the object that writes its free run (and inverse) as C (piezo_narx_ros.export).
    """

    kind = 'abstract'
    file_format_version = 1
    state_from_input = False
    #: predict/simulate return (N, n_out) arrays (see the class docstring).
    output_2d_ = False
    fs = None
    input_range = None
    output_range = None
    _parameter_constraints: dict = {}

    n_in = property(lambda self: int(getattr(self, 'n_in_', 1)),
                    lambda self, value: setattr(self, 'n_in_', int(value)),
                    doc='Number of input channels (n_in_, 1 until fitted).')
    n_out = property(lambda self: int(getattr(self, 'n_out_', 1)),
                     lambda self, value: setattr(self, 'n_out_', int(value)),
                     doc='Number of output channels (n_out_, 1 until fitted).')
    inputs = property(lambda self: self._channel_names('input'),
                      lambda self, names: self._name_channels('input', names),
                      doc="Input names in column order (default u1.., or ('u',) for one).")
    outputs = property(lambda self: self._channel_names('output'),
                       lambda self, names: self._name_channels('output', names),
                       doc="Output names in column order (default y1.., or ('y',) for one).")

    def _channel_names(self, what: str) -> tuple:
        names = getattr(self, f'_{what}s', None)
        n = self.n_in if what == 'input' else self.n_out
        return tuple(names) if names is not None else default_names(
            'u' if what == 'input' else 'y', n)

    def _name_channels(self, what: str, names) -> None:
        n = self.n_in if what == 'input' else self.n_out
        setattr(self, f'_{what}s', None if names is None else _names(names, n, what))

    @property
    def n0(self) -> int:
        """Leading samples without a full regressor row / history, max(nu, ny)."""
        return max(self.nu, self.ny)

    def fit(self, u, y, fs=None):   # pragma: no cover - interface
        raise NotImplementedError

    def predict(self, u, y):   # pragma: no cover - interface
        raise NotImplementedError

    def simulate(self, u, y0=None, state=None):   # pragma: no cover - interface
        raise NotImplementedError

    def stepper(self, u_past=None, y_past=None, state=None):   # pragma: no cover - interface
        """
        Return the family's per-sample free run, started like simulate().

        Every Stepper has step(u_k) -> y_k, step_many(u (n,) or (n, n_in) V) -> y (n,) or
        (n, n_out) m (the same numbers as n steps, one call per batch), peek(u_k), reset(u_past,
        y_past), state and offset.
        """
        raise NotImplementedError

    # Initial state from measurement (ident/state/): every family implements these three.
    state_size = 0   # length of the state vector
    #: True when the free run is affine in the states `_adjustable_state` names (the output
    #: dynamics' and creep histories of a linear output part): the window's Gauss-Newton then
    #: reuses one Jacobian (ident/state/). False (a network fed its own outputs): recomputed.
    adjustable_state_linear = False

    def _run_from(self, values, u):   # pragma: no cover - interface
        """Free run (m, without offset) of u (N,) V from the state vector `values`."""
        raise NotImplementedError

    def _state_candidates(self, u, past='any'):   # pragma: no cover - interface
        """
        Return the ModelStates the model reaches through input histories ending at u[0].

        past: how the history ended (state.estimate.PASTS); a family adds what it can represent.
        """
        raise NotImplementedError

    def _bracket_states(self, u0):   # pragma: no cover - interface
        """Two ModelStates at input u0 (V) from the most different pasts the model admits."""
        raise NotImplementedError

    def _adjustable_state(self, n_window):   # pragma: no cover - interface
        """Return (indices of the state a window of n_window samples may adjust, their size)."""
        raise NotImplementedError

    def estimate_state(self, u, y, prior=None, past='any'):
        """
        Return the ModelState at u[0] that best explains a window u (N,) V, y (N,) m.

        Hysteresis memory, creep, output dynamics and sensor offset (ident/state/); prior: a
        ModelState believed to hold (its memory is kept, the rest refined on the window); past:
        how the record's unlogged past ended ('any' or 'fade-out', ident/state/estimate.py step 5).
        """
        from .state.estimate import estimate_state
        return estimate_state(self, u, y, prior, past=past)

    def _check_state(self, state):
        """Return a ModelState's vector (float64 copy); DataError when it does not fit."""
        values = np.array(getattr(state, 'values', None), dtype=np.float64).ravel()
        try:
            offset = np.array(getattr(state, 'offset', math.nan), dtype=np.float64)
        except (TypeError, ValueError):
            offset = np.array(math.nan)
        offset_ok = np.all(np.isfinite(offset)) and (
            offset.size == self.n_out if self.n_out > 1 else offset.size == 1)
        if values.size != self.state_size or not np.all(np.isfinite(values)) or not offset_ok:
            what = 'a finite offset' if self.n_out == 1 else \
                f'a finite offset per output ({self.n_out})'
            raise DataError(f'state does not fit {type(self).__name__}: need {self.state_size} '
                            f'finite values and {what}, got {values.size}')
        return values

    def _check_offset(self, state):
        """Return a checked ModelState's offset: a float for one output, else (n_out,) m."""
        if self.n_out == 1:
            return float(np.asarray(state.offset, dtype=np.float64).reshape(-1)[0])
        return np.array(state.offset, dtype=np.float64).reshape(self.n_out)

    def _as_output(self, y2d):
        """Return an (N, n_out) output as the model hands it out: (N,) unless output_2d_."""
        return y2d if self.output_2d_ else y2d[:, 0]

    def _is_fitted(self) -> bool:   # pragma: no cover - interface
        raise NotImplementedError

    # ------------------------------------------------------------------ model file and export
    def file_document(self) -> dict:   # pragma: no cover - interface
        """
        Return the family's blocks of the model file's JSON document.

        {'structure': {'kind': ..., ...}, 'normalisation': dict or None, 'training': dict}; plain
        or numpy values (model_io makes them JSON). The model is fitted.
        """
        raise NotImplementedError

    def file_weights(self) -> dict:   # pragma: no cover - interface
        """Return every weight array of the model file's .npz, by name, in the order written."""
        raise NotImplementedError

    @classmethod
    def from_file_document(cls, doc, arrays, name, wpath, fs):   # pragma: no cover - interface
        """
        Return the model described by a model file's JSON `doc` and weight `arrays`.

        name, wpath: the JSON and .npz paths for messages; fs: the validated sample rate (Hz or
        None). Raises ModelFileError (one line, naming the file) on a malformed block, or
        DataError (model_io names the weights file). model_io sets fs, ranges and metadata after.
        """
        raise NotImplementedError

    def c_emitter(self):   # pragma: no cover - interface
        """Return the family's C emitter (see piezo_narx_ros.export.c_code.Emitter)."""
        raise NotImplementedError

    def _require_fitted(self):
        if not self._is_fitted():
            raise DataError(f'{type(self).__name__} has no weights yet: '
                            f'call fit() or load a model file')

    def _record_ranges(self, u, y, fs):
        """
        Store input/output ranges (V, m) of the estimation data and the sample rate (Hz).

        u, y: (N,) or (N, channels); one channel gives today's (min, max) pair, several give
        ((min...), (max...)) per channel.
        """
        self.input_range = _ranges(u)
        self.output_range = _ranges(y)
        if fs is not None:
            fs = float(fs)
            if not np.isfinite(fs) or fs <= 0:
                raise DataError(f'sample rate fs must be a positive number of Hz, got {fs!r}')
            self.fs = fs


def _ranges(x):
    """(min, max) of one channel (floats) or ((min...), (max...)) of several."""
    x = np.asarray(x, dtype=np.float64)
    if x.ndim == 1 or x.shape[1] == 1:
        return (float(np.min(x)), float(np.max(x)))
    return (tuple(float(v) for v in np.min(x, axis=0)),
            tuple(float(v) for v in np.max(x, axis=0)))


def _names(names, n, what):
    names = tuple(str(s) for s in names)
    if len(names) != n or len(set(names)) != n or not all(s.strip() for s in names):
        raise DataError(f'{n} distinct {what} name(s) needed, got {list(names)}')
    return names


def channel_ranges(model):
    """
    Return the model's trained ranges per channel: (inputs (n_in, 2), outputs (n_out, 2)).

    Rows [min, max] in V and m; None for a range the model does not know. Serves both the
    one-axis (min, max) pair and the per-channel form of several axes.
    """
    def rows(rng, n):
        if rng is None:
            return None
        lo, hi = rng
        lo = np.atleast_1d(np.asarray(lo, dtype=np.float64))
        hi = np.atleast_1d(np.asarray(hi, dtype=np.float64))
        if lo.shape != hi.shape or lo.size not in (1, n):
            raise DataError(f'range {rng!r} does not fit {n} channel(s)')
        return np.column_stack([np.broadcast_to(lo, (n,)), np.broadcast_to(hi, (n,))])
    return (rows(getattr(model, 'input_range', None), model.n_in),
            rows(getattr(model, 'output_range', None), model.n_out))


#: Model families by their model-file kind, in registration order (see register_family).
_FAMILIES: dict = {}


def register_family(cls):
    """
    Class decorator: make `cls` (a DynamicModel with its own `kind`) the family of that kind.

    model_io loads a file and the C export writes a model through this registry.
    """
    kind = cls.__dict__.get('kind')
    if not (isinstance(cls, type) and issubclass(cls, DynamicModel) and isinstance(kind, str)):
        raise TypeError(f'{cls!r} is not a DynamicModel with its own kind')
    known = _FAMILIES.get(kind)
    if known is not None and _name(known) != _name(cls):   # a module reload re-registers
        raise TypeError(f'model kind {kind!r} is already registered by {_name(known)}')
    _FAMILIES[kind] = cls
    return cls


def _name(cls) -> str:
    return f'{cls.__module__}.{cls.__qualname__}'


def registered_families() -> dict:
    """Return {kind: class} of the families registered so far (see ident.families)."""
    return dict(_FAMILIES)


def _record_pairs(u, y):
    """Return (u list, y list, several) of one record (arrays) or several (lists); DataError."""
    several = isinstance(u, (list, tuple))
    if several != isinstance(y, (list, tuple)):
        raise DataError('give u and y both as arrays (one record) or both as lists (several)')
    us, ys = (list(u), list(y)) if several else ([u], [y])
    if not us or len(us) != len(ys):
        raise DataError(f'u and y must hold the same number of records, got {len(us)} and '
                        f'{len(ys)}')
    return us, ys, several


def as_record_list(u, y, min_len=1):
    """
    Return (list of u arrays V, list of y arrays m) from one record or several.

    One record: 1-D arrays; several: a list or tuple of 1-D arrays each. DataError on mismatched or
    bad arrays.
    """
    us, ys, several = _record_pairs(u, y)
    out_u, out_y = [], []
    for i, (ui, yi) in enumerate(zip(us, ys)):
        tag = f' (record {i})' if several else ''
        ui = as_signal(ui, 'u' + tag, min_len=min_len)
        out_u.append(ui)
        out_y.append(as_signal(yi, 'y' + tag, n=ui.size))
    return out_u, out_y


def as_channel_lists(u, y, min_len=1):
    """
    Return (list of (N_i, n_in) u V, list of (N_i, n_out) y m, y_is_1d) from one record or more.

    One record: arrays (N,) or (N, channels); several: a list or tuple of them. Every record must
    have the same channel counts; y_is_1d is True when every y was given 1-D (the one-axis case:
    the model then returns (N,) outputs). DataError (one line) on mismatched or bad arrays.
    """
    us, ys, several = _record_pairs(u, y)
    out_u, out_y, flat = [], [], True
    for i, (ui, yi) in enumerate(zip(us, ys)):
        tag = f' (record {i})' if several else ''
        flat = flat and np.ndim(yi) == 1
        ui = as_channels(ui, 'u' + tag, min_len=min_len,
                         width=out_u[0].shape[1] if out_u else None)
        out_u.append(ui)
        out_y.append(as_channels(yi, 'y' + tag, n=ui.shape[0],
                                 width=out_y[0].shape[1] if out_y else None))
    return out_u, out_y, flat
