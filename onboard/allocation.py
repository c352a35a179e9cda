"""Thrust allocation over vectored water-jets: a warm-started OSQP QP and the fixed-mixing baseline.

Pure math, no IO and no clock of its own (the solve time is measured, not scheduled). Split as
in PX4's control_allocator: what the jets can do (`JetGeometry`: the fixed 6 x 3k wrench map B
of spec 3, the per-unit frames d, e_alpha, e_beta, the seed-000 thrust model and its inverse)
is separate from how it is inverted (`QpAllocator`, `PseudoInverseAllocator`). Both return the
same frozen `Allocation`, which carries its own diagnostics like a qpsolvers `Solution`.

The QP (decision variable: the force vector f_i of each unit, body FRD, newtons):

    min_f  (B f - tau)' W (B f - tau) + w_e |f|^2 + w_c |f - f_prev|^2
    s.t.   0 <= d_i' f_i <= T_cap,i                              thrust, no backwards push
           k_lo,a t_i <= e_alpha,i' f_i <= k_hi,a t_i            azimuth travel this step
           k_lo,b t_i <= e_beta,i'  f_i <= k_hi,b t_i            elevation travel this step

with t_i = d_i' f_i. The direction set of a unit is nonconvex, so the constraints are a
polyhedral inner approximation linearised at the current joint angles: a force tilted from d_i
by the joint changes (da, db) has e_alpha / d and e_beta / d components cos(b) tan(da) and
tan(db), and da, db are bounded by rate_limit * dt and by the angle limits. The magnitude cap
T_cap = T_max / sqrt(1 + k_a^2 + k_b^2) keeps |f_i| <= T_max(J_i), with T_max the seed-000
thrust (eq. 15) at n_max and the unit's estimated axial inflow. After the solve every unit's
force is turned back into (n, alpha, beta) exactly (inverse of d(alpha, beta) and of eq. 15),
the angles and n are clipped to their limits, and the achieved wrench is recomputed from the
clipped command with the forward model, so what is reported is what the jets will do.

Unit health (`set_health`, from onboard.monitor): a weak unit with efficiency e_i reaches only
e_i times its commanded speed, so it gives at most T(e_i n_max, V_a) (= e_i^2 T_max without
inflow) and its speed command is the speed the thrust needs divided by e_i; a dead unit (e_i = 0)
gives nothing: its thrust rows collapse to 0 <= d' f <= 0, so f_i = 0, and its joints stay where
they are. A stuck joint is fixed at its measured angle: the linearisation point is that angle and
its travel window is [0, 0], so the unit's force stays in the plane the joint allows. Only the
bounds and A's values change, in place: the QP is still set up once and warm-started.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
import osqp
import scipy.sparse as sp
from numba import njit

from . import model, pwm
from .jit import MODEL_SOURCE, key_caches_on
from .vehicle import Vehicle

AXES = ("surge", "sway", "heave", "roll", "pitch", "yaw")
_SOLVED = (osqp.SolverStatus.OSQP_SOLVED, osqp.SolverStatus.OSQP_SOLVED_INACCURATE)


# ------------------------------------------------------------------------------------------------
# Configuration


@dataclass(frozen=True)
class AllocationConfig:
    """Weights and solver budget of the allocation (defaults suit the reference vehicle).

    `axis_weights` are relative importances [surge, sway, heave, roll, pitch, yaw]; the wrench
    error is normalised by `force_scale_n` (forces) and `force_scale_n * moment_arm_m` (moments)
    so the weights compare like with like. Roll, pitch and heave weigh more than surge, sway and
    yaw: a submarine that keeps level and depth while it loses some speed is still safe.
    """

    axis_weights: tuple = (1.0, 1.0, 10.0, 10.0, 10.0, 1.0)
    force_scale_n: float = 4.0  # about one jet's bollard thrust
    moment_arm_m: float = 0.1  # about the jets' distance from the body origin
    effort_weight: float = 1e-3  # on |f|^2 / force_scale^2
    # on |f - f_prev|^2 / force_scale^2. A weaker change term lets the azimuths wander in B's null
    # space from step to step, and each swing costs thrust through the seed-004 axial loss (the
    # onboard loop measured ~30 % lost thrust in closed loop at 1e-2). The lag it adds is small
    # beside the joints' own: a 1 N surge step with the jets at beta = 0.6 is met 39, 72, 91, 97 %
    # in the first four 10 ms steps at 1.0, and 39, 72, 99 % at 0.1 (the first two are the
    # joints' rate limit).
    change_weight: float = 1.0
    time_budget_s: float = 1e-3  # over this the previous command is kept (fallback)
    max_iter: int = 400
    eps_abs: float = 1e-5
    eps_rel: float = 1e-5

    def __post_init__(self):
        w = tuple(float(x) for x in self.axis_weights)
        if len(w) != 6 or not all(math.isfinite(x) and x >= 0 for x in w) or max(w) <= 0:
            raise ValueError(f"AllocationConfig.axis_weights: expected 6 finite weights >= 0 "
                             f"[{', '.join(AXES)}], not all zero; got {self.axis_weights!r}")
        object.__setattr__(self, "axis_weights", w)
        for name in ("force_scale_n", "moment_arm_m", "time_budget_s", "eps_abs", "eps_rel"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"AllocationConfig.{name}: expected a finite number > 0, got {v!r}")
        for name in ("effort_weight", "change_weight"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v >= 0):
                raise ValueError(f"AllocationConfig.{name}: expected a finite number >= 0, got {v!r}")
        if not (isinstance(self.max_iter, int) and self.max_iter >= 1):
            raise ValueError(f"AllocationConfig.max_iter: expected an integer >= 1, got {self.max_iter!r}")

    @classmethod
    def from_vehicle(cls, v: Vehicle, **overrides) -> "AllocationConfig":
        """Scales from the vehicle: one jet's bollard thrust and the mean jet lever arm (for a
        vehicle of fixed thrusters: one thruster's forward thrust and their mean lever arm)."""
        if v.fixed and not v.units:
            geo = FixedGeometry(v)
            kw = {"force_scale_n": float(geo.t_max.mean()),
                  "moment_arm_m": float(np.mean(np.linalg.norm(geo.position, axis=1))) or 0.1}
            kw.update(overrides)
            return cls(**kw)
        geo = JetGeometry(v)
        scale = float(geo.thrust_max(np.zeros(v.n_units)).mean())
        arm = float(np.mean(np.linalg.norm(geo.position, axis=1)))
        kw = {"force_scale_n": scale if scale > 0 else 1.0, "moment_arm_m": arm if arm > 0 else 0.1}
        kw.update(overrides)
        return cls(**kw)

    def weight_matrix(self) -> np.ndarray:
        """W = diag(importance / scale^2), scale = F_s for forces and F_s L for moments."""
        F, L = self.force_scale_n, self.moment_arm_m
        s = np.array([F, F, F, F * L, F * L, F * L])
        return np.diag(np.asarray(self.axis_weights) / s**2)


