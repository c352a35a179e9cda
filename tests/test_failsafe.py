"""Failsafe state machine: every transition, the refusals, explicit recovery, and the safe output."""

from __future__ import annotations

import math

import numpy as np
import pytest

from hil.plant import Plant
from onboard.failsafe import (
    IMU_TIMEOUT_S,
    FailsafeState,
    Mode,
    on_arm,
    on_disarm,
    on_imu,
    on_reset,
    on_tick,
    safe_command,
)
from onboard.vehicle import load_vehicle


def armed_at(t=1.0) -> FailsafeState:
    s = on_imu(FailsafeState(), t)
    s = on_arm(s, t)
    assert s.mode is Mode.ARMED and s.outputs_enabled
    return s


def test_starts_disarmed_with_outputs_off():
    s = FailsafeState()
    assert s.mode is Mode.DISARMED and not s.outputs_enabled
    assert IMU_TIMEOUT_S == 0.3


def test_arm_refused_without_imu_then_granted():
    s = on_arm(FailsafeState(), 0.0)
    assert s.mode is Mode.DISARMED and "no IMU yet" in s.reason
    s = on_imu(s, 0.5)
    s = on_arm(s, 0.9)  # IMU 0.4 s old: still refused
    assert s.mode is Mode.DISARMED and "no IMU for 0.40 s" in s.reason
    s = on_arm(on_imu(s, 1.0), 1.0)
    assert s.mode is Mode.ARMED and s.since_s == 1.0


def test_arm_refused_while_estimator_diverged():
    s = on_arm(on_imu(FailsafeState(), 1.0), 1.0, estimator_diverged=True)
    assert s.mode is Mode.DISARMED and "estimator diverged" in s.reason


def test_imu_gap_of_0_3_s_is_tolerated_and_longer_trips_failsafe():
    s = armed_at(1.0)
    assert on_tick(s, 1.0 + 0.3).mode is Mode.ARMED  # exactly the limit: still fine
    f = on_tick(s, 1.0 + 0.31)
    assert f.mode is Mode.FAILSAFE and not f.outputs_enabled
    assert "no IMU for 0.31 s" in f.reason and f.since_s == pytest.approx(1.31)


def test_fresh_imu_keeps_it_armed():
    s = armed_at(1.0)
    for k in range(1, 200):
        t = 1.0 + 0.01 * k
        s = on_tick(on_imu(s, t), t)
    assert s.mode is Mode.ARMED


def test_estimator_divergence_trips_failsafe_with_its_reason():
    s = armed_at(1.0)
    f = on_tick(on_imu(s, 1.1), 1.1, estimator_diverged=True, estimator_reason="depth: 50 consecutive gated rejections")
    assert f.mode is Mode.FAILSAFE and f.reason == "estimator diverged: depth: 50 consecutive gated rejections"


def test_recovery_is_not_automatic():
    f = on_tick(armed_at(1.0), 2.0)
    assert f.mode is Mode.FAILSAFE
    for k in range(100):  # the IMU comes back and the estimator is healthy: stays in FAILSAFE
        t = 2.0 + 0.01 * k
        f = on_tick(on_imu(f, t), t)
    assert f.mode is Mode.FAILSAFE
    g = on_arm(f, 3.0)  # arming does not clear it either
    assert g.mode is Mode.FAILSAFE and "disarm (or reset) first" in g.reason


@pytest.mark.parametrize("recover", [on_disarm, on_reset])
def test_explicit_recovery_then_rearm(recover):
    f = on_tick(armed_at(1.0), 2.0)
    d = recover(f, 2.5)
    assert d.mode is Mode.DISARMED and "no IMU for" in d.reason  # the cause stays in the log
    a = on_arm(on_imu(d, 2.6), 2.6)
    assert a.mode is Mode.ARMED


def test_disarm_from_armed_and_reset_is_a_no_op_outside_failsafe():
    s = armed_at(1.0)
    assert on_reset(s, 1.1) == s
    d = on_disarm(s, 1.1)
    assert d.mode is Mode.DISARMED and d.reason == "disarmed"
    assert on_disarm(d, 1.2) == d
    assert on_tick(d, 5.0) == d  # no failsafe while disarmed: outputs are safe already


def test_clock_going_backwards_does_not_rewind_the_last_imu():
    s = on_imu(on_imu(FailsafeState(), 2.0), 1.0)
    assert s.last_imu_s == 2.0


def test_bad_times_raise_clear_errors():
    with pytest.raises(ValueError, match="on_tick: time_s must be a finite number"):
        on_tick(armed_at(), math.nan)
    with pytest.raises(ValueError, match="on_imu: time_s"):
        on_imu(FailsafeState(), "soon")


def test_states_are_frozen():
    with pytest.raises(Exception):
        FailsafeState().mode = Mode.ARMED  # type: ignore[misc]


def test_safe_command_makes_the_vehicle_rise_slowly_and_stay_level():
    """Zero thrust, joints neutral: net buoyancy B - W lifts it at its terminal heave speed w_t,
    (D_l + D_q w_t) w_t = B - W -> w_t = (-2.6 + sqrt(2.6^2 + 4 * 24 * 1.4715)) / 48 = 0.199 m/s."""
    v = load_vehicle()
    u = safe_command(v.n_units)
    np.testing.assert_array_equal(u, np.zeros(12))
    b, e, h = v.body, v.environment, v.hydro
    net = e.rho * e.g * b.volume - b.mass * e.g
    dl, dq = h.linear_damping[2], h.quadratic_damping[2]
    w_t = (-dl + math.sqrt(dl * dl + 4 * dq * net)) / (2 * dq)
    assert w_t == pytest.approx(0.199, abs=1e-3)
    plant = Plant(v, seed=0, depth_m=0.8, command=u, noise=False)
    plant.state[10] = 0.3  # tumbling a little when the failsafe hits
    s = plant.advance(4.0)
    assert plant.state[9] == pytest.approx(-w_t, rel=0.03)  # rising (w < 0) at terminal speed
    assert 0.8 - plant.state[2] < 4.0 * w_t  # never faster than terminal
    roll, pitch, _ = s.truth[-1].euler_rad
    assert abs(roll) < 0.05 and abs(pitch) < 0.05  # the righting moment levels it
    with pytest.raises(ValueError, match="n_units"):
        safe_command(0)
