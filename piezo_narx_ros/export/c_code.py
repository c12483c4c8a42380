"""
What every family's C emitter shares: number literals, constant arrays and the Emitter base.

The generated C must give the Python kernels' numbers to the bit, so the emitters copy the
kernels' arithmetic operation for operation (same order of sums, divisions kept as divisions)
and write every weight with repr(), which C compilers read back to the same double.
"""
from __future__ import annotations

import math

import numpy as np

from piezo_narx_ros.export import ExportError

WIDTH = 99          # line length of the generated C

# Printable ASCII that means nothing special anywhere in C text (no backslash, quote or '?',
# which could start an escape or a trigraph).
_PLAIN = frozenset(chr(c) for c in range(0x20, 0x7f)) - set('\\"?')


def c_escape(text) -> str:
    """
    Return `text` as printable ASCII that is safe in any C text: the one escaping rule.

    Backslash, double quote and '?' (trigraphs) are escaped; every other character that is not
    printable ASCII (newlines, control characters, non-ASCII) becomes octal escapes of its
    UTF-8 bytes (three digits each, so a following digit cannot extend one). What reaches the
    generated C from outside (a file name, a model file's strings) goes through here: inside a
    string literal (`c_string`) it reads back as the same bytes, inside a comment
    (`c_comment`) it stays one line of text.
    """
    out = []
    for ch in str(text):
        if ch in _PLAIN:
            out.append(ch)
        elif ch in '\\"?':
            out.append('\\' + ch)
        else:
            out.extend(f'\\{b:03o}' for b in ch.encode('utf-8', 'surrogatepass'))
    return ''.join(out)


def c_string(text) -> str:
    """Return a C string literal holding `text` (c_escape)."""
    return f'"{c_escape(text)}"'


def c_comment(text) -> str:
    """Return `text` safe inside a /* */ comment: c_escape, and no comment opened or closed."""
    return c_escape(text).replace('*/', '*\\/').replace('/*', '/\\*')


def c_float(x) -> str:
    """Return the C double literal of a finite number, exact (repr round-trips)."""
    x = float(x)
    if not math.isfinite(x):
        raise ExportError(f'cannot write {x!r} as a C constant (finite numbers only)')
    return repr(x)      # always has '.' or 'e': a double literal


def c_macro_number(x) -> str:
    """Return a number for a #define: exact, parenthesised when negative."""
    text = c_float(x)
    return f'({text})' if text.startswith('-') else text


def _wrapped(items, indent: str) -> list[str]:
    """Return comma-separated items packed into lines of at most WIDTH characters."""
    lines, cur = [], indent
    for i, item in enumerate(items):
        piece = item + (',' if i < len(items) - 1 else '')
        if cur.strip() and len(cur) + 1 + len(piece) > WIDTH:
            lines.append(cur.rstrip())
            cur = indent
        cur += ('' if cur == indent else ' ') + piece
    lines.append(cur.rstrip())
    return lines


def c_array(name: str, values, comment: str = '') -> str:
    """
    Return `static const double NAME[n]` (or `[n][m]`) holding `values` exactly.

    Empty arrays are not valid C: the emitters leave them (and the loops over them) out.
    """
    a = np.asarray(values, dtype=np.float64)
    if a.size == 0 or a.ndim not in (1, 2):
        raise ExportError(f'internal: {name} must be a non-empty 1-D or 2-D array')
    head = (f'/* {c_comment(comment)} */\n' if comment else '') + \
        f'static const double {name}' + ''.join(f'[{n}]' for n in a.shape) + ' = {'
    if a.ndim == 1:
        return '\n'.join([head] + _wrapped([c_float(v) for v in a], '    ') + ['};'])
    rows = []
    for r, row in enumerate(a):
        end = ',' if r < a.shape[0] - 1 else ''
        one = '    {' + ', '.join(c_float(v) for v in row) + '}' + end
        if len(one) <= WIDTH:
            rows.append(one)
            continue
        body = _wrapped([c_float(v) for v in row], '        ')
        rows += ['    {'] + body + ['    }' + end]
    return '\n'.join([head] + rows + ['};'])


def c_scalar(name: str, value, comment: str = '') -> str:
    """Return `static const double NAME = value;` (exact)."""
    tail = f'   /* {c_comment(comment)} */' if comment else ''
    return f'static const double {name} = {c_float(value)};{tail}'


