"""Replay a recording through a model: the measured motion, its generalised-force residual, and
multiple-shooting windows re-initialised from the measurements.

Pure math on arrays: a `Recording` and a parameter vector in, frozen results out.

1. `reconstruct` puts every stream on one uniform grid (the IMU's) and estimates the rigid-body
   state with the model (`estimate.smooth`: EKF + RTS over the nominal vehicle driven by the
   commands, with a generalised-force disturbance and IMU biases), so horizontal velocity comes
   from the dynamics and the measurements together, with or without motion capture.
   Commands are the SERVO_OUTPUT_RAW PWM held from the sample on (spec 6).
2. `actuator_run_commands` (`actuator_run_lead` after a window's lead-in) integrates what the
   actuators do (propeller speeds, joint angles, the seed-004 transient filters) from the
   commands alone: it does not depend on the body's motion, so one continuous run gives the
   actuator state at every instant without open-loop drift.
3. `model_acceleration` evaluates the model's nu' at every estimated state, and
   `acceleration_residual` is what the measured motion needed minus what the model gives:
       r = nu'_measured - nu'_model(x_estimated, u)   (Fossen 2011 eq. 6.1, rearranged)
   with both sides passed through the same Savitzky-Golay filter, so the smoothing's lag at a
   command step cancels (times the nominal mass, a generalised force).
4. `shoot` simulates short windows, each started from the reconstructed state (multiple
   shooting), and returns the predicted sensor signals to compare with the recording.
"""

from __future__ import annotations

import functools
import hashlib
import math
import threading
import weakref
from dataclasses import dataclass, field

import numpy as np
from numba import njit
from scipy.ndimage import convolve1d
from scipy.signal import savgol_coeffs, savgol_filter

from onboard import model
from onboard.fixed import ardusub_directions
from onboard.jit import MODEL_SOURCE, key_caches_on
from onboard.pwm import pwm_to_command
from onboard.vehicle import Vehicle

from . import estimate

SMOOTH_S = 0.21  # Savitzky-Golay window for rates and accelerations (order 2)
MOCAP_SMOOTH_S = 0.31  # Savitzky-Golay window for velocity from motion-capture position
MIN_OVERLAP_S = 3.0  # shorter than this, the smoothing windows and the held-out edges leave nothing
ACT_MAX_STEP_S = 0.005  # largest RK4 step of the actuator run
SIGNALS = ("gyro_x", "gyro_y", "gyro_z", "accel_x", "accel_y", "accel_z", "depth", "roll", "pitch", "yaw")
AXES = ("surge", "sway", "heave", "roll", "pitch", "yaw")


class ReplayError(ValueError):
    """A recording that lacks what replay needs; the message says which stream."""


class TooShort(ReplayError):
    """IMU, pressure and commands overlap too briefly for the estimator and its smoothers."""


@dataclass(frozen=True)
class SensorCorrection:
    """Sensor-side terms of a candidate: biases and latency (spec 5)."""

    gyro_bias: tuple = (0.0, 0.0, 0.0)  # rad/s
    accel_bias: tuple = (0.0, 0.0, 0.0)  # m/s^2
    delay_s: float = 0.0


@dataclass(frozen=True)
class Trajectory:
    """The recording on a uniform grid plus the state reconstructed from it."""

    time_s: np.ndarray  # (N,)
    dt_s: float
    command: np.ndarray  # (N, 3k) held commands
    pos_ned_m: np.ndarray  # (N, 3)
    quat: np.ndarray  # (N, 4)
    nu: np.ndarray  # (N, 6) smoothed
    nu_dot: np.ndarray  # (N, 6) smoothed (measured: gyro derivative and specific force)
    lin_acc: np.ndarray  # (N, 3) unsmoothed v' = f + R^T g e3 - w x v from the accelerometer
    gyro: np.ndarray  # (N, 3) unsmoothed, bias-corrected body rates
    kinematic: np.ndarray  # (N, 6) sensor consistency: gyro - attitude rate, accel - mocap acceleration
    measured: dict  # signal name -> (N,) the raw sensor signals on the grid (SIGNALS)
    has_mocap: bool
    correction: SensorCorrection = field(default_factory=SensorCorrection)
    noise_probe: np.ndarray | None = None  # (N, 10) white noise like each signal's, on the grid
    estimate: object = field(default=None, repr=False)  # estimate.Estimate: the smoothed state, disturbance


# ------------------------------------------------------------------------------------------------
# Reconstruction


