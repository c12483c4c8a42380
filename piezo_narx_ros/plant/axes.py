"""
Plants of several axes driven by a command vector: independent cantilevers or a coupled stage.

`AxisPlants` steps one PiezoCantilever per axis (the simulator of one axis, or of several that do
not interact). `CoupledCantilever` is a two-axis (or more) piezo cantilever whose axes couple: each
axis has its own actuator chain (amplifier, hysteresis, creep, bending mode, sensor low-pass, from
its own PlantParams), and the stage mixes the chains' deflections through a coupling matrix C
(m/m, 1 on the diagonal): driving one axis moves the other by C[i, j] of its own deflection, with
the same dynamics (a bimorph bending out of plane also bends in plane). Each axis's sensor then
adds its own noise and quantisation to the mixed deflection. config/plant_2axis.yaml holds one.

Both give `step(u)` (one command vector, V) and `run(U)` ((N, n_axes) commands) with the same
numbers to the last bit, so a node may answer a batch with one run() call.
"""
from __future__ import annotations

import numpy as np

from piezo_narx_ros.axis_names import distinct_names
from piezo_narx_ros.errors import ConfigError, DataError
from piezo_narx_ros.plant.params import load_plant_params, plant_params_from, read_yaml_mapping
from piezo_narx_ros.plant.piezo import _NOISE_BLOCK, _NOISE_STREAM, PiezoCantilever


