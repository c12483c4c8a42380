"""
`write_c(model, directory)`: pnr_model.h and pnr_model.c of a model (DESIGN.md's contract).

The writer asks the model's family for its emitter (`model.c_emitter()`, registered with the
family) and writes around the family's C the API every family shares: the state type, pnr_init
(rest), pnr_step (non-finite inputs refused), pnr_peek, pnr_init_history (the estimator's `init:
measurement`), pnr_init_inputs (a history of inputs from rest), pnr_set_state / pnr_get_state
(a full state vector in the family's documented layout) and, for one input and one output, the
inverse (c_inverse.py).
"""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from piezo_narx_ros.export import ExportError, c_inverse
from piezo_narx_ros.export.c_code import c_comment, c_macro_number, c_string, comment_block

HEADER = 'pnr_model.h'
SOURCE = 'pnr_model.c'
#: controller_node's default widening of the trained output range into accepted references.
RANGE_MARGIN = 0.05
# Every generated file says so in its first comment: a file there without it is not ours (the
# second phrase: a pnr_model.c of an export before the mark was added to it).
_MARK = 'exported by `piezo-narx export`'
_MARKS = (_MARK, f'{SOURCE}: see {HEADER}.')


def emitter_of(model):
    """Return the family's C emitter of `model`; ExportError when its family has none."""
    kind = getattr(model, 'kind', type(model).__name__)
    make = getattr(model, 'c_emitter', None)
    try:
        if make is None:
            raise NotImplementedError
        return make()
    except NotImplementedError:
        raise ExportError(f'the C export does not know model kind {kind!r} (its family has no '
                          'C emitter)') from None


def _sample_rate(model_fs, fs) -> float:
    """Return the export's sample rate, Hz: the model's, or `fs` when the model has none."""
    if fs is not None and not (isinstance(fs, (int, float)) and math.isfinite(fs) and fs > 0):
        raise ExportError(f'fs must be a positive number of Hz, got {fs!r}')
    if model_fs is None:
        if fs is None:
            raise ExportError('the sample rate is unknown: the model file has no fs (give --fs)')
        return float(fs)
    if fs is not None and float(fs) != float(model_fs):
        raise ExportError(f'the model was fitted at {model_fs:g} Hz and runs at that rate; '
                          f'--fs {fs:g} differs')
    return float(model_fs)


def _default_target(emitter) -> str:
    # controller_node's default: quasi_static where the family has it.
    return 'quasi_static' if 'quasi_static' in emitter.targets else 'output'


def _advance_quasi_static(model, fs: float):
    """Return ModelInverse's estimate of the quasi-static target's advance, samples."""
    from piezo_narx_ros.control.inverse import ModelInverse
    return ModelInverse(model, fs=fs, target='quasi_static').estimate_advance()


def _y_range(model):
    """Return the references controller_node accepts by default, (m, m), or None."""
    rng = getattr(model, 'output_range', None)
    if rng is None:
        return None
    pad = RANGE_MARGIN * (rng[1] - rng[0])
    return rng[0] - pad, rng[1] + pad


