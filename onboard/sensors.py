"""Sensor samples and the sensor model of spec/vehicle-model.md section 5 (pure functions).

Samples are the domain types that flow between the plant, the links and the onboard loop;
units and frames are in the field names. The noise is passed in, so the functions stay pure
and the caller owns the random generator (seeded and deterministic in the plant).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .model import P_G, P_PATM, P_RHO, P_SURF, quat_to_euler, specific_force
from .vehicle import Vehicle


@dataclass(frozen=True)
class ImuSample:
    time_s: float
    accel_frd_m_s2: tuple  # specific force, body FRD
    gyro_frd_rad_s: tuple


@dataclass(frozen=True)
class PressureSample:
    time_s: float
    press_abs_pa: float
    temperature_c: float = 20.0


@dataclass(frozen=True)
class AttitudeSample:
    time_s: float
    roll_rad: float
    pitch_rad: float
    yaw_rad: float
    rollspeed_rad_s: float
    pitchspeed_rad_s: float
    yawspeed_rad_s: float


@dataclass(frozen=True)
class ActuatorSample:
    """What the actuators are doing: commanded PWM and measured propeller speeds."""

    time_s: float
    pwm_us: tuple  # channels 1..16, 0 where unused
    rpm: tuple  # measured propeller speed of each unit


@dataclass(frozen=True)
class TruthSample:
    """The plant's true state at a sample time (for TRUTH.csv and tests)."""

    time_s: float
    pos_ned_m: tuple
    euler_rad: tuple  # roll, pitch, yaw
    nu: tuple  # u, v, w (m/s), p, q, r (rad/s)


def imu_sample(t: float, x, xdot, p, v: Vehicle, noise_accel, noise_gyro) -> ImuSample:
    """gyro = w + b_g + n_g; accel = R^T (a_ned - [0, 0, g]) + b_a + n_a (spec 5)."""
    s = v.sensors
    f = specific_force(x, xdot, p) + np.asarray(s.accel_bias) + noise_accel
    w = np.asarray(x[10:13]) + np.asarray(s.gyro_bias) + noise_gyro
    return ImuSample(t, tuple(float(c) for c in f), tuple(float(c) for c in w))


def pressure_sample(t: float, x, p, noise_pa: float) -> PressureSample:
    """p = p_atm + rho g max(depth, 0) + noise (spec 5)."""
    depth = x[2] - p[P_SURF]
    return PressureSample(t, float(p[P_PATM] + p[P_RHO] * p[P_G] * max(depth, 0.0) + noise_pa))


def attitude_sample(t: float, x, noise_rad) -> AttitudeSample:
    """True attitude (ZYX Euler) plus noise; rates are the body rates (spec 5)."""
    roll, pitch, yaw = quat_to_euler(x[3:7])
    yaw = float((yaw + noise_rad[2] + np.pi) % (2 * np.pi) - np.pi)
    return AttitudeSample(
        t, float(roll + noise_rad[0]), float(pitch + noise_rad[1]), yaw,
        float(x[10]), float(x[11]), float(x[12]),
    )


def truth_sample(t: float, x) -> TruthSample:
    return TruthSample(
        t, tuple(float(c) for c in x[0:3]), tuple(float(c) for c in quat_to_euler(x[3:7])),
        tuple(float(c) for c in x[7:13]),
    )


def depth_from_pressure(press_abs_pa: float, v: Vehicle) -> float:
    """Inverse of the pressure model: depth (m) below the free surface."""
    e = v.environment
    return (press_abs_pa - e.p_atm) / (e.rho * e.g)
