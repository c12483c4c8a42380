"""
C emitter of the ARX family (piezo-narx export; docs/export.md).

pnr_step copies arx_step (ident/narx/kernels.py) operation for operation, on the state
[u(k-nu) .. u(k-1), y(k-ny) .. y(k-1)]:

    y(k) = c + bu . [u(k-nu) .. u(k)] + ay . [y(k-ny) .. y(k-1)]     (time order)
"""
from ...export.c_code import ChannelHistoryEmitter, HistoryEmitter, c_array, c_scalar


class ARXEmitter(HistoryEmitter):
    """The C of an ARXModel: its folded coefficients as constants and arx_step."""

    def definitions(self) -> str:
        """Return the weights, pnr_step_ and pnr_init_history_ (see Emitter)."""
        m = self.model
        nu, ny = self.nu, self.ny
        bu, ay, c = m.stepper().kernel_state[1]
        parts = [c_array('ARX_BU', bu, 'input coefficients, u(k-nu) .. u(k), m/V'),
                 c_array('ARX_AY', ay, 'output coefficients, y(k-ny) .. y(k-1), m/m'),
                 c_scalar('ARX_C', c, 'intercept, m')]
        body = ['static void pnr_step_(pnr_state_t *s, const double *u, double *y)', '{',
                '    double *x = s->x;', '    double out = ARX_C;', '    int i;']
        if nu:
            body += [f'    for (i = 0; i < {nu}; ++i) {{',
                     '        out += ARX_BU[i] * x[i];', '    }']
        body += [f'    out += ARX_BU[{nu}] * u[0];',
                 f'    for (i = 0; i < {ny}; ++i) {{',
                 f'        out += ARX_AY[i] * x[{nu} + i];', '    }']
        body += self.shift_lines() + ['    y[0] = out;', '}']
        return '\n\n'.join(parts + ['\n'.join(body), self.history_definitions()])


class ARXChannelEmitter(ChannelHistoryEmitter):
    """
    The C of an ARXModel with several inputs or outputs: arx_step_mimo on the channel state.

    ARX_BU[j * (nu+1) + lag][i] and ARX_AY[j * ny + lag][m] are the kernel's Bu and Ay (rows in
    time order), summed in the kernel's order.
    """

    def definitions(self) -> str:
        """Return the weights, pnr_step_ and pnr_init_history_ (see Emitter)."""
        nu, ny, n_in, n_out = self.nu, self.ny, self.n_in, self.n_out
        bu, ay, c = self.model.stepper().kernel_state[1]
        parts = [c_array('ARX_BU', bu.reshape(n_out * (nu + 1), n_in),
                         'input coefficients [output * (nu+1) + lag][input], lag 0 = u(k-nu), '
                         'm/V'),
                 c_array('ARX_AY', ay.reshape(n_out * ny, n_out),
                         'output coefficients [output * ny + lag][output], lag 0 = y(k-ny), m/m'),
                 c_array('ARX_C', c, 'intercepts, m')]
        body = [f'    for (j = 0; j < {n_out}; ++j) {{', '        double acc = ARX_C[j];']
        if nu:
            body += [f'        for (lag = 0; lag < {nu}; ++lag) {{',
                     f'            for (i = 0; i < {n_in}; ++i) {{',
                     f'                acc += ARX_BU[j * {nu + 1} + lag][i] * '
                     f'x[lag * {n_in} + i];',
                     '            }', '        }']
        body += [f'        for (i = 0; i < {n_in}; ++i) {{',
                 f'            acc += ARX_BU[j * {nu + 1} + {nu}][i] * u[i];', '        }',
                 f'        for (lag = 0; lag < {ny}; ++lag) {{',
                 f'            for (i = 0; i < {n_out}; ++i) {{',
                 f'                acc += ARX_AY[j * {ny} + lag][i] * '
                 f'x[{nu * n_in} + lag * {n_out} + i];',
                 '            }', '        }', '        out[j] = acc;', '    }']
        return '\n\n'.join(parts + [self.step_lines(body), self.history_definitions()])