def white_noise_sigma(y) -> np.ndarray:
    """sigma of white noise on a sampled signal: 1.4826 MAD(diff2) / sqrt(6), per column.

    For white noise of sigma s, the second difference has sigma s sqrt(6); smooth motion adds
    little at the sensor rate, and the median makes the rare fast transient harmless. A sample
    that is not a finite number is left out (the differences it touches): one NaN pressure sample
    made the median NaN, the depth noise fell to its floor, 20x below the sensor's, and the fit
    of a perfect recording doubled (an adversary's find). NaN when a column has none left.
    """
    y = np.asarray(y, float)
    if y.ndim == 1:
        y = y[:, None]
    if len(y) < 5:
        return np.zeros(y.shape[1])
    d2 = y[2:] - 2 * y[1:-1] + y[:-2]
    d2[~np.isfinite(d2)] = np.nan
    mad = np.full(d2.shape[1], np.nan)  # an all-NaN column: NaN, said by the caller
    ok = np.isfinite(d2).any(axis=0)  # (only those: numpy warns on the rest, and the warnings
    # filters a catch_warnings would set are not thread-safe: core._each)
    if ok.any():
        mad[ok] = np.nanmedian(np.abs(d2[:, ok] - np.nanmedian(d2[:, ok], axis=0)), axis=0)
    return 1.4826 * mad / math.sqrt(6.0)


def _interp(t_grid, t, y):
    y = np.asarray(y, float)
    if y.ndim == 1:
        return np.interp(t_grid, t, y)
    return np.column_stack([np.interp(t_grid, t, y[:, j]) for j in range(y.shape[1])])


@functools.lru_cache(maxsize=64)
def _savgol_ops(window: int, order: int, deriv: int, delta: float):
    """The Savitzky-Golay filter as linear operators: the interior kernel (scipy's
    `savgol_coeffs`) and the two (window // 2, window) edge matrices of mode "interp" (the
    polynomial fitted to the first or last window of samples, evaluated or differentiated at the
    edge samples), made once per shape; scipy refits the edges by `polyfit` on every call."""
    half = window // 2
    pos = np.arange(window, dtype=float)
    # (order+1, window): the least-squares polynomial of a window, highest power first. np.polyfit
    # would match scipy to 1e-14 where this is 1e-10 off at 1 kHz windows, but with it the
    # reversed-BlueROV2-thruster fit (tests/test_diagnose_fixed.py) stalls at fraction 0 instead
    # of reaching -0.95: that fit is this sensitive to its start (README, honest limits)
    fit = np.linalg.pinv(np.vander(pos, order + 1))
    powers = np.arange(order, -1, -1)
    edges = []
    for at in (pos[:half], pos[window - half:]):
        # d^deriv/dx^deriv of sum c_j x^p_j at `at`
        D = np.zeros((len(at), order + 1))
        for j, pw in enumerate(powers):
            if pw >= deriv:
                D[:, j] = math.perm(int(pw), deriv) * at ** (pw - deriv)
        edges.append(D @ fit / delta ** deriv)
    return savgol_coeffs(window, order, deriv=deriv, delta=delta), edges[0], edges[1]


def savgol(y, window: int, order: int, deriv: int = 0, delta: float = 1.0, axis: int = 0) -> np.ndarray:
    """`scipy.signal.savgol_filter(y, window, order, deriv, delta, axis, mode="interp")` with its
    operators made once per shape (`_savgol_ops`): the same numbers to 1e-14 at 100 Hz windows
    (1e-10 at 1 kHz ones), without refitting the edges by least squares on every call (an
    eighth of the diagnosis' time went there)."""
    y = np.moveaxis(np.asarray(y, float), axis, 0)
    if y.shape[0] < window:
        return np.moveaxis(savgol_filter(y, window, order, deriv=deriv, delta=delta, axis=0, mode="interp"), 0, axis)
    kernel, first, last = _savgol_ops(int(window), int(order), int(deriv), float(delta))
    out = convolve1d(y, kernel, axis=0, mode="constant")
    half = window // 2
    out[:half] = np.tensordot(first, y[:window], axes=(1, 0))
    out[len(y) - half:] = np.tensordot(last, y[len(y) - window:], axes=(1, 0))
    return np.moveaxis(out, 0, axis)


def _odd(n: int) -> int:
    n = max(int(n), 5)
    return n if n % 2 else n + 1


def grid_for(rec) -> tuple[np.ndarray, float]:
    """The uniform grid: IMU period, over the span where IMU, pressure and commands all exist."""
    for name in ("imu", "pressure", "servo"):
        s = getattr(rec, name)
        if s is None or not len(s.time_s):
            raise ReplayError(
                f"{rec.source}: the recording has no usable {name} stream "
                f"({'HIGHRES_IMU or SCALED_IMU' if name == 'imu' else 'SCALED_PRESSURE2' if name == 'pressure' else 'SERVO_OUTPUT_RAW'} needed)")
        if len(s.time_s) < 10:  # the stream is there, this stretch of it is too short: a verdict
            raise TooShort(f"{rec.source}: only {len(s.time_s)} {name} samples in this stretch")
    dt = float(np.median(np.diff(rec.imu.time_s)))
    t0 = max(rec.imu.time_s[0], rec.pressure.time_s[0], rec.servo.time_s[0])
    t1 = min(rec.imu.time_s[-1], rec.pressure.time_s[-1])
    if t1 - t0 < max(20 * dt, MIN_OVERLAP_S):
        raise TooShort(f"{rec.source}: IMU, pressure and commands overlap for only {t1 - t0:.2f} s")
    n = int(np.floor((t1 - t0) / dt + 1e-9)) + 1
    return t0 + dt * np.arange(n), dt


