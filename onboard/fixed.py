"""Fixed two-way thrusters (spec 3.1): the thrust curve of `[fixed_thruster]` and its inverse.

Pure functions of the vehicle file's description, shared by the PWM maps (`onboard.pwm`), the
model's parameters (`onboard.model.pack_params`: each unit's thrust limits), the allocator and
the plots, so there is one curve. A fixed unit's command is its static thrust T (N); the model
lags the actual thrust behind it (`motor_lag`, `time_constant`).

Table: thrust is interpolated linearly in PWM on the table's points (so a table point gives its
own value exactly), between two voltage columns linearly in voltage; zero inside the table's
dead band, negative and weaker below it, as the table says (Blue Robotics T200: about
1468-1532 us, reverse ~78 % of forward at 16 V). Beyond `pwm_range` a command is clipped.
Coefficients: with the dead band [a, b] and pwm_range [lo, hi], s = (pwm - b) / (hi - b) above
it and s = (a - pwm) / (a - lo) below it; T = c1 s + c2 s^2 forward, -(c1 s + c2 s^2) reverse.
"""

from __future__ import annotations

import numpy as np

from .vehicle import FixedThruster

NEUTRAL_US = 1500.0  # the width commanded for no thrust when the curve's dead band holds it


def table_column(ft: FixedThruster) -> tuple[np.ndarray, np.ndarray]:
    """(pwm_us, thrust_n) of the table at the file's supply voltage (linear between columns)."""
    pwm = np.asarray(ft.table_pwm, float)
    rows = np.asarray(ft.table_thrust, float)
    volts = np.asarray(ft.table_voltages, float)
    if len(volts) == 1:
        return pwm, rows[0].copy()
    j = int(np.clip(np.searchsorted(volts, ft.voltage) - 1, 0, len(volts) - 2))
    w = (ft.voltage - volts[j]) / (volts[j + 1] - volts[j])
    return pwm, (1.0 - w) * rows[j] + w * rows[j + 1]


def thrust_of_pwm(ft: FixedThruster, pwm_us) -> np.ndarray:
    """Static thrust T (N) of each PWM width (us), clipped to pwm_range (spec 3.1)."""
    lo, hi = ft.pwm_range
    x = np.clip(np.asarray(pwm_us, float), lo, hi)
    if ft.kind == "table":
        pwm, thrust = table_column(ft)
        return np.interp(x, pwm, thrust)
    a, b = ft.dead_band
    up = np.clip((x - b) / (hi - b), 0.0, None)
    down = np.clip((a - x) / (a - lo), 0.0, None)
    c1, c2 = ft.forward
    r1, r2 = ft.reverse
    return np.where(x > b, c1 * up + c2 * up * up, np.where(x < a, -(r1 * down + r2 * down * down), 0.0))


def thrust_limits(ft: FixedThruster) -> tuple[float, float]:
    """(T_min, T_max): the most reverse and the most forward static thrust of the curve (N)."""
    grid = curve(ft)[1]
    return float(min(grid.min(), 0.0)), float(max(grid.max(), 0.0))


def curve(ft: FixedThruster, step_us: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """(pwm_us, thrust_n) over pwm_range: the table's own points (and its range ends), or the
    coefficient model every `step_us`; for plots and for the inverse."""
    lo, hi = ft.pwm_range
    if ft.kind == "table":
        pwm, _ = table_column(ft)
        x = np.unique(np.concatenate([[lo, hi], pwm[(pwm > lo) & (pwm < hi)]]))
    else:
        x = np.unique(np.concatenate([np.arange(lo, hi, step_us), [hi], list(ft.dead_band)]))
    return x, thrust_of_pwm(ft, x)


def pwm_of_thrust(ft: FixedThruster, thrust_n) -> np.ndarray:
    """The PWM width (us) that gives each static thrust: the inverse of `thrust_of_pwm` on each
    branch (forward above the dead band, reverse below), clipped to what the curve reaches; zero
    thrust gives the neutral width (1500 us if the dead band holds it, else its middle)."""
    x, t = curve(ft)
    zero = np.flatnonzero(t == 0.0)
    if len(zero):
        a, b = x[zero[0]], x[zero[-1]]
    else:  # no flat dead band: the sign change
        k = int(np.flatnonzero(np.diff(np.sign(t)) > 0)[0])
        a = b = x[k] - t[k] * (x[k + 1] - x[k]) / (t[k + 1] - t[k])
    neutral = NEUTRAL_US if a <= NEUTRAL_US <= b else 0.5 * (a + b)
    fx, ft_ = x[x >= b], np.maximum.accumulate(t[x >= b])  # forward branch, made monotone
    rx, rt = x[x <= a], np.maximum.accumulate(t[x <= a])  # reverse branch (T rises with PWM)
    T = np.asarray(thrust_n, float)
    out = np.full(T.shape, neutral)
    pos, neg = T > 0.0, T < 0.0
    out[pos] = np.interp(T[pos], ft_, fx)
    out[neg] = np.interp(T[neg], rt, rx)
    return out


# ArduSub's motor outputs: SERVOn_FUNCTION 33-40 are Motor1-8, 82-85 Motor9-12 (SRV_Channel.h).
_MOTOR_FUNCTIONS = {**{33 + m: m + 1 for m in range(8)}, **{82 + m: m + 9 for m in range(4)}}


def ardusub_directions(parameters: dict, vehicle) -> tuple | None:
    """Per unit (jets first, then the fixed thrusters), the sign ArduSub applied to each fixed
    thruster's thrust, from the autopilot's parameters a recording carries: MOT_n_DIRECTION = -1
    mirrors motor n's demand before its PWM (AP_Motors6DOF.cpp, output_armed_stabilizing:
    _thrust_rpyt_out[i] = _motor_reverse[i] * (...)), for a motor mounted or wired the other way
    round, so the recorded PWM of that motor pushes against the vehicle file's `direction`. Motor
    n of fixed thruster i is the motor whose SERVOc_FUNCTION its channel c carries (motor c where
    the log does not say). None when nothing is reversed or the vehicle has no fixed thrusters."""
    if not vehicle.fixed or not parameters:
        return None
    signs = []
    for c in vehicle.pwm.fixed_channels:
        fn = parameters.get(f"SERVO{int(c)}_FUNCTION")
        motor = _MOTOR_FUNCTIONS.get(int(fn)) if fn is not None and float(fn).is_integer() else None
        motor = int(c) if fn is None else motor
        d = parameters.get(f"MOT_{motor}_DIRECTION") if motor is not None else None
        signs.append(-1.0 if d is not None and d < 0 else 1.0)
    if all(s > 0 for s in signs):
        return None
    return (1.0,) * vehicle.n_jets + tuple(signs)