# ------------------------------------------------------------------------------------------------
# Effectiveness: what the jets can do (spec 3, seed 000, seed 003 sec. 3.1). Compiled kernels
# (numba, like onboard.model) so a control step spends its time in the solver, not in numpy
# call overhead; `JetGeometry` is their readable front.
#
# Thrust parameters tp = [rho, D, kt0, kt1, kt2, j_lo, j_hi, n_max, inflow (1/0)].


@njit(cache=True)
def _K(J, tp):
    """K(J) = kt0 + kt1 J + kt2 J^2 (seed 000 eq. 14-15), the model's own function."""
    return model.thrust_coefficient(J, tp[2], tp[3], tp[4])


@njit(cache=True)
def jet_frames(alpha, beta, e1):
    """F[i] = [d_i, e_alpha,i, e_beta,i] (k x 3 x 3) at joint angles alpha, beta (spec 3, 4.1).

    e1 = neutral, e2 = e3 x e1 = (-e1y, e1x, 0), e3 = body z;
    d = cos b cos a e1 + cos b sin a e2 - sin b e3; e_alpha = -sin a e1 + cos a e2;
    e_beta = -sin b cos a e1 - sin b sin a e2 - cos b e3.
    """
    k = alpha.shape[0]
    F = np.empty((k, 3, 3))
    for i in range(k):
        F[i] = model.jet_frame(alpha[i], beta[i], e1[i, 0], e1[i, 1])
    return F


@njit(cache=True)
def frame_angles(f, e1, alpha_default, beta_default):
    """(alpha, beta) of the direction of each row of f: the inverse of d(alpha, beta).

    With c_j = f . e_j and nu = |e1| (1 up to the file's rounding): f . e1 = |f| cos b cos a nu^2,
    f . e2 = |f| cos b sin a nu^2, f . e3 = -|f| sin b, so alpha = atan2(c2, c1) and
    beta = atan2(-c3, sqrt(c1^2 + c2^2) / nu^2). A zero force keeps the default angles.
    """
    k = f.shape[0]
    a = np.empty(k)
    b = np.empty(k)
    for i in range(k):
        m = math.sqrt(f[i, 0] ** 2 + f[i, 1] ** 2 + f[i, 2] ** 2)
        if m <= 1e-9:
            a[i], b[i] = alpha_default[i], beta_default[i]
            continue
        nu2 = e1[i, 0] ** 2 + e1[i, 1] ** 2
        c1 = f[i, 0] * e1[i, 0] + f[i, 1] * e1[i, 1]
        c2 = -f[i, 0] * e1[i, 1] + f[i, 1] * e1[i, 0]
        a[i] = math.atan2(c2, c1)
        b[i] = math.atan2(-f[i, 2], math.sqrt(c1 * c1 + c2 * c2) / nu2)
    return a, b


@njit(cache=True)
def axial_inflow(nu_r, pos, F):
    """V_a,i = (v_r + omega x r_i) . d_i (spec 3; seed 000 eq. 11: only the axial part counts)."""
    k = pos.shape[0]
    out = np.empty(k)
    for i in range(k):
        c0, c1, c2 = model.cross(nu_r[3], nu_r[4], nu_r[5], pos[i, 0], pos[i, 1], pos[i, 2])
        out[i] = (nu_r[0] + c0) * F[i, 0, 0] + (nu_r[1] + c1) * F[i, 0, 1] + (nu_r[2] + c2) * F[i, 0, 2]
    return out


@njit(cache=True)
def thrust_of_speed(n, v_axial, tp):
    """T = rho D^4 n^2 K(J), J = clip(V_a / (n D), j_range), J = 0 at n = 0 (seed 000 eq. 15)."""
    k = n.shape[0]
    out = np.empty(k)
    for i in range(k):
        J = model.advance_ratio(v_axial[i], n[i], tp[1], tp[5], tp[6]) if tp[8] > 0.5 else 0.0
        out[i] = tp[0] * tp[1] ** 4 * n[i] * n[i] * _K(J, tp)
    return out


@njit(cache=True)
def max_thrust(v_axial, tp, eff):
    """T_max(J) of each unit: T(eff_i n_max, V_a) (seed 000 eq. 15), a weak unit's top speed scaled."""
    k = v_axial.shape[0]
    n_top = np.empty(k)
    for i in range(k):
        n_top[i] = tp[7] * eff[i]
    return thrust_of_speed(n_top, v_axial, tp)


@njit(cache=True)
def _speed1(T, Va, tp):
    """n >= 0 with T(n, V_a) = T: the inverse of eq. 15, closed form per regime of J.

    J = V_a / (n D) is clipped to [j_lo, j_hi]: where it is clipped T = rho D^4 K(j) n^2; in
    between T = rho D^2 (kt0 D^2 n^2 + kt1 D V_a n + kt2 V_a^2), a quadratic in n. The root whose
    own J lies in its regime is the answer (T rises with n, so exactly one does).
    """
    if T <= 0.0:
        return 0.0
    rho, D = tp[0], tp[1]
    c = rho * D ** 4
    if tp[8] < 0.5:
        return math.sqrt(T / (c * tp[2]))
    j_lo, j_hi = tp[5], tp[6]
    K_hi = _K(j_hi, tp)
    if K_hi > 0.0:
        n = math.sqrt(T / (c * K_hi))  # slow propeller in fast inflow: J clipped to j_hi
        if Va / (n * D) >= j_hi:
            return n
    a = c * tp[2]
    b = rho * D ** 3 * tp[3] * Va
    cc = rho * D * D * tp[4] * Va * Va - T
    disc = b * b - 4.0 * a * cc
    if disc >= 0.0:
        n = (-b + math.sqrt(disc)) / (2.0 * a)
        if n > 0.0:
            J = Va / (n * D)
            if j_lo - 1e-12 <= J <= j_hi + 1e-12:
                return n
    K_lo = _K(j_lo, tp)  # J clipped to j_lo (e.g. inflow from behind)
    return math.sqrt(T / (c * K_lo)) if K_lo > 0.0 else 0.0


@njit(cache=True)
def speed_of_thrust(T, v_axial, tp):
    """Vector form of `_speed1`."""
    out = np.empty(T.shape[0])
    for i in range(T.shape[0]):
        out[i] = _speed1(T[i], v_axial[i], tp)
    return out


