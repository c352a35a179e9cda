"""Model-aided EKF: convergence on the plant's noisy samples, gating, NaN handling, divergence."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest

from hil.plant import Plant
from onboard import model
from onboard.estimator import (
    N_X, STREAMS, X_DEPTH, X_DIST, X_EULER, Estimator, EstimatorTuning, _linearise, small_inverse, state_from_truth,
)
from onboard.sensors import AttitudeSample, ImuSample, depth_from_pressure
from onboard.vehicle import load_vehicle

DEG = math.pi / 180
TRUE_BIAS = (0.02, -0.015, 0.01)  # rad/s, what the plant's gyro adds


@pytest.fixture(scope="module")
def vehicle():
    return load_vehicle()


def command(k=4, n=30.0, beta=-0.3):
    """Moderate thrust, jets tilted down (beta < 0 gives -sin(beta) e3 > 0: pushes the body down)."""
    u = np.zeros(3 * k)
    u[:k] = n
    u[2 * k:] = beta
    return u


def fly(plant, est, u, t_end, dt=0.01, attitude=True, tamper=None):
    """Drive the estimator with the plant's samples; returns [(t, estimate, truth)] at IMU instants."""
    out = []
    t = plant.time_s
    v = plant.vehicle
    while t < t_end - 1e-9:
        t += dt
        s = plant.advance(t)
        est.predict(dt, u)
        for imu, truth in zip(s.imu, s.truth):
            if tamper:
                imu = tamper("imu", imu)
            est.update_imu(imu)
            out.append((t, est.estimate, truth))
        for p in s.pressure:
            d = depth_from_pressure(p.press_abs_pa, v)
            est.update_depth(tamper("depth", d) if tamper else d)
        if attitude:
            for a in s.attitude:
                est.update_attitude(tamper("attitude", a) if tamper else a)
    return out


def angle_err(a, b):
    return abs((a - b + math.pi) % (2 * math.pi) - math.pi)


def test_accelerometer_jacobian_matches_hand_derivation(vehicle):
    """Level, at rest, 0.5 m deep, jets off: f = v' - g R^T e3 with v' = (W - B) R^T e3 / (m + m_A).

    d f_y / d roll = -g - (W - B) / (m + m_A,sway) ... sign: R^T e3 = [-s(theta), s(phi) c(theta),
    c(phi) c(theta)], so d f_y / d phi = -g + (W - B) / (m + X_vdot) and d f_x / d theta = g - (W - B) / (m + X_udot).
    """
    e, b, h = vehicle.environment, vehicle.body, vehicle.hydro
    W, B = b.mass * e.g, e.rho * e.g * b.volume  # 63.765 N, 65.2365 N
    xr = np.zeros(N_X)
    xr[X_DEPTH] = 0.5
    full = model.initial_state(vehicle, 0.5)
    _, H, f = _linearise(xr, full, np.zeros(12), model.pack_params(vehicle), 2.0)
    assert f[2] == pytest.approx(-e.g + (W - B) / (b.mass + h.added_mass[2] * _wall(vehicle, 0.5)), abs=1e-9)
    assert H[1, X_EULER] == pytest.approx(-e.g + (W - B) / (b.mass + h.added_mass[1]), rel=1e-5)
    assert H[0, X_EULER + 1] == pytest.approx(e.g - (W - B) / (b.mass + h.added_mass[0]), rel=1e-5)
    assert H[0, X_EULER + 1] == pytest.approx(9.96015, abs=1e-4)  # 9.81 + 1.4715 / 9.8
    np.testing.assert_array_equal(H[:, X_DIST:X_DIST + 3], np.eye(3))  # f_spec = ... + d


def _wall(v, depth):
    """1 + k_wall (R / d)^3 with d = floor - z (spec 4), the heave added-mass factor."""
    w = v.effects.wall_proximity
    d = max(v.environment.floor_depth - depth, 1.2 * v.body.radius)
    return 1 + w.k_wall * (v.body.radius / d) ** 3


