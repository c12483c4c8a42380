"""
C emitter of the envelope family's chains model (hysteresis.chains; piezo-narx export).

One one-axis envelope chain per input, each written by the one-axis emitter
(hysteresis.export.HysteresisEmitter) under its own prefix (hc0_, hc1_, ...: constants HC0_...),
mixed by the coupling: y = M z, z_j = chain_j(u_j). The state vector is the chains' kernel states
end to end, as ChainsStepper.state; u and y are vectors of PNR_N_INPUTS volts and PNR_N_OUTPUTS
metres. The inverse stays one-axis (the writer leaves it out); control/axes.py inverts the chains
one by one after M^-1 in Python.
"""
import numpy as np

from ...export.c_code import Emitter, ExportError, c_array
from .export import HysteresisEmitter, input_history


class ChainsEmitter(Emitter):
    """The C of a HysteresisChains: each chain's one-axis C, the coupling, step and history."""

    max_inputs = 64
    max_outputs = 64
    targets = ('output',)
    history_note = ('u_past: the last PNR_NU input rows, fed from rest (the state is a function '
                    'of the input history); y_past is not used')

    def __init__(self, model, prefix: str = 'hc'):
        """Emitter of a chains model; its C names start with `prefix` (an ensemble's member)."""
        super().__init__(model)
        self.prefix = prefix
        self.chains = [HysteresisEmitter(c, prefix=f'{prefix}{j}', quasi_static=False)
                       for j, c in enumerate(model.chains_)]
        #: Where each chain's state starts in the state vector, and the end.
        self.starts = np.cumsum([0] + [e.state_size for e in self.chains]).tolist()

    @property
    def state_size(self) -> int:
        """Return the chains' state sizes summed."""
        return int(self.starts[-1])

    @property
    def state_layout(self) -> list:
        """Return the layout lines for the header: each chain's parts at their place."""
        lines = []
        for j, e in enumerate(self.chains):
            lines.append(f'chain {j} (input {j}), x[{self.starts[j]} .. '
                         f'{self.starts[j + 1] - 1}]:')
            lines += ['  ' + ln for ln in e.layout_lines(self.starts[j])]
        return lines + ["normalised by each chain's own scales, as the Python kernels",
                        '(ChainsStepper.state); rest is all zeros; y = HC_M z']

    def state_vector(self, stepper) -> np.ndarray:
        """Return the chains' kernel states of a ChainsStepper, end to end."""
        return np.concatenate([e.state_vector(s) for e, s in zip(self.chains, stepper.chains)])

    def dc_gain(self) -> float:
        """Refuse: the inverse's quasi-static target is one-axis only."""
        raise ExportError('the chains model has no quasi-static target in C (one chain each: '
                          'export a chain alone for its inverse)')

    def _step(self) -> str:
        n, p = self.n_out, self.prefix
        calls = [f'    z[{j}] = {p}{j}_step(&x[{self.starts[j]}], u[{j}]);'
                 for j in range(len(self.chains))]
        return '\n'.join(
            ['/* Each chain on its input and its part of the state x, then y = M z (m). */',
             f'static void {p}_step(double *x, const double *u, double *y)', '{',
             f'    double z[{n}];', '    int i, j;'] + calls +
            [f'    for (i = 0; i < {n}; ++i) {{', '        y[i] = 0.0;',
             f'        for (j = 0; j < {n}; ++j) {{',
             f'            y[i] += {p.upper()}_M[i][j] * z[j];',
             '        }', '    }', '}'])

    def model_definitions(self) -> str:
        """Return the coupling, every chain's model and `<prefix>_step` on a state array."""
        coupling = c_array(f'{self.prefix.upper()}_M', self.model.coupling_,
                           f'coupling: y_i = sum_j {self.prefix.upper()}_M[i][j] z_j, z_j chain '
                           "j's output (m)")
        return '\n\n'.join([coupling] + [e.model_definitions() for e in self.chains] +
                           [self._step()])

    def definitions(self) -> str:
        """Return the model, pnr_step_ and pnr_init_history_."""
        step = '\n'.join(['static void pnr_step_(pnr_state_t *s, const double *u, double *y)',
                          '{', f'    {self.prefix}_step(s->x, u, y);', '}'])
        return '\n\n'.join([self.model_definitions(), step,
                            input_history(self.nu, self.n_in, self.n_out)])