@njit(cache=True)
def evaluate(n, alpha, beta, nu_r, pos, e1, tp):
    """(T, force vectors, wrench) of a command at inflow nu_r: tau = sum [T_i d_i, r_i x T_i d_i]."""
    F = jet_frames(alpha, beta, e1)
    T = thrust_of_speed(n, axial_inflow(nu_r, pos, F), tp)
    k = n.shape[0]
    force = np.empty((k, 3))
    tau = np.zeros(6)
    for i in range(k):
        for j in range(3):
            force[i, j] = T[i] * F[i, 0, j]
            tau[j] += force[i, j]
        m0, m1, m2 = model.cross(pos[i, 0], pos[i, 1], pos[i, 2], force[i, 0], force[i, 1], force[i, 2])
        tau[3] += m0
        tau[4] += m1
        tau[5] += m2
    return T, force, tau


@njit(cache=True)
def plan_step(tau, a0, b0, nu_r, pos, e1, tp, lim, step, BtW, wc, f_prev, q, l, u, ax, inf, eff, free):
    """Fill the QP data of one step (q, l, u, A values); return T_max and the joint windows.

    Window: da in [max(-s, -lim - a0), min(s, lim - a0)] with s = step * free (rate * dt and the
    angle limits; free[i] = (1 or 0 for the azimuth, 1 or 0 for the elevation): 0 = stuck), same
    for beta. T_max = T(eff_i n_max, V_a): a unit of efficiency eff_i (0 = dead) reaches eff_i of
    its commanded speed. Rows per unit i, over f_i: d' f in [0, T_cap]; (e_alpha - k d)' f <= 0 and
    >= 0 for k = cos(b0) tan(da_hi), cos(b0) tan(da_lo); likewise e_beta with tan(db_hi),
    tan(db_lo). T_cap = T_max / sqrt(1 + k_a^2 + k_b^2) keeps |f_i| <= T_max (inner polytope).
    """
    k = a0.shape[0]
    F = jet_frames(a0, b0, e1)
    Va = axial_inflow(nu_r, pos, F)
    t_max = np.empty(k)
    win = np.empty((k, 4))
    tm = max_thrust(Va, tp, eff)
    for i in range(k):
        t_max[i] = max(tm[i], 0.0)
        sa = step * free[i, 0]
        sb = step * free[i, 1]
        win[i, 0] = max(-sa, -lim - a0[i])
        win[i, 1] = min(sa, lim - a0[i])
        win[i, 2] = max(-sb, -lim - b0[i])
        win[i, 3] = min(sb, lim - b0[i])
        cb = math.cos(b0[i])
        kk = (cb * math.tan(win[i, 1]), cb * math.tan(win[i, 0]), math.tan(win[i, 3]), math.tan(win[i, 2]))
        ka = max(kk[0] * kk[0], kk[1] * kk[1])
        kb = max(kk[2] * kk[2], kk[3] * kk[3])
        r = 5 * i
        l[r], u[r] = 0.0, t_max[i] / math.sqrt(1.0 + ka + kb)
        l[r + 1], u[r + 1] = -inf, 0.0
        l[r + 2], u[r + 2] = 0.0, inf
        l[r + 3], u[r + 3] = -inf, 0.0
        l[r + 4], u[r + 4] = 0.0, inf
        for j in range(3):
            o = (3 * i + j) * 5
            dj = F[i, 0, j]
            ax[o] = dj
            ax[o + 1] = F[i, 1, j] - kk[0] * dj
            ax[o + 2] = F[i, 1, j] - kk[1] * dj
            ax[o + 3] = F[i, 2, j] - kk[2] * dj
            ax[o + 4] = F[i, 2, j] - kk[3] * dj
    for c in range(3 * k):
        s = wc * f_prev[c]
        for r in range(6):
            s += BtW[c, r] * tau[r]
        q[c] = -2.0 * s
    return t_max, win


@njit(cache=True)
def step_inputs(tau, alpha, beta, nu_r, lim, stuck_alpha, stuck_beta):
    """(a0, b0, nu, angles finite, tau finite) of one allocation's inputs, as fresh arrays.

    a0, b0: the current joint angles clipped to +-lim, a stuck joint (stuck angle finite; NaN =
    free) replaced by its stuck angle; angles finite: the given angles were. nu: nu_r, or zeros
    if any of it is not finite (a diverged estimate must not poison the thrust limits).
    """
    k = alpha.shape[0]
    a0 = np.empty(k)
    b0 = np.empty(k)
    angles_ok = True
    for i in range(k):
        a = min(max(alpha[i], -lim), lim)
        b = min(max(beta[i], -lim), lim)
        angles_ok = angles_ok and math.isfinite(a) and math.isfinite(b)
        a0[i] = stuck_alpha[i] if math.isfinite(stuck_alpha[i]) else a
        b0[i] = stuck_beta[i] if math.isfinite(stuck_beta[i]) else b
    nu = np.empty(6)
    nu_ok = True
    for i in range(6):
        nu[i] = nu_r[i]
        nu_ok = nu_ok and math.isfinite(nu_r[i])
    if not nu_ok:
        nu[:] = 0.0
    tau_ok = True
    for i in range(6):
        tau_ok = tau_ok and math.isfinite(tau[i])
    return a0, b0, nu, angles_ok, tau_ok


@njit(cache=True)
def all_finite(x):
    """True if every entry of the 1-d array x is finite."""
    for i in range(x.shape[0]):
        if not math.isfinite(x[i]):
            return False
    return True


@njit(cache=True)
def outcome(n, alpha, beta, nu_r, pos, e1, tp, tau, W, eff):
    """`evaluate` of the command at what each unit reaches (n eff), its residual achieved - tau
    and weighted error sqrt(res' W res) (NaN if the residual is not finite)."""
    k = n.shape[0]
    n_actual = np.empty(k)
    for i in range(k):
        n_actual[i] = n[i] * eff[i]
    T, force, achieved = evaluate(n_actual, alpha, beta, nu_r, pos, e1, tp)
    res = achieved - tau
    finite = True
    for i in range(6):
        finite = finite and math.isfinite(res[i])
    if not finite:
        return T, force, achieved, res, math.nan
    err = 0.0
    for j in range(6):
        v = 0.0
        for i in range(6):
            v += res[i] * W[i, j]
        err += v * res[j]
    return T, force, achieved, res, math.sqrt(err)