def test_converges_from_20_deg_attitude_error_and_wrong_gyro_bias(vehicle):
    plant_v = vehicle.with_values({"sensors.gyro_bias": list(TRUE_BIAS)})
    u = command()
    plant = Plant(plant_v, seed=3, depth_m=0.5, command=u)
    est = Estimator(vehicle, depth_m=0.5, euler_rad=(20 * DEG, -15 * DEG, 0.5))
    assert est.estimate.euler_rad[0] == pytest.approx(20 * DEG)  # the plant starts level: 20 deg off
    log = fly(plant, est, u, 10.0)
    final = [(e, tr) for t, e, tr in log if t > 6.0]
    for e, tr in final:
        for i in range(3):
            assert angle_err(e.euler_rad[i], tr.euler_rad[i]) < 1.0 * DEG
    e_last = final[-1][0]
    np.testing.assert_allclose(e_last.gyro_bias_rad_s, TRUE_BIAS, atol=1.5e-3)
    # rates are bias-free: estimated rates match the true body rates
    np.testing.assert_allclose(e_last.rates_rad_s, final[-1][1].nu[3:6], atol=0.01)
    assert not e_last.health.diverged
    assert e_last.health.rejected_total == 0


def test_roll_pitch_converge_from_accelerometer_alone(vehicle):
    """No ATTITUDE stream: gravity in the model-predicted specific force levels the estimate."""
    plant_v = vehicle.with_values({"sensors.gyro_bias": list(TRUE_BIAS)})
    u = command()
    plant = Plant(plant_v, seed=4, depth_m=0.5, command=u)
    est = Estimator(vehicle, depth_m=0.5, euler_rad=(20 * DEG, -20 * DEG, 0.0))
    log = fly(plant, est, u, 8.0, attitude=False)
    for t, e, tr in log:
        if t > 4.0:
            assert angle_err(e.euler_rad[0], tr.euler_rad[0]) < 1.0 * DEG
            assert angle_err(e.euler_rad[1], tr.euler_rad[1]) < 1.0 * DEG
    np.testing.assert_allclose(log[-1][1].gyro_bias_rad_s[:2], TRUE_BIAS[:2], atol=2e-3)


def test_depth_and_heave_velocity_track(vehicle):
    """Diving and surfacing under thrust; the estimate starts 0.3 m off in depth."""
    plant = Plant(vehicle, seed=5, depth_m=0.4, command=command(beta=-0.5))
    est = Estimator(vehicle, depth_m=0.7)
    log = fly(plant, est, command(beta=-0.5), 4.0)
    log += fly(plant, est, command(n=10.0, beta=0.0), 8.0)  # jets weak: rises by buoyancy
    late = [(e, tr) for t, e, tr in log if t > 1.0]
    depth_err = np.array([e.depth_m - tr.pos_ned_m[2] for e, tr in late])
    w_err = np.array([e.velocity_body_m_s[2] - tr.nu[2] for e, tr in late])
    w_true = np.array([tr.nu[2] for e, tr in late])
    assert np.ptp(w_true) > 0.1  # the heave speed really changed
    assert np.sqrt(np.mean(depth_err ** 2)) < 0.005  # 5 mm (pressure noise is ~2 mm)
    assert np.sqrt(np.mean(w_err ** 2)) < 0.01  # 1 cm/s
    # depth rate is the kinematic z' = R[2, :] v of the estimate
    e = late[-1][0]
    assert e.depth_rate_m_s == pytest.approx(e.velocity_body_m_s[2], abs=0.01)


def _converged(vehicle, seed=6, tuning=None):
    u = command()
    plant = Plant(vehicle, seed=seed, depth_m=0.5, command=u)
    est = Estimator(vehicle, depth_m=0.5, tuning=tuning)
    fly(plant, est, u, 3.0)
    return plant, est, u


