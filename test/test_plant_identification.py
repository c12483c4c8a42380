"""
Identification on the simulated plant's default record (the paper's 25 s of multisine at 2 kHz).

The verdicts here are the project's defaults: free-run (simulation) residuals of the validation
half, whitened by an AR noise model fitted on the estimation half (NARMAX, Billings ch. 5), judged
with the chance-rate rule (docs/validation.md).

What holds, measured (docs/validation.md "The plant"):
* every ARX(na, nb), 1..10 x 1..10, fails: the hysteresis leaves φu²'ε² at >= 17 x the band;
* NARX 1/1 fails: φuε ~19 x the band (missing input dynamics);
* NARX 4/4 reaches free-run R² ~0.9999 (ARX 0.995), but does NOT pass: its own error (69 nm RMS
  against the noise-free sensor output) is twice the 33 nm sensor noise, so at N = 25,000 the
  tests resolve it (φu²'ε² 18 x the band: the error grows with |u|; φuε 4 x). The paper's
  "NARX passes" needs a model error well below the noise; the last test checks that cause, and
  would have to be turned into a pass test if a process model ever closes that gap.
"""
import pytest

from piezo_narx_ros.record import Record
from piezo_narx_ros.plant import PiezoCantilever, generate, load_plant_params

narx = pytest.importorskip('piezo_narx_ros.ident.narx.model')
from piezo_narx_ros.ident.arx.model import ARXModel  # noqa: E402
from piezo_narx_ros.ident.selection.scoring import evaluate_model, fit_noise_models  # noqa: E402
from piezo_narx_ros.ident.validation.metrics import r2, rmse  # noqa: E402

FS = 2000.0


@pytest.fixture(scope='module')
def record():
    params = load_plant_params()
    u = generate('multisine', FS, 25.0, 100.0, seed=0)
    y = PiezoCantilever(params, FS, seed=0).run(u).y
    # Same command, sensor without noise or quantisation: the output a perfect model would give.
    clean = PiezoCantilever(params.replace(noise_std=0.0, quantisation=0.0), FS, seed=0).run(u).y
    est, val = Record(u=u, y=y, fs=FS, source='plant', y_true=clean).split(0.5)
    return est, val, params.noise_std


def verdicts(model, est, val):
    """Return the default pipeline: tests on whitened simulation residuals (and the raw ones)."""
    noise = fit_noise_models(model, [est])
    out = evaluate_model(model, [val], noise_models=noise)
    return out['tests']['simulation'], out['tests']['raw']['simulation'], noise['simulation']


@pytest.fixture(scope='module')
def narx44(record):
    est, _, _ = record
    return narx.NARXNetwork(4, 4, 10, seed=0).fit(est.u, est.y, fs=FS)


def test_narx_free_run_beats_arx_on_hysteresis(record, narx44):
    est, val, _ = record
    arx = ARXModel(4, 4).fit(est.u, est.y, fs=FS)
    r2_arx = r2(val.y, arx.simulate(val.u, val.y[:arx.n0]), start=arx.n0)
    r2_narx = r2(val.y, narx44.simulate(val.u, val.y[:narx44.n0]), start=narx44.n0)
    assert r2_arx < 0.998            # measured 0.9949: the linear model misses the loop
    assert r2_narx > 0.9998          # measured 0.99992 (noise ceiling 0.99999)
    assert (1 - r2_arx) / (1 - r2_narx) > 20  # error variance at least 20x smaller


def test_every_arx_order_leaves_dynamics_in_its_residuals(record):
    est, val, _ = record
    flagged_hysteresis = 0
    for na in range(1, 11):
        for nb in range(1, 11):
            model = ARXModel(na, nb).fit(est.u, est.y, fs=FS)
            tests, _, _ = verdicts(model, est, val)
            assert not tests['passed'], (na, nb)
            flagged_hysteresis += not tests['tests']['phi_u2e2']['passed']
    assert flagged_hysteresis == 100   # the error variance follows u²: the missing loop


def test_narx_with_too_few_lags_fails(record):
    est, val, _ = record
    model = narx.NARXNetwork(1, 1, 10, seed=0).fit(est.u, est.y, fs=FS)
    tests, _, _ = verdicts(model, est, val)
    assert not tests['passed']
    assert not tests['tests']['phi_ue']['passed']   # measured ~19 x the band


def test_narx_4_4_error_exceeds_the_sensor_noise_so_the_tests_still_see_it(record, narx44):
    # Why NARX 4/4 does not pass here: its free-run error against the noise-free output is
    # larger than the sensor noise, and the AR noise model leaves innovations well above the
    # noise floor; what remains is correlated with the input level (φu²'ε²).
    est, val, sigma = record
    n0 = narx44.n0
    sim = narx44.simulate(val.u, val.y[:n0])
    model_error = rmse(val.y_true, sim, start=n0)
    assert model_error > sigma                  # measured 69 nm vs 33 nm
    tests, raw, noise = verdicts(narx44, est, val)
    assert noise.order > 0 and noise.residual_std > 1.2 * sigma   # measured AR(18), 51 nm
    assert not raw['passed'] and not tests['passed']
    assert not tests['tests']['phi_u2e2']['passed']