class AxisPlants:
    """
    One PiezoCantilever per axis, stepped together; axes do not interact.

    plants: {axis name: PiezoCantilever}, in axis order.
    """

    def __init__(self, plants: dict):
        if not plants:
            raise ConfigError('a plant needs at least one axis')
        self.plants = dict(plants)
        self.axes = tuple(self.plants)
        self._chain = list(self.plants.values())

    @property
    def n_axes(self) -> int:
        return len(self.axes)

    def step(self, u) -> tuple[list[float], list[float]]:
        """One sample: command per axis (V) -> (measured m per axis, applied V per axis)."""
        y, ua = [], []
        for plant, x in zip(self._chain, u):
            y_meas, _, u_app = plant.step(x)
            y.append(y_meas)
            ua.append(u_app)
        return y, ua

    def run(self, u) -> tuple[np.ndarray, np.ndarray]:
        """(N, n_axes) commands, V -> (measured (N, n_axes) m, applied (N, n_axes) V)."""
        u = _commands(u, self.n_axes)
        y = np.empty_like(u)
        ua = np.empty_like(u)
        for i, plant in enumerate(self._chain):
            r = plant.run(u[:, i])
            y[:, i], ua[:, i] = r.y, r.u_applied
        return y, ua

    def run_checked(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """
        run() for commands already checked: (N, n_axes) float64 V, all finite.

        The same numbers and state as run(u), without its checks and copies (a node's batch
        path). The outputs may be transposed views ((n_axes, N) arrays seen as (N, n_axes)).
        """
        n = u.shape[0]
        if len(self._chain) == 1:
            y, ua = np.empty((n, 1)), np.empty((n, 1))
            self._chain[0].run_into(np.ascontiguousarray(u[:, 0]), y[:, 0], ua[:, 0])
            return y, ua
        y, ua = np.empty((len(self._chain), n)), np.empty((len(self._chain), n))
        for i, plant in enumerate(self._chain):
            plant.run_into(np.ascontiguousarray(u[:, i]), y[i], ua[i])
        return y.T, ua.T

    def hold(self, u, count: int) -> None:
        """Advance `count` samples with the command vector u held (a gap in the commands)."""
        if count > 0:
            self.run(np.tile(np.asarray(u, dtype=np.float64), (count, 1)))

    def warm_up(self) -> None:
        """Load the compiled kernels now (not on the first command) and go back to rest."""
        for plant in self._chain:
            plant.step(0.0)          # the one-sample kernel and the batch one
            plant.run(np.zeros(2))
            plant.reset()


class CoupledCantilever(AxisPlants):
    """
    Axes with their own actuator chains whose deflections the stage mixes (module docstring).

    params: one PlantParams per axis; coupling: (n, n) matrix C, deflection of axis i =
    sum_j C[i, j] * deflection of chain j (m/m); fs: Hz; seed: sensor noise seed.
    """

    def __init__(self, axes, params, coupling, fs: float = 2000.0, seed: int = 0):
        axes = tuple(axes)
        c = np.array(coupling, dtype=np.float64)
        n = len(axes)
        if len(params) != n or c.shape != (n, n):
            raise ConfigError(f'{n} axes need {n} plant parameter sets and an {n} x {n} coupling '
                              f'matrix, got {len(params)} and {c.shape}')
        if not np.isfinite(c).all() or not (np.diag(c) == 1.0).all():
            raise ConfigError('coupling must be finite with 1 on its diagonal (each axis moves '
                              'by its own deflection)')
        # The chains are noise-free and unquantised: the sensors act after the stage mixes.
        super().__init__({a: PiezoCantilever(p.replace(noise_std=0.0, quantisation=0.0), fs=fs,
                                             seed=seed)
                          for a, p in zip(axes, params)})
        self.params = tuple(params)
        self.coupling = c
        self.seed = int(seed)
        self._std = np.array([p.noise_std for p in params])
        self._quant = np.array([p.quantisation for p in params])
        self.reset()

    def reset(self) -> None:
        """Every chain to rest, the noise generator re-seeded."""
        for plant in self._chain:
            plant.reset()
        self._rng = np.random.Generator(np.random.PCG64([self.seed, _NOISE_STREAM, 2]))
        self._noise = np.empty((0, self.n_axes))
        self._pos = 0

    def warm_up(self) -> None:
        super().warm_up()
        self.reset()

    def _draw(self, n: int) -> np.ndarray:
        """Next n rows of standard normals (one per axis), from blocks of _NOISE_BLOCK rows."""
        parts, need = [], n
        while need:
            if self._pos >= self._noise.shape[0]:
                self._noise = self._rng.standard_normal((_NOISE_BLOCK, self.n_axes))
                self._pos = 0
            take = min(need, self._noise.shape[0] - self._pos)
            parts.append(self._noise[self._pos:self._pos + take])
            self._pos += take
            need -= take
        return parts[0] if len(parts) == 1 else np.concatenate(parts)

    def _sense(self, deflection: np.ndarray) -> np.ndarray:
        """Mixed sensor states (N, n) m -> measured: plus noise, quantised per axis."""
        y = deflection @ self.coupling.T + self._std * self._draw(deflection.shape[0])
        q = self._quant
        return np.where(q > 0.0, q * np.floor(y / np.where(q > 0.0, q, 1.0) + 0.5), y)

    def step(self, u) -> tuple[list[float], list[float]]:
        """One sample: command per axis (V) -> (measured m per axis, applied V per axis)."""
        y, ua = super().step(u)
        return self._sense(np.array([y])).ravel().tolist(), ua

    def run(self, u) -> tuple[np.ndarray, np.ndarray]:
        """(N, n_axes) commands, V -> (measured (N, n_axes) m, applied (N, n_axes) V)."""
        y, ua = super().run(u)
        return self._sense(y), ua

    def run_checked(self, u: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """run_checked of the chains, then the stage's mixing and sensors, as run()."""
        y, ua = super().run_checked(u)
        return self._sense(y), ua

    def run_with_truth(self, u) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """run(u), also returning the stage's true deflection: (measured, applied, true) (N, n)."""
        chain, ua = AxisPlants.run(self, u)
        return self._sense(chain), ua, self.true_deflection(chain)

    def true_deflection(self, chain_deflection) -> np.ndarray:
        """Mix chain deflections (N, n) m through the coupling: the stage's true deflection."""
        return np.asarray(chain_deflection) @ self.coupling.T


def _commands(u, n_axes: int) -> np.ndarray:
    """(N, n_axes) float64 volts; DataError on a wrong shape."""
    u = np.ascontiguousarray(u, dtype=np.float64)
    if u.ndim == 1 and n_axes == 1:
        u = u[:, None]
    if u.ndim != 2 or u.shape[1] != n_axes:
        raise DataError(f'commands must be (N, {n_axes}) volts, got shape {u.shape}')
    return u


def load_axes_config(path) -> tuple[tuple, list, np.ndarray | None]:
    """
    Read a plant file of one or several axes: (axes, [PlantParams per axis], coupling or None).

    A file with `axes:` (list of names) describes a stage: `plant:` the fields every axis shares
    (config/plant.yaml's), `axis_params: {name: {fields}}` what differs per axis, `coupling:`
    the (n, n) matrix (default: the identity). A file without `axes:` is config/plant.yaml's
    one-axis format (axes () and coupling None: the caller names the axes).
    """
    doc = read_yaml_mapping(path)
    where = f'plant config {path}'
    if 'axes' not in doc:
        return (), [load_plant_params(path)], None
    unknown = sorted(set(doc) - {'axes', 'plant', 'axis_params', 'coupling'})
    if unknown:
        raise ConfigError(f'{where}: unknown key {unknown[0]!r} (axes, plant, axis_params, '
                          'coupling)')
    axes = doc['axes']
    if not isinstance(axes, list) or not distinct_names(axes):
        raise ConfigError(f'{where}: axes must be a list of distinct non-empty names, got '
                          f'{axes!r}')
    base = plant_params_from(doc.get('plant') or {}, where)
    per_axis = doc.get('axis_params') or {}
    if not isinstance(per_axis, dict) or set(per_axis) - set(axes):
        raise ConfigError(f'{where}: axis_params must map names of axes {axes} to parameters')
    params = [plant_params_from(per_axis.get(a) or {}, f'{where}, axis {a}', base)
              for a in axes]
    coupling = doc.get('coupling', np.eye(len(axes)).tolist())
    try:
        c = np.array(coupling, dtype=np.float64)
    except (TypeError, ValueError):
        raise ConfigError(f'{where}: coupling must be a matrix of numbers') from None
    if c.shape != (len(axes), len(axes)) or not np.isfinite(c).all():
        raise ConfigError(f'{where}: coupling must be a finite {len(axes)} x {len(axes)} '
                          f'matrix, got shape {c.shape}')
    return tuple(axes), params, c


def make_axis_plants(axes, path=None, fs: float = 2000.0, seed: int = 0) -> AxisPlants:
    """
    Build the plant a simulator runs: a stage file (`axes:`), or one cantilever per axis.

    axes: the axis names asked for (a stage file's own names win; a different non-default list
    is refused). One-axis files give independent cantilevers, axis i seeded seed + i, as before.
    """
    if path:
        names, params, coupling = load_axes_config(path)
    else:
        names, params, coupling = (), [load_plant_params()], None
    axes = tuple(axes)
    if axes and not distinct_names(axes):
        raise ConfigError(f'axes must be distinct non-empty names, got {list(axes)}')
    if names:
        if axes not in ((), ('x',), names):
            raise ConfigError(f"axes {list(axes)} differ from the plant file's {list(names)}")
        return CoupledCantilever(names, params, coupling, fs=fs, seed=seed)
    return AxisPlants({a: PiezoCantilever(params[0], fs=fs, seed=seed + i)
                       for i, a in enumerate(axes)})