def pwm_to_commands(vehicle: Vehicle, pwm_us: np.ndarray) -> np.ndarray:
    """`onboard.pwm.pwm_to_command` for every row of an (N, 16) PWM array.

    Its maps are element-wise and pick channels on the first axis, so the transposed (16, N)
    array goes through it whole and comes back (3k, N).
    """
    return pwm_to_command(vehicle, np.asarray(pwm_us, float).T).T


def held_commands(rec, vehicle: Vehicle, t_grid) -> np.ndarray:
    """Command vector for each step of a uniform grid: the recorded commands (each held until
    the next SERVO_OUTPUT_RAW, spec 6) averaged over the step [t, t + dt) the model holds it
    for, as the thrusters act on them: with the motor directions the autopilot's parameters in
    the log give (ArduSub's MOT_n_DIRECTION, `onboard.fixed.ardusub_directions`), applied here
    once, so the smoother, the candidates, the null draws and the shooting all see them.

    The average, not the command at t: the grid is the IMU's period (25-50 Hz at ArduSub
    rates) and the commands change every 10 ms, so the one at the step's start lagged the
    step's mean command by dt/2 plus up to a command period, 15-25 ms at 50-25 Hz, by an amount
    that depends on the IMU's phase; lags and delays were fitted 8-25 % off to make up for it
    (dev cases 1108, 1134, 1184: 7.8, 23 and 7.6 % off, then 4.0, 3.8 and 1.0 %). The same
    value is the model's instantaneous input at t (half a step early there; it matters where
    the nominal has no motor or servo lag, so the command acts directly). A single grid time
    (no step) gets the command in force at it."""
    ts = np.asarray(rec.servo.time_s, float)
    cmd = flown_commands(rec, vehicle)
    t_grid = np.asarray(t_grid, float)
    last = lambda t: np.clip(np.searchsorted(ts, t + 1e-9, side="right") - 1, 0, len(ts) - 1)  # noqa: E731
    if len(t_grid) < 2:
        return cmd[last(t_grid)]
    dt = float(t_grid[1] - t_grid[0])
    # the integral of the held command from the first record, at any time (before it: the first)
    area = np.vstack([np.zeros((1, cmd.shape[1])), np.cumsum(cmd[:-1] * np.diff(ts)[:, None], axis=0)])

    def integral(t):
        i = last(t)
        return area[i] + cmd[i] * (t - ts[i])[:, None]

    return (integral(t_grid + dt) - integral(t_grid)) / dt


def flown_commands(rec, vehicle: Vehicle) -> np.ndarray:
    """The command of every SERVO_OUTPUT_RAW row as the thrusters act on it: through the [pwm]
    maps, signed by the motor directions in the log's autopilot parameters (ArduSub's
    MOT_n_DIRECTION, `onboard.fixed.ardusub_directions`). The diagnosis and the plot's replay
    read the recorded commands only through here."""
    cmd = pwm_to_commands(vehicle, rec.servo.pwm_us)
    signs = ardusub_directions(rec.parameters, vehicle)
    return cmd if signs is None else model.faulty_command(vehicle, cmd, signs)


MOCAP_COVERAGE = 0.9  # motion capture counts when it covers this share of the grid ...
MOCAP_HOLD_PERIODS = 5  # ... a grid time being covered within this many of its sample periods


def mocap_covers(rec, t_grid) -> bool:
    """Whether motion capture measures the whole stretch: at least MOCAP_COVERAGE of the grid
    within MOCAP_HOLD_PERIODS sample periods of a motion-capture sample. A few seconds of it
    would otherwise be held (interpolation) over the rest as a vehicle standing still, and a
    horizontal current called tested (an adversary's find)."""
    m = rec.mocap
    if m is None or len(m.time_s) <= 10:
        return False
    tm = np.asarray(m.time_s, float)
    hold = MOCAP_HOLD_PERIODS * float(np.median(np.diff(tm)))
    j = np.clip(np.searchsorted(tm, t_grid), 1, len(tm) - 1)
    near = np.minimum(np.abs(t_grid - tm[j - 1]), np.abs(tm[j] - t_grid))
    return bool(np.mean(near <= hold) >= MOCAP_COVERAGE)


def _euler_to_quat_rows(e):
    r, p, y = e[:, 0] / 2, e[:, 1] / 2, e[:, 2] / 2
    cr, sr, cp, sp, cy, sy = np.cos(r), np.sin(r), np.cos(p), np.sin(p), np.cos(y), np.sin(y)
    return np.column_stack([
        cr * cp * cy + sr * sp * sy, sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy, cr * cp * sy - sr * sp * cy,
    ])