@njit(cache=True)
def command_of_forces(f, a0, b0, win, nu_r, pos, e1, tp, lim, eff):
    """(n, alpha, beta) of planned force vectors f (k x 3): exact inverse, then the limits.

    alpha, beta from f_i / |f_i|, clipped to this step's window and +-angle_limit; T_i = f_i . d_i
    at the clipped angles (the part of f_i they can give), within [0, T(eff_i n_max) at the new
    inflow]; the speed the propeller needs from the inverse of seed 000 eq. 15, commanded as that
    speed / eff_i (the unit reaches eff_i of its command), within [0, n_max]. A dead unit
    (eff_i = 0) gets n = 0 and keeps its joints where they are.
    """
    k = f.shape[0]
    a, b = frame_angles(f, e1, a0, b0)
    for i in range(k):
        if eff[i] <= 0.0:
            a[i], b[i] = a0[i], b0[i]
        a[i] = min(max(min(max(a[i], a0[i] + win[i, 0]), a0[i] + win[i, 1]), -lim), lim)
        b[i] = min(max(min(max(b[i], b0[i] + win[i, 2]), b0[i] + win[i, 3]), -lim), lim)
    F = jet_frames(a, b, e1)
    Va = axial_inflow(nu_r, pos, F)
    tm = max_thrust(Va, tp, eff)
    T = np.empty(k)
    for i in range(k):
        t = f[i, 0] * F[i, 0, 0] + f[i, 1] * F[i, 0, 1] + f[i, 2] * F[i, 0, 2]
        T[i] = min(max(t, 0.0), max(tm[i], 0.0))
    n = speed_of_thrust(T, Va, tp)
    for i in range(k):
        n[i] = min(max(n[i] / eff[i], 0.0), tp[7]) if eff[i] > 0.0 else 0.0
    return n, a, b


class JetGeometry:
    """The jets of a vehicle: wrench map, unit frames and the seed-000 thrust model."""

    def __init__(self, v: Vehicle):
        self.vehicle = v
        self.k = v.n_units
        self.position = np.array([u.position for u in v.units], float)  # r_i (k, 3)
        self.e1 = np.array([u.neutral for u in v.units], float)
        self.B = model.wrench_map(v)  # tau = B f (6 x 3k), independent of the joint angles
        t = v.thruster
        self.tp = np.array([v.environment.rho, t.diameter, *t.kt, *t.j_range, t.n_max,
                            1.0 if v.effects.on("thrust_inflow") else 0.0])
        self.n_max = t.n_max
        self.angle_limit = v.servo.angle_limit
        self.rate_limit = v.servo.rate_limit

    def frames(self, alpha, beta):
        """d, e_alpha, e_beta of every unit, each (k, 3) (spec 3, 4.1)."""
        F = jet_frames(np.asarray(alpha, float), np.asarray(beta, float), self.e1)
        return F[:, 0], F[:, 1], F[:, 2]

    def angles(self, force):
        """(alpha, beta) of force directions (k, 3); zero forces give 0, 0."""
        z = np.zeros(self.k)
        return frame_angles(np.asarray(force, float), self.e1, z, z)

    def axial_inflow(self, nu_r, alpha, beta):
        """V_a,i at joint angles alpha, beta for body velocity relative to the water nu_r."""
        F = jet_frames(np.asarray(alpha, float), np.asarray(beta, float), self.e1)
        return axial_inflow(np.asarray(nu_r, float), self.position, F)

    def effectiveness(self, alpha, beta) -> np.ndarray:
        """6 x k map from thrust magnitudes to the body wrench: column i = [d_i, r_i x d_i]."""
        d, _, _ = self.frames(alpha, beta)
        return np.vstack([d.T, np.cross(self.position, d).T])

    def thrust(self, n, v_axial) -> np.ndarray:
        """T(n, V_a) of each unit (seed 000 eq. 15)."""
        return thrust_of_speed(np.asarray(n, float), np.asarray(v_axial, float), self.tp)

    def thrust_max(self, v_axial, efficiency=None) -> np.ndarray:
        """T_max(J) = T(e n_max, V_a): the most a jet of efficiency e (default 1) gives against
        its axial inflow (>= 0)."""
        e = np.ones(self.k) if efficiency is None else np.asarray(efficiency, float)
        return np.maximum(max_thrust(np.asarray(v_axial, float), self.tp, e), 0.0)

    def speed(self, thrust, v_axial) -> np.ndarray:
        """n with T(n, V_a) = thrust (inverse of seed 000 eq. 15, closed form)."""
        return speed_of_thrust(np.asarray(thrust, float), np.asarray(v_axial, float), self.tp)

    def evaluate(self, n, alpha, beta, nu_r=None):
        """(T, force vectors (k, 3), wrench) of command (n, alpha, beta) at inflow nu_r."""
        nu = np.zeros(6) if nu_r is None else np.asarray(nu_r, float)
        return evaluate(np.asarray(n, float), np.asarray(alpha, float), np.asarray(beta, float),
                        nu, self.position, self.e1, self.tp)


# ------------------------------------------------------------------------------------------------
# Result


def _frozen(a) -> np.ndarray:
    a = np.array(a, dtype=float)
    a.setflags(write=False)
    return a


def _owned(a: np.ndarray) -> np.ndarray:
    """A float array nobody else holds (a kernel's fresh result), made read-only without a copy."""
    a.setflags(write=False)
    return a


@dataclass(frozen=True)
class Allocation:
    """One allocation: the command, what it achieves, and the solver's diagnostics.

    `residual_wrench` = achieved - demand ([N, N, N, N m, N m, N m], body FRD);
    `weighted_error` = sqrt(residual' W residual) with the allocator's W.
    """

    n_rev_s: np.ndarray
    alpha_rad: np.ndarray
    beta_rad: np.ndarray
    thrust_n: np.ndarray
    force_body_n: np.ndarray  # (k, 3) planned force vector of each unit
    wrench_demand: np.ndarray
    wrench_achieved: np.ndarray
    residual_wrench: np.ndarray
    weighted_error: float
    status: str
    solve_time_s: float  # the whole allocate() call (setup of the step, solve, conversion)
    qp_time_s: float  # OSQP's own run time (0 for the baseline)
    iterations: int
    fallback: bool
    thrust_max_n: np.ndarray = field(default_factory=lambda: _frozen([]))

    @property
    def command(self) -> np.ndarray:
        """u = [n_cmd (rev/s) x k, alpha_cmd (rad) x k, beta_cmd (rad) x k]."""
        return np.concatenate([self.n_rev_s, self.alpha_rad, self.beta_rad])

    def pwm_us(self, v: Vehicle) -> np.ndarray:
        """PWM on channels 1..16 (onboard.pwm maps of the vehicle file)."""
        return pwm.command_to_pwm(v, self.command)

    def normalised(self, v: Vehicle) -> np.ndarray:
        """HIL_ACTUATOR_CONTROLS layout: jets 0..1, then azimuths and elevations -1..1."""
        return pwm.command_to_normalised(v, self.command)


# ------------------------------------------------------------------------------------------------
# Shared pieces of both allocators


def _vector(x, size: int, what: str) -> np.ndarray:
    a = np.asarray(x, dtype=float).reshape(-1)
    if a.shape != (size,):
        raise ValueError(f"{what}: expected {size} values, got shape {np.shape(x)}")
    return a


# Why a vehicle with both kinds of actuator is refused (onboard.vehicle.require_jets says it at load
# time for every command that runs the onboard loop).
_MIXED = ("a mixed vehicle is simulated but not allocated: the jets' QP plans each jet inside its joint "
          "window and the loop compensates and monitors jets only")


