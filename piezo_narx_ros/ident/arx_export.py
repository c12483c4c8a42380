"""
C emitter of the ARX family (piezo-narx export; docs/export.md).

pnr_step copies arx_step (ident/kernels.py) operation for operation, on the state
[u(k-nu) .. u(k-1), y(k-ny) .. y(k-1)]:

    y(k) = c + bu . [u(k-nu) .. u(k)] + ay . [y(k-ny) .. y(k-1)]     (time order)
"""
from ..export.c_code import HistoryEmitter, c_array, c_scalar


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
