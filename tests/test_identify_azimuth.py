"""Seed 004 signal compression: eq. 1-3 design, compression, Bode, eq. 5/6 fits on the clamped plant."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
from scipy.signal import freqz, lfilter

from ground.identify import azimuth as az

# Seed 004 Tables 1-5, 55 % PWM rows: the deliberately wrong starting point of the fits
PRIOR_55 = {
    "f1x": [1018.79, 97.21, 138.87, 18.70, 0.48, 7.30, 3410.18],
    "f1y": [846.72, 195.17, 115.87, 31.70, 25.03, 4.01, 2453.09],
    "m1z": [685.06, 14.85, 864.03, 4751.23, 229.86],
    "f2x": [846.72, 195.17, 115.87, 31.70, 25.03, 4.01, 2453.09],
    "f2z": [1289.06, 51.75, 120.17, 6.19, 11.49, 8.10, 2712.26],
}


@pytest.fixture(scope="module")
def design():
    return az.design_pseudo_impulse()  # N 18000 at 400 Hz: a = 450 -> 10 Hz band


@pytest.fixture(scope="module")
def rig(vehicle, design):
    """Both joints of unit 0 driven on the clamped plant (75 % of n_max), noise-free."""
    return {axis: az.simulate_fixed_rig(vehicle, design, axis) for axis in ("azimuth", "elevation")}


def test_power_spectrum_and_expansion_filter_are_eq1_and_eq3():
    assert az.power_spectrum(450.0, 450.0, 2.0) == pytest.approx(2.0 / math.e)
    assert az.power_spectrum(0.0, 450.0, 2.0) == 2.0
    assert az.power_spectrum(900.0, 450.0) == pytest.approx(math.exp(-(2.0 ** 12)))
    n = np.array([0.0, 10.0, 300.0])
    H = az.expansion_filter(n, 2100.0)
    assert np.abs(H) == pytest.approx(1.0)
    assert np.angle(H * np.exp(1j * 12 * n ** 2 / 2100.0)) == pytest.approx(0.0, abs=1e-9)
    spec = az.pseudo_impulse_spectrum(64, 10.0, 50.0)
    assert spec[32] == 0
    assert spec[1:32] == pytest.approx(np.conj(spec[33:][::-1]))  # a real signal (eq. 2)


def test_design_meets_the_limits_and_sweeps_as_eq3_says(design, vehicle):
    x = design.rate_rad_s
    assert np.max(np.abs(x)) == pytest.approx(1.0)
    assert np.max(np.abs(design.angle_rad)) <= 0.8 * vehicle.servo.angle_limit + 1e-12
    assert design.band_hz == pytest.approx(450 * 400.0 / 18000)  # 10 Hz, as seed 004 designed
    # the angle command integrates the rate: a[i + 1] - a[i] = rate[i] dt
    assert np.diff(design.angle_rad) * design.rate_hz == pytest.approx(x[:-1])
    # group delay of eq. 3: bin n arrives at 24 n N / (2 pi b) samples, at frequency n fs / N
    n = 300
    centre = int(24 * n * design.n_samples / (2 * math.pi * design.b))
    win = x[centre - 200:centre + 200]  # 1 s
    crossings = np.count_nonzero(np.diff(np.sign(win)) != 0)
    assert crossings / 2 == pytest.approx(n * design.rate_hz / design.n_samples, rel=0.05)


def test_compression_turns_the_pseudo_impulse_back_into_an_impulse(design):
    c = az.compress(design.rate_rad_s, design.n_samples, design.b)
    N = design.n_samples
    P = np.zeros(N)
    P[: N // 2] = az.power_spectrum(np.arange(N // 2), design.a, design.q)
    P[N // 2 + 1:] = P[1: N // 2][::-1]
    assert c == pytest.approx(np.real(np.fft.ifft(P)), abs=1e-12)
    assert np.argmax(np.abs(c)) == 0


def test_frequency_response_is_exact_for_a_known_filter(design):
    b, a = [0.02, 0.01], [1.0, -1.6, 0.7]  # a stable discrete resonance
    u = np.concatenate([design.rate_rad_s, np.zeros(design.n_samples)])
    y = lfilter(b, a, u)
    bode = az.frequency_response(u, y, design.rate_hz, design.band_hz)
    _, h = freqz(b, a, worN=bode.raw_omega_rad_s / design.rate_hz)
    assert bode.raw_magnitude_db == pytest.approx(20 * np.log10(np.abs(h)), abs=1e-6)
    assert bode.raw_omega_rad_s[-1] <= 2 * math.pi * design.band_hz


@pytest.mark.parametrize("row", az.ROWS)
def test_clamped_plant_gives_back_the_75_percent_rows(vehicle, design, rig, row):
    truth = np.array(getattr(vehicle.effects.azimuth_transient, row))
    rec = rig[az.ROW_AXIS[row]]
    scale = vehicle.effects.azimuth_transient.gain_per_newton * rec.thrust_n
    u, y = az.row_signals(rec, row)
    bode = az.frequency_response(u, y, design.rate_hz, design.band_hz)
    # the measured Bode magnitude is the row's eq. 5/6 magnitude times gain_per_newton T
    expect = az.magnitude_db(row, truth, bode.raw_omega_rad_s) + 20 * math.log10(scale)
    err = np.abs(bode.raw_magnitude_db - expect)
    assert np.max(err[bode.raw_omega_rad_s >= 0.1]) < 0.02  # m1z's lowest bin (0.05 rad/s) is 0.05 dB off
    assert np.max(err) < 0.1
    fit = az.fit_row(row, bode, PRIOR_55[row], scale)
    assert fit.correlation >= az.SEED004_CORRELATION_75[row]
    assert fit.correlation > 0.999
    assert np.array(fit.coeffs) == pytest.approx(truth, rel=0.025)
    assert fit.at_bound == ()
    w = np.geomspace(0.1, 2 * math.pi * design.band_hz, 100)
    assert np.max(np.abs(az.magnitude_db(row, fit.coeffs, w) - az.magnitude_db(row, truth, w))) < 0.1


@pytest.mark.slow
def test_a_noisy_rig_still_beats_the_papers_correlation(vehicle, design, rig):
    rng = np.random.default_rng(11)
    for axis, rec in rig.items():
        n = rec.time_s.size
        noisy = dataclasses.replace(
            rec,
            axial_loss_n=rec.axial_loss_n + 0.002 * rng.standard_normal(n),
            lateral_alpha_n=rec.lateral_alpha_n + 0.002 * rng.standard_normal(n),
            lateral_beta_n=rec.lateral_beta_n + 0.002 * rng.standard_normal(n),
            reaction_moment_nm=rec.reaction_moment_nm + 0.0004 * rng.standard_normal(n),
        )
        scale = vehicle.effects.azimuth_transient.gain_per_newton * rec.thrust_n
        for row in (r for r in az.ROWS if az.ROW_AXIS[r] == axis):
            bode = az.frequency_response(*az.row_signals(noisy, row), design.rate_hz, design.band_hz)
            fit = az.fit_row(row, bode, PRIOR_55[row], scale)
            assert fit.correlation >= az.SEED004_CORRELATION_75[row], row


def test_the_axial_rows_are_driven_by_the_rate_magnitude(vehicle, design, rig):
    # spec 4.1: f1x follows |alpha'|; read against the signed rate it is no linear response at all
    rec = rig["azimuth"]
    u_abs, y = az.row_signals(rec, "f1x")
    scale = vehicle.effects.azimuth_transient.gain_per_newton * rec.thrust_n
    rms = []
    for u in (u_abs, rec.alpha_rate_rad_s):
        b = az.frequency_response(u, y, design.rate_hz, design.band_hz)
        expect = az.magnitude_db("f1x", vehicle.effects.azimuth_transient.f1x, b.raw_omega_rad_s)
        rms.append(float(np.sqrt(np.mean((b.raw_magnitude_db - expect - 20 * math.log10(scale)) ** 2))))
    assert rms[0] < 0.02
    assert rms[1] > 3.0


def test_bad_arguments_are_named(vehicle, design):
    with pytest.raises(ValueError, match="even number"):
        az.design_pseudo_impulse(n_samples=101)
    with pytest.raises(ValueError, match="axis must be"):
        az.simulate_fixed_rig(vehicle, design, "roll")
    with pytest.raises(ValueError, match="servo_lag is off"):
        az.simulate_fixed_rig(vehicle.with_effects(servo_lag=False), design)
    bode = az.BodeMagnitude(np.arange(1.0, 30.0), np.zeros(29), np.arange(1.0, 30.0), np.zeros(29))
    with pytest.raises(ValueError, match="7 positive coefficients"):
        az.fit_row("f1x", bode, [1.0, 2.0])
    with pytest.raises(ValueError, match="row must be one of"):
        az.row_signals(None, "f9q")


def test_rig_kernels_cache_is_keyed_on_the_model_source():
    # the rig kernels compile onboard.model into themselves: their disk cache must change with it
    import hashlib
    from pathlib import Path

    from onboard import model

    digest = hashlib.sha256(Path(model.__file__).read_bytes()).hexdigest()
    for kernel in (az._rig_run, az._rig_derivative):
        assert kernel._cache._impl.locator.get_source_stamp()[1] == (digest,)