def _quat_to_euler_rows(q):
    w, a, b, c = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    roll = np.arctan2(2 * (w * a + b * c), 1 - 2 * (a * a + b * b))
    pitch = np.arcsin(np.clip(2 * (w * b - c * a), -1, 1))
    yaw = np.arctan2(2 * (w * c + a * b), 1 - 2 * (b * b + c * c))
    return np.column_stack([roll, pitch, yaw])


def _continuous(q: np.ndarray) -> np.ndarray:
    """Quaternion rows with signs chosen so consecutive rows agree (q and -q are one attitude)."""
    flip = np.sum(q[1:] * q[:-1], axis=1) < 0
    sign = np.concatenate([[1.0], np.where(np.cumsum(flip) % 2 == 1, -1.0, 1.0)])
    return q * sign[:, None]


def rotation_rows(q) -> np.ndarray:
    """R(q) body->NED for every row (N, 3, 3) (Fossen 2011 eq. 2.72)."""
    w, a, b, c = q[:, 0], q[:, 1], q[:, 2], q[:, 3]
    R = np.empty((len(q), 3, 3))
    R[:, 0, 0] = 1 - 2 * (b * b + c * c)
    R[:, 0, 1] = 2 * (a * b - w * c)
    R[:, 0, 2] = 2 * (a * c + w * b)
    R[:, 1, 0] = 2 * (a * b + w * c)
    R[:, 1, 1] = 1 - 2 * (a * a + c * c)
    R[:, 1, 2] = 2 * (b * c - w * a)
    R[:, 2, 0] = 2 * (a * c - w * b)
    R[:, 2, 1] = 2 * (b * c + w * a)
    R[:, 2, 2] = 1 - 2 * (a * a + b * b)
    return R


@dataclass(frozen=True)
class LeadIn:
    """What came before a window cut from a longer recording: the commands of the seconds before
    it (on the window's grid spacing, oldest first), so the actuators are mid-flight at its start;
    optionally a state for the smoother to start from (`estimate` layout), else its generic prior
    (`estimate.initial_state`)."""

    command: np.ndarray  # (L, 3k)
    x0: np.ndarray | None = None  # (estimate.NX,)


