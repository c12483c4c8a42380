"""
C emitter of the envelope family on several axes (hysteresis.mimo; piezo-narx export).

pnr_step_ copies hysteresis.mimo_kernels.step operation for operation on the kernel's own state
array, whose layout (hysteresis.mimo.state_layout) is the exported state vector; u and y are
vectors of PNR_N_INPUTS volts and PNR_N_OUTPUTS metres.
"""
import numpy as np

from ...export.c_code import Emitter, ExportError, c_array, c_scalar


class MimoEmitter(Emitter):
    """The C of a several-axes HysteresisNARX: its arrays as constants, step and history."""

    max_inputs = 64
    max_outputs = 64
    targets = ('output',)
    history_note = ('u_past: the last PNR_NU input rows, fed from rest (the state is a function '
                    'of the input history); y_past, when given, sets the output history')

    def __init__(self, model):
        super().__init__(model)
        self.p = model.mimo_
        self.nf = self.p.n_features
        self.order = self.p.order
        self.lay = self.p.layout

    @property
    def state_size(self) -> int:
        """Return the kernel state's length."""
        return int(self.p.state_size)

    @property
    def state_layout(self) -> list:
        """Return the layout lines for the header."""
        what = {'u_plays': 'plays of each input (input-major)',
                'y_plays': 'plays of each stage-1 output (output-major)',
                'env': 'running mean square of the normalised inputs',
                'x_hist': f'features x(k-1) .. x(k-n), {self.nf} per sample, newest first',
                'yt_hist': 'stage-1 outputs yt(k-1) .. yt(k-n), newest first',
                'y_hist': 'outputs y(k-1) .. y(k-n) (normalised), newest first',
                'yl_hist': "each local output model's outputs, n rows of n_out per model"}
        return ([f'x[{lo} .. {hi - 1}]: {what[k]}' for k, (lo, hi) in self.lay.items()
                 if hi > lo] +
                ['normalised units (u / HM_U_SCALE, y / HM_Y_SCALE per channel), as the Python',
                 'kernel (MimoStepper.kernel_state); rest is all zeros'])

    def state_vector(self, stepper) -> np.ndarray:
        """Return a copy of a MimoStepper's kernel state."""
        return np.array(stepper.kernel_state[0][0], dtype=np.float64)

    def dc_gain(self) -> float:
        """Refuse: the inverse's quasi-static target is one-axis only."""
        raise ExportError('the several-axes envelope model has no quasi-static target')

    # ------------------------------------------------------------------ C text
    def _constants(self) -> list:
        p = self.p
        return [c_array('HM_U_SCALE', p.u_scale, 'input scales, V'),
                c_array('HM_Y_SCALE', p.y_scale, 'output scales, m'),
                c_array('HM_UR', p.ur, 'play radii of the inputs (normalised)'),
                c_array('HM_YR', p.yr, 'play radii of the stage-1 outputs (normalised)'),
                c_array('HM_ENV_W', p.env_w, 'weights of the running mean square'),
                c_scalar('HM_ENV_LAM', p.env_lam, 'running mean square pole'),
                c_array('HM_A', p.a, 'stage-1 denominator a_1 .. a_n'),
                c_array('HM_B1', p.B1.reshape(-1, self.order + 1),
                        'stage-1 numerators, row i * n_in + j'),
                c_array('HM_AO', p.a_out, 'output denominators a_1 .. a_n, row l'),
                c_array('HM_B0', p.B0, 'output numerators of x(k), row l * n_out + i'),
                c_array('HM_BH', p.Bh, 'output numerators of the feature history (state '
                        'order), row l * n_out + i')] + (
            [] if p.n_local == 1 else
            [c_array('HM_C', p.centres, 'running amplitudes the local output models are '
                     'centred at')])

    def _step(self) -> str:
        ni, no, nf, n = self.n_in, self.n_out, self.nf, self.order
        nur, nyr = self.p.ur.size, self.p.yr.size
        i_yp, i_env = self.lay['y_plays'][0], self.lay['env'][0]
        i_x, i_yt, i_y = self.lay['x_hist'][0], self.lay['yt_hist'][0], self.lay['y_hist'][0]
        nl = self.p.n_local
        i_yl = self.lay['yl_hist'][0] if nl > 1 else i_y
        L = ['/* sum a[k] b[k], k < n (hysteresis_mimo.dot, which may order it otherwise) */',
             'static double pnr_dot_(const double *a, const double *b, int n)', '{',
             '    double s = 0.0;', '    int k;', '    for (k = 0; k < n; ++k) {',
             '        s += a[k] * b[k];', '    }', '    return s;', '}', '',
             'static void pnr_step_(pnr_state_t *s, const double *u, double *y)', '{',
             '    double *st = s->x;',
             f'    double un[{ni}], yt[{no}], x[{nf}], yl[{nl * no}], w[{nl}];',
             '    double acc, e2, e, p;', '    int i, j, r, f, lag, k;',
             f'    for (i = 0; i < {no}; ++i) {{', '        acc = 0.0;',
             f'        for (j = 0; j < {ni}; ++j) {{',
             f'            acc += HM_B1[i * {ni} + j][0] * (u[j] / HM_U_SCALE[j]);',
             f'            for (lag = 1; lag < {n + 1}; ++lag) {{',
             f'                acc += HM_B1[i * {ni} + j][lag]'
             f' * st[{i_x} + (lag - 1) * {nf} + j];',
             '            }', '        }',
             f'        for (lag = 1; lag < {n + 1}; ++lag) {{',
             f'            acc -= HM_A[lag - 1] * st[{i_yt} + (lag - 1) * {no} + i];',
             '        }',
             '        yt[i] = acc;', '    }',
             f'    for (j = 0; j < {ni}; ++j) {{', '        un[j] = u[j] / HM_U_SCALE[j];',
             '    }',
             f'    e2 = HM_ENV_LAM * st[{i_env}];',
             f'    for (j = 0; j < {ni}; ++j) {{',
             '        e2 += (1.0 - HM_ENV_LAM) * HM_ENV_W[j] * un[j] * un[j];', '    }',
             f'    st[{i_env}] = e2;', '    e = sqrt(e2);', '    f = 0;',
             f'    for (j = 0; j < {ni}; ++j) {{', '        x[f++] = un[j];', '    }',
             f'    for (j = 0; j < {ni}; ++j) {{', f'        for (r = 0; r < {nur}; ++r) {{',
             f'            p = st[j * {nur} + r];',
             '            if (p < un[j] - HM_UR[r]) {', '                p = un[j] - HM_UR[r];',
             '            } else if (p > un[j] + HM_UR[r]) {',
             '                p = un[j] + HM_UR[r];', '            }',
             f'            st[j * {nur} + r] = p;', '            x[f++] = p;', '        }',
             '    }',
             f'    for (j = 0; j < {ni}; ++j) {{', '        x[f++] = un[j] * e;', '    }',
             f'    for (i = 0; i < {no}; ++i) {{', '        x[f] = yt[i];',
             '        x[f + 1] = yt[i] * fabs(yt[i]);', '        x[f + 2] = yt[i] * e;',
             '        x[f + 3] = yt[i] * e * e;', '        f += 4;', '    }',
             f'    for (i = 0; i < {no}; ++i) {{', f'        for (r = 0; r < {nyr}; ++r) {{',
             f'            p = st[{i_yp} + i * {nyr} + r];',
             '            if (p < yt[i] - HM_YR[r]) {', '                p = yt[i] - HM_YR[r];',
             '            } else if (p > yt[i] + HM_YR[r]) {',
             '                p = yt[i] + HM_YR[r];', '            }',
             f'            st[{i_yp} + i * {nyr} + r] = p;', '            x[f++] = yt[i] - p;',
             '        }', '    }',
             ] + self._products() + [
             f'    for (r = 0; r < {nl * no}; ++r) {{',
             f'        acc = pnr_dot_(HM_B0[r], x, {nf}) + pnr_dot_(HM_BH[r], &st[{i_x}], '
             f'{n * nf});',
             f'        for (lag = 1; lag < {n + 1}; ++lag) {{',
             f'            acc -= HM_AO[r / {no}][lag - 1]'
             f' * st[{i_yl} + (r / {no}) * {n * no} + (lag - 1) * {no} + r % {no}];',
             '        }', '        yl[r] = acc;', '    }',
             ] + (['    w[0] = 1.0;'] if nl == 1 else [
                 '    /* Blend the local models: hats on the centres HM_C, clamped at the ends */',
                 f'    for (r = 0; r < {nl}; ++r) {{', '        w[r] = 0.0;', '    }',
                 f'    e = e < HM_C[0] ? HM_C[0] : (e > HM_C[{nl - 1}] ? HM_C[{nl - 1}] : e);',
                 '    j = 0;', f'    while (j < {nl - 2} && e > HM_C[j + 1]) {{', '        ++j;',
                 '    }', '    p = (e - HM_C[j]) / (HM_C[j + 1] - HM_C[j]);',
                 '    w[j] = 1.0 - p;', '    w[j + 1] = p;']) + [
             f'    for (i = 0; i < {no}; ++i) {{', '        acc = 0.0;',
             f'        for (r = 0; r < {nl}; ++r) {{',
             f'            acc += w[r] * yl[r * {no} + i];',
             '        }', '        y[i] = acc;', '    }',
             f'    for (k = {n * nf - 1}; k > {nf - 1}; --k) {{',
             f'        st[{i_x} + k] = st[{i_x} + k - {nf}];', '    }',
             f'    for (f = 0; f < {nf}; ++f) {{', f'        st[{i_x} + f] = x[f];', '    }',
             f'    for (k = {n * no - 1}; k > {no - 1}; --k) {{',
             f'        st[{i_yt} + k] = st[{i_yt} + k - {no}];',
             f'        st[{i_y} + k] = st[{i_y} + k - {no}];', '    }',
             ] + ([] if nl == 1 else [
                 f'    for (r = 0; r < {nl}; ++r) {{',
                 f'        for (k = {n * no - 1}; k > {no - 1}; --k) {{',
                 f'            st[{i_yl} + r * {n * no} + k] = '
                 f'st[{i_yl} + r * {n * no} + k - {no}];',
                 '        }', f'        for (i = 0; i < {no}; ++i) {{',
                 f'            st[{i_yl} + r * {n * no} + i] = yl[r * {no} + i];', '        }',
                 '    }']) + [
             f'    for (i = 0; i < {no}; ++i) {{', f'        st[{i_yt} + i] = yt[i];',
             f'        st[{i_y} + i] = y[i];', '        y[i] *= HM_Y_SCALE[i];', '    }', '}']
        return '\n'.join(L)

    def _products(self) -> list:
        """Return the C lines of the stage-1 outputs' product features (hysteresis.mimo.CROSS)."""
        no = self.n_out
        out = []
        if self.p.cross >= 1:
            out += ['    /* Products of the stage-1 outputs */',
                    f'    for (i = 0; i < {no}; ++i) {{',
                    f'        for (j = i + 1; j < {no}; ++j) {{',
                    '            x[f++] = yt[i] * yt[j];', '        }', '    }']
        if self.p.cross >= 2:
            out += [f'    for (i = 0; i < {no}; ++i) {{', f'        for (j = 0; j < {no}; ++j) {{',
                    '            if (j != i) {', '                x[f++] = yt[i] * fabs(yt[j]);',
                    '            }', '        }', '    }']
        return out

    def _history(self) -> str:
        no, ny, nu, ni = self.n_out, self.ny, self.nu, self.n_in
        i_y = self.lay['y_hist'][0]
        # Several local output models: each one's history starts at the given outputs.
        nl = self.p.n_local if self.p.n_local > 1 else 0
        i_yl = self.lay['yl_hist'][0]
        return '\n'.join([
            '/* Rest, then the input rows u_past (as stepper(u_past, y_past) does); y_past, when',
            ' * given, sets the output history (oldest row first). */',
            'static void pnr_init_history_(pnr_state_t *s, const double *u_past,',
            '                              const double *y_past)', '{',
            f'    double y[{no}];', '    int i, k;', '    pnr_init(s);', '    if (u_past) {',
            f'        for (k = 0; k < {nu}; ++k) {{',
            f'            pnr_step_(s, &u_past[k * {ni}], y);', '        }', '    }',
            '    if (y_past) {', f'        for (k = 0; k < {ny}; ++k) {{',
            f'            for (i = 0; i < {no}; ++i) {{',
            f'                s->x[{i_y} + k * {no} + i] = y_past[({ny - 1} - k) * {no} + i]'
            ' / HM_Y_SCALE[i];',
            ] + [f'                s->x[{i_yl + m * ny * no} + k * {no} + i] = '
                 f's->x[{i_y} + k * {no} + i];' for m in range(nl)] + [
            '            }', '        }', '    }', '}'])

    def definitions(self) -> str:
        """Return the constants, pnr_step_ and pnr_init_history_."""
        return '\n\n'.join(self._constants() + [self._step(), self._history()])
