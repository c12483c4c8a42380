"""
C emitter of an ensemble (ident/ensemble/model.py; piezo-narx export): the mean of its members' C.

Each member is written by its family's emitter under its own prefix (e0_, e1_, ...; a chains
member e0c0_, ...), as the chains model writes its chains: the envelope family's members only
(one-axis HysteresisNARX, HysteresisChains), whose emitters take a prefix. The state vector is
the members' states end to end, as EnsembleStepper.state (without the offset, which the writer
keeps apart as every family's). No C inverse (PNR_HAS_INVERSE 0).
"""
import numpy as np

from ...export.c_code import Emitter, ExportError
from ..hysteresis.chains_export import ChainsEmitter
from ..hysteresis.export import HysteresisEmitter


def member_emitter(model, prefix: str):
    """Return a member's emitter under `prefix`, or ExportError for a family without prefixes."""
    if model.kind == 'hysteresis_narx' and hasattr(model, 'chains_'):
        return ChainsEmitter(model, prefix=prefix + 'c')
    if model.kind == 'hysteresis_narx' and model.n_in == model.n_out == 1:
        return HysteresisEmitter(model, prefix=prefix, quasi_static=False)
    raise ExportError(f'the C export of an ensemble takes envelope members only (one-axis or a '
                      f'chain per axis), not {model!r}')


class EnsembleEmitter(Emitter):
    """The C of an EnsembleModel: each member's C, pnr_step_ their mean, the input history."""

    max_inputs = 64
    max_outputs = 64
    targets = ('output',)
    history_note = ('u_past: the last PNR_NU input rows, each member fed its own last ones from '
                    "rest (the members' states are functions of the input history); y_past is "
                    'not used')

    def __init__(self, model):
        super().__init__(model)
        self.members = [member_emitter(m, f'e{i}') for i, m in enumerate(model.members)]
        #: Where each member's state starts in the state vector, and the end.
        self.starts = np.cumsum([0] + [e.state_size for e in self.members]).tolist()

    @property
    def state_size(self) -> int:
        """Return the members' state sizes summed."""
        return int(self.starts[-1])

    @property
    def state_layout(self) -> list:
        """Return the layout lines for the header: each member's at its place."""
        lines = []
        for i, e in enumerate(self.members):
            lines.append(f'member {i} ({e.kind}), x[{self.starts[i]} .. '
                         f'{self.starts[i + 1] - 1}]')
        return lines + ["each in its member's own layout (EnsembleStepper.state); rest is all "
                        'zeros; y = mean of the members']

    def state_vector(self, stepper) -> np.ndarray:
        """Return the members' C states of an EnsembleStepper, end to end."""
        return np.concatenate([e.state_vector(s) for e, s in zip(self.members, stepper.members)])

    def dc_gain(self) -> float:
        """Refuse: no quasi-static target (no C inverse of an ensemble)."""
        raise ExportError('an ensemble has no quasi-static target in C')

    def _calls(self, u: str) -> list:
        """C lines adding each member's output for the input vector `u` into y."""
        n, lines = self.n_out, []
        for i, e in enumerate(self.members):
            x = f'&s->x[{self.starts[i]}]'
            if isinstance(e, ChainsEmitter):
                lines += [f'    {e.prefix}_step({x}, {u}, m);',
                          f'    for (k = 0; k < {n}; ++k) {{', '        y[k] += m[k];', '    }']
            else:
                lines.append(f'    y[0] += {e.prefix}_step({x}, {u}[0]);')
        return lines

    def _step(self) -> str:
        n = self.n_out
        return '\n'.join(
            ['/* Every member on its part of the state, y = the mean of their outputs (m). */',
             'static void pnr_step_(pnr_state_t *s, const double *u, double *y)', '{',
             f'    double m[{n}];', '    int k;', f'    for (k = 0; k < {n}; ++k) {{',
             '        y[k] = 0.0;', '    }', '    (void)m;'] + self._calls('u') +
            [f'    for (k = 0; k < {n}; ++k) {{',
             f'        y[k] *= {1.0 / len(self.members)!r};', '    }', '}'])

    def _history(self) -> str:
        """pnr_init_history_: rest, then each member fed its own last nu input rows."""
        n_in, nu = self.n_in, self.nu
        lines = ['/* Rest, then each member its last nu_i input rows of u_past (oldest first), as',
                 ' * EnsembleStepper.reset; y_past is not used. */',
                 'static void pnr_init_history_(pnr_state_t *s, const double *u_past,',
                 '                              const double *y_past)', '{',
                 f'    double m[{self.n_out}];', '    int r;', '    (void)y_past;',
                 '    (void)m;', '    (void)r;', '    (void)u_past;', '    pnr_init(s);']
        for i, (e, member) in enumerate(zip(self.members, self.model.members)):
            if not member.nu:
                continue
            x = f'&s->x[{self.starts[i]}]'
            row = f'&u_past[r * {n_in}]'
            call = (f'        {e.prefix}_step({x}, {row}, m);' if isinstance(e, ChainsEmitter)
                    else f'        (void){e.prefix}_step({x}, u_past[r]);')
            lines += [f'    for (r = {nu - member.nu}; r < {nu}; ++r) {{', call, '    }']
        return '\n'.join(lines + ['}'])

    def definitions(self) -> str:
        """Return every member's model, pnr_step_ and pnr_init_history_."""
        return '\n\n'.join([e.model_definitions() for e in self.members] +
                           [self._step(), self._history()])