class _Base:
    def __init__(self, v: Vehicle, dt_s: float, config: AllocationConfig | None = None):
        if not (isinstance(dt_s, (int, float)) and math.isfinite(dt_s) and dt_s > 0):
            raise ValueError(f"dt_s: expected the control period in seconds (> 0), got {dt_s!r}")
        if v.fixed:  # one clear line, not a division by zero in the warm-up (see FixedQpAllocator)
            raise ValueError(f"{v.name}: {type(self).__name__} allocates vectored jets only; this vehicle has "
                             f"{len(v.fixed)} fixed thrusters ({_MIXED})")
        self.vehicle = v
        self.geo = JetGeometry(v)
        self.k = v.n_units
        self.dt_s = float(dt_s)
        self.config = config if config is not None else AllocationConfig.from_vehicle(v)
        self.W = self.config.weight_matrix()
        self._zeros6 = np.zeros(6)
        self._zeros3k = np.zeros(3 * self.k)
        self.previous = None
        self.set_health()
        self._warm_up_shared()

    def _warm_up_shared(self) -> None:
        """Load the compiled input and outcome kernels now, not in the first step, for the array
        kinds a step passes (angles given by the caller, or the previous command's read-only ones)."""
        k, g = self.k, self.geo
        z, ro = np.zeros(k), _frozen(np.zeros(k))
        for a in (z, ro):
            step_inputs(self._zeros6, a, a, self._zeros6, g.angle_limit, self.stuck_alpha_rad, self.stuck_beta_rad)
        outcome(z, z, z, self._zeros6, g.position, g.e1, g.tp, self._zeros6, self.W, np.ones(k))
        all_finite(self._zeros6)

    @property
    def previous(self) -> Allocation | None:
        """The last committed allocation (the change reference and the fallback), or None."""
        return self._previous

    @previous.setter
    def previous(self, allocation: Allocation | None) -> None:
        self._previous = allocation
        # its force vectors, flat and writable, as the QP's change reference (copied once here)
        self._f_prev = None if allocation is None else np.array(allocation.force_body_n, dtype=np.float64).reshape(-1)

    def set_health(self, efficiency=None, stuck_alpha_rad=None, stuck_beta_rad=None) -> None:
        """Tell the allocator what each unit can still do (onboard.monitor.UnitHealth's fields).

        efficiency: k values in [0, 1] (None: all 1): the unit reaches e_i of its commanded speed,
        0 = dead (no thrust; excluded). stuck_alpha_rad, stuck_beta_rad: k angles each, NaN where
        the joint is free (None: all free); a stuck joint is held at its angle (within the limits).
        """
        k = self.k
        eff = np.ones(k) if efficiency is None else _vector(efficiency, k, "efficiency (per unit)")
        if not np.all((eff >= 0.0) & (eff <= 1.0)):  # also false for NaN
            raise ValueError(f"efficiency: expected {k} values in [0, 1] (1 healthy, 0 dead), got {efficiency!r}")
        stuck = []
        for name, val in (("stuck_alpha_rad", stuck_alpha_rad), ("stuck_beta_rad", stuck_beta_rad)):
            a = np.full(k, np.nan) if val is None else _vector(val, k, f"{name} (NaN where free)")
            if np.any(np.isinf(a)):
                raise ValueError(f"{name}: expected finite angles (rad) or NaN where free, got {val!r}")
            stuck.append(np.clip(a, -self.geo.angle_limit, self.geo.angle_limit))
        self.efficiency = eff
        self.stuck_alpha_rad, self.stuck_beta_rad = stuck
        self._stuck_a = np.isfinite(stuck[0])
        self._stuck_b = np.isfinite(stuck[1])
        self._free = np.ascontiguousarray(np.stack([~self._stuck_a, ~self._stuck_b], axis=1).astype(float))
        self._nominal = bool(np.all(eff == 1.0) and not self._stuck_a.any() and not self._stuck_b.any())

    def _inputs(self, wrench, alpha, beta, nu_r):
        """(tau, a0, b0, nu, tau finite): the demand (may be non-finite: the callers fall back),
        the current joint angles (default: the last committed command) within the limits and at
        any stuck angle, nu_r (zeros if absent or not finite). One compiled call (`step_inputs`)."""
        k = self.k
        tau = _vector(wrench, 6, "wrench demand [X, Y, Z, K, M, N]")
        prev = self._previous
        if alpha is None:
            alpha = prev.alpha_rad if prev is not None else self._zeros3k[:k]
        else:
            alpha = _vector(alpha, k, "alpha_rad (current azimuths)")
        if beta is None:
            beta = prev.beta_rad if prev is not None else self._zeros3k[:k]
        else:
            beta = _vector(beta, k, "beta_rad (current elevations)")
        nu = self._zeros6 if nu_r is None else _vector(nu_r, 6, "nu_r (body velocity relative to the water)")
        a0, b0, nu, angles_ok, tau_ok = step_inputs(tau, alpha, beta, nu, self.geo.angle_limit,
                                                    self.stuck_alpha_rad, self.stuck_beta_rad)
        if not angles_ok:
            raise ValueError("current joint angles must be finite")
        return tau, a0, b0, nu, tau_ok

    def _finish(self, tau, n, alpha, beta, nu, status, solve_time, iters, fallback, t_max, qp_time=0.0):
        """Exact forward model of the final command: thrust at its own inflow (what a weak unit
        reaches: n eff), achieved wrench, residual and weighted error (`outcome`, one compiled call)."""
        g = self.geo
        T, force, achieved, res, err = outcome(n, alpha, beta, nu, g.position, g.e1, g.tp, tau, self.W,
                                               self.efficiency)
        return Allocation(
            n_rev_s=_frozen(n), alpha_rad=_frozen(alpha), beta_rad=_frozen(beta), thrust_n=_owned(T),
            force_body_n=_owned(force), wrench_demand=_frozen(tau), wrench_achieved=_owned(achieved),
            residual_wrench=_owned(res), weighted_error=float(err), status=status, solve_time_s=float(solve_time),
            qp_time_s=float(qp_time), iterations=int(iters), fallback=bool(fallback), thrust_max_n=_frozen(t_max),
        )

    def commit(self, allocation: Allocation) -> None:
        """Make `allocation` the previous one (the change reference and the fallback)."""
        self.previous = allocation

    def reset(self) -> None:
        """Forget the previous command (a new start: no change reference, no fallback command)."""
        self.previous = None


# ------------------------------------------------------------------------------------------------
# Baseline: fixed mixing (ArduSub-style)