def reconstruct(rec, vehicle: Vehicle, correction: SensorCorrection | None = None,
                lead: LeadIn | None = None, runs: ActuatorRuns | None = None) -> Trajectory:
    """The recording on the IMU grid and the rigid-body state estimated from it (module doc 1);
    the nominal actuator run from `runs` when given (shared with the candidates)."""
    corr = correction or SensorCorrection()
    t, dt = grid_for(rec)
    d = corr.delay_s  # a sample stamped t_m describes the vehicle at t_m - delay
    env = vehicle.environment
    imu_t = rec.imu.time_s - d
    gyro_raw = _interp(t, rec.imu.time_s, rec.imu.gyro_frd_rad_s)
    accel_raw = _interp(t, rec.imu.time_s, rec.imu.accel_frd_m_s2)
    gyro = _interp(t, imu_t, rec.imu.gyro_frd_rad_s) - np.asarray(corr.gyro_bias)
    accel = _interp(t, imu_t, rec.imu.accel_frd_m_s2) - np.asarray(corr.accel_bias)
    depth_raw = (_interp(t, rec.pressure.time_s, rec.pressure.press_abs_pa) - env.p_atm) / (env.rho * env.g)
    w_s = _odd(round(SMOOTH_S / dt))
    w_m = _odd(round(MOCAP_SMOOTH_S / dt))
    command = held_commands(rec, vehicle, t)
    # the state, estimated with the model (estimate.py): EKF + RTS over the nominal vehicle driven by
    # the commands, with a generalised-force disturbance and IMU biases
    p = model.pack_params(vehicle)
    act = (runs or ActuatorRuns()).get(command, dt, p, vehicle.n_units, lead)
    meas = estimate.measurements(rec, vehicle, t, d, corr.gyro_bias, corr.accel_bias)
    x0 = lead.x0 if lead is not None and lead.x0 is not None else estimate.initial_state(meas, env.surface_depth)
    est = estimate.smooth(meas, act, command, p, x0)
    xs = est.x
    pos = xs[:, 0:3].copy()
    quat = est.quat()
    gyro = gyro - xs[:, estimate.I_BG:estimate.I_BG + 3]
    accel = accel - xs[:, estimate.I_BA:estimate.I_BA + 3]
    v_body = xs[:, 6:9].copy()
    euler_raw = np.zeros((len(t), 3))
    q_meas = None
    if rec.attitude is not None and len(rec.attitude.time_s) > 2:
        e = np.array(rec.attitude.euler_rad, float)
        e[:, 2] = np.unwrap(e[:, 2])
        euler_raw = _interp(t, rec.attitude.time_s, e)
        q_meas = _euler_to_quat_rows(_interp(t, rec.attitude.time_s - d, e))
    has_mocap = mocap_covers(rec, t)  # partial motion capture is not held over the rest
    if has_mocap:
        qm = _continuous(np.array(rec.mocap.quat_wxyz, float))
        q_meas = _interp(t, rec.mocap.time_s, qm)
        q_meas /= np.linalg.norm(q_meas, axis=1, keepdims=True)
        if rec.attitude is None:
            euler_raw = _quat_to_euler_rows(q_meas)
            euler_raw[:, 2] = np.unwrap(euler_raw[:, 2])
    R = rotation_rows(quat)
    g_body = env.g * R[:, 2, :]  # R^T [0, 0, g]
    kinematic = np.zeros((len(t), 6))
    if q_meas is not None:
        # w = 2 vec(q* (x) q') from the attitude measurement, against the gyro smoothed alike
        qd = savgol(q_meas, w_s, 2, deriv=1, delta=dt, axis=0)
        qs = savgol(q_meas, w_s, 2, axis=0)
        w_att = 2.0 * np.column_stack([
            qs[:, 0] * qd[:, 1] - qs[:, 1] * qd[:, 0] - qs[:, 2] * qd[:, 3] + qs[:, 3] * qd[:, 2],
            qs[:, 0] * qd[:, 2] + qs[:, 1] * qd[:, 3] - qs[:, 2] * qd[:, 0] - qs[:, 3] * qd[:, 1],
            qs[:, 0] * qd[:, 3] - qs[:, 1] * qd[:, 2] + qs[:, 2] * qd[:, 1] - qs[:, 3] * qd[:, 0],
        ])
        kinematic[:, :3] = savgol(gyro, w_s, 2, axis=0) - w_att
    if has_mocap:
        # motion capture is the pool's, not the vehicle's: no sensor delay on it
        mpos = _interp(t, rec.mocap.time_s, rec.mocap.pos_ned_m)
        a_ned = savgol(mpos, w_m, 2, deriv=2, delta=dt, axis=0)
        f_ned = savgol(np.einsum("nij,nj->ni", R, accel), w_m, 2, axis=0)
        # specific force = R^T (a_ned - g e3): accel - mocap, in body axes
        kinematic[:, 3:] = np.einsum("nji,nj->ni", R, f_ned - a_ned + np.array([0.0, 0.0, env.g]))
    omega = savgol(gyro, w_s, 2, axis=0)
    omega_dot = savgol(gyro, w_s, 2, deriv=1, delta=dt, axis=0)
    # v' = f + R^T g e3 - w x v (spec 5 inverted)
    lin_acc = accel + g_body - np.cross(gyro, v_body)
    v_dot = savgol(lin_acc, w_s, 2, axis=0)
    nu = np.column_stack([v_body, omega])
    nu_dot = np.column_stack([v_dot, omega_dot])
    # a white-noise probe per signal: noise of the level estimated from the native samples,
    # drawn at the native sample times and put on the grid the same way as the signal
    rng = np.random.default_rng(7)

    def probe(t_native, y_native):
        y = np.asarray(y_native, float)
        y = y[:, None] if y.ndim == 1 else y
        return _interp(t, t_native, rng.normal(size=y.shape) * white_noise_sigma(y))

    pg, pa = probe(rec.imu.time_s, rec.imu.gyro_frd_rad_s), probe(rec.imu.time_s, rec.imu.accel_frd_m_s2)
    pp = probe(rec.pressure.time_s, rec.pressure.press_abs_pa)[:, 0] / (env.rho * env.g)
    if rec.attitude is not None and len(rec.attitude.time_s) > 2:
        e = np.array(rec.attitude.euler_rad, float)
        e[:, 2] = np.unwrap(e[:, 2])
        pe = probe(rec.attitude.time_s, e)
    else:
        pe = np.zeros((len(t), 3))
    noise_probe = np.column_stack([pg, pa, pp, pe])
    noise_probe.setflags(write=False)
    measured = {
        "gyro_x": gyro_raw[:, 0], "gyro_y": gyro_raw[:, 1], "gyro_z": gyro_raw[:, 2],
        "accel_x": accel_raw[:, 0], "accel_y": accel_raw[:, 1], "accel_z": accel_raw[:, 2],
        "depth": depth_raw, "roll": euler_raw[:, 0], "pitch": euler_raw[:, 1], "yaw": euler_raw[:, 2],
    }
    for a in (t, command, pos, quat, nu, nu_dot, lin_acc, gyro, kinematic, *measured.values()):
        a.setflags(write=False)
    return Trajectory(t, dt, command, pos, quat, nu, nu_dot, lin_acc, gyro, kinematic, measured,
                      has_mocap, corr, noise_probe, est)


# ------------------------------------------------------------------------------------------------
# Actuators and the model's acceleration along the reconstructed trajectory


@njit(cache=True)
def _act_derivative(xa, u, p, k, out):
    """The actuator part of the model (spec 4 and 3.1), from `onboard.model.actuator` itself."""
    for i in range(k):
        model.actuator(xa, u, p, k, i, out)


