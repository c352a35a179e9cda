"""PWM <-> actuator commands, the linear clipped maps of the vehicle file's `[pwm]` table."""

from __future__ import annotations

import numpy as np

from .vehicle import Vehicle

N_CHANNELS = 16


def pwm_to_command(v: Vehicle, pwm_us) -> np.ndarray:
    """Command vector [n_cmd..., alpha_cmd..., beta_cmd...] from PWM on channels 1..16.

    Jets: jet_range -> 0..n_max; joints: servo_range -> -angle_limit..+angle_limit; clipped.
    `pwm_us[c - 1]` is channel c.
    """
    pwm = np.asarray(pwm_us, dtype=float)
    jlo, jhi = v.pwm.jet_range
    slo, shi = v.pwm.servo_range
    lim = v.servo.angle_limit
    jets = pwm[np.array(v.pwm.jet_channels) - 1]
    az = pwm[np.array(v.pwm.azimuth_channels) - 1]
    el = pwm[np.array(v.pwm.elevation_channels) - 1]
    n = np.clip((jets - jlo) / (jhi - jlo), 0.0, 1.0) * v.thruster.n_max
    a = np.clip((az - slo) / (shi - slo) * 2.0 - 1.0, -1.0, 1.0) * lim
    b = np.clip((el - slo) / (shi - slo) * 2.0 - 1.0, -1.0, 1.0) * lim
    return np.concatenate([n, a, b])


def command_to_pwm(v: Vehicle, command) -> np.ndarray:
    """PWM (us, integer) on channels 1..16 for a command vector; unused channels are 0."""
    k = v.n_units
    c = np.asarray(command, dtype=float)
    jlo, jhi = v.pwm.jet_range
    slo, shi = v.pwm.servo_range
    lim = v.servo.angle_limit
    out = np.zeros(N_CHANNELS)
    out[np.array(v.pwm.jet_channels) - 1] = jlo + np.clip(c[:k] / v.thruster.n_max, 0, 1) * (jhi - jlo)
    for sl, ch in ((slice(k, 2 * k), v.pwm.azimuth_channels), (slice(2 * k, 3 * k), v.pwm.elevation_channels)):
        out[np.array(ch) - 1] = slo + (np.clip(c[sl] / lim, -1, 1) + 1.0) / 2.0 * (shi - slo)
    return np.rint(out).astype(int)


def normalised_to_command(v: Vehicle, controls) -> np.ndarray:
    """HIL_ACTUATOR_CONTROLS layout (jets 0..1, then azimuths -1..1, then elevations -1..1)."""
    k = v.n_units
    c = np.asarray(controls, dtype=float)[: 3 * k]
    c = np.where(np.isfinite(c), c, 0.0)
    return np.concatenate([
        np.clip(c[:k], 0, 1) * v.thruster.n_max,
        np.clip(c[k:3 * k], -1, 1) * v.servo.angle_limit,
    ])


def command_to_normalised(v: Vehicle, command) -> np.ndarray:
    k = v.n_units
    c = np.asarray(command, dtype=float)
    return np.concatenate([
        np.clip(c[:k] / v.thruster.n_max, 0, 1),
        np.clip(c[k:3 * k] / v.servo.angle_limit, -1, 1),
    ])
