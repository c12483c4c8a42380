"""
C emitter of the envelope family, HysteresisNARX (piezo-narx export; docs/export.md).

pnr_step copies hysteresis.kernels.step operation for operation (normalised units inside: un = u
/ u_scale, y = yn * y_scale) on the kernel's own state array, whose layout (hysteresis.kernels'
docstring) is the exported state vector:

    [v(k-1) .. v(k-Lh) (Lh = max(n_lags, 1)), plays (n_plays), Duhem states (n_duhem),
     creep states (n_creep), z(k-1) .. z(k-nb), yl(k-1) .. yl(k-na)]   (normalised)

`pnr_quasi_static_` copies peek_static (the inverse's 'quasi_static' target).

The one-sample model is its own function on a state array (`hn_step`), so that a model of several
chains (hysteresis_chains_export.py) writes each chain with this emitter under its own prefix and
calls it on its part of the state.
"""
import re

import numpy as np

from ...export.c_code import Emitter, c_array, c_scalar
from . import kernels as hk


class HysteresisEmitter(Emitter):
    """The C of a HysteresisNARX: its kernel parameters as constants, step and peek_static."""

    targets = ('output', 'quasi_static')
    history_note = ('u_past: the last PNR_NU inputs, fed from rest (the state is a function of '
                    'the input history); y_past is not used')

    def __init__(self, model, prefix: str = 'hn', quasi_static: bool = True):
        """
        Emitter of a one-axis model; its C names start with `prefix` (constants in capitals).

        quasi_static=False: no pnr_quasi_static_ (a chain of a several-axes model, whose C has
        no inverse; an unused static function would not compile under -Werror).
        """
        super().__init__(model)
        self.prefix = prefix
        if not quasi_static:
            self.targets = ('output',)
        (self.radii, self.n_lags, self.duhem, self.rho, self.kap, self.W1, self.b1, self.w2,
         self.c, self.w_rest, self.g, self.lam, self.a, self.b, self.y_off) = model._kernel_args
        self.m, self.q, self.nl = self.radii.size, self.duhem.shape[0], self.lam.size
        # A drive with an amplifier bandwidth (hysteresis.kernels.amplifier); without one the C
        # is the slew-limited drive's, as before it existed.
        self.amp = bool(np.isfinite(self.kap))
        self.na, self.nb = self.a.size, self.b.size - 1
        self.lh = max(self.n_lags, 1)
        self.i_p = self.lh
        self.i_s = self.i_p + self.m
        self.i_x = self.i_s + self.q
        self.i_z = self.i_x + self.nl
        self.i_y = self.i_z + self.nb

    @property
    def state_size(self) -> int:
        """Return the kernel state's length."""
        return hk.state_size(self.m, self.n_lags, self.q, self.nl, self.na, self.nb)

    def layout_lines(self, start: int = 0) -> list:
        """Return the state's parts as header lines, indices from `start` (its first double)."""
        rows = [(0, self.lh, 'drive v(k-1) .. v(k-Lh), newest first'),
                (self.i_p, self.m, 'play operators'), (self.i_s, self.q, 'Duhem states'),
                (self.i_x, self.nl, 'creep states'), (self.i_z, self.nb, 'z(k-1) .. z(k-nb)'),
                (self.i_y, self.na, 'yl(k-1) .. yl(k-na), output dynamics')]
        return [f'x[{start + lo} .. {start + lo + n - 1}]: {what}' for lo, n, what in rows if n]

    @property
    def state_layout(self) -> list:
        """Return the layout lines for the header."""
        return (self.layout_lines() +
                ['normalised units (u / PNR_U_SCALE, y / PNR_Y_SCALE), as the Python kernel',
                 '(HysteresisStepper.kernel_state); rest is all zeros'])

    def state_vector(self, stepper) -> np.ndarray:
        """Return a copy of a HysteresisStepper's kernel state."""
        return np.array(stepper.kernel_state[0][0], dtype=np.float64)

    def dc_gain(self) -> float:
        """Return the output dynamics' DC gain G as ModelInverse computes it."""
        return float(np.sum(self.b) / (1.0 + np.sum(self.a)))

    # ------------------------------------------------------------------ C text
    def _constants(self) -> list:
        m = self.model
        out = [c_scalar('HN_U_SCALE', m.u_scale_, 'input scale, V'),
               c_scalar('HN_Y_SCALE', m.y_scale_, 'output scale, m'),
               c_scalar('HN_RHO', self.rho, 'drive slew limit per sample (normalised)'),
               *([c_scalar('HN_KAP', self.kap, 'drive amplifier bandwidth, 2 pi f_a / fs')]
                 if self.amp else []),
               c_array('HN_RADII', self.radii, 'play radii (normalised)'),
               c_array('HN_W1T', self.W1.T, 'network-input x hidden weights (W1 transposed)'),
               c_array('HN_B1', self.b1, 'hidden biases'),
               c_array('HN_W2', self.w2, 'hidden -> w weights'),
               c_array('HN_C', self.c, 'linear term of the network'),
               c_scalar('HN_W_REST', self.w_rest, 'network output at rest')]
        if self.q:
            out += [c_array('HN_DUHEM', self.duhem, 'Duhem parameters, 6 per state'),
                    c_scalar('HN_BETA_MIN', hk.BETA_MIN, 'smallest Duhem decay rate')]
        if self.nl:
            out += [c_array('HN_LAM', self.lam, 'creep poles'),
                    c_array('HN_OML', 1.0 - self.lam, '1 - creep poles'),
                    c_array('HN_G', self.g, 'creep gains')]
        if self.na:
            out.append(c_array('HN_A', self.a, 'output dynamics A(q)'))
        out += [c_array('HN_B', self.b, 'output dynamics B(q)'),
                c_scalar('HN_Y_OFF', self.y_off, 'output offset (normalised)')]
        if 'quasi_static' in self.targets:
            out.append(c_scalar('HN_DC_GAIN', self.dc_gain(), 'output dynamics DC gain'))
        return out

    def _helpers(self) -> list:
        duhem = """static double hn_duhem(double s, double d, const double *p)
{
    double sg, alpha, rho, beta, ad, x, e, phi;
    if (d == 0.0) {
        return s;
    }
    if (d > 0.0) {
        sg = 1.0;
        alpha = p[0];
        rho = s >= 0.0 ? p[2] : p[3];
    } else {
        sg = -1.0;
        alpha = p[1];
        rho = s >= 0.0 ? p[4] : p[5];
    }
    beta = rho * rho + HN_BETA_MIN;
    ad = fabs(d);
    x = beta * ad;
    e = exp(-x);
    phi = x > 1e-8 ? (1.0 - e) / beta : ad * (1.0 - 0.5 * x);
    return s * e + sg * alpha * phi;
}"""
        amp = """static double hn_amplifier(double prev, double un, double rho, double kap)
{
    double e = un - prev;
    double ae = fabs(e);
    double eps = rho / kap;
    double sg, t;
    if (ae <= eps) {
        return un - e * exp(-kap);
    }
    sg = e > 0.0 ? 1.0 : -1.0;
    t = (ae - eps) / rho;
    if (t >= 1.0) {
        return prev + sg * rho;
    }
    return un - sg * eps * exp(-kap * (1.0 - t));
}"""
        return ([duhem] if self.q else []) + ([amp] if self.amp else []) + [self._chain()]

    def _chain(self) -> str:
        """`hn_chain`: drive, operators, network and creep of one sample -> z (normalised)."""
        m, nl, q, n_lags, lh = self.m, self.nl, self.q, self.n_lags, self.lh
        hidden, d = self.W1.shape
        L = ['/* One sample of the input chain (step() up to z): the drive clipped to +-rho, the',
             ' * operators, the network and the creep; st[0 .. i_z) updated. */',
             ('static double hn_chain(double *st, double un, double rho, double kap)'
              if self.amp else 'static double hn_chain(double *st, double un, double rho)'),
             '{',
             f'    double phi[{d}];', '    double dv = un - st[0];',
             f'    double zh[{hidden}];', '    double v, lo, hi, w, z;']
        if n_lags:
            L.append('    double cur, prev;')
        if q:
            L.append('    double dk, sd;')
        clip = ['if (dv > rho) {', '    dv = rho;', '} else if (dv < -rho) {', '    dv = -rho;',
                '}']
        if self.amp:     # kap INFINITY (the quasi-static value): the plain clip, as the kernel
            clip = (['if (kap == INFINITY) {'] + ['    ' + x for x in clip]
                    + ['} else {', '    dv = hn_amplifier(st[0], un, rho, kap) - st[0];', '}'])
        L += ['    int h, i, j;'] + ['    ' + x for x in clip] + [
              '    un = st[0] + dv;',
              f'    for (i = 0; i < {m}; ++i) {{', f'        v = st[{self.i_p} + i];',
              '        lo = un - HN_RADII[i];', '        hi = un + HN_RADII[i];',
              '        if (v < lo) {', '            v = lo;', '        } else if (v > hi) {',
              '            v = hi;', '        }', f'        st[{self.i_p} + i] = v;',
              '        phi[i] = v;', '    }']
        if n_lags:
            L += ['    prev = un;', f'    for (j = 0; j < {n_lags}; ++j) {{',
                  '        cur = prev;', '        prev = st[j];',
                  f'        phi[{m} + j] = cur - prev;', '    }']
        if q:
            L += ['    dk = un - st[0];', f'    for (j = 0; j < {q}; ++j) {{',
                  f'        sd = hn_duhem(st[{self.i_s} + j], dk, HN_DUHEM[j]);',
                  f'        st[{self.i_s} + j] = sd;', f'        phi[{m + n_lags} + j] = sd;',
                  '    }']
        if lh > 1:
            L += [f'    for (j = {lh - 1}; j > 0; --j) {{', '        st[j] = st[j - 1];', '    }']
        # Input by input across the hidden units: each unit's sum keeps the kernel's order (the
        # same bits) while the units' independent sums overlap in the pipeline.
        L += ['    st[0] = un;', f'    for (h = 0; h < {hidden}; ++h) {{',
              '        zh[h] = HN_B1[h];', '    }', f'    for (i = 0; i < {d}; ++i) {{',
              f'        for (h = 0; h < {hidden}; ++h) {{',
              '            zh[h] += HN_W1T[i][h] * phi[i];', '        }', '    }',
              '    w = -HN_W_REST;', f'    for (h = 0; h < {hidden}; ++h) {{',
              '        w += HN_W2[h] * (1.0 / (1.0 + exp(-zh[h])));', '    }',
              f'    for (i = 0; i < {d}; ++i) {{', '        w += HN_C[i] * phi[i];', '    }',
              '    z = w;']
        if nl:
            L += [f'    for (i = 0; i < {nl}; ++i) {{',
                  f'        v = HN_LAM[i] * st[{self.i_x} + i] + HN_OML[i] * w;',
                  f'        st[{self.i_x} + i] = v;', '        z += HN_G[i] * v;', '    }']
        if not (n_lags or q):     # lh > 1 needs n_lags: j has no use
            L[L.index('    int h, i, j;')] = '    int h, i;'
        L += ['    return z;', '}']
        return '\n'.join(L)

    def _sample(self) -> str:
        """`hn_step`: one sample of the model on its state array st, u (V) -> y (m)."""
        na, nb = self.na, self.nb
        L = ['/* One sample on the state st: u (V) -> y (m), the state advanced. */',
             'static double hn_step(double *st, double u)', '{',
             ('    double z = hn_chain(st, u / HN_U_SCALE, HN_RHO, HN_KAP);' if self.amp
              else '    double z = hn_chain(st, u / HN_U_SCALE, HN_RHO);'),
             '    double yl = HN_B[0] * z;']
        if na or nb:
            L.append('    int i;')
        if nb:
            L += [f'    for (i = 0; i < {nb}; ++i) {{',
                  f'        yl += HN_B[i + 1] * st[{self.i_z} + i];', '    }']
        if na:
            L += [f'    for (i = 0; i < {na}; ++i) {{',
                  f'        yl -= HN_A[i] * st[{self.i_y} + i];',
                  '    }']
        for lo, n, new in ((self.i_z, nb, 'z'), (self.i_y, na, 'yl')):
            if n > 1:
                L += [f'    for (i = {n - 1}; i > 0; --i) {{',
                      f'        st[{lo} + i] = st[{lo} + i - 1];', '    }']
            if n:
                L.append(f'    st[{lo}] = {new};')
        L += ['    return (yl + HN_Y_OFF) * HN_Y_SCALE;', '}']
        return '\n'.join(L)

    def _quasi_static(self) -> str:
        n, lh, hi = self.state_size, self.lh, self.lh + self.m + self.q
        inf = 'INFINITY, INFINITY' if self.amp else 'INFINITY'
        return '\n'.join([
            '/* The quasi-static value (m) for input u: hysteresis_kernels.peek_static. */',
            'static double pnr_quasi_static_(const pnr_state_t *s, double u)', '{',
            '    double un = u / HN_U_SCALE;', f'    double s1[{n}], s2[{n}];', '    double z;',
            '    int i;', f'    for (i = 0; i < {n}; ++i) {{', '        s1[i] = s->x[i];',
            '        s2[i] = s->x[i];', '    }',
            f'    hn_chain(s1, un, {inf});   /* the operators move to un along the real path */',
            f'    for (i = {lh}; i < {hi}; ++i) {{', '        s2[i] = s1[i];', '    }',
            f'    for (i = 0; i < {lh}; ++i) {{',
            '        s2[i] = un;                /* input increments 0 */', '    }',
            f'    z = hn_chain(s2, un, {inf});',
            '    return HN_Y_SCALE * (HN_DC_GAIN * z + HN_Y_OFF);', '}'])

    def named(self, text: str) -> str:
        """Return C text written with the HN_ / hn_ names under this emitter's prefix."""
        if self.prefix == 'hn':
            return text
        upper, lower = self.prefix.upper() + '_', self.prefix + '_'
        return re.sub(r'\b(HN|hn)_', lambda m: upper if m.group(1) == 'HN' else lower, text)

    def model_definitions(self) -> str:
        """Return the constants, the operators' chain and `<prefix>_step`, under the prefix."""
        return self.named('\n\n'.join(self._constants() + self._helpers() + [self._sample()]))

    def definitions(self) -> str:
        """Return the model, pnr_step_, pnr_init_history_ and pnr_quasi_static_."""
        step = '\n'.join(['static void pnr_step_(pnr_state_t *s, const double *u, double *y)',
                          '{', '    y[0] = hn_step(s->x, u[0]);', '}'])
        parts = [self.model_definitions(), step, input_history(self.nu, 1, 1)]
        if 'quasi_static' in self.targets:
            parts.append(self.named(self._quasi_static()))
        return '\n\n'.join(parts)


def input_history(nu: int, n_in: int, n_out: int) -> str:
    """
    Return `pnr_init_history_` of a model whose state is a function of its inputs alone.

    Rest, then the nu input rows u_past (n_in values each, oldest first) through pnr_step_, as
    simulate() / stepper(u_past) do; y_past is not used: the operators' memory cannot be read
    from a few outputs.
    """
    head = ['/* Rest, then the inputs u_past (as simulate()/stepper(u_past) do); y_past is not',
            " * used: the operators' memory cannot be read from a few outputs. */",
            'static void pnr_init_history_(pnr_state_t *s, const double *u_past,',
            '                              const double *y_past)', '{']
    if not nu:
        return '\n'.join(head + ['    (void)u_past;', '    (void)y_past;', '    pnr_init(s);',
                                 '}'])
    row = 'u_past[i]' if n_in == 1 else f'u_past[i * {n_in}]'
    return '\n'.join(head + [
        f'    double y[{n_out}];', '    int i;', '    (void)y_past;', '    pnr_init(s);',
        '    if (u_past) {', f'        for (i = 0; i < {nu}; ++i) {{',
        f'            pnr_step_(s, &{row}, y);', '        }', '    }', '}'])
