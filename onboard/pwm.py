"""PWM <-> actuator commands: the linear clipped maps of the vehicle file's `[pwm]` table for jets
and joints, the thrust curve of `[fixed_thruster]` for fixed thrusters (`onboard.fixed`)."""

from __future__ import annotations

import numpy as np

from . import fixed
from .vehicle import Vehicle

N_CHANNELS = 16
NO_PULSE_BELOW_US = 500.0  # a fixed thruster's width under this is no pulse: its ESC stops (T = 0)


def _index(channels) -> np.ndarray:
    return np.asarray(channels, dtype=int) - 1


def pwm_to_command(v: Vehicle, pwm_us) -> np.ndarray:
    """Command vector [n_cmd..., alpha_cmd..., beta_cmd...] from PWM on channels 1..16.

    Jets: jet_range -> 0..n_max (from `jet_neutral` if the file gives one); joints: servo_range
    -> -angle_limit..+angle_limit; clipped. Fixed thrusters: their static thrust (N) from the
    thrust curve, their joint slots 0. `pwm_us[c - 1]` is channel c.
    """
    pwm = np.asarray(pwm_us, dtype=float)
    jlo, jhi = v.pwm.jet_range
    if v.pwm.jet_neutral is not None:  # two-way autopilot outputs: below neutral the jet is off
        jlo = v.pwm.jet_neutral
    slo, shi = v.pwm.servo_range
    lim = v.servo.angle_limit
    jets = pwm[_index(v.pwm.jet_channels)]
    az = pwm[_index(v.pwm.azimuth_channels)]
    el = pwm[_index(v.pwm.elevation_channels)]
    n = np.clip((jets - jlo) / (jhi - jlo), 0.0, 1.0) * v.thruster.n_max
    a = np.clip((az - slo) / (shi - slo) * 2.0 - 1.0, -1.0, 1.0) * lim
    b = np.clip((el - slo) / (shi - slo) * 2.0 - 1.0, -1.0, 1.0) * lim
    if not v.fixed:
        return np.concatenate([n, a, b])
    widths = pwm[_index(v.pwm.fixed_channels)]
    t = np.where(widths >= NO_PULSE_BELOW_US, fixed.thrust_of_pwm(v.fixed_thruster, widths), 0.0)
    z = np.zeros_like(t)  # no joints; pwm_us may be (16, samples): column-wise, like the jets
    return np.concatenate([n, t, a, z, b, z])


def command_to_pwm(v: Vehicle, command) -> np.ndarray:
    """PWM (us, integer) on channels 1..16 for a command vector; unused channels are 0.
    A fixed thruster's width is the inverse of its thrust curve (`onboard.fixed.pwm_of_thrust`)."""
    k, j = v.n_units, v.n_jets
    c = np.asarray(command, dtype=float)
    jlo, jhi = v.pwm.jet_range
    if v.pwm.jet_neutral is not None:
        jlo = v.pwm.jet_neutral
    slo, shi = v.pwm.servo_range
    lim = v.servo.angle_limit
    out = np.zeros(N_CHANNELS)
    out[_index(v.pwm.jet_channels)] = jlo + np.clip(c[:j] / v.thruster.n_max, 0, 1) * (jhi - jlo)
    for sl, ch in ((slice(k, k + j), v.pwm.azimuth_channels), (slice(2 * k, 2 * k + j), v.pwm.elevation_channels)):
        out[_index(ch)] = slo + (np.clip(c[sl] / lim, -1, 1) + 1.0) / 2.0 * (shi - slo)
    if v.fixed:
        out[_index(v.pwm.fixed_channels)] = fixed.pwm_of_thrust(v.fixed_thruster, c[j:k])
    return np.rint(out).astype(int)


def normalised_to_command(v: Vehicle, controls) -> np.ndarray:
    """HIL_ACTUATOR_CONTROLS layout (jets 0..1, then azimuths -1..1, then elevations -1..1)."""
    k = v.n_units
    c = np.asarray(controls, dtype=float)[: 3 * k]
    c = np.where(np.isfinite(c), c, 0.0)
    if v.fixed:  # fixed thrusters: -1..1 of their reverse and forward reach; no joints
        j = v.n_jets
        t_min, t_max = fixed.thrust_limits(v.fixed_thruster)
        f = np.clip(c[j:k], -1, 1)
        joints = np.clip(c[k:3 * k], -1, 1) * v.servo.angle_limit
        joints[j:k] = joints[k + j:] = 0.0
        return np.concatenate([np.clip(c[:j], 0, 1) * v.thruster.n_max,
                               np.where(f > 0, f * t_max, -f * t_min), joints])
    return np.concatenate([
        np.clip(c[:k], 0, 1) * v.thruster.n_max,
        np.clip(c[k:3 * k], -1, 1) * v.servo.angle_limit,
    ])


def command_to_normalised(v: Vehicle, command) -> np.ndarray:
    k = v.n_units
    c = np.asarray(command, dtype=float)
    if v.fixed:
        j = v.n_jets
        t_min, t_max = fixed.thrust_limits(v.fixed_thruster)
        t = c[j:k]
        joints = np.clip(c[k:3 * k] / v.servo.angle_limit, -1, 1)
        joints[j:k] = joints[k + j:] = 0.0
        return np.concatenate([np.clip(c[:j] / v.thruster.n_max, 0, 1),
                               np.clip(np.where(t > 0, t / t_max, -t / t_min), -1, 1), joints])
    return np.concatenate([
        np.clip(c[:k] / v.thruster.n_max, 0, 1),
        np.clip(c[k:3 * k] / v.servo.angle_limit, -1, 1),
    ])