class PseudoInverseAllocator(_Base):
    """ArduSub-style fixed mixing: t = pinv(E(alpha, beta)) tau, clipped to [0, T_max(J)].

    The joints stay where they are (E is the effectiveness at the current angles); this is what
    a user has without vectoring-aware allocation.
    """

    def allocate(self, wrench, alpha=None, beta=None, nu_r=None, commit: bool = True) -> Allocation:
        t0 = time.perf_counter()
        tau, a0, b0, nu, finite = self._inputs(wrench, alpha, beta, nu_r)
        g = self.geo
        Va = g.axial_inflow(nu, a0, b0)
        eff = self.efficiency
        t_max = g.thrust_max(Va, eff)
        if finite:
            E = g.effectiveness(a0, b0)
            E[:, eff <= 0.0] = 0.0  # a dead unit's column: pinv gives it nothing
            T = np.clip(np.linalg.pinv(E) @ tau, 0.0, t_max)
            status = "solved"
        else:
            T = np.zeros(self.k)
            status = "fallback: non-finite demand; jets off"
        live = eff > 0.0
        n = np.zeros(self.k)
        n[live] = np.clip(g.speed(T, Va)[live] / eff[live], 0.0, g.n_max)
        out = self._finish(tau, n, a0, b0, nu, status, time.perf_counter() - t0, 0, status != "solved", t_max)
        if commit:
            self.commit(out)
        return out


# ------------------------------------------------------------------------------------------------
# The QP allocator


