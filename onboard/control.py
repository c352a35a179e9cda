"""Depth, attitude and body-velocity control with model feed-forward: estimate + setpoint -> wrench.

Pure math, one stateful object (`Controller`: reference models and integrators), no clock and
no IO. Every degree of freedom follows a smooth reference (a prefilter on the setpoint) and the
demand is the model's inverse dynamics along that reference plus mass-scaled feedback
(Fossen 2011 sec. 12.3, "computed torque" / model-based feed-forward):

    tau = M (nu_r' + a_fb) + C(nu) nu + D(nu_r) nu_r + g_F(eta)                        (1)

- M = M_RB + M_A from `onboard.model.mass_matrix` at the estimated depth (surface and wall
  effects scale the added mass as in the plant); C(nu) nu the Coriolis/centripetal terms at the
  estimate; D(nu_r) nu_r the linear + quadratic damping at the REFERENCE velocity; g_F the force
  part of the restoring term g(eta) at the estimated attitude (net buoyancy, ~1.5 N up on the
  reference vehicle, scaled by the submerged fraction near the surface). The restoring MOMENT is
  left to act: the vehicle is bottom-heavy and its righting moment helps hold it level.
- a_fb is the feedback acceleration: PID on depth (NED z, mapped to the body by R^T), PID on the
  small-angle attitude error (body frame), PI on surge and sway velocity.
- `feedforward=False` keeps exactly the same feedback (same gains, same M scaling) and drops
  nu_r', C, D and g_F: "gains alone", the baseline the tests compare against.

Gains come from bandwidths, not from hand-tuned numbers (`Gains`, `Controller.gains_si`): with
M_ii the diagonal of the model's mass matrix (rigid body + added mass) each loop is shaped as
mass-normalised error dynamics:
    position/attitude, bandwidth w, damping z:  a_fb = w^2 e + 2 z w e' + (w^3 / 10) int e
        (char. polynomial s^3 + 2 z w s^2 + w^2 s + w^3/10: the PD pair at w, the integral pole
        near w/10; Routh-stable since 2 z w^3 > w^3 / 10)
    velocity, bandwidth w:                      a_fb = w e + (w^2 / 4) int e
        (s^2 + w s + w^2 / 4 = (s + w/2)^2, critically damped)
so the force gains are K_p = M_ii w^2, K_d = 2 z w M_ii, ... The default bandwidths sit a factor
4 or more below the actuators (motor lag 0.08 s -> 12.5 rad/s; servo 0.03 s with a 5 rad/s rate
limit) so the allocator and the jets can follow.

References: depth critically damped second order, velocities first order, yaw critically damped
third order (`yaw_reference`), so a new heading does not step the yaw feed-forward moment (the
azimuths that make it turn at a finite rate); it steps only where the rate limit sets in (~0.03
N m for 90 deg, half what the azimuths slew in a step) and, in joystick rate mode, by
I_z rate / T_v. Their reaction moment (seed 004) is cancelled ahead along the reference's known
future (`Controller.yaw_preview`, onboard.compensation.YawPreview).

Anti-windup: each integrator is clamped so its share of the acceleration stays within
`integral_share` of the axis capacity (capacity: what the jets can give on that axis, from the
bollard thrust and the geometry, `axis_capacity`); and it stops integrating (conditional
integration) while the axis demand is saturated in the direction of its error, judged from the
achieved wrench the allocator reports (`step(..., achieved=...)`) or else from the capacity.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from . import model
from .jit import MODEL_SOURCE, key_caches_on
from .estimator import EstimatedState
from .vehicle import Vehicle


# ------------------------------------------------------------------------------------------------
# Domain types

def _finite(name: str, value, allow_none: bool = True):
    if value is None and allow_none:
        return None
    try:
        f = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"Setpoint.{name}: expected a finite number{' or None' if allow_none else ''}, got {value!r}") from None
    if not math.isfinite(f):
        raise ValueError(f"Setpoint.{name}: expected a finite number, got {value!r}")
    return f


@dataclass(frozen=True)
class ManualAxes:
    """MANUAL_CONTROL-style stick axes, each normalised to [-1, 1] (the link maps the raw +-1000).

    surge: forward +; sway: right +; heave_down: descend +; yaw_right: clockwise seen from above +.
    (ArduSub's z throttle 0..1000 with 500 neutral, up above 500, maps to heave_down = (500 - z) / 500.)
    """

    surge: float = 0.0
    sway: float = 0.0
    heave_down: float = 0.0
    yaw_right: float = 0.0

    def __post_init__(self):
        for name in ("surge", "sway", "heave_down", "yaw_right"):
            v = _finite(f"manual.{name}", getattr(self, name), allow_none=False)
            object.__setattr__(self, name, min(max(v, -1.0), 1.0))


@dataclass(frozen=True)
class Setpoint:
    """What the vehicle should do. None leaves an axis to the rules below.

    - depth_m: hold this depth (m below the surface). Wins over a heave velocity.
    - yaw_rad: hold this heading (NED, ZYX yaw); None holds the heading the reference is at.
    - velocity_body_m_s: (u, v, w) in m/s; None on u or v leaves that axis uncontrolled (no force);
      w is used only when depth_m is None (the depth reference then moves at w); both None: heave
      uncontrolled (the vehicle rises slowly by its buoyancy).
    - manual: stick axes; when given it replaces depth/yaw/velocity: sticks command body
      velocities and yaw rate, a centred heave or yaw stick holds the depth or heading reached.
    Roll and pitch are always held level.
    """

    depth_m: float | None = None
    yaw_rad: float | None = None
    velocity_body_m_s: tuple = (0.0, 0.0, None)
    manual: ManualAxes | None = None

    def __post_init__(self):
        object.__setattr__(self, "depth_m", _finite("depth_m", self.depth_m))
        object.__setattr__(self, "yaw_rad", _finite("yaw_rad", self.yaw_rad))
        vel = self.velocity_body_m_s
        if vel is None or len(tuple(vel)) != 3:
            raise ValueError(f"Setpoint.velocity_body_m_s: expected (u, v, w) with numbers or None, got {vel!r}")
        object.__setattr__(self, "velocity_body_m_s", tuple(
            _finite(f"velocity_body_m_s[{i}]", c) for i, c in enumerate(vel)))
        if self.manual is not None and not isinstance(self.manual, ManualAxes):
            raise ValueError(f"Setpoint.manual: expected ManualAxes or None, got {type(self.manual).__name__}")


@dataclass(frozen=True)
class Wrench:
    """A body-frame wrench: force (N, FRD) and moment (N m, about the body origin)."""

    force_body_n: tuple = (0.0, 0.0, 0.0)
    moment_body_nm: tuple = (0.0, 0.0, 0.0)

    def as_array(self) -> np.ndarray:
        """[X, Y, Z, K, M, N]."""
        return np.array(tuple(self.force_body_n) + tuple(self.moment_body_nm), dtype=float)

    @classmethod
    def from_array(cls, tau) -> "Wrench":
        t = [float(c) for c in np.asarray(tau, dtype=float).reshape(6)]
        return cls(tuple(t[:3]), tuple(t[3:]))


@dataclass(frozen=True)
class Reference:
    """The smoothed references the controller tracks at this step (for telemetry and scoring)."""

    depth_m: float | None
    depth_rate_m_s: float
    yaw_rad: float
    yaw_rate_rad_s: float
    velocity_body_m_s: tuple  # u_r, v_r (None if uncontrolled), w_r
    feedforward: tuple  # [X, Y, Z, K, M, N] model feed-forward part of the demand
    feedback: tuple  # [X, Y, Z, K, M, N] feedback part


@dataclass(frozen=True)
class Gains:
    """Loop bandwidths (rad/s) and limits; force/moment gains follow from the vehicle's M.

    Defaults suit the reference vehicle (actuator corners near 12 rad/s, see module docstring).
    """

    depth_bandwidth_rad_s: float = 1.2
    attitude_bandwidth_rad_s: float = 3.0  # roll and pitch
    yaw_bandwidth_rad_s: float = 2.0
    velocity_bandwidth_rad_s: float = 1.5  # surge and sway
    damping_ratio: float = 0.9
    depth_reference_rad_s: float = 1.0  # prefilter on depth setpoints (critically damped)
    yaw_reference_rad_s: float = 2.0  # prefilter on yaw setpoints (critically damped, third order)
    velocity_reference_s: float = 0.8  # first-order prefilter on velocity setpoints
    max_depth_rate_m_s: float = 0.25  # reference heave speed limit
    max_yaw_rate_rad_s: float = 0.8  # reference yaw rate limit
    manual_speed_m_s: float = 0.4  # full stick surge/sway
    manual_heave_m_s: float = 0.25  # full stick heave
    manual_yaw_rate_rad_s: float = 0.8  # full stick yaw rate
    manual_deadband: float = 0.05
    integral_share: float = 0.3  # integrator may use this share of the axis capacity
    feedforward: bool = True

    def __post_init__(self):
        for f in self.__dataclass_fields__:
            v = getattr(self, f)
            if f == "feedforward":
                continue
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"Gains.{f}: expected a finite number > 0, got {v!r}")


def axis_capacity(vehicle: Vehicle) -> np.ndarray:
    """Rough per-axis wrench the jets can give: k T_max on forces, k T_max |r|_max / 2 on moments.

    T_max = rho D^4 n_max^2 kt0 (bollard thrust, seed 000 eq. 15 at J = 0). Used only for
    anti-windup, never to clip the demand (the allocator degrades by its weights).
    """
    e, t = vehicle.environment, vehicle.thruster
    t_max = e.rho * t.diameter ** 4 * t.n_max ** 2 * t.kt[0]
    k = vehicle.n_units
    r = max(math.sqrt(sum(c * c for c in u.position)) for u in vehicle.units)
    return np.array([k * t_max] * 3 + [0.5 * k * t_max * r] * 3)


# ------------------------------------------------------------------------------------------------

class Controller:
    """Model feed-forward + PID/PI feedback; `step(estimate, setpoint, dt) -> Wrench`."""

    def __init__(self, vehicle: Vehicle, gains: Gains | None = None):
        self.vehicle = vehicle
        self.gains = gains or Gains()
        self.params = model.pack_params(vehicle)
        self.capacity = axis_capacity(vehicle)
        self._on_surface = vehicle.effects.on("surface_proximity")
        self._on_wall = vehicle.effects.on("wall_proximity")
        self._on_current = vehicle.effects.on("current")
        self.set_gains(self.gains)
        hydro = vehicle.hydro
        # yaw feed-forward along the reference (eq. 1, yaw row, level and deep): I_z r' + d1 r + d2 |r| r
        self._yaw_ff = (float(model.mass_matrix(self.params, 1.0, 1.0)[5, 5]),
                        float(hydro.linear_damping[5]), float(hydro.quadratic_damping[5]))
        self.reset()
        z6, ro6 = np.zeros(6), np.zeros(6)
        ro6.setflags(write=False)  # the allocator's achieved wrench is read-only
        for got in (z6, ro6):  # load the compiled kernels now, not in the first step
            _saturation(z6, got, self.capacity, True)
        yaw_reference(0.0, 0.0, 0.0, 0.0, 0.0, self._yaw_ref_gains, 0.01, 1)
        _yaw_feedforward(0.0, 0.0, 0.0, 0.0, 0.0, self._yaw_ref_gains, 0.01, 2, 1.0, 0.0, 0.0)

    def set_gains(self, gains: Gains) -> None:
        """New gains from the next step on (a MAVLink parameter set, onboard.params): references and
        integrators are kept, so a gain change in flight does not restart the setpoint's approach."""
        if not isinstance(gains, Gains):
            raise ValueError(f"Controller.set_gains: expected Gains, got {type(gains).__name__}")
        self.gains = g = gains
        self._gain_vec = np.array([
            g.depth_bandwidth_rad_s, g.attitude_bandwidth_rad_s, g.yaw_bandwidth_rad_s,
            g.velocity_bandwidth_rad_s, g.damping_ratio, g.integral_share,
        ])
        self._flags = np.array([float(g.feedforward), float(self._on_surface), float(self._on_wall),
                                float(self._on_current)])
        self._yaw_ref_gains = np.array([g.yaw_reference_rad_s, g.max_yaw_rate_rad_s, g.velocity_reference_s])

    @property
    def gains_si(self) -> dict:
        """The force/moment gains implied by the bandwidths and M at 0.5 m (for docs and checks)."""
        M = np.diag(self._mass_matrix(0.5))
        g = self.gains
        z = g.damping_ratio
        w_z, w_a, w_y, w_v = (g.depth_bandwidth_rad_s, g.attitude_bandwidth_rad_s,
                              g.yaw_bandwidth_rad_s, g.velocity_bandwidth_rad_s)
        return {
            "depth_kp_n_m": M[2] * w_z ** 2, "depth_kd_n_s_m": 2 * z * w_z * M[2], "depth_ki_n_m_s": M[2] * w_z ** 3 / 10,
            "roll_kp_nm_rad": M[3] * w_a ** 2, "roll_kd_nm_s_rad": 2 * z * w_a * M[3],
            "pitch_kp_nm_rad": M[4] * w_a ** 2, "pitch_kd_nm_s_rad": 2 * z * w_a * M[4],
            "yaw_kp_nm_rad": M[5] * w_y ** 2, "yaw_kd_nm_s_rad": 2 * z * w_y * M[5],
            "surge_kv_n_s_m": M[0] * w_v, "surge_ki_n_m": M[0] * w_v ** 2 / 4,
            "sway_kv_n_s_m": M[1] * w_v, "sway_ki_n_m": M[1] * w_v ** 2 / 4,
        }

    def reset(self) -> None:
        """Forget references and integrators; the next step starts from the estimate."""
        self._started = False
        self._z_r = 0.0
        self._zd_r = 0.0
        self._depth_held = False
        self._psi_r = 0.0
        self._psid_r = 0.0
        self._psidd_r = 0.0
        self._yaw_target = (math.nan, 0.0)  # (setpoint or NaN, commanded rate) of the last step
        self._vel_r = np.zeros(2)
        self._ints = np.zeros(6)  # int e dt: [u, v, z (NED), e_att (3, body)]
        self._last_tau = np.zeros(6)
        self.reference: Reference | None = None

    # -- model pieces --------------------------------------------------------------------------
    def _mass_matrix(self, depth_m: float) -> np.ndarray:
        p = self.params
        s = model.submerged_fraction(depth_m, p[model.P_RADIUS]) if self._on_surface else 1.0
        z = depth_m + p[model.P_SURF]
        wall = model.wall_factor(z, p[model.P_FLOOR], p[model.P_RADIUS], p[model.P_KWALL]) if self._on_wall else 1.0
        return model.mass_matrix(p, s, wall)

    def yaw_preview(self, n: int, dt: float) -> np.ndarray:
        """The yaw feed-forward moment N0 (N m) of the last step and of the n - 1 after it, the
        last step's setpoint held: N0 = I_z psi_r'' + d1 psi_r' + d2 |psi_r'| psi_r' along
        `yaw_reference` run on from its state. What the reference will ask is known ahead because
        the reference is this controller's own filter; the transient compensation uses it
        (onboard.compensation.YawPreview). Zeros before the first step."""
        if not self._started or n <= 0:
            return np.zeros(max(int(n), 0))
        izz, d1, d2 = self._yaw_ff
        return _yaw_feedforward(self._psi_r, self._psid_r, self._psidd_r, self._yaw_target[0], self._yaw_target[1],
                                self._yaw_ref_gains, float(dt), int(n), izz, d1, d2)

    # -- the step ------------------------------------------------------------------------------
    def step(self, estimate: EstimatedState, setpoint: Setpoint, dt: float, achieved=None) -> Wrench:
        """The demanded body wrench for this step (eq. 1). `achieved` (6, optional): the wrench the
        allocator achieved last step, for anti-windup."""
        dt = float(dt)
        if not (math.isfinite(dt) and 0.0 < dt <= 1.0):
            raise ValueError(f"Controller.step: dt must be a finite time step in (0, 1] s, got {dt!r}")
        g = self.gains
        p = self.params
        phi, theta, psi = estimate.euler_rad
        z = estimate.depth_m
        nu_t = tuple(estimate.velocity_body_m_s) + tuple(estimate.rates_rad_s)
        nu = np.array(nu_t, dtype=float)
        if not (all(map(math.isfinite, nu.tolist())) and math.isfinite(z)
                and all(map(math.isfinite, (phi, theta, psi)))):
            raise ValueError("Controller.step: the estimate holds non-finite values; hold the failsafe instead")
        if not self._started:
            self._z_r, self._zd_r = z, 0.0
            self._psi_r, self._psid_r, self._psidd_r = psi, 0.0, 0.0
            self._vel_r = nu[0:2].copy()
            self._started = True

        # ---- references (prefilters) --------------------------------------------------------
        man = setpoint.manual
        db = g.manual_deadband
        if man is not None:
            u_sp = man.surge * g.manual_speed_m_s
            v_sp = man.sway * g.manual_speed_m_s
            heave_rate = man.heave_down * g.manual_heave_m_s if abs(man.heave_down) > db else None
            yaw_rate = man.yaw_right * g.manual_yaw_rate_rad_s if abs(man.yaw_right) > db else 0.0
            depth_sp, yaw_sp, heave_on = None, None, True
        else:
            u_sp, v_sp, w_sp = setpoint.velocity_body_m_s
            depth_sp, yaw_sp = setpoint.depth_m, setpoint.yaw_rad
            heave_rate = w_sp if depth_sp is None else None
            heave_on = depth_sp is not None or w_sp is not None
            yaw_rate = 0.0
        zdd_r = psidd_r = 0.0
        if depth_sp is not None:
            # z_r'' = w^2 (z_sp - z_r) - 2 w z_r', |z_r'| <= max rate (critically damped prefilter)
            w = g.depth_reference_rad_s
            zdd_r = w * w * (depth_sp - self._z_r) - 2.0 * w * self._zd_r
            zd_new = min(max(self._zd_r + zdd_r * dt, -g.max_depth_rate_m_s), g.max_depth_rate_m_s)
            zdd_r = (zd_new - self._zd_r) / dt
            self._zd_r = zd_new
            self._z_r += self._zd_r * dt
        elif heave_rate is not None:
            # moving depth reference: z_r' follows the commanded heave rate (first order)
            target = min(max(heave_rate, -g.max_depth_rate_m_s), g.max_depth_rate_m_s)
            zdd_r = (target - self._zd_r) / g.velocity_reference_s
            self._zd_r += zdd_r * dt
            self._z_r += self._zd_r * dt
        elif heave_on:
            # hold (centred stick): the reference slows to a stop (first order) and stays there
            zdd_r = -self._zd_r / g.velocity_reference_s
            self._zd_r += zdd_r * dt
            self._z_r += self._zd_r * dt
        else:
            # heave free: the reference follows the vehicle, ready for the next depth command
            self._z_r, self._zd_r = z, 0.0
        self._yaw_target = (math.nan if yaw_sp is None else float(yaw_sp), yaw_rate)
        ref_yaw = yaw_reference(self._psi_r, self._psid_r, self._psidd_r, self._yaw_target[0], yaw_rate,
                                self._yaw_ref_gains, dt, 1)
        self._psi_r, self._psid_r, self._psidd_r = float(ref_yaw[0, 0]), float(ref_yaw[1, 0]), float(ref_yaw[2, 0])
        psidd_r = self._psidd_r
        vel_on = [u_sp is not None, v_sp is not None]
        # u_r' = (u_sp - u_r) / T, per axis on floats (numpy calls on 2 values cost more than this)
        vel_sp = (u_sp or 0.0, v_sp or 0.0)
        vel_r = self._vel_r.tolist()
        vel_dot_r = [0.0, 0.0]
        for i in range(2):
            if vel_on[i]:
                vel_dot_r[i] = (vel_sp[i] - vel_r[i]) / g.velocity_reference_s
            else:
                vel_r[i] = nu_t[i]
        self._vel_r = np.array([vel_r[0] + vel_dot_r[0] * dt, vel_r[1] + vel_dot_r[1] * dt])

        # ---- anti-windup inputs: which axes are saturated, and which way ----------------------
        cap = self.capacity
        demand = self._last_tau
        if achieved is not None:
            got = np.asarray(achieved, dtype=float).reshape(6)
            sat, sat_dir = _saturation(demand, got, cap, True)
        else:
            sat, sat_dir = _saturation(demand, demand, cap, False)
        ref = np.array([
            self._z_r, self._zd_r, zdd_r, self._psi_r, self._psid_r, psidd_r,
            self._vel_r[0], self._vel_r[1], vel_dot_r[0], vel_dot_r[1],
            1.0 if vel_on[0] else 0.0, 1.0 if vel_on[1] else 0.0, 1.0 if heave_on else 0.0,
        ])
        est = np.array([phi, theta, psi, z, estimate.depth_rate_m_s])
        tau, tau_ff, w_r = _control_law(
            p, est, nu, ref, self._gain_vec, cap, sat, sat_dir, self._ints, dt, self._flags,
        )
        self._last_tau = tau
        self.reference = Reference(
            depth_m=self._z_r if heave_on else None,
            depth_rate_m_s=self._zd_r,
            yaw_rad=self._psi_r,
            yaw_rate_rad_s=self._psid_r,
            velocity_body_m_s=(
                float(self._vel_r[0]) if vel_on[0] else None,
                float(self._vel_r[1]) if vel_on[1] else None,
                float(w_r),
            ),
            feedforward=tuple(tau_ff.tolist()),
            feedback=tuple((tau - tau_ff).tolist()),
        )
        return Wrench(tuple(tau[0:3].tolist()), tuple(tau[3:6].tolist()))


@njit(cache=True)
def yaw_reference(psi, psid, psidd, target, rate, gains, dt, n):
    """n steps of the yaw reference from (psi_r, psi_r', psi_r''): rows psi_r, psi_r', psi_r''.

    gains = [w, max rate, T_v]. With a heading target (not NaN), a critically damped third-order
    prefilter, so a new heading does not step the reference's acceleration, nor with it the yaw
    feed-forward moment (the azimuths that make that moment move at a finite rate; a second-order
    prefilter stepped it by I_z w^2 dpsi, 0.17 N m for 90 deg at w = 1.2); it steps only where
    the rate limit sets in:

        d/dt psi_r'' = w^3 wrap(target - psi_r) - 3 w^2 psi_r' - 3 w psi_r''

    Without a target (joystick rate), psi_r' follows `rate` (first order, T_v). In both, |psi_r'|
    is held within the max rate, psi_r'' being the change of psi_r' actually made (no wind-up).
    A pure function of its inputs: the controller steps it (n = 1) and previews its future under
    a held setpoint with it (`Controller.yaw_preview`).
    """
    w, rmax, tv = gains[0], gains[1], gains[2]
    out = np.empty((3, n))
    for k in range(n):
        if math.isnan(target):
            acc = (min(max(rate, -rmax), rmax) - psid) / tv
        else:
            e = (target - psi + math.pi) % (2.0 * math.pi) - math.pi
            acc = psidd + (w * w * w * e - 3.0 * w * w * psid - 3.0 * w * psidd) * dt
        new = min(max(psid + acc * dt, -rmax), rmax)
        psidd = (new - psid) / dt
        psid = new
        psi = (psi + psid * dt + math.pi) % (2.0 * math.pi) - math.pi
        out[0, k], out[1, k], out[2, k] = psi, psid, psidd
    return out


@njit(cache=True)
def _yaw_feedforward(psi, psid, psidd, target, rate, gains, dt, n, izz, d1, d2):
    """`Controller.yaw_preview` compiled: I_z psi_r'' + d1 psi_r' + d2 |psi_r'| psi_r' now and
    along n - 1 steps of `yaw_reference`."""
    out = np.empty(n)
    out[0] = _yaw_moment(psid, psidd, izz, d1, d2)
    ref = yaw_reference(psi, psid, psidd, target, rate, gains, dt, n - 1)
    for k in range(n - 1):
        out[k + 1] = _yaw_moment(ref[1, k], ref[2, k], izz, d1, d2)
    return out


@njit(cache=True)
def _yaw_moment(r, r_dot, izz, d1, d2):
    """Yaw row of eq. 1's feed-forward, level and deep: I_z r' + d1 r + d2 |r| r."""
    return izz * r_dot + d1 * r + d2 * abs(r) * r


@njit(cache=True)
def _saturation(demand, achieved, cap, use_achieved):
    """(sat, sat_dir) of the anti-windup: axis i is saturated if the achieved wrench (when given,
    and finite) missed last step's demand by more than 5 % of the axis capacity, else if the
    demand reached the capacity; sat_dir = sign(demand) where saturated, 0 elsewhere."""
    sat = np.empty(6, dtype=np.bool_)
    sat_dir = np.empty(6)
    for i in range(6):
        if use_achieved:
            s = math.isfinite(achieved[i]) and abs(demand[i] - achieved[i]) > 0.05 * cap[i]
        else:
            s = abs(demand[i]) >= cap[i]
        sat[i] = s
        sat_dir[i] = np.sign(demand[i]) * (1.0 if s else 0.0)
    return sat, sat_dir


@njit(cache=True)
def _control_law(p, est, nu, ref, gv, cap, sat, sat_dir, ints, dt, flags):
    """Eq. (1): tau = M (nu_r' + a_fb) + C(nu) nu + D(nu_r) nu_r + g_F(eta), and the integrators.

    est = [phi, theta, psi, depth, depth'], ref = [z_r, z_r', z_r'', psi_r, psi_r', psi_r'',
    u_r, v_r, u_r', v_r', surge on, sway on, heave on], gv = [w_depth, w_att, w_yaw, w_vel,
    zeta, integral share], ints = [int e_u, int e_v, int e_z, int e_att (3)] (updated in place),
    flags = [feedforward, surface, wall, current]. Returns (tau, tau_ff, w_r).
    """
    phi, theta, psi, z, zdot = est[0], est[1], est[2], est[3], est[4]
    z_r, zd_r, zdd_r, psi_r, psid_r, psidd_r = ref[0], ref[1], ref[2], ref[3], ref[4], ref[5]
    surge_on, sway_on, heave_on = ref[10] > 0.5, ref[11] > 0.5, ref[12] > 0.5
    w_z, w_a, w_y, w_v, zeta, share = gv[0], gv[1], gv[2], gv[3], gv[4], gv[5]
    # ---- kinematics ------------------------------------------------------------------------
    q = model.euler_to_quat(phi, theta, psi)
    R = model.rotation(q)  # body -> NED
    e3b = np.array([R[2, 0], R[2, 1], R[2, 2]])  # R^T [0, 0, 1]
    # body rates of the level reference turning at psi_r': w_r = T^-1(phi, theta) [0, 0, psi_r']
    # (Fossen 2011 eq. 2.30: p = phi' - s(theta) psi', q = c(phi) theta' + s(phi) c(theta) psi',
    #  r = -s(phi) theta' + c(phi) c(theta) psi')
    sph, cph, sth, cth = math.sin(phi), math.cos(phi), math.sin(theta), math.cos(theta)
    nu_ref = np.empty(6)
    nud_ref = np.empty(6)
    t_inv = np.array([-sth, sph * cth, cph * cth])
    # v_r = [u_r, v_r, 0] + R^T [0, 0, z_r'] (heave from the depth reference)
    hz, hzd = (zd_r, zdd_r) if heave_on else (0.0, 0.0)
    for i in range(3):
        nu_ref[i] = e3b[i] * hz
        nud_ref[i] = e3b[i] * hzd
        nu_ref[3 + i] = t_inv[i] * psid_r
        nud_ref[3 + i] = t_inv[i] * psidd_r
    on = (surge_on, sway_on)
    for i in range(2):
        if on[i]:
            nu_ref[i] += ref[6 + i]
            nud_ref[i] += ref[8 + i]
        else:
            nu_ref[i], nud_ref[i] = nu[i], 0.0
    # ---- errors ------------------------------------------------------------------------------
    # attitude: q_e = q^-1 (x) q_ref, q_ref = level at psi_r; e = 2 sgn(q_e,w) vec(q_e) (body)
    c2, s2 = math.cos(psi_r / 2), math.sin(psi_r / 2)
    qw, qx, qy, qz = q[0], -q[1], -q[2], -q[3]
    ew = qw * c2 - qz * s2
    ex = qx * c2 + qy * s2
    ey = qy * c2 - qx * s2
    ez = qw * s2 + qz * c2
    sgn = 1.0 if ew >= 0.0 else -1.0
    e_att = np.array([2.0 * sgn * ex, 2.0 * sgn * ey, 2.0 * sgn * ez])
    # ---- mass matrix at the estimated depth ---------------------------------------------------
    s = model.submerged_fraction(z, p[model.P_RADIUS]) if flags[1] > 0.5 else 1.0
    wall = model.wall_factor(z + p[model.P_SURF], p[model.P_FLOOR], p[model.P_RADIUS], p[model.P_KWALL]) if flags[2] > 0.5 else 1.0
    M = model.mass_matrix(p, s, wall)
    a_fb = np.zeros(6)
    # ---- depth (NED z): PID in acceleration form, mapped to the body by R^T -------------------
    if heave_on:
        e_z, e_zd = z_r - z, zd_r - zdot
        ki = w_z ** 3 / 10.0
        if not (sat[2] and np.sign(e_z * e3b[2]) == sat_dir[2]):
            ints[2] += e_z * dt
        lim = share * cap[2] / M[2, 2] / ki
        ints[2] = min(max(ints[2], -lim), lim)
        a_z = w_z * w_z * e_z + 2.0 * zeta * w_z * e_zd + ki * ints[2]
        for i in range(3):
            a_fb[i] = e3b[i] * a_z
    else:
        ints[2] = 0.0
    # ---- surge, sway: PI on velocity -----------------------------------------------------------
    for i in range(2):
        if not on[i]:
            ints[i] = 0.0
            continue
        e_v = ref[6 + i] - nu[i]
        ki = w_v * w_v / 4.0
        if not (sat[i] and np.sign(e_v) == sat_dir[i]):
            ints[i] += e_v * dt
        lim = share * cap[i] / M[i, i] / ki
        ints[i] = min(max(ints[i], -lim), lim)
        a_fb[i] += w_v * e_v + ki * ints[i]
    # ---- roll, pitch, yaw: PID on the attitude error -------------------------------------------
    for j in range(3):
        wa = w_a if j < 2 else w_y
        ki = wa ** 3 / 10.0
        if not (sat[3 + j] and np.sign(e_att[j]) == sat_dir[3 + j]):
            ints[3 + j] += e_att[j] * dt
        lim = share * cap[3 + j] / M[3 + j, 3 + j] / ki
        ints[3 + j] = min(max(ints[3 + j], -lim), lim)
        a_fb[3 + j] = wa * wa * e_att[j] + 2.0 * zeta * wa * (nu_ref[3 + j] - nu[3 + j]) + ki * ints[3 + j]
    tau_fb = M @ a_fb
    # ---- feed-forward ------------------------------------------------------------------------------
    tau_ff = np.zeros(6)
    if flags[0] > 0.5:
        nu_c = np.zeros(6)
        if flags[3] > 0.5:  # nu_c = [R^T v_c, 0]
            for i in range(3):
                nu_c[i] = R[0, i] * p[model.P_CURRENT] + R[1, i] * p[model.P_CURRENT + 1] + R[2, i] * p[model.P_CURRENT + 2]
        tau_ff = (
            M @ nud_ref  # M nu_r'
            + model.coriolis_times_nu(M, nu - nu_c)  # C(nu_r) nu_r at the estimate
            + model.damping(nu_ref - nu_c, p)  # D(nu_r) nu_r at the reference
        )
        g_eta = model.restoring(R, p, s)  # -g(eta) as the model writes it
        for i in range(3):
            tau_ff[i] -= g_eta[i]  # + g_F(eta): forces only, the righting moment is left to help
        for i in range(2):
            if not on[i]:
                tau_ff[i] = 0.0
        if not heave_on:  # heave free: no vertical effort
            fz = e3b[0] * tau_ff[0] + e3b[1] * tau_ff[1] + e3b[2] * tau_ff[2]
            for i in range(3):
                tau_ff[i] -= e3b[i] * fz
    return tau_fb + tau_ff, tau_ff, nu_ref[2]


__all__ = ["Controller", "Gains", "ManualAxes", "Reference", "Setpoint", "Wrench", "axis_capacity", "yaw_reference"]


# Kernels above compile onboard.model functions into themselves: key their disk cache on it.
key_caches_on(globals(), MODEL_SOURCE)