def test_nonfinite_samples_are_rejected_counted_and_not_propagated(vehicle):
    plant, est, u = _converged(vehicle)
    est.estimate  # reading fuses the samples of the last instant
    twin = Estimator(vehicle, depth_m=0.5)  # same state, sees only the usable samples
    twin._ekf.x, twin._ekf.P = est._ekf.x.copy(), est._ekf.P.copy()
    twin._full, twin._command, twin._H_acc = est._full.copy(), est._command.copy(), est._H_acc.copy()
    x0 = est._ekf.x.copy()
    before = est.health
    half_bad = ImuSample(3.0, (0.05, 0.0, -9.7), (math.nan,) * 3)  # gyro bad, accel usable
    est.update_imu(ImuSample(3.0, (math.nan, 0.0, 0.0), (0.0, math.inf, 0.0)))  # both halves bad
    est.update_imu(half_bad)
    est.update_depth(math.nan)
    est.update_depth("garbage")
    est.update_attitude(AttitudeSample(3.0, math.inf, 0.0, 0.0, 0.0, 0.0, 0.0))
    twin.update_imu(half_bad)
    after = est.health  # (fuses the pending samples of both)
    twin.health
    d = np.subtract(after.rejected_nonfinite, before.rejected_nonfinite)
    assert dict(zip(STREAMS, d)) == {"gyro": 2, "accel": 1, "depth": 2, "attitude": 1}
    assert after.rejected_gated == before.rejected_gated
    assert not np.array_equal(est._ekf.x, x0)  # the usable accelerometer half was fused
    # the rejected samples changed nothing: bit-identical to the twin that never saw them
    np.testing.assert_array_equal(est._ekf.x, twin._ekf.x)
    np.testing.assert_array_equal(est._ekf.P, twin._ekf.P)
    assert not after.diverged


def test_nonfinite_only_stream_leaves_state_bit_identical(vehicle):
    _, est, _ = _converged(vehicle, seed=7)
    est.estimate
    x, P = est._ekf.x.copy(), est._ekf.P.copy()
    for _ in range(10):
        est.update_imu(ImuSample(3.0, (math.nan,) * 3, (math.nan,) * 3))
        est.update_depth(math.inf)
    est.estimate
    np.testing.assert_array_equal(est._ekf.x, x)
    np.testing.assert_array_equal(est._ekf.P, P)
    assert est.health.rejected_nonfinite == (10, 10, 10, 0)


def test_outlier_burst_is_gated_and_the_ungated_filter_is_not(vehicle):
    def tamper_factory(start, count):
        seen = {"imu": 0, "depth": 0}

        def tamper(stream, value):
            if stream in seen:
                seen[stream] += 1
                i = seen[stream]
                if start <= i < start + count:
                    if stream == "depth":
                        return value + 2.0  # 2 m spike
                    return ImuSample(value.time_s, (value.accel_frd_m_s2[0] + 40.0,) + value.accel_frd_m_s2[1:],
                                     (value.gyro_frd_rad_s[0] + 3.0,) + value.gyro_frd_rad_s[1:])
            return value
        return tamper

    results = {}
    for gate in (0.9999, 1.0):  # chi2.ppf(1.0) = inf: no gate
        plant, est, u = _converged(vehicle, seed=8, tuning=EstimatorTuning(gate_probability=gate))
        h0 = est.health
        log = fly(plant, est, u, 5.0, tamper=tamper_factory(20, 5))
        burst = [(e, tr) for t, e, tr in log if 3.0 < t < 4.0]
        worst_depth = max(abs(e.depth_m - tr.pos_ned_m[2]) for e, tr in burst)
        worst_roll = max(angle_err(e.euler_rad[0], tr.euler_rad[0]) for e, tr in burst)
        results[gate] = (worst_depth, worst_roll, np.subtract(est.health.rejected_gated, h0.rejected_gated), est.health)
    worst_depth, worst_roll, rej, health = results[0.9999]
    assert dict(zip(STREAMS, rej)) == {"gyro": 5, "accel": 5, "depth": 5, "attitude": 0}
    assert worst_depth < 0.01 and worst_roll < 1.0 * DEG
    assert not health.diverged
    # without the gate the same burst drags the estimate off: the gate is what protects it
    assert results[1.0][0] > 0.1 or results[1.0][1] > 3.0 * DEG


def test_persistent_disagreement_is_flagged_as_divergence(vehicle):
    """An ATTITUDE stream 0.5 rad off in roll for 2 s (50 Hz): gyro and accelerometer keep the
    estimate on the truth, so every sample is gated; the 50th in a row latches `diverged`."""
    plant, est, u = _converged(vehicle, seed=9)
    assert not est.health.diverged
    off = lambda s, v: dataclasses.replace(v, roll_rad=v.roll_rad + 0.5) if s == "attitude" else v  # noqa: E731
    fly(plant, est, u, 5.0, tamper=off)
    h = est.health
    assert h.diverged and "attitude" in h.diverged_reason and "consecutive" in h.diverged_reason
    assert h.rejected_gated[STREAMS.index("attitude")] >= est.tuning.max_consecutive_rejections
    # latched until an explicit reset
    fly(plant, est, u, 6.0)
    assert est.health.diverged
    est.reset(depth_m=plant.state[2])
    assert not est.health.diverged and est.health.rejected_total == 0


