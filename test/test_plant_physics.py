"""
Physics of the simulated cantilever: hysteresis, rate independence, creep, resonance, sensor.

Also the amplifier limits. Figures are measured on short signals; the tolerances are stated next to
each check and in docs/plant.md.
"""
import numpy as np
import pytest
from scipy import signal as sps

from piezo_narx_ros.plant import PiezoCantilever, PlantParams, generate, load_plant_params
# Loop width as defined in docs/plant.md; one sine period after one period of settling.
from piezo_narx_ros.plant.figures import loop_width, sine_period as sine_loop

FS = 2000.0


@pytest.fixture(scope='module')
def params():
    return load_plant_params()


def test_slow_sine_loop_is_hysteretic_with_design_width(params):
    # Design: loop width 13 % of the stroke at +/-100 V (config/plant.yaml); tolerance +/-2 points.
    u, y, _ = sine_loop(params, 100.0, 0.1)
    width, _, up, down = loop_width(u, y)
    assert 0.11 <= width <= 0.15, width
    # Counter-clockwise piezo loop: the descending branch lies above the ascending one everywhere.
    assert np.all(down - up > 0)
    # Stroke about 0.40 um/V (peak-to-peak deflection / peak-to-peak voltage), within 10 %.
    gain = np.ptp(y) / np.ptp(u)
    assert 0.36e-6 <= gain <= 0.44e-6, gain


def test_loop_widens_with_amplitude(params):
    small = loop_width(*sine_loop(params, 25.0, 1.0)[:2])[0]
    large = loop_width(*sine_loop(params, 100.0, 1.0)[:2])[0]
    assert 0.04 <= small <= 0.08 and large > small + 0.04, (small, large)


def test_loop_nearly_rate_independent_between_0p1_and_1_hz(params):
    # Bouc-Wen is rate-independent; creep (slow) and the mode (fast) make it inexact. Measured with
    # this config: width differs by < 0.5 point and branches by < 1.5 % of the stroke.
    u_s, y_s, _ = sine_loop(params, 100.0, 0.1)
    u_f, y_f, _ = sine_loop(params, 100.0, 1.0)
    w_s, c, up_s, down_s = loop_width(u_s, y_s)
    w_f, _, up_f, down_f = loop_width(u_f, y_f)
    assert abs(w_s - w_f) < 0.005, (w_s, w_f)
    branch_gap = max(np.max(np.abs(up_s - up_f)), np.max(np.abs(down_s - down_f))) / np.ptp(y_s)
    assert branch_gap < 0.015, branch_gap
    # ... but not identical: creep does make a difference one could measure.
    assert branch_gap > 1e-4