def comment_block(lines) -> str:
    """Return the lines as one C block comment (each line through c_comment)."""
    return '\n'.join(['/*'] + [(' * ' + c_comment(ln)).rstrip() for ln in lines] + [' */'])


class Emitter:
    """
    A family's C emitter: the family part of pnr_model.c and what the writer needs to know.

    The writer (export.writer) writes the API around it: pnr_init (state all zeros: rest),
    pnr_peek, pnr_init_inputs, pnr_set_state / pnr_get_state (the state is one array
    `double x[PNR_STATE_SIZE]` in the family's documented layout) and the inverse. A subclass
    provides:

      state_size, state_layout (lines for the header) and state_vector(stepper) (the same
        vector from a Python Stepper, for tests and for handing a state over);
      definitions(): C text defining the weights, `void pnr_step(pnr_state_t *s, const double
        *u, double *y)` and `void pnr_init_history(pnr_state_t *s, const double *u_past, const
        double *y_past)` (the estimator's `init: measurement`, as model.stepper(u_past, y_past)),
        and, when 'quasi_static' is in `targets`, `static double pnr_quasi_static_(const
        pnr_state_t *s, double u)` (the value ModelInverse uses for that target, m);
      max_inputs / max_outputs: the channels its C supports (u and y are vectors of
        PNR_N_INPUTS / PNR_N_OUTPUTS everywhere else).
    """

    max_inputs = 1
    max_outputs = 1
    targets = ('output',)
    history_note = 'u_past: the last PNR_NU inputs, y_past: the last PNR_NY outputs'

    def __init__(self, model):
        if not model._is_fitted():
            raise ExportError(f'cannot export {model!r}: it has no weights (fit it first)')
        self.model = model
        self.n_in = int(getattr(model, 'n_in', 1))
        self.n_out = int(getattr(model, 'n_out', 1))
        if self.n_in > self.max_inputs or self.n_out > self.max_outputs:
            raise ExportError(f'the C export of {model.kind} supports {self.max_inputs} input(s) '
                              f'and {self.max_outputs} output(s); this model has {self.n_in} and '
                              f'{self.n_out}')

    @property
    def kind(self) -> str:
        """Return the model file's kind."""
        return self.model.kind

    @property
    def nu(self) -> int:
        """Input history of pnr_init_history, samples per input."""
        return int(self.model.nu)

    @property
    def ny(self) -> int:
        """Output history of pnr_init_history, samples per output."""
        return int(self.model.ny)

    # ------------------------------------------------------------------ to implement
    @property
    def state_size(self) -> int:   # pragma: no cover - interface
        """Return the length of the state vector."""
        raise NotImplementedError

    @property
    def state_layout(self) -> list:   # pragma: no cover - interface
        """Return the state vector's layout, as lines of text for the header."""
        raise NotImplementedError

    def state_vector(self, stepper) -> np.ndarray:   # pragma: no cover - interface
        """Return the C state vector (PNR_STATE_SIZE,) of a Python Stepper of the model."""
        raise NotImplementedError

    def definitions(self) -> str:   # pragma: no cover - interface
        """Return the family's C: weights, pnr_step, pnr_init_history (see the class)."""
        raise NotImplementedError

    def dc_gain(self) -> float:   # pragma: no cover - interface
        """Return the DC gain the quasi-static target uses (families that support it)."""
        raise NotImplementedError


def shift_left(array: str, start: str, count: int, new: str) -> list[str]:
    """
    Return C lines moving array[start+1 .. start+count-1] down one place, `new` into the last.

    Time-ordered histories (oldest first), as the Python kernels keep them.
    """
    if count <= 0:
        return []
    lines = []
    if count > 1:
        lines += [f'    for (i = 0; i < {count - 1}; ++i) {{',
                  f'        {array}[{start} + i] = {array}[{start} + i + 1];',
                  '    }']
    lines.append(f'    {array}[{start} + {count - 1}] = {new};')
    return lines


