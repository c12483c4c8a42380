"""
The envelope family's model file, written and read back with every check.

Its structure, normalisation and training blocks and its named weight arrays, one-axis and
several-axes (layout MIMO_LAYOUT). HysteresisNARX takes these methods from HysteresisFile; other
layouts of the same kind (the chains of hysteresis/chains.py) register their class in LAYOUTS.
"""
import math

import numpy as np

from ...errors import ConfigError, DataError, ModelFileError
from .. import document
from ..base import check_parameters
from . import mimo as hm

# Weight arrays of the model file, in the order of the parameter vector theta_.
_FILE_PARTS = ('W1', 'b1', 'w2', 'c', 'duhem', 'drive', 'g', 'a', 'b', 'y_off')
#: structure.layout of a several-axes model file (hysteresis.mimo).
MIMO_LAYOUT = 'operators per input, common-denominator MIMO dynamics'
#: Other structure.layout values of this kind -> their class, registered by their own modules
#: (ident/hysteresis/chains.py; ident/families.py imports it).
LAYOUTS: dict = {}
# Structure keys that are constructor arguments.
_FILE_STRUCTURE = ('hidden', 'n_plays', 'n_duhem', 'n_lags', 'na', 'nb', 'creep_taus')


class HysteresisFile:
    """The model-file methods of HysteresisNARX (DynamicModel's file interface)."""

    def file_document(self):
        """Return the envelope family's blocks of the model file (structure, scales, training)."""
        if self.mimo_ is not None:
            return self._mimo_document()
        return {'structure': {'kind': self.kind, 'hidden': self.hidden, 'n_plays': self.n_plays,
                              'n_duhem': self.n_duhem, 'n_lags': self.n_lags, 'na': self.na,
                              'nb': self.nb, 'creep_taus': list(self.creep_taus),
                              'activation': self.activation, 'nu': self.nu, 'ny': self.ny,
                              'n_params': self.n_params,
                              **({'amplifier': True} if self.amplifier_ else {})},
                'normalisation': {'u_scale': self.u_scale_, 'y_scale': self.y_scale_},
                'training': {'seed': self.seed, 'options': self.params_dict(),
                             'info': self.training_info_,
                             'method': 'output-error Levenberg-Marquardt'}}

    def _file_shapes(self):
        """Return {weight array name: shape} of the model file (theta_ split by its layout)."""
        lay, _ = self._layout()
        shapes = {k: (hi - lo,) for k, (lo, hi) in lay.items()}
        shapes['W1'] = (self.hidden, self.n_inputs)
        shapes['duhem'] = (self.n_duhem, 6)
        return lay, shapes

    def file_weights(self):
        """Return theta_ split into its named parts (shapes as in the layout) and radii_."""
        if self.mimo_ is not None:
            return self.mimo_.arrays()
        lay, shapes = self._file_shapes()
        out = {k: self.theta_[lo:hi].reshape(shapes[k]) for k, (lo, hi) in lay.items()}
        out['radii'] = self.radii_
        return out

    @classmethod
    def from_file_document(cls, doc, arrays, name, wpath, fs):
        """Return the HysteresisNARX of a model file (see DynamicModel.from_file_document)."""
        struct = document.get(doc, 'structure', name, (dict,))
        if struct.get('layout') == MIMO_LAYOUT:
            return cls._mimo_from_document(doc, arrays, name, wpath, fs)
        other = LAYOUTS.get(struct.get('layout'))
        if other is not None:      # a structure of its own module (hysteresis.chains)
            return other.from_file_document(doc, arrays, name, wpath, fs)
        missing = [k for k in _FILE_STRUCTURE if k not in struct]
        if missing:
            raise ModelFileError(f'{name}: missing key {"structure." + missing[0]!r}')
        try:
            values = check_parameters(cls, {k: struct[k] for k in _FILE_STRUCTURE})
        except ConfigError as exc:
            raise ModelFileError(f'{name}: structure.{exc}') from None
        act = document.get(doc, 'structure.activation', name, (str,))
        if act != cls.activation:
            raise ModelFileError(f'{name}: unsupported activation {act!r} (only logistic)')
        if fs is None or not math.isfinite(fs):
            raise ModelFileError(f'{name}: a hysteresis_narx model needs a finite fs (its creep '
                                 f'time constants are in seconds), got {fs!r}')
        u_scale = document.get(doc, 'normalisation.u_scale', name, (int, float))
        y_scale = document.get(doc, 'normalisation.y_scale', name, (int, float))
        if not (math.isfinite(u_scale) and math.isfinite(y_scale) and u_scale > 0
                and y_scale > 0):
            raise ModelFileError(f'{name}: normalisation u_scale and y_scale must be finite '
                                 'and > 0')
        training = document.training_block(doc)
        seed = training.get('seed', 0)
        model = cls(**values, seed=seed if isinstance(seed, int) and seed >= 0 else 0)
        # Written only by a model whose drive has a bandwidth (older files: a slew limit alone).
        amplifier = struct.get('amplifier', False)
        if not isinstance(amplifier, bool):
            raise ModelFileError(f'{name}: structure.amplifier must be true or false, got '
                                 f'{amplifier!r}')
        model.amplifier_ = amplifier
        _, shapes = model._file_shapes()
        theta = np.concatenate([document.weight_array(arrays, k, shapes[k], wpath).ravel()
                                for k in _FILE_PARTS])
        radii = document.weight_array(arrays, 'radii', (model.n_plays,), wpath)
        model.set_theta(theta, u_scale, y_scale, radii, fs)
        if np.any(np.abs(model.output_poles) >= 1.0):
            raise ModelFileError(f'{wpath}: the output dynamics are unstable (a root of A(q) '
                                 f'has modulus {np.max(np.abs(model.output_poles)):.4f} >= 1)')
        model.training_info_ = training.get('info') or {}
        return model

    def _mimo_document(self):
        p = self.mimo_
        return {'structure': {'kind': self.kind, 'layout': MIMO_LAYOUT,
                              'mimo_order': self.mimo_order, 'n_features': p.n_features,
                              'local_models': p.n_local,
                              'u_radii': list(hm.U_RADII), 'y_radii': list(hm.Y_RADII),
                              'env_tau_s': hm.ENV_TAU_S, 'nu': self.nu, 'ny': self.ny,
                              'n_params': self.n_params},
                'normalisation': {'u_scale': [float(v) for v in p.u_scale],
                                  'y_scale': [float(v) for v in p.y_scale]},
                'training': {'seed': self.seed, 'options': self.params_dict(),
                             'info': self.training_info_,
                             'method': 'frequency-domain denominator, output-error least '
                                       'squares numerators'}}

    @classmethod
    def _mimo_from_document(cls, doc, arrays, name, wpath, fs):
        """Return the several-axes HysteresisNARX of a model file (layout MIMO_LAYOUT)."""
        struct = doc['structure']
        order = struct.get('mimo_order')
        try:
            values = check_parameters(cls, {'mimo_order': order})
        except ConfigError as exc:
            raise ModelFileError(f'{name}: structure.{exc}') from None
        if (list(struct.get('u_radii', ())) != list(hm.U_RADII)
                or list(struct.get('y_radii', ())) != list(hm.Y_RADII)
                or struct.get('env_tau_s') != hm.ENV_TAU_S):
            raise ModelFileError(f'{name}: the several-axes operators (u_radii, y_radii, '
                                 "env_tau_s) differ from this reader's")
        if fs is None or not math.isfinite(fs) or fs <= 0:
            raise ModelFileError(f'{name}: a hysteresis_narx model needs a finite fs, got {fs!r}')
        n = values['mimo_order']
        shapes = {'mimo_a': (n,), 'mimo_u_scale': None, 'mimo_y_scale': None,
                  'mimo_env_w': None, 'mimo_B1': None, 'mimo_B': None, 'mimo_state_mean': None,
                  'mimo_state_cov': None, 'mimo_resid_rms': None}
        got = {}
        for key, shape in shapes.items():
            if key not in arrays:
                raise ModelFileError(f'{wpath}: missing weight array {key!r}')
            got[key] = np.asarray(arrays[key], dtype=np.float64)
            if shape is not None and got[key].shape != shape:
                raise ModelFileError(f'{wpath}: {key} must have shape {shape}, got '
                                     f'{got[key].shape}')
            if not np.all(np.isfinite(got[key])):
                raise ModelFileError(f'{wpath}: {key} holds non-finite values')
        # Local output models (several amplitudes): optional, checked by from_arrays.
        got.update({key: np.asarray(arrays[key], dtype=np.float64) for key in hm.LOCAL_ARRAYS
                    if key in arrays})
        try:
            parts = hm.MimoParts.from_arrays(got, math.exp(-1.0 / (hm.ENV_TAU_S * fs)))
        except (DataError, IndexError, ValueError) as exc:
            raise ModelFileError(f'{wpath}: {exc}') from None
        if np.any(np.abs(parts.poles()) >= 1.0):
            raise ModelFileError(f'{wpath}: the output dynamics are unstable (a root of A(q) '
                                 f'has modulus {np.max(np.abs(parts.poles())):.4f} >= 1)')
        training = document.training_block(doc)
        model = cls(mimo_order=n)
        model.mimo_ = parts
        model.n_in_, model.n_out_ = parts.n_in, parts.n_out
        model.output_2d_ = True
        model.fs = float(fs)
        model.u_scale_ = float(np.max(parts.u_scale))
        model.y_scale_ = float(np.max(parts.y_scale))
        model.training_info_ = training.get('info') or {}
        return model
