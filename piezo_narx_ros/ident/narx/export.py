"""
C emitter of the paper's NARX network (piezo-narx export; docs/export.md).

pnr_step copies narx_step (ident/narx/kernels.py) operation for operation, with the weights folded
into raw units as the Python kernels use them, on the state [u(k-nu) .. u(k-1), y(k-ny) ..
y(k-1)]:

    y(k) = b2 + sum_h w2[h] / (1 + exp(-(b1[h] + Wu[h] . u[k-nu .. k] + Wy[h] . y[k-ny .. k-1])))
"""
from ...export.c_code import ChannelHistoryEmitter, HistoryEmitter, c_array, c_scalar


class NARXEmitter(HistoryEmitter):
    """The C of a NARXNetwork: its folded weights as constants and narx_step."""

    def definitions(self) -> str:
        """Return the weights, pnr_step_ and pnr_init_history_ (see Emitter)."""
        m = self.model
        nu, ny, hidden = self.nu, self.ny, m.hidden
        Wu, Wy, b1, w2, b2 = m.stepper().kernel_state[1]
        parts = [c_array('NARX_WUT', Wu.T, 'input x hidden weights, u(k-nu) .. u(k), 1/V'),
                 c_array('NARX_WYT', Wy.T, 'output x hidden weights, y(k-ny) .. y(k-1), 1/m'),
                 c_array('NARX_B1', b1, 'hidden biases'),
                 c_array('NARX_W2', w2, 'output weights, m'),
                 c_scalar('NARX_B2', b2, 'output bias, m')]
        # Input by input across the hidden units: each unit's sum keeps narx_step's order (the
        # same bits) while the units' independent sums overlap in the pipeline.
        body = ['static void pnr_step_(pnr_state_t *s, const double *u, double *y)', '{',
                '    double *x = s->x;', '    double out = NARX_B2;', f'    double z[{hidden}];',
                '    int h, i;',
                f'    for (h = 0; h < {hidden}; ++h) {{', '        z[h] = NARX_B1[h];', '    }']
        if nu:
            body += [f'    for (i = 0; i < {nu}; ++i) {{',
                     f'        for (h = 0; h < {hidden}; ++h) {{',
                     '            z[h] += NARX_WUT[i][h] * x[i];', '        }', '    }']
        body += [f'    for (h = 0; h < {hidden}; ++h) {{',
                 f'        z[h] += NARX_WUT[{nu}][h] * u[0];', '    }',
                 f'    for (i = 0; i < {ny}; ++i) {{',
                 f'        for (h = 0; h < {hidden}; ++h) {{',
                 f'            z[h] += NARX_WYT[i][h] * x[{nu} + i];', '        }', '    }',
                 f'    for (h = 0; h < {hidden}; ++h) {{',
                 '        out += NARX_W2[h] / (1.0 + exp(-z[h]));', '    }']
        body += self.shift_lines() + ['    y[0] = out;', '}']
        return '\n\n'.join(parts + ['\n'.join(body), self.history_definitions()])


class NARXChannelEmitter(ChannelHistoryEmitter):
    """
    The C of a NARXNetwork with several inputs or outputs: narx_step_mimo on the channel state.

    NARX_WU[h * (nu+1) + lag][i], NARX_WY[h * ny + lag][m] (rows in time order), NARX_W2[j][h],
    summed in the kernel's order.
    """

    def definitions(self) -> str:
        """Return the weights, pnr_step_ and pnr_init_history_ (see Emitter)."""
        nu, ny, n_in, n_out = self.nu, self.ny, self.n_in, self.n_out
        hidden = self.model.hidden
        Wu, Wy, b1, W2, b2 = self.model.stepper().kernel_state[1]
        parts = [c_array('NARX_WU', Wu.reshape(hidden * (nu + 1), n_in),
                         'input weights [unit * (nu+1) + lag][input], lag 0 = u(k-nu), 1/V'),
                 c_array('NARX_WY', Wy.reshape(hidden * ny, n_out),
                         'output weights [unit * ny + lag][output], lag 0 = y(k-ny), 1/m'),
                 c_array('NARX_B1', b1, 'hidden biases'),
                 c_array('NARX_W2', W2, 'output weights [output][unit], m'),
                 c_array('NARX_B2', b2, 'output biases, m')]
        xu = 'x[lag * %d + i]' % n_in
        xy = 'x[%d + lag * %d + i]' % (nu * n_in, n_out)
        body = ['    int h;', '    double z, sig;',
                f'    for (j = 0; j < {n_out}; ++j) {{', '        out[j] = NARX_B2[j];', '    }',
                f'    for (h = 0; h < {hidden}; ++h) {{', '        z = NARX_B1[h];']
        if nu:
            body += [f'        for (lag = 0; lag < {nu}; ++lag) {{',
                     f'            for (i = 0; i < {n_in}; ++i) {{',
                     f'                z += NARX_WU[h * {nu + 1} + lag][i] * {xu};',
                     '            }', '        }']
        body += [f'        for (i = 0; i < {n_in}; ++i) {{',
                 f'            z += NARX_WU[h * {nu + 1} + {nu}][i] * u[i];', '        }',
                 f'        for (lag = 0; lag < {ny}; ++lag) {{',
                 f'            for (i = 0; i < {n_out}; ++i) {{',
                 f'                z += NARX_WY[h * {ny} + lag][i] * {xy};',
                 '            }', '        }',
                 '        sig = 1.0 / (1.0 + exp(-z));',
                 f'        for (j = 0; j < {n_out}; ++j) {{',
                 '            out[j] += NARX_W2[j][h] * sig;', '        }', '    }']
        # Declarations first (C99 allows them later, but the step's locals read better here).
        return '\n\n'.join(parts + [self.step_lines(body), self.history_definitions()])