@njit(cache=True, nogil=True)  # (the null draws run on threads: core._each)
def _actuator_run(command, p, dt, substeps, xa0):
    n, k = command.shape[0], command.shape[1] // 3
    m = xa0.shape[0]
    out = np.empty((n, m))
    xa = xa0.copy()
    h = dt / substeps
    k1, k2, k3, k4 = np.empty(m), np.empty(m), np.empty(m), np.empty(m)
    for s in range(n):
        u = command[s]
        if s == 0:
            model.actuator_project(xa, u, p, k)
        out[s] = xa
        for _ in range(substeps):
            _act_derivative(xa, u, p, k, k1)
            _act_derivative(xa + 0.5 * h * k1, u, p, k, k2)
            _act_derivative(xa + 0.5 * h * k2, u, p, k, k3)
            _act_derivative(xa + h * k3, u, p, k, k4)
            xa = xa + (h / 6.0) * (k1 + 2 * k2 + 2 * k3 + k4)
            model.actuator_project(xa, u, p, k)
    return out


def actuator_run(traj: Trajectory, p: np.ndarray, n_units: int, substeps: int = 2, command=None) -> np.ndarray:
    """(N, 3k + 20k) actuator and transient-filter states along the grid (module doc 2)."""
    return actuator_run_commands(traj.command if command is None else command, traj.dt_s, p, n_units, substeps)


def actuator_run_lead(command: np.ndarray, dt: float, p: np.ndarray, n_units: int, lead=None,
                      substeps: int = 2) -> np.ndarray:
    """`actuator_run_commands` after the lead-in's commands (a window of a longer recording)."""
    if lead is None or not len(lead.command):
        return actuator_run_commands(command, dt, p, n_units, substeps)
    m = len(lead.command)
    return actuator_run_commands(np.concatenate([lead.command, command]), dt, p, n_units, substeps)[m:]


class IdentityMemo:
    """f(obj) remembered by obj's identity, through a weak reference: the memo keeps nothing
    alive, and an id reused after its object is gone finds a dead reference, not a hit. Only for
    objects that cannot change (a frozen Vehicle, an array frozen where it is made). Bounded:
    cleared when `limit` entries are held. Thread-safe enough for the null draws' threads (each
    dict operation is atomic; a race costs one recomputation)."""

    def __init__(self, limit: int):
        self.limit = limit
        self._d: dict = {}  # id -> (weak reference, value)

    def get(self, obj, compute):
        hit = self._d.get(id(obj))
        if hit is not None and hit[0]() is obj:
            return hit[1]
        value = compute(obj)
        if len(self._d) >= self.limit:
            self._d.clear()
        self._d[id(obj)] = (weakref.ref(obj), value)
        return value


class ActuatorRuns:
    """`actuator_run_lead`, remembered by what it depends on: the commands (lead-in included),
    the grid spacing and the actuator parameters (`model.actuator_param_indices`). Windows of one
    recording, their null draws (same commands) and candidates that leave the actuators alone
    share one run; the same inputs give the same array, so sharing changes no result. Bounded:
    the least recently used runs are dropped past `max_bytes` (a run is stored without its
    lead-in, so what is counted is what is held)."""

    def __init__(self, max_bytes: int = 256 * 2 ** 20):
        self.max_bytes = max_bytes
        self._runs: dict = {}
        self._bytes = 0
        self._digests = IdentityMemo(4096)  # read-only commands hashed once (windows, draws, lead-ins: far fewer)
        self._lock = threading.Lock()  # the null draws run on threads (core._each)

    def _digest(self, a: np.ndarray) -> bytes:
        """blake2b of `a`'s values; remembered (`IdentityMemo`) for a read-only array that owns its
        data (the trajectories' and lead-ins' commands, frozen where they are made and never
        thawed). Hashing the same commands on every call was 5 % of bench_diagnose (29 000
        updates, 2026-12-02)."""
        digest = lambda x: hashlib.blake2b(np.ascontiguousarray(x, float).tobytes(), digest_size=16).digest()  # noqa: E731
        return self._digests.get(a, digest) if not a.flags.writeable and a.base is None else digest(a)

    def get(self, command: np.ndarray, dt: float, p: np.ndarray, n_units: int, lead=None) -> np.ndarray:
        h = hashlib.blake2b(digest_size=16)
        h.update(self._digest(command))
        if lead is not None:
            h.update(b"lead")
            h.update(self._digest(lead.command))
        h.update(np.float64(dt).tobytes())
        h.update(np.ascontiguousarray(p[model.actuator_param_indices(n_units)]).tobytes())
        key = (h.digest(), command.shape, n_units)
        with self._lock:
            run = self._runs.pop(key, None)
            if run is not None:  # used again: to the back of the eviction order
                self._runs[key] = run
                return run
        # (run outside the lock: two threads may both run it once; the same inputs, the same array)
        run = np.array(actuator_run_lead(command, dt, p, n_units, lead))  # a copy: not a view into the lead-in's run
        run.setflags(write=False)
        with self._lock:
            if key in self._runs:
                return self._runs[key]
            while self._runs and self._bytes + run.nbytes > self.max_bytes:
                self._bytes -= self._runs.pop(next(iter(self._runs))).nbytes
            self._runs[key] = run
            self._bytes += run.nbytes
        return run