def test_creep_after_step_follows_configured_elements(params):
    # 50 V step held 20 s. Between t1 = 0.05 s (mode settled) and t2 = 20 s the configured creep
    # elements predict
    # y(t2)/y(t1) - 1 = sum k_i (e^-t1/tau_i - e^-t2/tau_i) / (1 + sum k_i (1 - e^-t1/tau_i)).
    seconds, t1, t2 = 20.0, 0.05, 20.0
    u = generate('steps', FS, seconds, 50.0, levels=[1.0])
    res = PiezoCantilever(params, FS, seed=1).run(u)
    k = np.asarray(params.creep_gains)
    tau = np.asarray(params.creep_time_constants)
    expected = (np.sum(k * (np.exp(-t1 / tau) - np.exp(-t2 / tau)))
                / (1 + np.sum(k * (1 - np.exp(-t1 / tau)))))
    win = int(0.01 * FS)  # 10 ms averages of the measured output beat the sensor noise
    i1, i2 = int(t1 * FS), int(t2 * FS) - 1
    y1 = res.y[i1 - win // 2:i1 + win // 2].mean()
    y2 = res.y[i2 - win:i2 + 1].mean()
    drift = y2 / y1 - 1.0
    assert drift > 0  # creeps on in the direction of the step
    assert drift == pytest.approx(expected, rel=0.05), (drift, expected)
    # Close to logarithmic: the drift per decade (0.2->2 s vs 2->20 s) agrees within 30 %.
    yt = res.y_true
    d1 = yt[int(2 * FS)] - yt[int(0.2 * FS)]
    d2 = yt[-1] - yt[int(2 * FS)]
    assert d2 == pytest.approx(d1, rel=0.3), (d1, d2)


def test_chirp_shows_resonance_at_configured_frequency(params):
    u = generate('chirp', FS, 8.0, 10.0, f0=100.0, f1=990.0)
    y = PiezoCantilever(params, FS, seed=2).run(u).y
    f, puu = sps.welch(u, FS, nperseg=2048)
    _, puy = sps.csd(u, y, FS, nperseg=2048)
    band = (f > 150) & (f < 900)  # inside the sweep, where the input has power
    gain = np.abs(puy[band] / puu[band])
    f_peak = f[band][np.argmax(gain)]
    assert f_peak == pytest.approx(params.mode_frequency, rel=0.02), f_peak
    # Lightly damped: peak well above the low-frequency gain (Q = 1/(2 zeta) = 25 at zeta = 0.02,
    # minus amplifier and sensor roll-off and the finite resolution of the estimate).
    low = np.median(gain[f[band] < 300])
    assert gain.max() / low > 8


def test_measured_noise_has_configured_std_and_quantisation(params):
    # At rest the measurement is pure sensor noise; y_true stays exactly 0.
    res = PiezoCantilever(params, FS, seed=3).run(np.zeros(40000))
    assert np.all(res.y_true == 0.0)
    assert np.std(res.y) == pytest.approx(params.noise_std, rel=0.03)  # std of std: 0.35 % here
    steps = res.y / params.quantisation
    assert np.allclose(steps, np.round(steps), atol=1e-6)
    # White: lag-1..5 autocorrelation inside +/-4/sqrt(N).
    e = res.y - res.y.mean()
    rho = [np.dot(e[:-k], e[k:]) / np.dot(e, e) for k in range(1, 6)]
    assert np.max(np.abs(rho)) < 4 / np.sqrt(e.size)


def test_measurement_is_sensor_view_of_true_deflection(params):
    u = generate('multisine', FS, 2.0, 100.0, seed=4)
    res = PiezoCantilever(params, FS, seed=4).run(u)
    err = res.y - res.y_true
    # Error = noise + sensor lag: small against the stroke, larger than the noise alone is not
    # needed.
    assert np.std(err) < 3 * params.noise_std + 0.002 * np.std(res.y_true)
    assert np.std(err) > 0.5 * params.noise_std


def test_amplifier_saturates_and_slew_limits(params):
    fs = FS
    u = np.concatenate([np.zeros(20), np.full(200, 300.0), np.full(200, -300.0)])
    res = PiezoCantilever(params, fs, seed=0).run(u)
    ua = res.u_applied
    assert ua.max() <= params.v_max + 1e-9 and ua.min() >= params.v_min - 1e-9
    assert ua[210] == pytest.approx(params.v_max, abs=1e-6)
    assert ua[-1] == pytest.approx(params.v_min, abs=1e-6)
    max_step = params.slew_rate / fs
    assert np.max(np.abs(np.diff(ua))) <= max_step * (1 + 1e-9)
    # The 0 -> 200 V edge is slew-bound: a ramp of slew/fs = 50 V per sample, then the first-order
    # tail of the last few volts.
    assert ua[20:23] == pytest.approx([max_step, 2 * max_step, 3 * max_step], rel=1e-9)
    assert 0.9 * params.v_max < ua[23] < params.v_max
    # A non-saturated small step is bandwidth-bound instead: first-order, 1 - e^-(2 pi f_a / fs)
    # at k=0.
    small = PiezoCantilever(params, fs).run(np.full(5, 1.0)).u_applied
    assert small[0] == pytest.approx(1 - np.exp(-2 * np.pi * params.amp_bandwidth / fs), rel=1e-9)


def test_no_noise_no_quantisation_gives_true_sensor_signal():
    p = PlantParams(noise_std=0.0, quantisation=0.0, sensor_bandwidth=1e7)
    res = PiezoCantilever(p, FS).run(generate('sine', FS, 1.0, 50.0, freq=5.0))
    assert np.max(np.abs(res.y - res.y_true)) < 1e-3 * np.ptp(res.y_true)