class HistoryEmitter(Emitter):
    """
    Emitter base of the families whose whole state is their last nu inputs and ny outputs.

    (ARX and the paper's NARX network.) State x = [u(k-nu) .. u(k-1), y(k-ny) .. y(k-1)], V and
    m, oldest first: exactly Stepper.u_past and Stepper.y_past, so pnr_init_history copies them.
    A subclass writes its weights and `pnr_step_`, the one-sample kernel on that state, from
    `output_lines()`.
    """

    @property
    def state_size(self) -> int:
        """Return nu + ny."""
        return self.nu + self.ny

    @property
    def state_layout(self) -> list:
        """Return the layout lines for the header."""
        return [f'x[0 .. {self.nu - 1}]: u(k-{self.nu}) .. u(k-1), V (oldest first)'
                if self.nu else '(no input history: nu = 0)',
                f'x[{self.nu} .. {self.nu + self.ny - 1}]: y(k-{self.ny}) .. y(k-1), m '
                '(oldest first)',
                'as Stepper.u_past and Stepper.y_past; rest is all zeros']

    def state_vector(self, stepper) -> np.ndarray:
        """Return [u_past, y_past] of a Python Stepper."""
        return np.concatenate([stepper.u_past, stepper.y_past])

    def history_definitions(self) -> str:
        """Return `pnr_init_history_`: the histories copied into the state (NULL: rest)."""
        ku, ky = self.nu * self.n_in, self.ny * self.n_out   # values in each history
        lines = ['static void pnr_init_history_(pnr_state_t *s, const double *u_past,',
                 '                              const double *y_past)', '{', '    int i;']
        if ku:
            lines += [f'    for (i = 0; i < {ku}; ++i) {{',
                      '        s->x[i] = u_past ? u_past[i] : 0.0;', '    }']
        else:
            lines.append('    (void)u_past;')
        lines += [f'    for (i = 0; i < {ky}; ++i) {{',
                  f'        s->x[{ku} + i] = y_past ? y_past[i] : 0.0;', '    }', '}']
        return '\n'.join(lines)

    def shift_lines(self) -> list:
        """Return the C lines that shift u[0] and the new output `out` into the histories."""
        return shift_left('x', '0', self.nu, 'u[0]') + shift_left('x', str(self.nu), self.ny,
                                                                  'out')


class ChannelHistoryEmitter(HistoryEmitter):
    """
    HistoryEmitter of a lagged model with several inputs or outputs (VectorStepper's state).

    State x = [u(k-nu) .. u(k-1) (rows of PNR_N_INPUTS), y(k-ny) .. y(k-1) (rows of
    PNR_N_OUTPUTS)], oldest first, each sample's channels in order: Stepper.u_past and y_past
    flattened row by row. pnr_step_ writes the outputs to `out[PNR_N_OUTPUTS]` and calls
    `shift_lines()`.
    """

    max_inputs = 64
    max_outputs = 64

    @property
    def state_size(self) -> int:
        """Return nu n_in + ny n_out."""
        return self.nu * self.n_in + self.ny * self.n_out

    @property
    def state_layout(self) -> list:
        """Return the layout lines for the header."""
        ku = self.nu * self.n_in
        return [f'x[0 .. {ku - 1}]: u(k-{self.nu}) .. u(k-1), V, {self.n_in} per sample '
                '(oldest first)' if self.nu else '(no input history: nu = 0)',
                f'x[{ku} .. {self.state_size - 1}]: y(k-{self.ny}) .. y(k-1), m, {self.n_out} '
                'per sample (oldest first)',
                'as Stepper.u_past and Stepper.y_past row by row; rest is all zeros']

    def state_vector(self, stepper) -> np.ndarray:
        """Return [u_past rows, y_past rows] of a Python VectorStepper."""
        return np.concatenate([stepper.u_past.ravel(), stepper.y_past.ravel()])

    def shift_lines(self) -> list:
        """Return the C lines shifting the rows u[] and out[] into the histories."""
        lines = []
        for start, rows, width, new in ((0, self.nu, self.n_in, 'u'),
                                        (self.nu * self.n_in, self.ny, self.n_out, 'out')):
            if not rows:
                continue
            if rows > 1:
                lines += [f'    for (i = 0; i < {(rows - 1) * width}; ++i) {{',
                          f'        x[{start} + i] = x[{start} + i + {width}];', '    }']
            lines += [f'    for (i = 0; i < {width}; ++i) {{',
                      f'        x[{start + (rows - 1) * width} + i] = {new}[i];', '    }']
        return lines

    def step_lines(self, body: list) -> str:
        """Return pnr_step_ around `body` (which fills out[PNR_N_OUTPUTS] from x and u)."""
        return '\n'.join(['static void pnr_step_(pnr_state_t *s, const double *u, double *y)',
                          '{', '    double *x = s->x;', f'    double out[{self.n_out}];',
                          '    int i, j, lag;'] + body + self.shift_lines()
                         + [f'    for (j = 0; j < {self.n_out}; ++j) {{',
                            '        y[j] = out[j];', '    }', '}'])