def actuator_run_commands(command: np.ndarray, dt: float, p: np.ndarray, n_units: int, substeps: int = 2) -> np.ndarray:
    """`actuator_run` on a held-command array. Initial state as spec 6: propellers at rest,
    joints at the first command, filters zero."""
    k = n_units
    xa0 = np.zeros(3 * k + model.N_TF_STATES * k)
    xa0[k:3 * k] = command[0, k:3 * k]
    # the seed-004 filters have poles near 60 rad/s: RK4 steps of at most 5 ms keep them stable
    # however slow the recording's IMU (ArduSub sends 2-25 Hz)
    substeps = max(int(substeps), int(math.ceil(dt / ACT_MAX_STEP_S - 1e-9)))
    return _actuator_run(np.ascontiguousarray(command), p, dt, substeps, xa0)


@njit(cache=True, nogil=True)  # (the null draws run on threads: core._each)
def _model_acc(pos, quat, nu, act, command, p, idx):
    m = idx.shape[0]
    nx = 13 + act.shape[1]
    out = np.empty((m, 6))
    x = np.zeros(nx)
    xdot = np.zeros(nx)
    for j in range(m):
        i = idx[j]
        x[0:3] = pos[i]
        x[3:7] = quat[i]
        x[7:13] = nu[i]
        x[13:] = act[i]
        model.derivative(x, command[i], p, xdot)
        out[j] = xdot[7:13]
    return out


def model_acceleration(traj: Trajectory, act: np.ndarray, p: np.ndarray, idx=None, command=None) -> np.ndarray:
    """nu'_model(x_measured, u) at grid indices `idx` (all by default), (m, 6)."""
    idx = np.arange(len(traj.time_s)) if idx is None else np.asarray(idx, np.int64)
    command = traj.command if command is None else np.ascontiguousarray(command)
    return _model_acc(traj.pos_ned_m, traj.quat, traj.nu, act, command, p, idx)


def smooth(traj: Trajectory, y: np.ndarray) -> np.ndarray:
    """The Savitzky-Golay smoother the reconstruction used, applied to a model signal."""
    return savgol(y, _odd(round(SMOOTH_S / traj.dt_s)), 2, axis=0)


def nominal_mass_diag(vehicle: Vehicle) -> np.ndarray:
    """diag(M_RB + M_A) at depth, away from walls: converts acceleration residuals to N, N m."""
    b = vehicle.body
    return np.array([b.mass] * 3 + list(b.inertia)) + np.asarray(vehicle.hydro.added_mass)


def acceleration_residual(traj: Trajectory, act: np.ndarray, p: np.ndarray, acc=None) -> np.ndarray:
    """nu'_measured - nu'_model (N, 6), both through the same linear filter (module doc 3).

    Linear axes: S(v'_accel - v'_model), S the Savitzky-Golay smoother. Angular axes:
    D(w_gyro - integral of w'_model), D the Savitzky-Golay derivative: the gyro is
    differentiated and the model integrated (trapezoid), so the same D acts on both and the
    filter's response to fast yaw transients cancels exactly.
    """
    acc = model_acceleration(traj, act, p) if acc is None else acc
    out = np.empty_like(acc)
    win = _odd(round(SMOOTH_S / traj.dt_s))
    out[:, :3] = savgol(traj.lin_acc - acc[:, :3], win, 2, axis=0)
    dt = traj.dt_s
    integral = np.concatenate([np.zeros((1, 3)), np.cumsum(0.5 * dt * (acc[1:, 3:] + acc[:-1, 3:]), axis=0)])
    out[:, 3:] = savgol(traj.gyro - integral, win, 2, deriv=1, delta=dt, axis=0)
    return out


# ------------------------------------------------------------------------------------------------
# Multiple shooting


@njit(cache=True)
def _derivative_ext(x, u, p, ext, mdiag, feat, xdot):
    """The model's x' plus an extra force F = features(x) @ ext acting through diag(M)."""
    model.derivative(x, u, p, xdot)
    if ext.shape[0] > 0:
        from_sparse_features(x, p, feat)
        for j in range(6):
            f = 0.0
            for i in range(ext.shape[0]):
                f += feat[i] * ext[i, j]
            xdot[7 + j] += f / mdiag[j]


@njit(cache=True)
def from_sparse_features(x, p, feat):
    k = (x.shape[0] - 13) // (3 + model.N_TF_STATES)
    _sparse_features(x, p, k, feat)


@njit(cache=True)
def _rk4_ext(x, u, p, h, ext, mdiag, feat):
    n = x.shape[0]
    k1, k2, k3, k4 = np.empty(n), np.empty(n), np.empty(n), np.empty(n)
    _derivative_ext(x, u, p, ext, mdiag, feat, k1)
    _derivative_ext(x + 0.5 * h * k1, u, p, ext, mdiag, feat, k2)
    _derivative_ext(x + 0.5 * h * k2, u, p, ext, mdiag, feat, k3)
    _derivative_ext(x + h * k3, u, p, ext, mdiag, feat, k4)
    out = x + (h / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)
    model.project(out, u, p)
    return out


