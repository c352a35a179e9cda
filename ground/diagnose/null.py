"""Recordings of the null hypothesis: the nominal model flown under the recorded commands.

To calibrate the decision on the recording itself (parametric bootstrap; Efron & Tibshirani 1993,
ch. 6), each draw re-simulates every fitting window of the recording with the NOMINAL vehicle:
started from the state the smoother estimated at the window's start, driven by the recorded
commands, sampled at the recording's own sample times, with white sensor noise at the levels
estimated from the recording (`locate.sensor_noise`) and the nominal sensor biases and delay.
Such a draw is what the recording would look like if nothing were missing; the decision
statistics computed on it are the null distribution of this recording (its commands, its
regimes, its sensors and rates). Windows are short (the nominal model flown open loop drifts
from the real trajectory when the model is wrong) and start from the measured state.

Pure: arrays and frozen recordings in, new recordings out (the random generator is an argument).
"""

from __future__ import annotations

import dataclasses

import numpy as np
from numba import njit

from onboard import model
from onboard.jit import MODEL_SOURCE, key_caches_on


@njit(cache=True, nogil=True)  # (the null draws run on threads: core._each)
def _simulate(x0, command, p, dt, substeps, out):
    """RK4 from x0 under held commands; out[k] = [pos(3), quat(4), gyro(3), specific force(3)]."""
    n = command.shape[0]
    x = x0.copy()
    xdot = np.zeros(x.shape[0])
    h = dt / substeps
    for k in range(n):
        u = command[k]
        model.derivative(x, u, p, xdot)
        f = model.specific_force(x, xdot, p)
        out[k, 0:7] = x[0:7]
        out[k, 7:10] = x[10:13]
        out[k, 10:13] = f
        for _ in range(substeps):
            x = model.rk4_step(x, u, p, h)


key_caches_on(globals(), MODEL_SOURCE)


def simulate_window(rec, traj, act: np.ndarray, vehicle, sigmas: dict, rng, start=None, substeps: int = 10):
    """One null draw of one window: a Recording like `rec` (the window's own recording) whose
    sensor streams come from the nominal model started at the smoothed state `traj` gives."""
    from ground.recording import AttitudeStream, ImuStream, MocapStream, PressureStream, Skipped

    p = model.pack_params(vehicle)
    t = traj.time_s
    # the draw starts where the vehicle may have been: the smoothed state (of the whole recording,
    # `start` = (x, sd) in the estimate layout, else this window's) plus its own uncertainty
    xs, sd = start if start is not None else (traj.estimate.x[0], traj.estimate.std[0])
    xe = xs[:12] + rng.normal(size=12) * sd[:12]
    x0 = np.concatenate([xe[0:3], model.euler_to_quat(*xe[3:6]), xe[6:12], act[0]])
    out = np.zeros((len(t), 13))
    _simulate(x0, np.ascontiguousarray(traj.command), p, traj.dt_s, substeps, out)
    s = vehicle.sensors
    env = vehicle.environment
    delay = s.delay  # a sample stamped t shows the vehicle at t - delay (spec 5)

    def at(times, cols):
        tt = np.asarray(times) - delay
        return np.column_stack([np.interp(tt, t, out[:, c]) for c in cols])

    def noisy(y, sigma):
        return y + rng.normal(size=y.shape) * np.broadcast_to(np.asarray(sigma, float), y.shape[1:])

    imu_t = rec.imu.time_s
    gyro = noisy(at(imu_t, range(7, 10)) + np.asarray(s.gyro_bias), sigmas["gyro_rad_s"])
    accel = noisy(at(imu_t, range(10, 13)) + np.asarray(s.accel_bias), sigmas["accel_m_s2"])
    imu = ImuStream(imu_t, accel, gyro, rec.imu.message)
    pt = rec.pressure.time_s
    depth = np.maximum(at(pt, [2])[:, 0] - env.surface_depth, 0.0)
    press = noisy((env.p_atm + env.rho * env.g * depth)[:, None], sigmas["pressure_pa"])[:, 0]
    pressure = PressureStream(pt, press, rec.pressure.message)
    attitude = None
    if rec.attitude is not None:
        at_t = rec.attitude.time_s
        q = at(at_t, range(3, 7))
        e = np.array([model.quat_to_euler(qq / np.linalg.norm(qq)) for qq in q]).reshape(-1, 3)
        e = noisy(e, sigmas.get("attitude_rad", 0.0))
        e[:, 2] = (e[:, 2] + np.pi) % (2 * np.pi) - np.pi
        attitude = AttitudeStream(at_t, e, at(at_t, range(7, 10)))
    mocap = None
    if rec.mocap is not None:
        mt = rec.mocap.time_s
        # motion capture carries no vehicle sensor delay
        pos = np.column_stack([np.interp(mt, t, out[:, c]) for c in range(3)])
        q = np.column_stack([np.interp(mt, t, out[:, c]) for c in range(3, 7)])
        q = noisy(q, sigmas.get("mocap_quat", 0.0))
        mocap = MocapStream(mt, q / np.linalg.norm(q, axis=1, keepdims=True), noisy(pos, sigmas.get("mocap_m", 0.0)))
    return dataclasses.replace(rec, source=rec.source + " (null draw)", skipped=Skipped(), imu=imu,
                               pressure=pressure, attitude=attitude, mocap=mocap, esc=None)