def render(model, fs: float | None = None, source: str | None = None) -> tuple[str, str]:
    """
    Return the text of (pnr_model.h, pnr_model.c) for a fitted model.

    fs: sample rate, Hz, for a model without one (a discrete-time model runs at the rate it was
    fitted at: another rate is refused);
    source: the model file's name, quoted in the files.
    """
    em = emitter_of(model)
    fs = _sample_rate(getattr(model, 'fs', None), fs)
    from piezo_narx_ros.ident.model_io import weights_sha256
    digest = weights_sha256(model)
    siso = em.n_in == 1 and em.n_out == 1
    target = _default_target(em)
    advance = _advance_quasi_static(model, fs) if siso and 'quasi_static' in em.targets \
        else None
    about = [f'{HEADER} / {SOURCE}: a {em.kind} model {_MARK}',
             f'from {source or repr(model)}; weights sha256 {digest}.',
             'Generated: re-export rather than edit. C99, no allocation, libm only;',
             'docs/export.md shows how to use it.',
             '',
             'Volts in, metres out, one pnr_step per sample at PNR_FS_HZ. State layout',
             '(pnr_set_state / pnr_get_state, PNR_STATE_SIZE doubles):']
    about += ['  ' + ln for ln in em.state_layout]
    about += ['pnr_init_history: ' + em.history_note + '.']
    rng_in = getattr(model, 'input_range', None)
    rng_out = getattr(model, 'output_range', None)
    macros = [('PNR_KIND', c_string(em.kind), "model family (the model file's structure.kind)"),
              ('PNR_N_INPUTS', str(em.n_in), 'inputs per sample, V'),
              ('PNR_N_OUTPUTS', str(em.n_out), 'outputs per sample, m'),
              ('PNR_FS_HZ', c_macro_number(fs), 'sample rate, Hz'),
              ('PNR_NU', str(em.nu), 'input history of pnr_init_history, samples per input'),
              ('PNR_NY', str(em.ny), 'output history of pnr_init_history, samples per output'),
              ('PNR_STATE_SIZE', str(em.state_size), 'doubles in the state vector')]
    for name, rng, unit in (('INPUT', rng_in, 'V'), ('OUTPUT', rng_out, 'm')):
        if rng is not None and np.ndim(rng[0]) == 0:
            macros += [(f'PNR_{name}_MIN', c_macro_number(rng[0]),
                        f'trained {name.lower()} range, {unit}'),
                       (f'PNR_{name}_MAX', c_macro_number(rng[1]), '')]
        elif rng is not None:   # several channels: one pair per channel, numbered from 0
            for k, (lo, hi) in enumerate(zip(*rng)):
                macros += [(f'PNR_{name}_MIN_{k}', c_macro_number(lo),
                            f'trained range of {name.lower()} {k}, {unit}'),
                           (f'PNR_{name}_MAX_{k}', c_macro_number(hi), '')]
    h = [comment_block(about), '#ifndef PNR_MODEL_H', '#define PNR_MODEL_H', '',
         '#ifdef __cplusplus', 'extern "C" {', '#endif', '']
    h += [f'#define {n} {v}' + (f'   /* {c_comment(c)} */' if c else '') for n, v, c in macros]
    h += ['', 'typedef struct {', '    double x[PNR_STATE_SIZE];', '} pnr_state_t;', '',
          '/* Rest: every past input and output 0. */',
          'void pnr_init(pnr_state_t *s);',
          '/* One sample: u[PNR_N_INPUTS] (V) -> y[PNR_N_OUTPUTS] (m), the free run advanced.',
          ' * A non-finite input leaves the state untouched and gives y = NAN. */',
          'void pnr_step(pnr_state_t *s, const double *u, double *y);',
          '/* The output pnr_step would give, the state untouched. */',
          'void pnr_peek(const pnr_state_t *s, const double *u, double *y);',
          "/* As the estimator's `init: measurement` (model.stepper(u_past, y_past)): the",
          ' * histories in time order, oldest first, PNR_NU x PNR_N_INPUTS and PNR_NY x',
          ' * PNR_N_OUTPUTS values (NULL: rest). 0, or -1 (state untouched) for a non-finite',
          ' * value. */',
          'int pnr_init_history(pnr_state_t *s, const double *u_past, const double *y_past);',
          '/* Rest, then n input samples (n x PNR_N_INPUTS values, sample by sample): the state',
          ' * a free run from rest reaches on that history. */',
          'void pnr_init_inputs(pnr_state_t *s, const double *u, long n);',
          '/* A full state vector x[PNR_STATE_SIZE] in the layout above: 0, or -1 (state',
          ' * untouched) for a non-finite value. */',
          'int pnr_set_state(pnr_state_t *s, const double *x);',
          'void pnr_get_state(const pnr_state_t *s, double *x);', '']
    if siso:
        h.append(c_inverse.header(em.targets, target, advance))
    else:
        h += ['#define PNR_HAS_INVERSE 0   /* the inverse needs one input and one output */', '']
    h += ['#ifdef __cplusplus', '}', '#endif', '', '#endif /* PNR_MODEL_H */']

    c = [comment_block([f'{SOURCE}: see {HEADER} ({_MARK}).']),
         "/* The numbers equal the Python kernels' to the bit only if the compiler does not",
         ' * fuse a * b + c into one rounding (FMA): -std=c99 does not; GNU modes on FMA',
         ' * targets do unless told not to, as below. */',
         '#if defined(__GNUC__) && !defined(__clang__)',
         '#pragma GCC optimize("fp-contract=off")',
         '#elif defined(__clang__)',
         '#pragma STDC FP_CONTRACT OFF',
         '#endif', '', '#include <math.h>', '', f'#include "{HEADER}"', '',
         _rule(f"The family's model (its emitter: {type(em).__module__})"),
         em.definitions(), '', _rule('The API of every family'), _common()]
    if siso:
        c.append(c_inverse.source(em.targets, target, _y_range(model)))
    return '\n'.join(h) + '\n', '\n'.join(c) + '\n'