class QpAllocator(_Base):
    """Weighted-wrench QP over the units' force vectors; OSQP set up once, updated each step.

    `allocate(tau, alpha, beta, nu_r)` plans the command for the next control period `dt_s`
    from the current joint angles (default: the last committed command) and the estimated
    velocity relative to the water nu_r (for each jet's inflow and so its T_max). With
    `commit=False` it only plans (the transient compensator iterates that way); `commit()`
    makes a plan the reference for the change penalty and the fallback.
    """

    ROWS = 5  # constraint rows per unit

    def __init__(self, v: Vehicle, dt_s: float, config: AllocationConfig | None = None):
        super().__init__(v, dt_s, config)
        k, c = self.k, self.config
        Fs2 = c.force_scale_n**2
        B = self.geo.B
        # Objective 1/2 x'Px + q'x with P = 2 (B'WB + (w_e + w_c) I): B does not depend on the
        # joint angles, so P is fixed; only q, A's values and the bounds change per step. Without a
        # previous command (first step, after reset) there is nothing to change from, so w_c is
        # left out of P then: the two P differ on the diagonal only (same sparsity pattern).
        BWB = B.T @ self.W @ B
        self._H = {True: BWB + (c.effort_weight + c.change_weight) / Fs2 * np.eye(3 * k),
                   False: BWB + c.effort_weight / Fs2 * np.eye(3 * k)}
        self._BtW = np.ascontiguousarray(B.T @ self.W)
        self._wc = c.change_weight / Fs2
        P = sp.triu(sp.csc_matrix(2.0 * self._H[False]), format="csc")
        P_change = sp.triu(sp.csc_matrix(2.0 * self._H[True]), format="csc")
        assert np.array_equal(P.indices, P_change.indices) and np.array_equal(P.indptr, P_change.indptr)
        self._Px = {False: P.data.copy(), True: P_change.data.copy()}
        self._P_with_change = False
        # Constraint matrix: 5 rows per unit, each dense over the unit's 3 variables; the pattern
        # is fixed (explicit zeros kept) so `update(Ax=...)` refills it in place.
        m = self.ROWS * k
        indptr = np.arange(3 * k + 1, dtype=np.int64) * self.ROWS
        indices = np.concatenate([np.arange(self.ROWS) + self.ROWS * (col // 3) for col in range(3 * k)])
        self._q = np.zeros(3 * k)
        self._l = np.zeros(m)
        self._u = np.zeros(m)
        self._ax = np.zeros(3 * k * self.ROWS)
        try:
            self._inf = float(osqp.OSQP().constant("OSQP_INFTY"))  # OSQP's "no bound"
        except Exception:  # pragma: no cover - other osqp versions
            self._inf = 1e30
        z = np.zeros(k)
        plan_step(np.zeros(6), z, z, np.zeros(6), self.geo.position, self.geo.e1, self.geo.tp,
                  self.geo.angle_limit, 0.0, self._BtW, 0.0, np.zeros(3 * k), self._q, self._l, self._u, self._ax,
                  self._inf, np.ones(k), np.ones((k, 2)))
        self._A_pattern = (indices, indptr, (m, 3 * k))
        A = sp.csc_matrix((self._ax.copy(), indices, indptr), shape=(m, 3 * k))
        self._solver = osqp.OSQP()
        self._solver.setup(
            P, self._q, A, self._l, self._u,
            verbose=False, warm_starting=True, polishing=False, eps_abs=c.eps_abs, eps_rel=c.eps_rel,
            max_iter=c.max_iter, time_limit=c.time_budget_s, check_termination=5,
            adaptive_rho=True, adaptive_rho_interval=25,
        )
        self.setups = 1  # the workspace is built once here and only updated afterwards
        # The compiled workspace, called directly where the osqp wrapper exposes it (osqp 1.x): the
        # wrapper's bookkeeping (bound clipping, derivative cache, a result namespace) costs more
        # than this problem's solve.
        inner = getattr(self._solver, "_solver", None)
        ok = inner is not None and all(hasattr(inner, a) for a in ("update_data_vec", "update_data_mat", "solution"))
        self._inner = inner if ok else None
        self._warm_up()

    def _warm_up(self) -> None:
        """Run each compiled kernel once (numba loads or compiles it now, not in the first step)."""
        k, g = self.k, self.geo
        z = np.zeros(k)
        f = np.tile([1.0, 0.0, 0.0], (k, 1))
        win = np.tile([-0.01, 0.01, -0.01, 0.01], (k, 1))
        n, a, b = command_of_forces(f, z, z, win, np.zeros(6), g.position, g.e1, g.tp, g.angle_limit, np.ones(k))
        evaluate(n, a, b, np.zeros(6), g.position, g.e1, g.tp)

    def constraints(self, alpha, beta, nu_r=None):
        """(A, l, u, T_max): the step's polytope l <= A f <= u (dense) at these joint angles."""
        g = self.geo
        a0 = np.clip(np.asarray(alpha, float), -g.angle_limit, g.angle_limit)
        b0 = np.clip(np.asarray(beta, float), -g.angle_limit, g.angle_limit)
        nu = np.zeros(6) if nu_r is None else np.asarray(nu_r, float)
        q, l, u, ax = np.zeros(3 * self.k), np.zeros_like(self._l), np.zeros_like(self._u), np.zeros_like(self._ax)
        if not self._nominal:
            a0 = np.where(self._stuck_a, self.stuck_alpha_rad, a0)
            b0 = np.where(self._stuck_b, self.stuck_beta_rad, b0)
        t_max, _ = plan_step(np.zeros(6), a0, b0, nu, g.position, g.e1, g.tp, g.angle_limit,
                             self.window_step_rad(), self._BtW, 0.0, np.zeros(3 * self.k), q, l, u, ax, self._inf,
                             self.efficiency, self._free)
        indices, indptr, shape = self._A_pattern
        return sp.csc_matrix((ax, indices, indptr), shape=shape).toarray(), l, u, t_max

    def window_step_rad(self) -> float:
        """Joint travel allowed per step, rate_limit * dt (also bounded by the angle limits)."""
        return self.geo.rate_limit * self.dt_s

    def allocate(self, wrench, alpha=None, beta=None, nu_r=None, commit: bool = True) -> Allocation:
        t_start = time.perf_counter()
        tau, a0, b0, nu, finite = self._inputs(wrench, alpha, beta, nu_r)
        g = self.geo
        with_change = self._previous is not None
        f_prev = self._f_prev if with_change else self._zeros3k
        t_max, win = plan_step(
            tau if finite else self._zeros6, a0, b0, nu, g.position, g.e1, g.tp, g.angle_limit,
            self.window_step_rad(), self._BtW, self._wc if with_change else 0.0, f_prev,
            self._q, self._l, self._u, self._ax, self._inf, self.efficiency, self._free)
        if not finite:
            return self._fallback(tau, a0, b0, nu, "non-finite demand", 0.0, 0, t_max, commit)
        x, info = self._update_and_solve(with_change)
        elapsed = time.perf_counter() - t_start
        status = str(info.status)
        ok = info.status_val in _SOLVED
        if not ok or elapsed > self.config.time_budget_s or x is None or not all_finite(x):
            reason = status if not ok else (
                f"over time budget ({elapsed * 1e6:.0f} us > {self.config.time_budget_s * 1e6:.0f} us)")
            return self._fallback(tau, a0, b0, nu, reason, elapsed, info.iter, t_max, commit)
        f = np.asarray(x, float).reshape(self.k, 3)
        n, alpha, beta = command_of_forces(f, a0, b0, win, nu, g.position, g.e1, g.tp, g.angle_limit,
                                           self.efficiency)
        out = self._finish(tau, n, alpha, beta, nu, status, time.perf_counter() - t_start, info.iter, False, t_max,
                           info.run_time)
        if commit:
            self.commit(out)
        return out

    def _update_and_solve(self, with_change: bool):
        """Refill q, l, u and A's values, solve from the previous solution -> (x, info).

        Everything is handed over every call, a re-plan of the same step (only the demand, so
        only q, changed) included: OSQP re-scales the problem data (Ruiz equilibration and the cost
        scale, which depends on q) when A or P is updated, and a q-only update would keep the
        previous scaling, so the warm-started iterations (and within eps the solution) would differ
        from a fresh update's. The compiled workspace is called directly (`_inner`).
        Bounds are already within +-OSQP_INFTY (plan_step).
        """
        Px = None
        if with_change != self._P_with_change:  # only at the first step after a (re)start
            Px = self._Px[with_change]
            self._P_with_change = with_change
        inner = self._inner
        if inner is not None:
            inner.update_data_vec(q=self._q, l=self._l, u=self._u)
            inner.update_data_mat(P_x=Px, P_i=None, A_x=self._ax, A_i=None)
            inner.solve()
            return np.array(inner.solution.x), inner.info
        if Px is not None:  # pragma: no cover - other osqp versions
            self._solver.update(Px=Px)
        self._solver.update(q=self._q, l=self._l, u=self._u, Ax=self._ax)  # pragma: no cover
        res = self._solver.solve(raise_error=False)  # pragma: no cover - other osqp versions
        return res.x, res.info

    def _fallback(self, tau, a0, b0, nu, reason, elapsed, iters, t_max, commit):
        """Keep the previous command (clipped to this step's joint window), or jets off if none."""
        if self.previous is not None:
            step = self.window_step_rad()
            lim = self.geo.angle_limit
            alpha = np.clip(np.clip(self.previous.alpha_rad, a0 - step, a0 + step), -lim, lim)
            beta = np.clip(np.clip(self.previous.beta_rad, b0 - step, b0 + step), -lim, lim)
            n = np.clip(self.previous.n_rev_s, 0.0, self.geo.n_max)
            if not self._nominal:  # dead units stay off, stuck joints where they are
                n = np.where(self.efficiency > 0.0, n, 0.0)
                alpha = np.where(self._stuck_a, a0, alpha)
                beta = np.where(self._stuck_b, b0, beta)
            what = "previous command kept"
        else:
            alpha, beta, n = a0.copy(), b0.copy(), np.zeros(self.k)
            what = "no previous command: jets off"
        out = self._finish(tau, n, alpha, beta, nu, f"fallback: {reason}; {what}", elapsed, iters, True, t_max)
        if commit:
            self.commit(out)
        return out

    def unconstrained(self, wrench, f_prev=None) -> np.ndarray:
        """The QP's minimiser without constraints, (B'WB + (w_e + w_c) I)^-1 (B'W tau + w_c f_prev).

        A regularised weighted pseudo-inverse; the QP equals it whenever no limit is active.
        Without f_prev (no previous command) the change term is absent, as in `allocate`.
        """
        tau = np.asarray(wrench, float)
        if f_prev is None:
            return np.linalg.solve(self._H[False], self._BtW @ tau).reshape(self.k, 3)
        f_prev = np.asarray(f_prev, float).reshape(-1)
        return np.linalg.solve(self._H[True], self._BtW @ tau + self._wc * f_prev).reshape(self.k, 3)


# ------------------------------------------------------------------------------------------------
# Fixed thrusters: the QP's simplest case (spec 3.1)


class FixedGeometry:
    """The fixed two-way thrusters of a vehicle: the constant 6 x m effectiveness E (column i =
    [d_i, r_i x d_i]) and each unit's thrust range [T_min, T_max] from the one thrust curve."""

    def __init__(self, v: Vehicle):
        from .fixed import thrust_limits

        self.vehicle = v
        self.m = len(v.fixed)
        self.position = np.array([f.position for f in v.fixed], float).reshape(self.m, 3)
        self.direction = np.array([f.direction for f in v.fixed], float).reshape(self.m, 3)
        self.E = np.vstack([self.direction.T, np.cross(self.position, self.direction).T])
        t_min, t_max = thrust_limits(v.fixed_thruster) if v.fixed else (0.0, 0.0)
        self.t_min = np.full(self.m, t_min)
        self.t_max = np.full(self.m, t_max)


class FixedQpAllocator:
    """Weighted-wrench QP over the thrusts t of fixed two-way thrusters; OSQP set up once.

        min_t (E t - tau)' W (E t - tau) + w_e |t|^2 + w_c |t - t_prev|^2,  e_i T_min <= t_i <= e_i T_max

    (weights as `QpAllocator`'s, normalised by force_scale^2). No joints: E is constant, so only
    q and the bounds change from step to step; no joint window, no inflow (the curve is a bollard
    table), no transient to compensate. A unit of efficiency e_i (`set_health`) gives e_i of its
    thrust range; a dead one (0) none. The result is the same `Allocation` as the jets': its speed
    slot (`n_rev_s`) holds each thruster's thrust command in newtons (the command vector's slot for
    a fixed unit, spec 3.1), its joint angles are 0. `pwm_us` goes through the thrust curve's
    inverse.
    """

    def __init__(self, v: Vehicle, dt_s: float, config: AllocationConfig | None = None):
        if v.units:
            raise ValueError(f"{v.name}: FixedQpAllocator allocates fixed thrusters only; this vehicle "
                             f"has {v.n_jets} vectored jets too ({_MIXED})")
        if not v.fixed:
            raise ValueError(f"{v.name}: no [[fixed]] thrusters to allocate")
        if not (isinstance(dt_s, (int, float)) and math.isfinite(dt_s) and dt_s > 0):
            raise ValueError(f"dt_s: expected the control period in seconds (> 0), got {dt_s!r}")
        self.vehicle = v
        self.geo = FixedGeometry(v)
        self.k = self.geo.m
        self.dt_s = float(dt_s)
        self.config = config if config is not None else AllocationConfig.from_vehicle(v)
        self.W = self.config.weight_matrix()
        c, E = self.config, self.geo.E
        Fs2 = c.force_scale_n ** 2
        EWE = E.T @ self.W @ E
        self._H = {True: EWE + (c.effort_weight + c.change_weight) / Fs2 * np.eye(self.k),
                   False: EWE + c.effort_weight / Fs2 * np.eye(self.k)}
        self._EtW = E.T @ self.W
        self._wc = c.change_weight / Fs2
        P = {w: sp.triu(sp.csc_matrix(2.0 * self._H[w]), format="csc") for w in (False, True)}
        self._Px = {w: P[w].data.copy() for w in P}
        self._P_with_change = False
        self._solver = osqp.OSQP()
        self._solver.setup(P[False], np.zeros(self.k), sp.identity(self.k, format="csc"), self.geo.t_min.copy(),
                           self.geo.t_max.copy(), verbose=False, warm_starting=True, polishing=False,
                           eps_abs=c.eps_abs, eps_rel=c.eps_rel, max_iter=c.max_iter * 10)
        self.setups = 1
        self.previous = None
        self.set_health()

    def set_health(self, efficiency=None) -> None:
        """efficiency: one value in [0, 1] per thruster (None: all 1); 0 = dead."""
        eff = np.ones(self.k) if efficiency is None else _vector(efficiency, self.k, "efficiency (per thruster)")
        if not np.all((eff >= 0.0) & (eff <= 1.0)):
            raise ValueError(f"efficiency: expected {self.k} values in [0, 1] (1 healthy, 0 dead), got {efficiency!r}")
        self.efficiency = eff

    def unconstrained(self, wrench, t_prev=None) -> np.ndarray:
        """The QP's minimiser without bounds: (E'WE + (w_e + w_c) I)^-1 (E'W tau + w_c t_prev)."""
        tau = np.asarray(wrench, float)
        if t_prev is None:
            return np.linalg.solve(self._H[False], self._EtW @ tau)
        return np.linalg.solve(self._H[True], self._EtW @ tau + self._wc * np.asarray(t_prev, float))

    def allocate(self, wrench, alpha=None, beta=None, nu_r=None, commit: bool = True) -> Allocation:
        """Thrusts for the demand [X, Y, Z, K, M, N] (alpha, beta, nu_r accepted and unused: no
        joints, no inflow model)."""
        t0 = time.perf_counter()
        tau = _vector(wrench, 6, "wrench demand [X, Y, Z, K, M, N]")
        lo, hi = self.efficiency * self.geo.t_min, self.efficiency * self.geo.t_max
        prev = self.previous
        if not np.all(np.isfinite(tau)):
            T = np.zeros(self.k) if prev is None else np.clip(prev.thrust_n, lo, hi)
            return self._finish(tau, T, "fallback: non-finite demand", t0, 0, True, 0.0, commit)
        with_change = prev is not None
        q = -2.0 * (self._EtW @ tau + (self._wc * prev.thrust_n if with_change else 0.0))
        if with_change != self._P_with_change:
            self._solver.update(Px=self._Px[with_change])
            self._P_with_change = with_change
        self._solver.update(q=q, l=lo, u=hi)
        res = self._solver.solve(raise_error=False)
        ok = res.info.status_val in _SOLVED and res.x is not None and np.all(np.isfinite(res.x))
        if not ok:
            T = np.zeros(self.k) if prev is None else np.clip(prev.thrust_n, lo, hi)
            return self._finish(tau, T, f"fallback: {res.info.status}", t0, res.info.iter, True,
                                res.info.run_time, commit)
        T = np.clip(np.asarray(res.x, float), lo, hi)
        return self._finish(tau, T, str(res.info.status), t0, res.info.iter, False, res.info.run_time, commit)

    def _finish(self, tau, T, status, t0, iters, fallback, qp_time, commit) -> Allocation:
        achieved = self.geo.E @ T
        res = achieved - tau
        err = float(np.sqrt(res @ self.W @ res)) if np.all(np.isfinite(res)) else math.nan
        z = np.zeros(self.k)
        out = Allocation(
            n_rev_s=_frozen(T), alpha_rad=_frozen(z), beta_rad=_frozen(z), thrust_n=_frozen(T),
            force_body_n=_frozen(T[:, None] * self.geo.direction), wrench_demand=_frozen(tau),
            wrench_achieved=_frozen(achieved), residual_wrench=_frozen(res), weighted_error=err, status=status,
            solve_time_s=time.perf_counter() - t0, qp_time_s=float(qp_time), iterations=int(iters),
            fallback=bool(fallback), thrust_max_n=_frozen(self.efficiency * self.geo.t_max),
        )
        if commit:
            self.previous = out
        return out

    def commit(self, allocation: Allocation) -> None:
        self.previous = allocation

    def reset(self) -> None:
        self.previous = None


def allocator_for(v: Vehicle, dt_s: float, config: AllocationConfig | None = None):
    """The QP allocator that fits the vehicle's actuators: `QpAllocator` for vectored jets,
    `FixedQpAllocator` for fixed thrusters."""
    if v.fixed:
        return FixedQpAllocator(v, dt_s, config)
    return QpAllocator(v, dt_s, config)


__all__ = [
    "AXES",
    "AllocationConfig",
    "Allocation",
    "JetGeometry",
    "QpAllocator",
    "PseudoInverseAllocator",
    "FixedGeometry",
    "FixedQpAllocator",
    "allocator_for",
]


# Kernels above compile onboard.model functions into themselves: key their disk cache on it.
key_caches_on(globals(), MODEL_SOURCE)