@njit(cache=True)
def _shoot(pos, quat, nu, act, command, p, starts, length, substeps, dt, out, ext, mdiag):
    """For each window start s: x(t_s) from the reconstruction, RK4 forward `length` grid steps.

    out[w, j] = [gyro(3), specific force(3), z, roll, pitch, yaw] at grid index s + j.
    """
    nx = 13 + act.shape[1]
    h = dt / substeps
    xdot = np.zeros(nx)
    for w in range(starts.shape[0]):
        s = starts[w]
        x = np.zeros(nx)
        x[0:3] = pos[s]
        x[3:7] = quat[s]
        x[7:13] = nu[s]
        x[13:] = act[s]
        feat = np.zeros(max(ext.shape[0], 1))
        for j in range(length):
            u = command[s + j]
            _derivative_ext(x, u, p, ext, mdiag, feat, xdot)
            f = model.specific_force(x, xdot, p)
            r, pi, y = model.quat_to_euler(x[3:7])
            out[w, j, 0:3] = x[10:13]
            out[w, j, 3:6] = f
            out[w, j, 6] = x[2]
            out[w, j, 7] = r
            out[w, j, 8] = pi
            out[w, j, 9] = y
            if j + 1 < length:
                for _ in range(substeps):
                    x = model.rk4_step(x, u, p, h) if ext.shape[0] == 0 else _rk4_ext(x, u, p, h, ext, mdiag, feat)


def shoot(traj: Trajectory, act: np.ndarray, p: np.ndarray, starts, length: int, substeps: int = 1,
          command=None, extra_force=None, mass_diag=None) -> np.ndarray:
    """Predicted signals (W, length, 10) of windows re-initialised from the measurements.

    `extra_force` (F, 6): coefficients of a data-driven force on `sparse.feature_library`'s
    features (a fitted `unknown` term), acting through diag(M) = `mass_diag`.
    """
    starts = np.asarray(starts, np.int64)
    out = np.zeros((len(starts), length, len(SIGNALS)))
    command = traj.command if command is None else np.ascontiguousarray(command)
    ext = np.zeros((0, 6)) if extra_force is None else np.ascontiguousarray(extra_force, dtype=float)
    mdiag = np.ones(6) if mass_diag is None else np.asarray(mass_diag, float)
    _shoot(traj.pos_ned_m, traj.quat, traj.nu, act, command, p, starts, length, substeps,
           traj.dt_s, out, ext, mdiag)
    return out


def predicted_vs_measured(traj: Trajectory, pred: np.ndarray, starts, length: int, vehicle: Vehicle,
                          correction: SensorCorrection | None = None):
    """(pred, meas) arrays (W, length, 10) in sensor terms: biases added, delay applied.

    The predicted state at grid time t is what the sensors report at t + delay, so the
    measurement is read at t + delay; yaw is compared as a change since the window start.
    """
    corr = correction or SensorCorrection()
    t = traj.time_s
    pred = pred.copy()
    pred[:, :, 0:3] += np.asarray(corr.gyro_bias)
    pred[:, :, 3:6] += np.asarray(corr.accel_bias)
    pred[:, :, 6] = pred[:, :, 6] - vehicle.environment.surface_depth
    pred[:, :, 6] = np.maximum(pred[:, :, 6], 0.0)
    idx = np.asarray(starts)[:, None] + np.arange(length)[None, :]
    meas = np.empty_like(pred)
    for j, name in enumerate(SIGNALS):
        y = traj.measured[name]
        meas[:, :, j] = np.interp(t[idx] + corr.delay_s, t, y) if corr.delay_s else y[idx]
    # yaw: change over the window (the heading reference is arbitrary); unwrap the prediction
    pred[:, :, 9] = np.unwrap(pred[:, :, 9], axis=1)
    pred[:, :, 9] -= pred[:, :1, 9]
    meas[:, :, 9] -= meas[:, :1, 9]
    return pred, meas


@njit(cache=True)
def _sparse_features(x, p, k, out):
    """One row of `sparse.feature_library` (same order) from a full model state x."""
    out[0] = 1.0
    for i in range(6):
        out[1 + i] = x[7 + i]
        out[7 + i] = abs(x[7 + i]) * x[7 + i]
    R = model.rotation(x[3:7])
    out[13] = R[2, 0]
    out[14] = R[2, 1]
    for i in range(3):
        out[15 + i] = R[0, i] * x[0] + R[1, i] * x[1] + R[2, i] * x[2]
    out[18] = x[2] - p[model.P_SURF]
    out[19] = 1.0 / max(p[model.P_FLOOR] - x[2], 0.05)
    for i in range(k):
        out[20 + i] = (x[13 + i] / p[model.P_NMAX]) ** 2


key_caches_on(globals(), MODEL_SOURCE)