def _rule(title: str) -> str:
    """Return a one-line section comment of the generated C."""
    text = f'/* ---- {title} '
    return text + '-' * max(4, 96 - len(text)) + ' */'


def _common() -> str:
    return """void pnr_init(pnr_state_t *s)
{
    int i;
    for (i = 0; i < PNR_STATE_SIZE; ++i) {
        s->x[i] = 0.0;
    }
}

static int finite_all(const double *v, long n)
{
    long i;
    for (i = 0; i < n; ++i) {
        if (!isfinite(v[i])) {
            return 0;
        }
    }
    return 1;
}

void pnr_step(pnr_state_t *s, const double *u, double *y)
{
    int i;
    if (!finite_all(u, PNR_N_INPUTS)) {
        for (i = 0; i < PNR_N_OUTPUTS; ++i) {
            y[i] = NAN;
        }
        return;
    }
    pnr_step_(s, u, y);
}

void pnr_peek(const pnr_state_t *s, const double *u, double *y)
{
    pnr_state_t t = *s;
    pnr_step(&t, u, y);
}

int pnr_init_history(pnr_state_t *s, const double *u_past, const double *y_past)
{
    if ((u_past && !finite_all(u_past, (long)PNR_NU * PNR_N_INPUTS)) ||
            (y_past && !finite_all(y_past, (long)PNR_NY * PNR_N_OUTPUTS))) {
        return -1;
    }
    pnr_init_history_(s, u_past, y_past);
    return 0;
}

void pnr_init_inputs(pnr_state_t *s, const double *u, long n)
{
    double y[PNR_N_OUTPUTS];
    long k;
    pnr_init(s);
    for (k = 0; k < n; ++k) {
        pnr_step(s, u + k * PNR_N_INPUTS, y);
    }
}

int pnr_set_state(pnr_state_t *s, const double *x)
{
    int i;
    if (!finite_all(x, PNR_STATE_SIZE)) {
        return -1;
    }
    for (i = 0; i < PNR_STATE_SIZE; ++i) {
        s->x[i] = x[i];
    }
    return 0;
}

void pnr_get_state(const pnr_state_t *s, double *x)
{
    int i;
    for (i = 0; i < PNR_STATE_SIZE; ++i) {
        x[i] = s->x[i];
    }
}
"""


def _refuse_foreign(path: Path, force: bool) -> None:
    """Raise ExportError when `path` exists and this exporter did not write it (unless force)."""
    if force or not (path.exists() or path.is_symlink()):
        return
    try:
        with open(path, 'rb') as fh:
            head = fh.read(400).decode('ascii', 'replace')
        ours = not path.is_symlink() and any(mark in head for mark in _MARKS)
    except OSError:
        ours = False
    if not ours:
        raise ExportError(f'{path} exists and was not written by piezo-narx export; choose '
                          'another directory or pass --force to overwrite it')


def write_c(model, directory, fs: float | None = None, source: str | None = None,
            force: bool = False) -> tuple:
    """
    Write DIR/pnr_model.h and DIR/pnr_model.c for `model`; returns their paths.

    A file of either name that the exporter did not write (its first comment says so) is
    replaced only with `force`; an earlier export is replaced.
    Each is written to a fresh temporary file and renamed (files.write_atomic), so a build
    never sees half a file and no planted name is followed. ExportError (one line) when the
    model cannot be exported.
    """
    from piezo_narx_ros.files import write_files_atomic
    header, code = render(model, fs=fs, source=source)
    directory = Path(directory)
    for name in (HEADER, SOURCE):
        _refuse_foreign(directory / name, force)
    paths = (directory / HEADER, directory / SOURCE)
    try:
        directory.mkdir(parents=True, exist_ok=True)
        write_files_atomic(dict(zip(paths, (header, code))))
    except OSError as exc:
        raise ExportError(f'cannot write the C files to {directory}: {exc.strerror or exc}') \
            from None
    return paths
