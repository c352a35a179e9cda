"""Thrust allocation (onboard/allocation.py) against hand-computed cases and cross-forms.

Expectations come from the equations: spec 3's d(alpha, beta) and tau = sum [T d, r x T d],
seed 000 eq. 15 T = rho D^4 n^2 K(J), the QP's closed-form minimiser when no constraint is
active, and the pseudo-inverse of the effectiveness. Limits are checked on every command under
random demands (hypothesis), and the weights are shown to decide how an infeasible demand
degrades by swapping them.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from onboard import model
from onboard.allocation import (
    AllocationConfig,
    JetGeometry,
    PseudoInverseAllocator,
    QpAllocator,
)

DT = 0.01  # s, a 100 Hz control step
S = 0.70711  # the reference layout's cos 45 deg (asr4.toml neutral vectors)
A_R, Z_R = 0.07778, 0.07  # unit position |x| = |y| and z (asr4.toml)

# A generous solver budget where a test is about the maths, not about the clock: the machine is
# shared, and the budget/fallback path has its own test.
RELAXED = dict(time_budget_s=1.0)


def exact(v, **kw):
    """Config with no change penalty and a vanishing effort weight: the QP then only matches the
    wrench (the tiny effort term only picks one solution where several match it equally)."""
    return AllocationConfig.from_vehicle(v, effort_weight=1e-9, change_weight=0.0, **RELAXED, **kw)


def bollard_thrust(v, n):
    """T = rho D^4 n^2 kt0 (seed 000 eq. 15 at J = 0)."""
    return v.environment.rho * v.thruster.diameter ** 4 * n * n * v.thruster.kt[0]


def bollard_speed(v, T):
    """n = sqrt(T / (rho D^4 kt0)), the inverse of the above."""
    return math.sqrt(T / (v.environment.rho * v.thruster.diameter ** 4 * v.thruster.kt[0]))


# ------------------------------------------------------------------------------------------------
# Effectiveness (what the jets can do)


def test_effectiveness_at_zero_angles_is_the_hand_written_matrix(vehicle):
    # Column i = [d_i, r_i x d_i] with d_i = neutral_i. Unit 1: r = (a, a, z), d = (s, s, 0):
    # r x d = (a*0 - z*s, z*s - a*0, a*s - a*s) = (-z s, z s, 0); the others by the same rule.
    zs = Z_R * S
    E_hand = np.array([
        [S, -S, -S, S],
        [S, S, -S, -S],
        [0, 0, 0, 0],
        [-zs, -zs, zs, zs],
        [zs, -zs, -zs, zs],
        [0, 0, 0, 0],
    ])
    geo = JetGeometry(vehicle)
    np.testing.assert_allclose(geo.effectiveness(np.zeros(4), np.zeros(4)), E_hand, atol=1e-5)


def test_frames_and_effectiveness_agree_with_the_model(vehicle):
    rng = np.random.default_rng(1)
    geo = JetGeometry(vehicle)
    for _ in range(5):
        a, b = rng.uniform(-1.3, 1.3, 4), rng.uniform(-1.3, 1.3, 4)
        d, ea, eb = geo.frames(a, b)
        for i, u in enumerate(vehicle.units):
            F = model.jet_frame(a[i], b[i], u.neutral[0], u.neutral[1])
            np.testing.assert_allclose([d[i], ea[i], eb[i]], F, atol=1e-12)
        np.testing.assert_allclose(geo.effectiveness(a, b), model.effectiveness(vehicle, a, b), atol=1e-12)
        # angles() inverts d(alpha, beta)
        a2, b2 = geo.angles(3.0 * d)
        np.testing.assert_allclose(a2, a, atol=1e-12)
        np.testing.assert_allclose(b2, b, atol=1e-12)


def test_thrust_model_is_seed_000_eq_15_and_matches_the_model(vehicle):
    geo = JetGeometry(vehicle)
    D, rho = vehicle.thruster.diameter, vehicle.environment.rho
    kt0, kt1, kt2 = vehicle.thruster.kt
    n, Va = 60.0, 0.4  # J = 0.4 / (60 * 0.0365) = 0.1826, inside j_range
    J = Va / (n * D)
    T_hand = rho * D ** 4 * n * n * (kt0 + kt1 * J + kt2 * J * J)
    assert geo.thrust(np.array([n]), np.array([Va]))[0] == pytest.approx(T_hand, rel=1e-12)
    rng = np.random.default_rng(2)
    for _ in range(20):
        n, Va = rng.uniform(0, vehicle.thruster.n_max), rng.uniform(-1, 3)
        assert geo.thrust(np.array([n]), np.array([Va]))[0] == pytest.approx(
            model.thrust_newton(vehicle, n, Va), rel=1e-12, abs=1e-15)


@settings(max_examples=200, deadline=None)
@given(n=st.floats(0.01, 83.3), va=st.floats(-2.0, 4.0))
def test_inverse_thrust_model_round_trips(vehicle, n, va):
    """speed(thrust(n, V_a), V_a) = n in every regime of J (clipped low, quadratic, clipped high)."""
    geo = JetGeometry(vehicle)
    T = geo.thrust(np.array([n]), np.array([va]))
    n_back = geo.speed(T, np.array([va]))[0]
    assert n_back == pytest.approx(n, rel=1e-9, abs=1e-9)


def test_inverse_thrust_without_inflow_is_bollard(vehicle):
    v = vehicle.with_effects(thrust_inflow=False)
    geo = JetGeometry(v)
    assert geo.speed(np.array([2.0]), np.array([1.0]))[0] == pytest.approx(bollard_speed(v, 2.0), rel=1e-12)


def test_thrust_max_falls_with_axial_inflow(vehicle):
    """T_max = rho D^4 n_max^2 K(J), J = V_a / (n_max D) (seed 000 eq. 15): inflow costs thrust."""
    geo = JetGeometry(vehicle)
    D, n_max = vehicle.thruster.diameter, vehicle.thruster.n_max
    kt0, kt1, kt2 = vehicle.thruster.kt
    Va = 0.5
    J = Va / (n_max * D)
    expected = vehicle.environment.rho * D ** 4 * n_max ** 2 * (kt0 + kt1 * J + kt2 * J * J)
    got = geo.thrust_max(np.array([0.0, Va, -Va, 0.0]))
    assert got[0] == pytest.approx(bollard_thrust(vehicle, n_max), rel=1e-12)
    assert got[1] == pytest.approx(expected, rel=1e-12)
    assert got[2] == pytest.approx(got[0], rel=1e-12)  # J < 0 is clipped to j_range[0] = 0


# ------------------------------------------------------------------------------------------------
# Hand-computed allocations


def test_pure_heave_at_equal_elevation_hand_computed(vehicle):
    """All units at beta = 0.6, alpha = 0, joints frozen: 4 T sin(beta) = lift, radial parts cancel.

    d_i = cos b e1 - sin b e3, so each unit lifts T sin b; the horizontal parts T cos b e1 of
    opposite units cancel and so do their moments (the layout is symmetric). For 3 N up
    (Z = -3 N in FRD): T = 3 / (4 sin 0.6), n = sqrt(T / (rho D^4 kt0)) at rest.
    """
    beta0 = 0.6
    T_hand = 3.0 / (4 * math.sin(beta0))
    n_hand = bollard_speed(vehicle, T_hand)
    tau = np.array([0, 0, -3.0, 0, 0, 0])
    a, b = np.zeros(4), np.full(4, beta0)
    frozen = QpAllocator(vehicle, 1e-9, exact(vehicle))  # travel rate * dt = 5e-9 rad: frozen
    for alloc in (frozen.allocate(tau, a, b), PseudoInverseAllocator(vehicle, DT).allocate(tau, a, b)):
        assert not alloc.fallback, alloc.status
        np.testing.assert_allclose(alloc.thrust_n, T_hand, rtol=1e-4)
        np.testing.assert_allclose(alloc.n_rev_s, n_hand, rtol=1e-4)
        np.testing.assert_allclose(alloc.beta_rad, beta0, atol=1e-8)
        np.testing.assert_allclose(alloc.wrench_achieved, tau, atol=1e-3)
    # The PWM of that command: 1100 + n / n_max * 800 us on the jet channels (asr4 [pwm]).
    pwm = frozen.allocate(tau, a, b).pwm_us(vehicle)
    assert list(pwm[:4]) == [round(1100 + n_hand / vehicle.thruster.n_max * 800)] * 4


def test_pure_heave_from_horizontal_jets_tilts_by_one_rate_step(vehicle):
    """At alpha = beta = 0 every jet is horizontal; a large lift demand can only be met by tilting.

    In one step of dt each elevation can move rate_limit * dt = delta, so the best is every jet at
    the thrust cap tilted up by delta, radial parts cancelling. The cap is the inner polytope's:
    d'f <= T_max / sqrt(1 + k_a^2 + k_b^2) with k_a = cos(0) tan(delta), k_b = tan(delta), so
    |f| = T_max sqrt(1 + tan^2 delta) / sqrt(1 + 2 tan^2 delta) (0.1 % under T_max) and the
    lift is 4 |f| sin(delta).
    """
    delta = vehicle.servo.rate_limit * DT
    T_max = bollard_thrust(vehicle, vehicle.thruster.n_max)
    t2 = math.tan(delta) ** 2
    T_hand = T_max * math.sqrt((1 + t2) / (1 + 2 * t2))
    qp = QpAllocator(vehicle, DT, exact(vehicle))
    alloc = qp.allocate([0, 0, -10.0, 0, 0, 0], np.zeros(4), np.zeros(4))
    assert not alloc.fallback, alloc.status
    np.testing.assert_allclose(alloc.beta_rad, delta, rtol=1e-6)
    # alternating azimuth tilts cancel in every axis, so the wrench leaves alpha free up to the
    # solver's precision (1e-5 N of lateral force ~ 1e-5 rad); 1e-3 rad is 0.06 deg
    np.testing.assert_allclose(alloc.alpha_rad, 0.0, atol=1e-3)
    np.testing.assert_allclose(alloc.thrust_n, T_hand, rtol=1e-4)
    np.testing.assert_allclose(alloc.n_rev_s, bollard_speed(vehicle, T_hand), rtol=1e-4)
    expected = np.array([0, 0, -4 * T_hand * math.sin(delta), 0, 0, 0])
    np.testing.assert_allclose(alloc.wrench_achieved, expected, atol=1e-4)
    # The baseline cannot lift at all with horizontal jets: heave is not in E's range.
    base = PseudoInverseAllocator(vehicle, DT).allocate([0, 0, -10.0, 0, 0, 0], np.zeros(4), np.zeros(4))
    assert abs(base.wrench_achieved[2]) < 1e-9


# ------------------------------------------------------------------------------------------------
# Cross-forms: the QP equals closed forms when no limit is active


def test_qp_equals_pseudo_inverse_with_frozen_joints_and_no_active_limit(vehicle):
    """Joints frozen: f_i = t_i d_i, so the QP is least squares in t. For tau = E t* in E's range
    with t* inside (0, T_max), both the QP and pinv(E) tau give t* exactly."""
    rng = np.random.default_rng(3)
    geo = JetGeometry(vehicle)
    # Frozen joints make the angle rows near-equalities, which ADMM resolves slowly: ask for a
    # tighter tolerance here so the comparison is about the maths, not the stopping rule.
    qp = QpAllocator(vehicle, 1e-9, exact(vehicle, eps_abs=1e-7, eps_rel=1e-7, max_iter=4000))
    base = PseudoInverseAllocator(vehicle, DT)
    for _ in range(10):
        a, b = rng.uniform(-1.2, 1.2, 4), rng.uniform(-1.2, 1.2, 4)
        t_star = rng.uniform(0.3, 3.5, 4)
        tau = geo.effectiveness(a, b) @ t_star
        q, p = qp.allocate(tau, a, b, commit=False), base.allocate(tau, a, b, commit=False)
        assert not q.fallback, q.status
        np.testing.assert_allclose(p.thrust_n, t_star, rtol=1e-9)
        np.testing.assert_allclose(q.thrust_n, t_star, rtol=1e-3, atol=1e-3)
        np.testing.assert_allclose(q.n_rev_s, p.n_rev_s, rtol=1e-3, atol=1e-2)


def test_qp_equals_its_unconstrained_minimiser_when_no_limit_is_active(vehicle):
    """With every constraint inactive the QP's solution is (B'WB + (w_e + w_c) I)^-1 B'W tau.

    On the reference layout that minimiser always points some jet more than 80 deg from its
    neutral (the jets face outward; a shared force or a rigid-body moment field does not), so the
    cross-check uses the same vehicle with joints free to +-180 deg. The current joint angles are
    those of the minimiser's own force directions (no joint needs to move) and its thrusts stay
    below T_max: then nothing is active and the QP must return the minimiser.
    """
    wide = vehicle.with_values({"servo.angle_limit": math.pi})
    rng = np.random.default_rng(4)
    # The null space of B is fixed only by the small effort and change weights, where ADMM moves
    # slowly: a tight tolerance makes this a check of the maths, not of the stopping rule.
    qp = QpAllocator(wide, DT, AllocationConfig.from_vehicle(wide, eps_abs=1e-9, eps_rel=1e-9, max_iter=50000,
                                                             **RELAXED))
    geo = qp.geo
    for _ in range(12):
        tau = rng.normal(size=6) * np.array([1.0, 1.0, 1.0, 0.05, 0.05, 0.05])
        f_u = qp.unconstrained(tau)
        assert np.all(np.linalg.norm(f_u, axis=1) < 3.5)
        a, b = geo.angles(f_u)
        alloc = qp.allocate(tau, a, b, commit=False)
        assert not alloc.fallback, alloc.status
        np.testing.assert_allclose(alloc.force_body_n, f_u, atol=1e-5)
        np.testing.assert_allclose(alloc.wrench_achieved, geo.B @ f_u.reshape(-1), atol=1e-5)


# ------------------------------------------------------------------------------------------------
# Limits: never violated, whatever the demand


def assert_within_limits(v, alloc, a0, b0, dt, nu_r=None):
    lim, step = v.servo.angle_limit, v.servo.rate_limit * dt
    tol = 1e-9
    assert np.all(alloc.n_rev_s >= 0.0) and np.all(alloc.n_rev_s <= v.thruster.n_max + tol)
    assert np.all(np.abs(alloc.alpha_rad) <= lim + tol) and np.all(np.abs(alloc.beta_rad) <= lim + tol)
    assert np.all(np.abs(alloc.alpha_rad - np.clip(a0, -lim, lim)) <= step + tol)
    assert np.all(np.abs(alloc.beta_rad - np.clip(b0, -lim, lim)) <= step + tol)
    # thrust within [0, T_max(J)] at the final direction's inflow; never backwards
    geo = JetGeometry(v)
    Va = geo.axial_inflow(np.zeros(6) if nu_r is None else nu_r, alloc.alpha_rad, alloc.beta_rad)
    assert np.all(alloc.thrust_n >= -tol)
    assert np.all(alloc.thrust_n <= geo.thrust_max(Va) + 1e-9)
    assert np.all(np.isfinite(alloc.wrench_achieved))


_angle = st.floats(-1.4, 1.4)  # a little beyond +-80 deg: current angles are clipped first
_wrench = st.tuples(*[st.floats(-30, 30)] * 3, *[st.floats(-3, 3)] * 3)
_nu = st.tuples(*[st.floats(-0.5, 0.5)] * 3, *[st.floats(-1, 1)] * 3)


@pytest.fixture(scope="module")
def shared_qp(vehicle):
    return QpAllocator(vehicle, DT, AllocationConfig.from_vehicle(vehicle, **RELAXED))


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(tau=_wrench, a=st.lists(_angle, min_size=4, max_size=4), b=st.lists(_angle, min_size=4, max_size=4), nu=_nu)
def test_no_limit_is_ever_violated_under_random_demands(vehicle, shared_qp, tau, a, b, nu):
    a0, b0, nu_r = np.array(a), np.array(b), np.array(nu)
    alloc = shared_qp.allocate(np.array(tau), a0, b0, nu_r)
    assert_within_limits(vehicle, alloc, a0, b0, DT, nu_r)
    base = PseudoInverseAllocator(vehicle, DT).allocate(np.array(tau), a0, b0, nu_r)
    assert_within_limits(vehicle, base, a0, b0, DT, nu_r)


@settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(seq=st.lists(_wrench, min_size=5, max_size=30))
def test_no_limit_is_violated_over_a_sequence_of_committed_steps(vehicle, seq):
    """Each step starts from the previous command (the default): its travel stays within rate * dt."""
    qp = QpAllocator(vehicle, DT, AllocationConfig.from_vehicle(vehicle, **RELAXED))
    a0, b0 = np.zeros(4), np.zeros(4)
    for tau in seq:
        alloc = qp.allocate(np.array(tau))
        assert_within_limits(vehicle, alloc, a0, b0, DT)
        a0, b0 = alloc.alpha_rad, alloc.beta_rad


# ------------------------------------------------------------------------------------------------
# Infeasible demands degrade by the weights


def normalised_errors(alloc, config):
    """|residual| per axis over its scale (F for forces, F L for moments)."""
    F, L = config.force_scale_n, config.moment_arm_m
    return np.abs(alloc.residual_wrench) / np.array([F, F, F, F * L, F * L, F * L])


def test_infeasible_demand_degrades_by_the_weights(vehicle):
    """Surge and heave both asked far beyond reach, equally in normalised terms: the heavier
    weighted axis is matched better, and swapping the two weights swaps the outcome."""
    a, b = np.zeros(4), np.full(4, 0.5)
    base_cfg = AllocationConfig.from_vehicle(vehicle, **RELAXED)
    F = base_cfg.force_scale_n
    tau = np.array([3 * F, 0, -3 * F, 0, 0, 0])
    results = {}
    for name, w in {"heave first": (1, 1, 10, 10, 10, 1), "surge first": (10, 1, 1, 10, 10, 1)}.items():
        cfg = AllocationConfig.from_vehicle(vehicle, axis_weights=w, **RELAXED)
        alloc = QpAllocator(vehicle, DT, cfg).allocate(tau, a, b)
        assert not alloc.fallback, alloc.status
        assert_within_limits(vehicle, alloc, a, b, DT)
        results[name] = normalised_errors(alloc, cfg)
    assert results["heave first"][2] < results["heave first"][0]
    assert results["surge first"][0] < results["surge first"][2]
    assert results["heave first"][2] < results["surge first"][2]


def test_infeasible_moment_demand_keeps_roll_before_yaw(vehicle):
    """Roll (weight 10) and yaw (weight 1) both asked beyond reach: roll is matched better."""
    cfg = AllocationConfig.from_vehicle(vehicle, **RELAXED)
    M = 3 * cfg.force_scale_n * cfg.moment_arm_m
    a, b = np.full(4, 0.3), np.full(4, 0.5)
    alloc = QpAllocator(vehicle, DT, cfg).allocate([0, 0, 0, M, 0, M], a, b)
    e = normalised_errors(alloc, cfg)
    assert e[3] < e[5]
    assert_within_limits(vehicle, alloc, a, b, DT)


# ------------------------------------------------------------------------------------------------
# Workspace, warm start, fallback


def test_workspace_is_set_up_once_and_warm_started(vehicle):
    cfg = AllocationConfig.from_vehicle(vehicle, **RELAXED)
    qp = QpAllocator(vehicle, DT, cfg)
    solver = qp._solver
    a, b = np.full(4, 0.2), np.full(4, 0.4)
    tau = qp.geo.effectiveness(a, b) @ np.array([1.0, 2.0, 1.5, 2.5])  # reachable without moving
    first = qp.allocate(tau, a, b, commit=False)
    assert not first.fallback, first.status
    again = qp.allocate(tau, a, b, commit=False)
    cold = QpAllocator(vehicle, DT, cfg).allocate(tau, a, b, commit=False)
    assert qp._solver is solver and qp.setups == 1
    assert first.iterations == cold.iterations  # same problem from the same cold start
    assert again.iterations < first.iterations  # the workspace carries the previous solution
    np.testing.assert_allclose(again.command, first.command, rtol=1e-4, atol=1e-4)  # solver tolerance


def test_solver_failure_falls_back_to_the_previous_command(vehicle):
    a, b = np.full(4, 0.2), np.full(4, 0.4)
    good = QpAllocator(vehicle, DT, AllocationConfig.from_vehicle(vehicle, **RELAXED))
    prev = good.allocate([1.0, 0.5, -2.0, 0, 0, 0.02], a, b)
    assert not prev.fallback
    # One ADMM iteration cannot converge: OSQP reports it, the allocator keeps the previous command.
    starved = QpAllocator(vehicle, DT, AllocationConfig.from_vehicle(vehicle, max_iter=1, **RELAXED))
    starved.commit(prev)
    alloc = starved.allocate([5.0, -3.0, -8.0, 0.1, 0.1, 0.1], prev.alpha_rad, prev.beta_rad)
    assert alloc.fallback and "maximum iterations" in alloc.status and "previous command kept" in alloc.status
    np.testing.assert_allclose(alloc.command, prev.command)
    assert_within_limits(vehicle, alloc, prev.alpha_rad, prev.beta_rad, DT)


def test_time_budget_overrun_falls_back(vehicle):
    qp = QpAllocator(vehicle, DT, AllocationConfig.from_vehicle(vehicle, time_budget_s=1e-9))
    alloc = qp.allocate([1.0, 0, -2.0, 0, 0, 0], np.zeros(4), np.full(4, 0.3))
    assert alloc.fallback and alloc.status.startswith("fallback:")
    assert "no previous command: jets off" in alloc.status
    np.testing.assert_array_equal(alloc.n_rev_s, 0.0)
    np.testing.assert_allclose(alloc.beta_rad, 0.3)


def test_non_finite_demand_falls_back_without_raising(vehicle):
    qp = QpAllocator(vehicle, DT, AllocationConfig.from_vehicle(vehicle, **RELAXED))
    ok = qp.allocate([0, 0, -2.0, 0, 0, 0], np.zeros(4), np.full(4, 0.5))
    bad = qp.allocate([np.nan, 0, -2.0, 0, 0, 0])
    assert bad.fallback and "non-finite demand" in bad.status
    np.testing.assert_allclose(bad.command, ok.command)


def test_bad_input_gives_a_clear_error(vehicle):
    qp = QpAllocator(vehicle, DT)
    with pytest.raises(ValueError, match=r"wrench demand .*expected 6 values"):
        qp.allocate([1.0, 2.0, 3.0])
    with pytest.raises(ValueError, match=r"alpha_rad .*expected 4 values"):
        qp.allocate(np.zeros(6), alpha=[0.0, 0.0])
    with pytest.raises(ValueError, match=r"dt_s: expected the control period"):
        QpAllocator(vehicle, 0.0)
    with pytest.raises(ValueError, match=r"axis_weights: expected 6 finite weights"):
        AllocationConfig(axis_weights=(1, 1, 1))
    with pytest.raises(ValueError, match=r"effort_weight: expected a finite number >= 0"):
        AllocationConfig(effort_weight=-1.0)


def test_change_penalty_applies_only_with_a_previous_command(vehicle):
    """No previous command (first step, reset): nothing to change from, so the plan equals that of
    an allocator without the change term. With one, the plan stays nearer to it."""
    a, b = np.full(4, 0.1), np.full(4, 0.5)
    tau1 = np.array([1.0, 0.0, -3.0, 0.0, 0.0, 0.0])
    tau2 = np.array([-1.0, 0.8, -2.0, 0.0, 0.0, 0.1])
    with_c = QpAllocator(vehicle, DT, AllocationConfig.from_vehicle(vehicle, change_weight=1.0, **RELAXED))
    without = QpAllocator(vehicle, DT, AllocationConfig.from_vehicle(vehicle, change_weight=0.0, **RELAXED))
    first, ref = with_c.allocate(tau1, a, b), without.allocate(tau1, a, b)
    np.testing.assert_allclose(first.force_body_n, ref.force_body_n, atol=2e-3)
    pulled = with_c.allocate(tau2, a, b)  # previous = first
    free = without.allocate(tau2, a, b, commit=False)
    assert np.linalg.norm(pulled.force_body_n - first.force_body_n) < np.linalg.norm(free.force_body_n - first.force_body_n)
    with_c.reset()
    again = with_c.allocate(tau2, a, b, commit=False)
    np.testing.assert_allclose(again.force_body_n, free.force_body_n, atol=2e-3)


def test_assigning_previous_is_committing_it(vehicle):
    """The loop sets `allocator.previous = None` on a restart and tests set it directly: the change
    reference follows the assignment exactly as it follows commit() / reset() (same plan, bit for
    bit, on twin allocators), and an assigned allocation is not changed by later steps."""
    cfg = AllocationConfig.from_vehicle(vehicle, change_weight=1.0, **RELAXED)
    a, b = np.full(4, 0.1), np.full(4, 0.5)
    tau1 = np.array([1.0, 0.0, -3.0, 0.0, 0.0, 0.0])
    tau2 = np.array([-1.0, 0.8, -2.0, 0.0, 0.0, 0.1])
    x, y = QpAllocator(vehicle, DT, cfg), QpAllocator(vehicle, DT, cfg)
    first = x.allocate(tau1, a, b, commit=False)
    y.allocate(tau1, a, b, commit=False)  # same solver history
    x.commit(first)
    y.previous = first
    px, py = x.allocate(tau2, a, b, commit=False), y.allocate(tau2, a, b, commit=False)
    np.testing.assert_array_equal(px.command, py.command)
    assert np.linalg.norm(px.force_body_n - first.force_body_n) > 0  # a real step away from it
    x.reset()
    y.previous = None
    rx, ry = x.allocate(tau2, a, b), y.allocate(tau2, a, b)
    np.testing.assert_array_equal(rx.command, ry.command)
    assert not first.force_body_n.flags.writeable and not rx.thrust_n.flags.writeable


def test_allocator_thrust_is_the_plant_model_thrust_with_inflow_off_too():
    """With `thrust_inflow` off the allocator's thrust is the model's bollard thrust as well."""
    from onboard import model
    from onboard.allocation import JetGeometry
    from onboard.vehicle import load_vehicle

    rng = np.random.default_rng(7)
    for inflow in (False,):
        v = load_vehicle().with_effects(thrust_inflow=inflow)
        geo, p = JetGeometry(v), model.pack_params(v)
        n = rng.uniform(0.0, v.thruster.n_max, 200)
        va = rng.uniform(-1.0, 2.0, 200)
        expected = [model.jet_thrust(float(a), float(b), p) for a, b in zip(n, va)]
        np.testing.assert_allclose(geo.thrust(n, va), expected, rtol=1e-12, atol=1e-12)


# ------------------------------------------------------------------------------------------------
# Reconfiguration around unit faults (issue #7: onboard.monitor -> set_health)


def d_hand(v, i, alpha, beta):
    """Spec 3 thrust direction: d = cos b cos a e1 + cos b sin a e2 - sin b e3, e2 = (-e1y, e1x, 0)."""
    e1 = np.array(v.units[i].neutral, float)
    e2 = np.array([-e1[1], e1[0], 0.0])
    return math.cos(beta) * math.cos(alpha) * e1 + math.cos(beta) * math.sin(alpha) * e2 - math.sin(beta) * np.array([0, 0, 1.0])


def wrench_hand(v, thrust, alpha, beta):
    """tau = sum_i [T_i d_i, r_i x T_i d_i] (spec 3)."""
    tau = np.zeros(6)
    for i, T in enumerate(thrust):
        f = T * d_hand(v, i, alpha[i], beta[i])
        tau[:3] += f
        tau[3:] += np.cross(np.array(v.units[i].position, float), f)
    return tau


@pytest.fixture(scope="module")
def health_qp(vehicle):
    """One QP workspace for every health below: set_health only changes its bounds."""
    return QpAllocator(vehicle, DT, AllocationConfig.from_vehicle(vehicle, **RELAXED))


_share = st.floats(0.1, 0.9)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(dead=st.integers(0, 3), shares=st.lists(_share, min_size=4, max_size=4),
       a=st.lists(st.floats(-1.0, 1.0), min_size=4, max_size=4),
       b=st.lists(st.floats(-1.0, 1.0), min_size=4, max_size=4))
def test_dead_unit_is_never_used_and_a_three_unit_wrench_is_still_met(vehicle, health_qp, dead, shares, a, b):
    """Unit `dead` has efficiency 0. The demand is what the three others give at thrusts
    share_i * T_max along their current directions (hand-computed, spec 3), so it is feasible
    without moving a joint: the QP meets it (to the linearised direction polytope's precision, 5 %
    of |force| and of |moment|; exactly with frozen joints in the hand case below), never uses the
    dead unit (n = 0, T = 0, its joints left where they are) and breaks no limit."""
    v, qp = vehicle, health_qp
    eff = np.ones(4)
    eff[dead] = 0.0
    T_max = bollard_thrust(v, v.thruster.n_max)
    T = np.array(shares) * T_max
    T[dead] = 0.0
    a0, b0 = np.array(a), np.array(b)
    tau = wrench_hand(v, T, a0, b0)
    qp.set_health(eff)
    alloc = qp.allocate(tau, a0, b0, commit=False)
    qp.set_health()
    assert not alloc.fallback, alloc.status
    assert alloc.n_rev_s[dead] == 0.0 and alloc.thrust_n[dead] == 0.0
    assert alloc.alpha_rad[dead] == a0[dead] and alloc.beta_rad[dead] == b0[dead]
    assert_within_limits(v, alloc, a0, b0, DT)
    res = alloc.wrench_achieved - tau
    assert np.linalg.norm(res[:3]) <= 0.05 * np.linalg.norm(tau[:3]) + 1e-3
    assert np.linalg.norm(res[3:]) <= 0.05 * np.linalg.norm(tau[3:]) + 1e-4
    assert qp.setups == 1


def test_dead_unit_by_hand_heave_from_three_jets(vehicle):
    """All joints frozen at beta = 0.6 (alpha = 0), unit 0 dead. Unit 2 sits opposite unit 0, so
    without unit 0 the radial forces of 1 and 3 cancel each other but unit 2's does not: the only
    exact answer to a pure heave demand of -Z = 3 sin(0.6) T N... is none; ask instead for exactly
    what units 1, 2, 3 give at T = 1 N each (hand-computed wrench): the QP returns T = (0, 1, 1, 1)."""
    v = vehicle
    a0, b0 = np.zeros(4), np.full(4, 0.6)
    T = np.array([0.0, 1.0, 1.0, 1.0])
    tau = wrench_hand(v, T, a0, b0)
    frozen = QpAllocator(v, 1e-9, exact(v))
    frozen.set_health([0.0, 1.0, 1.0, 1.0])
    alloc = frozen.allocate(tau, a0, b0)
    assert not alloc.fallback, alloc.status
    np.testing.assert_allclose(alloc.thrust_n, T, atol=2e-3)
    assert alloc.n_rev_s[0] == 0.0
    np.testing.assert_allclose(alloc.n_rev_s[1:], bollard_speed(v, 1.0), rtol=2e-3)
    base = PseudoInverseAllocator(v, DT)
    base.set_health([0.0, 1.0, 1.0, 1.0])
    b = base.allocate(tau, a0, b0)
    np.testing.assert_allclose(b.thrust_n, T, atol=1e-9)  # E t = tau has the exact solution t = T
    assert b.n_rev_s[0] == 0.0


def test_weak_unit_is_commanded_faster_and_capped_at_its_own_maximum(vehicle):
    """Efficiency e = 0.5 on unit 2: it reaches e n_cmd, so T_max = rho D^4 (e n_max)^2 kt0 = e^2 T_max
    (bollard), and a thrust T needs n_cmd = sqrt(T / (rho D^4 kt0)) / e. Joints frozen at beta = 0.6.

    At equal elevations (1, -1, 1, -1) thrusts give no wrench (opposite units cancel), so the
    thrusts are chosen orthogonal to it: both allocators then return that minimum-norm answer."""
    v = vehicle
    e = 0.5
    a0, b0 = np.zeros(4), np.full(4, 0.6)
    T = np.array([1.0, 0.75, 0.5, 0.75])  # 0.5 N is below e^2 T_max = 0.25 * T_max(~4 N)
    assert T @ [1, -1, 1, -1] == 0.0
    assert T[2] < e * e * bollard_thrust(v, v.thruster.n_max)
    tau = wrench_hand(v, T, a0, b0)
    eff = [1.0, 1.0, e, 1.0]
    for alloc_ in (QpAllocator(v, 1e-9, exact(v)), PseudoInverseAllocator(v, DT)):
        alloc_.set_health(eff)
        alloc = alloc_.allocate(tau, a0, b0)
        assert not alloc.fallback, alloc.status
        np.testing.assert_allclose(alloc.thrust_n, T, atol=2e-3)  # the thrust the unit really gives
        np.testing.assert_allclose(alloc.n_rev_s[2], bollard_speed(v, T[2]) / e, rtol=2e-3)
        np.testing.assert_allclose(alloc.wrench_achieved, tau, atol=2e-3)
        np.testing.assert_allclose(alloc.thrust_max_n[2], e * e * bollard_thrust(v, v.thruster.n_max), rtol=1e-9)
    # a demand beyond the weak unit's cap: its thrust stops at e^2 T_max, at n_cmd = n_max
    qp = QpAllocator(v, 1e-9, exact(v))
    qp.set_health(eff)
    big = qp.allocate(wrench_hand(v, [1.0, 2.0, 3.0, 2.0], a0, b0), a0, b0)
    assert big.thrust_n[2] <= e * e * bollard_thrust(v, v.thruster.n_max) + 1e-9
    assert big.n_rev_s[2] <= v.thruster.n_max


@settings(max_examples=100, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(tau=_wrench, unit=st.integers(0, 3), joint=st.sampled_from(["alpha", "beta"]), angle=st.floats(-1.2, 1.2),
       a=st.lists(st.floats(-1.2, 1.2), min_size=4, max_size=4), b=st.lists(st.floats(-1.2, 1.2), min_size=4, max_size=4))
def test_stuck_joint_is_held_at_its_angle(vehicle, health_qp, tau, unit, joint, angle, a, b):
    """Joint `joint` of `unit` stuck at `angle`: whatever the demand and wherever the last command
    put it, the command keeps it at `angle`, the other joints travel at most rate * dt, no limit is broken, and the reported wrench is that of the joint at
    its stuck angle."""
    v, qp = vehicle, health_qp
    stuck = np.full(4, np.nan)
    stuck[unit] = angle
    qp.set_health(None, stuck if joint == "alpha" else None, stuck if joint == "beta" else None)
    a0, b0 = np.array(a), np.array(b)
    alloc = qp.allocate(np.array(tau), a0, b0, commit=False)
    got = alloc.alpha_rad if joint == "alpha" else alloc.beta_rad
    assert got[unit] == angle
    a_ref, b_ref = a0.copy(), b0.copy()
    (a_ref if joint == "alpha" else b_ref)[unit] = angle  # where the joint really is
    assert_within_limits(v, alloc, a_ref, b_ref, DT)
    # what is reported is what the jets give with that joint where it is stuck (spec 3 by hand)
    np.testing.assert_allclose(alloc.wrench_achieved, wrench_hand(v, alloc.thrust_n, alloc.alpha_rad, alloc.beta_rad),
                               rtol=1e-5, atol=1e-9)
    qp.set_health()


def test_set_health_rejects_bad_values_clearly(vehicle):
    qp = PseudoInverseAllocator(vehicle, DT)
    with pytest.raises(ValueError, match=r"efficiency: expected 4 values in \[0, 1\]"):
        qp.set_health([1.0, 1.5, 1.0, 1.0])
    with pytest.raises(ValueError, match="efficiency: expected 4 values in"):
        qp.set_health([1.0, float("nan"), 1.0, 1.0])
    with pytest.raises(ValueError, match="efficiency .per unit.: expected 4 values"):
        qp.set_health([1.0, 1.0])
    with pytest.raises(ValueError, match="stuck_alpha_rad: expected finite angles"):
        qp.set_health(None, [math.inf, math.nan, math.nan, math.nan])
