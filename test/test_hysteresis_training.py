"""How the hysteresis-operator NARX's training spends its work (hysteresis.training.train)."""
import numpy as np

from piezo_narx_ros.ident.hysteresis import kernels as hk
from piezo_narx_ros.ident.hysteresis import training as ht

FS = 2000.0


def held_walk(n=3000, hold=(1000, 2800), seed=0):
    """Return a normalised random walk held constant over samples hold[0] to hold[1]."""
    rng = np.random.default_rng(seed)
    u = np.clip(np.cumsum(rng.normal(0.0, 0.01, n)), -1.0, 1.0)
    u[hold[0]:hold[1]] = u[hold[0] - 1]
    return u


def test_jacobian_carries_no_subnormal_numbers():
    # While the input holds, the drive increments are 0 and their columns of J decay with the
    # output pole (0.3 per sample here) through the subnormal range: a matrix product with
    # subnormal entries ran 3x slower. They are 0 instead (their products vanish in J^T J
    # beside the normal entries anyway).
    un = held_walk()
    yn = np.tanh(un)
    radii = (np.arange(4) / 4) ** 2
    H, q, L, na, nb = 3, 1, 2, 1, 1
    theta, _ = ht.initial_theta([un], [yn], radii, L, H, q, 0, na, nb,
                                np.random.default_rng(0))
    d = radii.size + L + q
    lay, P = hk.layout(H, d, q, 0, na, nb)
    theta[lay['a'][0]] = -0.3
    W1, b1, w2, c, dh, dr, g, a, b, yo = ht._split_theta(theta, lay, H, d, q)
    _, (F, S, JD, DF, SR, DFK, SRK) = ht.operator_features(un, radii, L, dh, dr, with_jac=True)
    J = np.empty((un.size, P))
    hk.jacobian(F, S, JD, DF, SR, dr[0], DFK, SRK, dr[1], W1, b1, w2, c, g, np.zeros(0), a, b,
                yo, J)
    lag = [h * d + radii.size for h in range(H)]          # a first increment's columns
    assert np.all(J[2000:2700, lag] == 0.0)               # decayed during the hold
    assert np.all(J[:1000, lag] != 0.0)
    assert np.all((J == 0.0) | (np.abs(J) >= np.finfo(np.float64).tiny))


def test_training_computes_each_free_run_and_its_features_once(monkeypatch):
    # Each Jacobian is built from the operator features of the free run that accepted its
    # parameters (the same arrays, not a recomputation), and no parameter vector is run twice.
    forward, jacobian = hk.forward, hk.jacobian
    runs, features_seen, jac_features = [], [], []

    def spy_forward(F, S, *params):
        runs.append(b''.join(np.asarray(p, dtype=np.float64).tobytes() for p in params)
                    + S.tobytes()[:4096])
        features_seen.append(F)
        return forward(F, S, *params)

    def spy_jacobian(F, *rest):
        jac_features.append(F)
        return jacobian(F, *rest)

    monkeypatch.setattr(hk, 'forward', spy_forward)
    monkeypatch.setattr(hk, 'jacobian', spy_jacobian)
    un = held_walk(1500, (600, 700), seed=2)
    yn = np.tanh(1.5 * un) + 0.1 * un
    lam = np.exp(-1.0 / (np.array([0.01, 0.1]) * FS))
    theta, info = ht.train([un], [yn], (np.arange(4) / 4) ** 2, 2, 3, 1, lam, 2, 2, seed=0,
                           max_iter=6)
    assert info['iterations'] >= 3 and len(jac_features) == info['iterations']
    assert len(runs) == len(set(runs))
    assert all(any(F is seen for seen in features_seen) for F in jac_features)