def test_covariance_bound_flags_divergence(vehicle):
    """No measurements at all (and a poor rate model): the uncertainty grows past its bound."""
    est = Estimator(vehicle, depth_m=0.5, tuning=EstimatorTuning(q_rates_rad_s2_sqrt_hz=5.0))
    for _ in range(400):
        est.predict(0.01, np.zeros(12))
        if est.health.diverged:
            break
    assert est.health.diverged and "sigma" in est.health.diverged_reason


def test_bad_predict_arguments_raise_clear_errors(vehicle):
    est = Estimator(vehicle)
    with pytest.raises(ValueError, match="dt must be"):
        est.predict(0.0, np.zeros(12))
    with pytest.raises(ValueError, match="command must be 12 finite"):
        est.predict(0.01, np.zeros(11))
    with pytest.raises(ValueError, match="command must be 12 finite"):
        est.predict(0.01, np.full(12, np.nan))


def test_state_from_truth_round_trips(vehicle):
    x = model.initial_state(vehicle, 0.7)
    x[3:7] = model.euler_to_quat(0.1, -0.2, 2.0)
    x[7:13] = [0.3, -0.1, 0.05, 0.01, 0.02, -0.3]
    s = state_from_truth(x, vehicle, 1.5)
    np.testing.assert_allclose(s.euler_rad, (0.1, -0.2, 2.0), atol=1e-12)
    np.testing.assert_allclose(s.quat_wxyz, x[3:7], atol=1e-12)
    np.testing.assert_allclose(s.nu, x[7:13])
    assert s.depth_m == pytest.approx(0.7)
    # z' = R[2, :] v of the true state
    xdot = np.zeros_like(x)
    model.derivative(x, np.zeros(12), model.pack_params(vehicle), xdot)
    assert s.depth_rate_m_s == pytest.approx(xdot[2], abs=1e-12)


