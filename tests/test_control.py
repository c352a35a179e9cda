"""Controller: hand-computed feed-forward, gains from bandwidths, and closed loops on the plant.

The closed loops use the true state (`state_from_truth`) and a pseudo-inverse allocator written
here (the baseline a user would otherwise have): per-unit force vectors f = B^+ tau from the
6 x 3k wrench map, plus a radial-outward preload that lies in B's null space (the four radial
directions cancel in force and moment) so every jet pushes outward within its joint limits; each
f_i then becomes azimuth, elevation and propeller speed by the spec-3 geometry and seed-000
bollard thrust. The QP allocator (onboard/allocation.py) is tested on its own.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
import pytest

from hil.plant import Plant
from onboard import model
from onboard.control import Controller, Gains, ManualAxes, Setpoint, Wrench, axis_capacity
from onboard.estimator import state_from_truth
from onboard.vehicle import load_vehicle

VEHICLE = load_vehicle()
DEG = math.pi / 180
W_MINUS_B = VEHICLE.body.mass * 9.81 - 1000.0 * 9.81 * VEHICLE.body.volume  # 63.765 - 65.2365 N


# ------------------------------------------------------------------------------------------------
# baseline allocator (test helper)

def _geometry(v):
    e1 = np.array([u.neutral for u in v.units], dtype=float)
    e3 = np.array([0.0, 0.0, 1.0])
    e2 = np.cross(e3, e1)  # e2 = e3 x e1 (spec 3)
    return e1, e2, e3


def pinv_allocate(v, tau, B_pinv, preload_n=0.3):
    """u = [n, alpha, beta] from f = B^+ tau + b e1_i (null-space preload b >= what the limits need)."""
    k = v.n_units
    e1, e2, e3 = _geometry(v)
    f = (B_pinv @ np.asarray(tau, float)).reshape(k, 3)
    lim = v.servo.angle_limit
    cot = math.tan(math.pi / 2 - lim)  # |angle| <= lim  <=>  f.e1 >= cot(lim) |lateral|
    need = max(cot * max(abs(f[i] @ e2[i]), abs(f[i] @ e3)) - f[i] @ e1[i] for i in range(k))
    f = f + (max(need, 0.0) + preload_n) * e1
    rho, D, kt0 = v.environment.rho, v.thruster.diameter, v.thruster.kt[0]
    n, al, be = np.zeros(k), np.zeros(k), np.zeros(k)
    for i in range(k):
        c1, c2, c3 = f[i] @ e1[i], f[i] @ e2[i], f[i] @ e3
        # d = c(b) c(a) e1 + c(b) s(a) e2 - s(b) e3
        al[i] = np.clip(math.atan2(c2, c1), -lim, lim)
        be[i] = np.clip(math.atan2(-c3, math.hypot(c1, c2)), -lim, lim)
        d = model.jet_frame(al[i], be[i], e1[i, 0], e1[i, 1])[0]
        T = max(float(f[i] @ d), 0.0)
        n[i] = min(math.sqrt(T / (rho * D ** 4 * kt0)), v.thruster.n_max)  # T = rho D^4 n^2 kt0
    return np.concatenate([n, al, be])


def test_pinv_allocator_reproduces_a_feasible_wrench():
    """Static check of the helper: bollard thrust at the commanded angles gives back the demand."""
    v = VEHICLE.with_effects(thrust_inflow=False)
    tau = np.array([1.0, -0.5, 2.0, 0.02, -0.03, 0.05])
    u = pinv_allocate(v, tau, np.linalg.pinv(model.wrench_map(v)))
    k = v.n_units
    T = np.array([model.thrust_newton(v, n) for n in u[:k]])
    got = model.effectiveness(v, u[k:2 * k], u[2 * k:]) @ T
    # 1e-4: the file's neutral vectors (0.70711, 0.70711) are unit to 5 digits, so the radial
    # preload cancels to ~1e-5 N rather than exactly
    np.testing.assert_allclose(got, tau, atol=1e-4)


# ------------------------------------------------------------------------------------------------
# closed loop on the plant

def fly(schedule, t_end, feedforward=True, dt=0.01, depth0=0.5, vehicle=VEHICLE, seed=0):
    plant = Plant(vehicle, seed=seed, depth_m=depth0)
    ctl = Controller(vehicle, Gains(feedforward=feedforward))
    Bp = np.linalg.pinv(model.wrench_map(vehicle))
    rows = []
    t = 0.0
    while t < t_end - 1e-9:
        est = state_from_truth(plant.state, vehicle, t)
        w = ctl.step(est, schedule(t), dt)
        plant.set_command(pinv_allocate(vehicle, w.as_array(), Bp))
        r = ctl.reference
        rows.append((t, est.depth_m, np.nan if r.depth_m is None else r.depth_m, est.euler_rad[2], r.yaw_rad,
                     est.velocity_body_m_s[0], r.velocity_body_m_s[0] or 0.0, est.euler_rad[0], est.euler_rad[1]))
        t += dt
        plant.advance(t)
    return np.array(rows)


T, DEPTH, DEPTH_REF, YAW, YAW_REF, U, U_REF, ROLL, PITCH = range(9)


@lru_cache(maxsize=None)
def mission(name, feedforward=True):
    if name == "depth":
        return fly(lambda t: Setpoint(depth_m=0.8 if t >= 1.0 else 0.5, yaw_rad=0.0), 10.0, feedforward)
    if name == "yaw":
        return fly(lambda t: Setpoint(depth_m=0.5, yaw_rad=math.pi / 2 if t >= 1.0 else 0.0), 9.0, feedforward)
    if name == "surge":
        return fly(lambda t: Setpoint(depth_m=0.5, yaw_rad=0.0,
                                      velocity_body_m_s=(0.3 if t >= 1.0 else 0.0, 0.0, None)), 9.0, feedforward)
    raise KeyError(name)


def wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


def test_depth_step_settles():
    """0.5 -> 0.8 m at t = 1 s: within 1 cm from t = 8 s, overshoot < 1 cm, level within 1 deg."""
    L = mission("depth")
    after = L[L[:, T] >= 8.0]
    assert np.all(np.abs(after[:, DEPTH] - 0.8) < 0.01)
    assert L[:, DEPTH].max() < 0.81
    assert L[L[:, T] < 1.0, DEPTH].min() > 0.49  # held before the step
    assert np.all(np.abs(L[:, ROLL]) < 1 * DEG) and np.all(np.abs(L[:, PITCH]) < 1 * DEG)


def test_yaw_90_deg_turn():
    """Within 2 deg of 90 deg from t = 6 s, overshoot < 3 deg; depth held within 2 cm meanwhile."""
    L = mission("yaw")
    err = np.abs(wrap(L[:, YAW] - math.pi / 2))
    assert np.all(err[L[:, T] >= 6.0] < 2 * DEG)
    assert L[:, YAW].max() < math.pi / 2 + 3 * DEG
    assert np.all(np.abs(L[:, DEPTH] - 0.5) < 0.02)


def test_surge_0_3_m_s():
    """u within 0.015 m/s of 0.3 from t = 5 s; depth within 2 cm and heading within 1 deg throughout."""
    L = mission("surge")
    assert np.all(np.abs(L[L[:, T] >= 5.0, U] - 0.3) < 0.015)
    assert np.all(np.abs(L[:, DEPTH] - 0.5) < 0.02)
    assert np.all(np.abs(wrap(L[:, YAW])) < 1 * DEG)


def _rms(a):
    return float(np.sqrt(np.nanmean(np.square(a))))


@pytest.mark.parametrize("name,column,ref", [("depth", DEPTH, DEPTH_REF), ("surge", U, U_REF), ("yaw", YAW, YAW_REF)])
def test_feedforward_at_least_halves_tracking_error(name, column, ref):
    """Same feedback gains, with and without the model feed-forward: RMS error to the reference."""
    errs = []
    for ff in (True, False):
        L = mission(name, ff)
        e = L[:, column] - L[:, ref]
        errs.append(_rms(wrap(e) if column == YAW else e))
    assert errs[0] < 0.5 * errs[1], errs


def test_manual_sticks_fly_and_centred_sticks_hold():
    """Surge stick at 0.5 -> u -> 0.5 * 0.4 m/s; heave stick down for 2 s then centred holds depth."""
    def sticks(t):
        return Setpoint(manual=ManualAxes(surge=0.5, heave_down=1.0 if 1.0 <= t < 3.0 else 0.0))
    L = fly(sticks, 9.0)
    g = Gains()
    assert np.all(np.abs(L[L[:, T] >= 6.0, U] - 0.5 * g.manual_speed_m_s) < 0.015)
    late = L[L[:, T] >= 6.0, DEPTH]
    assert late.mean() > 0.5 + 0.3 and np.ptp(late) < 0.01  # went down ~2 s x 0.25 m/s, then held


# ------------------------------------------------------------------------------------------------
# hand-computed demands

def _at_rest(depth=0.5, u=0.0):
    x = model.initial_state(VEHICLE, depth)
    x[7] = u
    return state_from_truth(x, VEHICLE)


def test_hover_demand_is_net_buoyancy():
    """Level, at rest, holding where it is: tau = g(eta) = [0, 0, B - W, 0, 0, 0] (1.4715 N down)."""
    tau = Controller(VEHICLE).step(_at_rest(), Setpoint(depth_m=0.5, yaw_rad=0.0), 0.01).as_array()
    np.testing.assert_allclose(tau, [0, 0, -W_MINUS_B, 0, 0, 0], atol=1e-9)
    assert -W_MINUS_B == pytest.approx(1.4715, abs=1e-4)
    # gains alone: nothing until an error builds up
    tau0 = Controller(VEHICLE, Gains(feedforward=False)).step(_at_rest(), Setpoint(depth_m=0.5, yaw_rad=0.0), 0.01)
    np.testing.assert_allclose(tau0.as_array(), 0.0, atol=1e-12)


def test_cruise_demand_is_damping():
    """At u = 0.3 m/s on reference: X = (D_l + D_q |u|) u = 1.8 * 0.3 + 18 * 0.09 = 2.16 N."""
    est = _at_rest(u=0.3)
    tau = Controller(VEHICLE).step(est, Setpoint(depth_m=0.5, yaw_rad=0.0, velocity_body_m_s=(0.3, 0.0, None)), 0.01)
    assert tau.force_body_n[0] == pytest.approx(2.16, abs=1e-9)
    assert tau.force_body_n[2] == pytest.approx(-W_MINUS_B, abs=1e-9)


def test_gains_follow_from_bandwidth_and_mass():
    """K_p = (m + Z_wdot * wall) w^2 with wall = 1 + 0.375 (0.16 / 0.7)^3 at 0.5 m over a 1.2 m floor."""
    wall = 1 + 0.375 * (0.16 / 0.7) ** 3
    m_heave = 6.5 + 4.1 * wall
    g = Gains()
    k = Controller(VEHICLE, g).gains_si
    assert k["depth_kp_n_m"] == pytest.approx(m_heave * g.depth_bandwidth_rad_s ** 2, rel=1e-12)
    assert k["depth_kd_n_s_m"] == pytest.approx(2 * g.damping_ratio * g.depth_bandwidth_rad_s * m_heave, rel=1e-12)
    assert k["yaw_kp_nm_rad"] == pytest.approx((0.075 + 0.002) * g.yaw_bandwidth_rad_s ** 2, rel=1e-12)
    assert k["surge_kv_n_s_m"] == pytest.approx((6.5 + 3.3) * g.velocity_bandwidth_rad_s, rel=1e-12)


def test_anti_windup_clamps_and_stops_on_reported_saturation():
    """Vehicle pinned at 0.5 m with a 0.8 m setpoint for 30 s (reference settled):
    - no allocator feedback: the integrator runs to its clamp, integral_share * capacity = 0.3 * 4 T_max;
    - allocator reports nothing achieved: conditional integration keeps the integral at zero, so
      Z = K_p e + (B - W) = M_33 w^2 0.3 + 1.4715."""
    est = _at_rest()
    sp = Setpoint(depth_m=0.8, yaw_rad=0.0)
    g = Gains()
    t_max = 1000 * 0.0365 ** 4 * 83.3 ** 2 * 0.350165  # seed 000 bollard thrust, 4.3126 N
    assert axis_capacity(VEHICLE)[2] == pytest.approx(4 * t_max)
    wall = 1 + 0.375 * (0.16 / 0.7) ** 3
    p_part = (6.5 + 4.1 * wall) * g.depth_bandwidth_rad_s ** 2 * 0.3 - W_MINUS_B
    free, pinned = Controller(VEHICLE, g), Controller(VEHICLE, g)
    for _ in range(3000):
        z_free = free.step(est, sp, 0.01).force_body_n[2]
        z_pinned = pinned.step(est, sp, 0.01, achieved=np.zeros(6)).force_body_n[2]
    assert z_pinned == pytest.approx(p_part, abs=1e-6)
    assert z_free == pytest.approx(p_part + g.integral_share * 4 * t_max, abs=1e-6)


def test_setpoint_validation_names_the_field():
    with pytest.raises(ValueError, match="depth_m"):
        Setpoint(depth_m=float("nan"))
    with pytest.raises(ValueError, match=r"velocity_body_m_s"):
        Setpoint(velocity_body_m_s=(0.1, 0.2))
    with pytest.raises(ValueError, match=r"manual.surge"):
        ManualAxes(surge="fast")
    with pytest.raises(ValueError, match="depth_bandwidth_rad_s"):
        Gains(depth_bandwidth_rad_s=-1.0)
    assert ManualAxes(surge=3.0).surge == 1.0  # sticks saturate, they do not raise


def test_wrench_round_trip():
    w = Wrench.from_array([1, 2, 3, 4, 5, 6])
    assert w.force_body_n == (1.0, 2.0, 3.0) and w.moment_body_nm == (4.0, 5.0, 6.0)
    np.testing.assert_array_equal(w.as_array(), [1, 2, 3, 4, 5, 6])


def test_yaw_turns_the_short_way_across_pi():
    """At 170 deg asked for -170 deg: the error is +20 deg, so the yaw moment is positive and the
    reference crosses +180 deg rather than sweeping back through 0."""
    x = model.initial_state(VEHICLE, 0.5)
    x[3:7] = model.euler_to_quat(0.0, 0.0, 170 * DEG)
    est = state_from_truth(x, VEHICLE)
    ctl = Controller(VEHICLE)
    sp = Setpoint(depth_m=0.5, yaw_rad=-170 * DEG)
    first = ctl.step(est, sp, 0.01)
    assert first.moment_body_nm[2] > 0.0
    for _ in range(400):
        ctl.step(est, sp, 0.01)
    assert abs(wrap(ctl.reference.yaw_rad - (-170 * DEG))) < 1 * DEG
    assert ctl.reference.yaw_rate_rad_s >= -1e-6  # it never turned the long way


def test_heave_free_demands_no_vertical_effort():
    """No depth and no heave velocity: the vehicle is left to its buoyancy (Z = 0), level held."""
    tau = Controller(VEHICLE).step(_at_rest(), Setpoint(yaw_rad=0.0, velocity_body_m_s=(0.0, 0.0, None)), 0.01)
    np.testing.assert_allclose(tau.as_array(), 0.0, atol=1e-12)
    assert Controller(VEHICLE).step(_at_rest(), Setpoint(), 0.01).as_array() @ np.ones(6) == pytest.approx(0.0)


def test_controller_refuses_bad_dt_and_nonfinite_estimate():
    ctl = Controller(VEHICLE)
    with pytest.raises(ValueError, match="dt must be"):
        ctl.step(_at_rest(), Setpoint(), 0.0)
    bad = state_from_truth(model.initial_state(VEHICLE, 0.5), VEHICLE)
    from dataclasses import replace
    with pytest.raises(ValueError, match="non-finite"):
        ctl.step(replace(bad, depth_m=float("nan")), Setpoint(), 0.01)


# ------------------------------------------------------------------------------------------------
# the yaw reference and its preview (what the transient compensation plans along)

def test_yaw_reference_is_third_order_by_hand():
    """From rest toward pi/2 (w = 2, dt = 0.01): the first step's jerk is w^3 pi/2, so
    psi_r'' = 8 pi/2 0.01 = 0.12566, psi_r' = psi_r'' dt, psi_r = psi_r' dt. Without the rate
    limit the discrete reference follows the critically damped third-order step response
    pi/2 (1 - (1 + wt + (wt)^2 / 2) e^(-wt)); with it, |psi_r'| never exceeds the limit and the
    feed-forward I_z psi_r'' never steps by a quarter of what a second-order reference at 1.2 rad/s
    stepped it by at once (I_z 1.2^2 pi/2 = 0.17 N m); the largest step is where the limit sets in."""
    from onboard.control import yaw_reference

    w, dt = 2.0, 0.01
    first = yaw_reference(0.0, 0.0, 0.0, math.pi / 2, 0.0, np.array([w, 10.0, 0.8]), dt, 1)[:, 0]
    acc = w ** 3 * math.pi / 2 * dt
    np.testing.assert_allclose(first, [acc * dt * dt, acc * dt, acc], rtol=1e-9)  # (psi_r is wrapped)
    n = 600
    free = yaw_reference(0.0, 0.0, 0.0, math.pi / 2, 0.0, np.array([w, 10.0, 0.8]), dt, n)
    t = dt * np.arange(1, n + 1)
    exact = math.pi / 2 * (1 - (1 + w * t + (w * t) ** 2 / 2) * np.exp(-w * t))
    assert np.abs(free[0] - exact).max() < 0.01 * math.pi / 2
    g = Gains()
    held = yaw_reference(0.0, 0.0, 0.0, math.pi / 2, 0.0,
                         np.array([g.yaw_reference_rad_s, g.max_yaw_rate_rad_s, 0.8]), dt, n)
    assert np.abs(held[1]).max() == pytest.approx(g.max_yaw_rate_rad_s)  # the limit is reached, and held
    assert abs(held[0, -1] - math.pi / 2) < 1 * DEG
    i_z = VEHICLE.body.inertia[2] + VEHICLE.hydro.added_mass[5]
    jumps = np.abs(np.diff(np.r_[0.0, held[2]]))
    assert i_z * jumps.max() < 0.25 * i_z * 1.2 ** 2 * math.pi / 2
    assert np.argmax(jumps) == np.argmax(np.abs(held[1]) >= g.max_yaw_rate_rad_s)  # at the limit
    # joystick rate (no target): psi_r' follows the rate first order, as before
    rate = yaw_reference(0.0, 0.0, 0.0, math.nan, 0.5, np.array([w, 0.8, 0.8]), dt, 1)[:, 0]
    np.testing.assert_allclose(rate[1:], [0.5 / 0.8 * dt, 0.5 / 0.8], rtol=1e-12)


@pytest.mark.parametrize("setpoint", [Setpoint(depth_m=0.5, yaw_rad=math.pi / 2),
                                      Setpoint(depth_m=0.5, manual=ManualAxes(yaw_right=0.6))],
                         ids=["heading", "joystick rate"])
def test_yaw_preview_is_the_feedforward_the_controller_then_asks(setpoint):
    """`Controller.yaw_preview(n)` after a step equals the yaw feed-forward of that step and of
    the n - 1 steps the controller then takes with the setpoint held (at rest, level, where the
    yaw row of eq. 1's feed-forward is I_z psi_r'' + d1 psi_r' + d2 |psi_r'| psi_r')."""
    ctl = Controller(VEHICLE)
    est = _at_rest()
    for _ in range(15):
        ctl.step(est, setpoint, 0.01)
    ahead = ctl.yaw_preview(40, 0.01)
    asked = [ctl.reference.feedforward[5]]
    for _ in range(39):
        ctl.step(est, setpoint, 0.01)
        asked.append(ctl.reference.feedforward[5])
    assert np.abs(asked).max() > 0.01  # the reference is turning (the test can fail)
    np.testing.assert_allclose(ahead, asked, rtol=1e-9, atol=1e-12)
    assert np.all(Controller(VEHICLE).yaw_preview(5, 0.01) == 0.0)  # nothing before the first step