def test_compiled_backend_equals_filterpy(vehicle):
    """Cross-form check: the numba Joseph update and gate equal filterpy's EKF on the same inputs,
    including a gated outlier and a NaN sample."""
    u = command()
    plant = Plant(vehicle, seed=10, depth_m=0.5, command=u)
    ests = [Estimator(vehicle, depth_m=0.45, euler_rad=(0.2, -0.1, 0.3), backend=b) for b in ("filterpy", "compiled")]
    t = 0.0
    for step in range(300):
        t += 0.01
        s = plant.advance(t)
        for e in ests:
            e.predict(0.01, u)
            for imu in s.imu:
                e.update_imu(imu)
            for p in s.pressure:
                d = depth_from_pressure(p.press_abs_pa, vehicle)
                e.update_depth(d + (3.0 if step in (150, 151) else 0.0))  # one 50 Hz sample
            for a in s.attitude:
                bad = step in (200, 201)
                e.update_attitude(AttitudeSample(t, math.nan, 0, 0, 0, 0, 0) if bad else a)
    a, b = ests
    assert a.health == b.health  # (reading fuses the last instant's samples)
    np.testing.assert_allclose(a._ekf.x, b._ekf.x, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(a._ekf.P, b._ekf.P, rtol=1e-7, atol=1e-14)
    assert a.health == b.health
    assert a.health.rejected_gated[STREAMS.index("depth")] == 1
    assert a.health.rejected_nonfinite[STREAMS.index("attitude")] == 1
    with pytest.raises(ValueError, match="backend"):
        Estimator(vehicle, backend="ukf")


def test_small_inverse_is_the_inverse():
    """The compiled S^-1 of the update: a hand-inverted 2 x 2 (inverse = adj / det), a pivoting
    case (zero leading entry), numpy's inverse on innovation-like covariances of 1..10 rows, and
    numpy's error for a singular or non-finite S."""
    # [[4, 2], [2, 3]]^-1 = [[3, -2], [-2, 4]] / (4 * 3 - 2 * 2)
    np.testing.assert_allclose(small_inverse([[4.0, 2.0], [2.0, 3.0]]), np.array([[3.0, -2.0], [-2.0, 4.0]]) / 8.0,
                               rtol=1e-15)
    np.testing.assert_allclose(small_inverse([[0.0, 2.0], [0.5, 0.0]]), [[0.0, 2.0], [0.5, 0.0]], rtol=1e-15)
    rng = np.random.default_rng(3)
    for m in range(1, 11):
        H = rng.standard_normal((m, N_X))
        A = rng.standard_normal((N_X, N_X))
        S = H @ (A @ A.T * 1e-3) @ H.T + np.diag(rng.uniform(1e-6, 1e-2, m))  # H P H^T + R
        X = small_inverse(S)
        np.testing.assert_allclose(X, np.linalg.inv(S), rtol=1e-9, atol=1e-9 * np.abs(X).max())
        np.testing.assert_allclose(X @ S, np.eye(m), atol=1e-9)
    for bad in ([[1.0, 2.0], [2.0, 4.0]], [[1.0, np.nan], [0.0, 1.0]]):
        with pytest.raises(np.linalg.LinAlgError):
            small_inverse(bad)


def test_default_start_at_the_surface_locks_onto_the_first_depth(vehicle):
    """Built with no depth (0 m, at the surface), the first readings at 0.6 m are taken, not gated."""
    est = Estimator(vehicle)
    assert est.estimate.depth_m == 0.0
    for _ in range(10):
        est.predict(0.02, np.zeros(12))
        est.update_depth(0.6)
    assert est.estimate.depth_m == pytest.approx(0.6, abs=0.005)
    assert est.health.rejected_gated == (0, 0, 0, 0)


def test_saturated_pressure_above_the_surface(vehicle):
    """The sensor reads max(depth, 0): 0 with the estimate above the surface carries no information;
    0 with the estimate 0.3 m deep pulls it up to the surface."""
    est = Estimator(vehicle, depth_m=-0.05)
    x = est._ekf.x.copy()
    est.update_depth(0.0)
    est.estimate
    np.testing.assert_array_equal(est._ekf.x, x)
    est = Estimator(vehicle, depth_m=0.3)
    for _ in range(5):
        est.update_depth(0.0)
    assert abs(est.estimate.depth_m) < 0.01


def _depth_fault(vehicle, offset_m, n_bad, first_bad=50, seconds=4.0, seed=11):
    """Converged at 0.5 m, then `seconds` more with depth samples first_bad .. first_bad + n_bad - 1
    (counted from the start of that stretch) reading `offset_m` more than the sensor says.

    Returns (estimator, rows): one row per depth sample, (index, sample value, depth resets and
    depth gated-rejections after it, estimated depth after it, true depth)."""
    plant, est, u = _converged(vehicle, seed=seed)
    rows = []
    t, i = plant.time_s, 0
    t_end = t + seconds
    while t < t_end - 1e-9:
        t += 0.01
        s = plant.advance(t)
        est.predict(0.01, u)
        for imu in s.imu:
            est.update_imu(imu)
        for p in s.pressure:  # (at the step's IMU instant: s.truth[-1])
            truth = s.truth[-1]
            z = depth_from_pressure(p.press_abs_pa, vehicle) + (offset_m if first_bad <= i < first_bad + n_bad else 0.0)
            est.update_depth(z)
            h = est.health
            rows.append((i, z, h.depth_resets, h.rejected_gated[STREAMS.index("depth")], est.estimate.depth_m,
                         truth.pos_ned_m[2]))
            i += 1
    return est, rows


def test_depth_jump_that_stays_reanchors_depth_after_one_second(vehicle):
    """A depth sensor that jumps 0.4 m and stays: gated sample after sample; the sample 1 s after the
    first gated one (depth at 50 Hz: the 51st, index first_bad + 50) re-anchors depth on the sensor,
    is counted in depth_resets, and from there on the new readings are accepted."""
    rate = vehicle.sensors.pressure_rate  # 50 Hz: samples 0.02 s apart
    after = EstimatorTuning().depth_reset_after_s  # 1 s
    n_run = round(after * rate) + 1  # the run spans 1 s at its 51st sample (50 intervals of 0.02 s)
    est, rows = _depth_fault(vehicle, 0.4, n_bad=10_000, first_bad=50)
    gated0 = rows[49][3]
    reset_rows = [r for r in rows if r[2] == 1]
    i_reset, z_reset, _, gated_at_reset, depth_at_reset, _ = reset_rows[0]
    assert i_reset == 50 + n_run - 1  # the 51st jumped sample
    assert gated_at_reset - gated0 == n_run  # all 51 were gated, the last one then re-anchored
    assert depth_at_reset == pytest.approx(z_reset, abs=1e-12)  # depth := the sensor's reading
    assert all(r[2] == 0 for r in rows if r[0] < i_reset)
    # afterwards: accepted, one reset only, the estimate follows the (offset) sensor, not diverged
    late = [r for r in rows if r[0] > i_reset]
    assert late and all(r[2] == 1 and r[3] == gated_at_reset for r in late)
    assert all(abs(r[4] - (r[5] + 0.4)) < 0.01 for r in late[10:])
    h = est.health
    assert not h.diverged and h.depth_resets == 1 and h.as_dict()["depth_rst"] == 1.0


def test_depth_spike_shorter_than_one_second_is_rejected_without_reset(vehicle):
    """50 jumped samples at 50 Hz span 0.98 s (< 1 s): all gated, no reset, the estimate stays on the truth."""
    rate = vehicle.sensors.pressure_rate
    n_bad = round(EstimatorTuning().depth_reset_after_s * rate)  # 50: first to last 49 x 0.02 = 0.98 s
    est, rows = _depth_fault(vehicle, 0.4, n_bad=n_bad, first_bad=50, seconds=3.0)
    assert rows[-1][3] - rows[49][3] == n_bad
    assert all(r[2] == 0 for r in rows)
    assert all(abs(r[4] - r[5]) < 0.01 for r in rows)
    assert not est.health.diverged and est.health.depth_resets == 0


@pytest.mark.parametrize("backend", ["filterpy", "compiled"])
def test_one_update_per_instant_equals_fusing_one_after_another(vehicle, backend):
    """Cross-form check: the samples of an instant fused in one update (reading the estimate once)
    give the state and covariance of fusing them one at a time in arrival order (reading after
    each), from a start at the surface with the initial covariance (where the accelerometer's
    h(x) is most nonlinear in depth) through a dive, both arrival orders."""
    u = command()
    plant = Plant(vehicle, seed=12, depth_m=0.0, command=u)
    joint, seq = (Estimator(vehicle, backend=backend) for _ in range(2))
    t = 0.0
    for step in range(120):
        s = plant.advance(t + 1e-9)
        depth = [depth_from_pressure(p.press_abs_pa, vehicle) for p in s.pressure]
        imu_first = step % 4 == 1
        for e, read in ((joint, False), (seq, True)):
            if step:
                e.predict(0.01, u)
            todo = [("depth", d) for d in depth] + [("attitude", a) for a in s.attitude]
            todo = ([("imu", i) for i in s.imu] + todo) if imu_first else (todo + [("imu", i) for i in s.imu])
            for kind, sample in todo:
                getattr(e, f"update_{kind}")(sample)
                if read:
                    e.estimate
            e.estimate
        t += 0.01
    assert plant.state[2] > 0.05  # dived off the surface
    np.testing.assert_allclose(joint._ekf.x, seq._ekf.x, rtol=1e-6, atol=1e-9)  # rounding over 120 steps
    np.testing.assert_allclose(joint._ekf.P, seq._ekf.P, rtol=1e-6, atol=1e-12)
    a, b = joint.health, seq.health  # (the NIS averages differ: each sample is gated on the prior)
    assert (a.accepted, a.rejected_gated) == (b.accepted, b.rejected_gated)
    s = vehicle.sensors  # 1.2 s of samples, all accepted: gyro and accel at 100 Hz, depth and attitude at 50 Hz
    assert a.accepted == (round(1.2 * s.imu_rate),) * 2 + (round(1.2 * s.pressure_rate), round(1.2 * s.attitude_rate))
