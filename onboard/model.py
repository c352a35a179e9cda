"""The vehicle model of spec/vehicle-model.md as a sum of named terms, compiled with numba.

Pure math: a state vector and a command vector in, a state derivative out. The same compiled
function serves the HIL plant (integrated with every enabled effect), the onboard loop (its
thrust and geometry pieces) and the diagnosis (re-simulation with other parameters).

Layout. The state x is flat (`StateLayout`): NED position, quaternion (w, x, y, z; body to
NED), nu = [u, v, w, p, q, r] (absolute body velocities), propeller speeds n (rev/s), joint
angles alpha and beta (rad), then 20 transient-filter states per unit (seed 004, five rows of
four). The command u is [n_cmd (rev/s) per unit, alpha_cmd per unit, beta_cmd per unit].
The parameters are one flat float vector packed from a `Vehicle` by `pack_params`, so a batch
of vehicles with different parameters is just a 2-D array, and a test can change one number.

Each term is its own function below (`rigid_body_and_added_mass`, `damping`, `restoring`,
`jet_unit`, `azimuth_transient_*`, `submerged_fraction`, `wall_factor`, ...). `derivative`
sums them; an effect that is switched off contributes exactly what the spec says "off" means.
Every function carries the equation it implements.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from .vehicle import EFFECT_IDS, Vehicle

# ------------------------------------------------------------------------------------------------
# Parameter layout: one line per vehicle key, in the order packed. Offsets are module constants,
# which numba folds into the compiled code.

_KEYS: list[tuple[str, int]] = []


def _at(key: str, size: int = 1) -> int:
    off = sum(s for _, s in _KEYS)
    _KEYS.append((key, size))
    return off


P_RHO = _at("environment.rho")
P_G = _at("environment.g")
P_PATM = _at("environment.p_atm")
P_SURF = _at("environment.surface_depth")
P_FLOOR = _at("environment.floor_depth")
P_CURRENT = _at("environment.current", 3)
P_MASS = _at("body.mass")
P_VOLUME = _at("body.volume")
P_RADIUS = _at("body.radius")
P_INERTIA = _at("body.inertia", 3)
P_CG = _at("body.cg", 3)
P_CB = _at("body.cb", 3)
P_MA = _at("hydro.added_mass", 6)
P_DL = _at("hydro.linear_damping", 6)
P_DQ = _at("hydro.quadratic_damping", 6)
P_DIAM = _at("thruster.diameter")
P_KT = _at("thruster.kt", 3)
P_JRANGE = _at("thruster.j_range", 2)
P_NMAX = _at("thruster.n_max")
P_TAU_M = _at("thruster.motor_time_constant")
P_ALIM = _at("servo.angle_limit")
P_RLIM = _at("servo.rate_limit")
P_TAU_S = _at("servo.time_constant")
P_GAIN_T = _at("effects.azimuth_transient.gain_per_newton")
P_KWALL = _at("effects.wall_proximity.k_wall")
P_ON = _at("effects.*.enabled", len(EFFECT_IDS))  # 1.0 / 0.0 in EFFECT_IDS order
# Five transient rows (f1x, f1y, m1z, f2x, f2z), each as controllable canonical form:
# denominator [a1, a2, a3, a4] of s^4 + a1 s^3 + a2 s^2 + a3 s + a4, numerator [b1..b4] of
# b1 s^3 + b2 s^2 + b3 s + b4.
TRANSIENT_ROWS = ("f1x", "f1y", "m1z", "f2x", "f2z")
P_TF = _at("effects.azimuth_transient.<rows as state space>", 8 * len(TRANSIENT_ROWS))
# A test rig, not part of the vehicle: a linear spring in NED pulling the body origin to an
# anchor (seed 001 free-decay rig). Zero unless a `Plant` is built with `rig_stiffness`.
P_RIG_K = _at("rig.stiffness", 3)  # N/m along NED x, y, z
P_RIG_ANCHOR = _at("rig.anchor", 3)  # m NED
P_UNITS = _at("unit[*].position+neutral", 0)  # then 6 values per unit, then 4 per unit (below)
# After the 6 k unit values, 4 per unit: [kind, time constant (s), T_min (N), T_max (N)].
# kind 0: a vectored water-jet (spec 3; the other three are 0 and unused); kind 1: a fixed
# two-way thruster (spec 3.1), whose 6 values are position and direction d, whose command and
# state slot n_i hold its thrust in newtons, and whose joints stay at 0. One kernel, one path
# per unit chosen by data: a jet-only vehicle runs exactly the arithmetic it always did.
UNIT_TAIL = 4
KIND_JET, KIND_FIXED = 0.0, 1.0

ON_INFLOW, ON_MOTOR, ON_SERVO, ON_TRANSIENT, ON_SURFACE, ON_WALL, ON_CURRENT = (
    P_ON + EFFECT_IDS.index(e) for e in EFFECT_IDS
)

# Transient row indices and what drives them (seed 004, spec 4.1).
TF_F1X, TF_F1Y, TF_M1Z, TF_F2X, TF_F2Z = range(5)
N_TF_STATES = 4 * len(TRANSIENT_ROWS)


def transfer_function(row: str, coeffs) -> tuple[np.ndarray, np.ndarray]:
    """(num, den) polynomials, highest power first, of a seed-004 row.

    Force rows, seed 004 eq. 5: K (s^2 + a s + b) / ((s^2 + c s + d)(s^2 + e s + g)).
    Moment row, seed 004 eq. 6: K s^2 / (s^4 + a s^3 + b s^2 + c s + d).
    """
    if row == "m1z":
        k, a, b, c, d = coeffs
        return np.array([k, 0.0, 0.0]), np.array([1.0, a, b, c, d])
    k, a, b, c, d, e, g = coeffs
    return k * np.array([1.0, a, b]), np.polymul([1.0, c, d], [1.0, e, g])


def _canonical(num: np.ndarray, den: np.ndarray) -> np.ndarray:
    """[a1..a4, b1..b4] of a strictly proper 4th-order transfer function (den monic)."""
    den = np.asarray(den, float)
    num = np.asarray(num, float) / den[0]
    den = den / den[0]
    b = np.zeros(4)
    b[4 - len(num):] = num
    return np.concatenate([den[1:], b])


@dataclass(frozen=True)
class StateLayout:
    """Where each named piece of the state vector lives, for a vehicle with `n_units` jets."""

    n_units: int = 4

    @property
    def pos(self):
        return slice(0, 3)

    @property
    def quat(self):
        return slice(3, 7)

    @property
    def nu(self):
        return slice(7, 13)

    @property
    def n(self):
        return slice(13, 13 + self.n_units)

    @property
    def alpha(self):
        return slice(13 + self.n_units, 13 + 2 * self.n_units)

    @property
    def beta(self):
        return slice(13 + 2 * self.n_units, 13 + 3 * self.n_units)

    @property
    def transient(self):
        return slice(13 + 3 * self.n_units, self.size)

    @property
    def size(self) -> int:
        return 13 + 3 * self.n_units + N_TF_STATES * self.n_units


def pack_params(v: Vehicle) -> np.ndarray:
    """The flat parameter vector of a vehicle, in the layout above."""
    out: list[float] = []
    for key, size in _KEYS:
        if key == "effects.*.enabled":
            out += [1.0 if v.effects.on(e) else 0.0 for e in EFFECT_IDS]
        elif key.startswith("effects.azimuth_transient.<"):
            at = v.effects.azimuth_transient
            for row in TRANSIENT_ROWS:
                out += list(_canonical(*transfer_function(row, getattr(at, row))))
        elif key.startswith("rig."):
            out += [0.0] * size
        elif key.startswith("unit[*]"):
            for u in v.units:
                out += list(u.position) + list(u.neutral)
            for f in v.fixed:
                out += list(f.position) + list(f.direction)
            out += [0.0] * (UNIT_TAIL * v.n_jets)
            if v.fixed:
                from .fixed import thrust_limits

                t_min, t_max = thrust_limits(v.fixed_thruster)
                out += [KIND_FIXED, v.fixed_thruster.time_constant, t_min, t_max] * len(v.fixed)
        else:
            val = v.get(key)
            out += list(val) if size > 1 else [float(val)]
    return np.array(out, dtype=np.float64)


def initial_state(v: Vehicle, depth_m: float = 0.5, command=None) -> np.ndarray:
    """At rest, level, yaw 0, x = y = 0 at `depth_m`; n = 0; joints at the first command (spec 6)."""
    lay = StateLayout(v.n_units)
    x = np.zeros(lay.size)
    x[2] = v.environment.surface_depth + depth_m
    x[3] = 1.0
    if command is not None:
        lim = v.servo.angle_limit
        k, j = v.n_units, v.n_jets  # a fixed thruster's joints stay at 0
        x[lay.alpha][:j] = np.clip(np.asarray(command)[k:k + j], -lim, lim)
        x[lay.beta][:j] = np.clip(np.asarray(command)[2 * k:2 * k + j], -lim, lim)
    return x


# ------------------------------------------------------------------------------------------------
# Small vector algebra (scalar code: numba turns it into straight-line machine code).

@njit(cache=True, inline="always")
def cross(a0, a1, a2, b0, b1, b2):
    return a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0


@njit(cache=True, inline="always")
def add_force_at(tau, rx, ry, rz, fx, fy, fz, mz_extra=0.0):
    """tau += [F; r x F] for a force F applied at r (body FRD), plus a pure moment about body z
    (Fossen 2011 eq. 2.116: the generalised force of a point force)."""
    mx, my, mz = cross(rx, ry, rz, fx, fy, fz)
    tau[0] += fx
    tau[1] += fy
    tau[2] += fz
    tau[3] += mx
    tau[4] += my
    tau[5] += mz + mz_extra


@njit(cache=True)
def rotation(q):
    """R(q), body to NED, of a unit quaternion q = [w, x, y, z] (Fossen 2011 eq. 2.72)."""
    w, a, b, c = q[0], q[1], q[2], q[3]
    R = np.empty((3, 3))
    R[0, 0] = 1 - 2 * (b * b + c * c)
    R[0, 1] = 2 * (a * b - w * c)
    R[0, 2] = 2 * (a * c + w * b)
    R[1, 0] = 2 * (a * b + w * c)
    R[1, 1] = 1 - 2 * (a * a + c * c)
    R[1, 2] = 2 * (b * c - w * a)
    R[2, 0] = 2 * (a * c - w * b)
    R[2, 1] = 2 * (b * c + w * a)
    R[2, 2] = 1 - 2 * (a * a + b * b)
    return R


@njit(cache=True)
def solve6(M, b):
    """x with M x = b for a 6x6 M (Gaussian elimination with partial pivoting)."""
    A = M.copy()
    x = b.copy()
    for k in range(6):
        piv = k
        for i in range(k + 1, 6):
            if abs(A[i, k]) > abs(A[piv, k]):
                piv = i
        if piv != k:
            for j in range(6):
                A[k, j], A[piv, j] = A[piv, j], A[k, j]
            x[k], x[piv] = x[piv], x[k]
        for i in range(k + 1, 6):
            f = A[i, k] / A[k, k]
            for j in range(k, 6):
                A[i, j] -= f * A[k, j]
            x[i] -= f * x[k]
    for k in range(5, -1, -1):
        s = x[k]
        for j in range(k + 1, 6):
            s -= A[k, j] * x[j]
        x[k] = s / A[k, k]
    return x


# ------------------------------------------------------------------------------------------------
# Terms

@njit(cache=True)
def thrust_coefficient(J, kt0, kt1, kt2):
    """K(J) = kt0 + kt1 J + kt2 J^2 (seed 000 eq. 14-15)."""
    return kt0 + kt1 * J + kt2 * J * J


@njit(cache=True)
def advance_ratio(v_axial, n, diameter, j_lo, j_hi):
    """J = V_a / (n D), clipped to the fitted range; J = 0 when n = 0 (seed 000 eq. 11, spec 3)."""
    if n <= 1e-9:
        return 0.0
    return min(max(v_axial / (n * diameter), j_lo), j_hi)


@njit(cache=True)
def jet_thrust(n, v_axial, p):
    """T = rho D^4 n^2 K(J) (seed 000 eq. 15); with `thrust_inflow` off K = kt0 (bollard)."""
    D = p[P_DIAM]
    if p[ON_INFLOW] > 0.5:
        J = advance_ratio(v_axial, n, D, p[P_JRANGE], p[P_JRANGE + 1])
    else:
        J = 0.0
    return p[P_RHO] * D ** 4 * n * n * thrust_coefficient(J, p[P_KT], p[P_KT + 1], p[P_KT + 2])


@njit(cache=True)
def jet_frame(alpha, beta, e1x, e1y):
    """d, e_alpha, e_beta of a unit (spec 3 and 4.1), as a 3x3 array of rows.

    e1 = neutral (horizontal), e3 = body z, e2 = e3 x e1 = (-e1y, e1x, 0).
    d = cos b cos a e1 + cos b sin a e2 - sin b e3; e_alpha = dd/da / cos b; e_beta = dd/db.
    """
    e2x, e2y = -e1y, e1x
    ca, sa, cb, sb = math.cos(alpha), math.sin(alpha), math.cos(beta), math.sin(beta)
    F = np.empty((3, 3))
    F[0, 0] = cb * ca * e1x + cb * sa * e2x
    F[0, 1] = cb * ca * e1y + cb * sa * e2y
    F[0, 2] = -sb
    F[1, 0] = -sa * e1x + ca * e2x
    F[1, 1] = -sa * e1y + ca * e2y
    F[1, 2] = 0.0
    F[2, 0] = -sb * ca * e1x - sb * sa * e2x
    F[2, 1] = -sb * ca * e1y - sb * sa * e2y
    F[2, 2] = -cb
    return F


@njit(cache=True)
def submerged_fraction(depth, radius):
    """s = h^2 (3R - h) / (4 R^3), h = clip(depth + R, 0, 2R) (spherical cap; seed 003 sec. 3)."""
    h = min(max(depth + radius, 0.0), 2.0 * radius)
    return h * h * (3.0 * radius - h) / (4.0 * radius ** 3)


@njit(cache=True)
def wall_factor(z, floor_depth, radius, k_wall):
    """1 + k_wall (R / d)^3, d = max(floor_depth - z, 1.2 R) (seed 001 gap effect, spec 4)."""
    d = max(floor_depth - z, 1.2 * radius)
    return 1.0 + k_wall * (radius / d) ** 3


@njit(cache=True)
def servo_rate(a, a_cmd, limit, rate_limit, tau):
    """a' = clip((clip(a_cmd) - a) / tau, +-rate_limit) (spec 4, `servo_lag`)."""
    target = min(max(a_cmd, -limit), limit)
    return min(max((target - a) / tau, -rate_limit), rate_limit)


@njit(cache=True)
def filter_derivative(xf, drive, coef, out):
    """Controllable canonical form: x1' = x2, x2' = x3, x3' = x4, x4' = -a4 x1 - ... - a1 x4 + u."""
    out[0] = xf[1]
    out[1] = xf[2]
    out[2] = xf[3]
    out[3] = -coef[3] * xf[0] - coef[2] * xf[1] - coef[1] * xf[2] - coef[0] * xf[3] + drive


@njit(cache=True)
def filter_output(xf, coef):
    """y = b4 x1 + b3 x2 + b2 x3 + b1 x4."""
    return coef[7] * xf[0] + coef[6] * xf[1] + coef[5] * xf[2] + coef[4] * xf[3]


@njit(cache=True)
def mass_matrix(p, s_added, wall):
    """M = M_RB + M_A (Fossen 2011 eq. 3.44, 6.5); M_A = s diag(added_mass), heave x wall."""
    m = p[P_MASS]
    xg, yg, zg = p[P_CG], p[P_CG + 1], p[P_CG + 2]
    M = np.zeros((6, 6))
    for i in range(3):
        M[i, i] = m
    # -m S(r_g) upper right, m S(r_g) lower left, S(a) b = a x b
    S = np.empty((3, 3))  # filled in place: a nested-list literal allocates a list per row
    S[0, 0], S[0, 1], S[0, 2] = 0.0, -zg, yg
    S[1, 0], S[1, 1], S[1, 2] = zg, 0.0, -xg
    S[2, 0], S[2, 1], S[2, 2] = -yg, xg, 0.0
    for i in range(3):
        for j in range(3):
            M[i, 3 + j] = -m * S[i, j]
            M[3 + i, j] = m * S[i, j]
    # I_b = I_g - m S(r_g)^2 (parallel axes); 3x3 product in loops (a BLAS call costs more)
    for i in range(3):
        for j in range(3):
            s2 = 0.0
            for r in range(3):
                s2 += S[i, r] * S[r, j]
            M[3 + i, 3 + j] = -m * s2
        M[3 + i, 3 + i] += p[P_INERTIA + i]
    for i in range(6):
        M[i, i] += s_added * p[P_MA + i] * (wall if i == 2 else 1.0)
    return M


@njit(cache=True)
def coriolis_times_nu(M, nu_r):
    """(C_RB + C_A)(nu_r) nu_r from Kirchhoff's equations (Fossen 2011 eq. 3.57, 6.43).

    With momentum h = M nu_r = [h1, h2]: C nu = [w x h1, w x h2 + v x h1].
    """
    h = np.zeros(6)  # h = M nu_r, in loops (a BLAS call costs more than the product)
    for i in range(6):
        for j in range(6):
            h[i] += M[i, j] * nu_r[j]
    v0, v1, v2, w0, w1, w2 = nu_r[0], nu_r[1], nu_r[2], nu_r[3], nu_r[4], nu_r[5]
    out = np.empty(6)
    out[0], out[1], out[2] = cross(w0, w1, w2, h[0], h[1], h[2])
    a0, a1, a2 = cross(w0, w1, w2, h[3], h[4], h[5])
    b0, b1, b2 = cross(v0, v1, v2, h[0], h[1], h[2])
    out[3], out[4], out[5] = a0 + b0, a1 + b1, a2 + b2
    return out


@njit(cache=True)
def damping(nu_r, p):
    """D(nu_r) nu_r = (D_l + D_q |nu_r|) nu_r, elementwise (spec 2)."""
    out = np.empty(6)
    for i in range(6):
        out[i] = (p[P_DL + i] + p[P_DQ + i] * abs(nu_r[i])) * nu_r[i]
    return out


@njit(cache=True)
def restoring(R, p, s_buoy):
    """-g(eta): weight at r_g, buoyancy B = rho g V s at r_b (Fossen 2011 eq. 4.6)."""
    W = p[P_MASS] * p[P_G]
    B = p[P_RHO] * p[P_G] * p[P_VOLUME] * s_buoy
    # R^T [0, 0, 1] is the third row of R
    kx, ky, kz = R[2, 0], R[2, 1], R[2, 2]
    fg0, fg1, fg2 = W * kx, W * ky, W * kz
    fb0, fb1, fb2 = -B * kx, -B * ky, -B * kz
    out = np.empty(6)
    out[0], out[1], out[2] = fg0 + fb0, fg1 + fb1, fg2 + fb2
    m0, m1, m2 = cross(p[P_CG], p[P_CG + 1], p[P_CG + 2], fg0, fg1, fg2)
    n0, n1, n2 = cross(p[P_CB], p[P_CB + 1], p[P_CB + 2], fb0, fb1, fb2)
    out[3], out[4], out[5] = m0 + n0, m1 + n1, m2 + n2
    return out


@njit(cache=True)
def rig_spring(x, R, p):
    """Test-rig spring force f = -K (p - p_anchor) in NED, expressed in the body (seed 001 eq. 6)."""
    out = np.zeros(6)
    f0 = -p[P_RIG_K] * (x[0] - p[P_RIG_ANCHOR])
    f1 = -p[P_RIG_K + 1] * (x[1] - p[P_RIG_ANCHOR + 1])
    f2 = -p[P_RIG_K + 2] * (x[2] - p[P_RIG_ANCHOR + 2])
    for i in range(3):
        out[i] = R[0, i] * f0 + R[1, i] * f1 + R[2, i] * f2
    return out


@njit(cache=True, inline="always")  # inlined: called per unit per RK4 stage (2.5x slower as a call)
def actuator(xa, u, p, k, i, out):
    """Unit i's actuator states (spec 4: motor_lag, servo_lag, the seed-004 filters) on the
    actuator part of the state, xa = x[13:] (speeds or thrusts k, azimuths k, elevations k, then
    N_TF_STATES per unit): writes their derivatives into out (same layout) and returns
    (n, a, b, ad, bd): the speed in use (a fixed thruster's thrust), the joint angles and rates.
    The one description of the actuators, used by the plant (`jets_and_transients`) and by the
    diagnosis' actuator replay (ground.diagnose.replay).

    A fixed two-way thruster (spec 3.1): its command is the static thrust of the PWM (the curve
    of `onboard.fixed`), clipped to [T_min, T_max]; with `motor_lag` T' = (T_cmd - T) /
    time_constant, else T = T_cmd. No joints, so no azimuth transient: those states stay at rest.
    """
    t = P_UNITS + 6 * k + UNIT_TAIL * i
    j = 3 * k + N_TF_STATES * i
    if p[t] > 0.5:
        T_cmd = min(max(u[i], p[t + 2]), p[t + 3])
        if p[ON_MOTOR] > 0.5:
            T = xa[i]
            out[i] = (T_cmd - T) / p[t + 1]
        else:
            T = T_cmd
            out[i] = 0.0
        out[k + i] = 0.0
        out[2 * k + i] = 0.0
        for r in range(N_TF_STATES):
            out[j + r] = 0.0
        return T, 0.0, 0.0, 0.0, 0.0
    lim, nmax = p[P_ALIM], p[P_NMAX]
    n_cmd = min(max(u[i], 0.0), nmax)
    if p[ON_MOTOR] > 0.5:
        n = min(max(xa[i], 0.0), nmax)
        out[i] = (n_cmd - n) / p[P_TAU_M]
    else:
        n = n_cmd
        out[i] = 0.0
    if p[ON_SERVO] > 0.5:
        a, b = xa[k + i], xa[2 * k + i]
        ad = servo_rate(a, u[k + i], lim, p[P_RLIM], p[P_TAU_S])
        bd = servo_rate(b, u[2 * k + i], lim, p[P_RLIM], p[P_TAU_S])
    else:
        a = min(max(u[k + i], -lim), lim)
        b = min(max(u[2 * k + i], -lim), lim)
        ad, bd = 0.0, 0.0
    out[k + i], out[2 * k + i] = ad, bd
    if p[ON_TRANSIENT] > 0.5 and p[P_GAIN_T] > 0.0:  # transient rows driven by the joint rates
        drives = (abs(ad), ad, ad, abs(bd), bd)
        for r in range(5):
            coef = p[P_TF + 8 * r:P_TF + 8 * r + 8]
            filter_derivative(xa[j + 4 * r:j + 4 * r + 4], drives[r], coef, out[j + 4 * r:j + 4 * r + 4])
    else:
        for r in range(N_TF_STATES):
            out[j + r] = 0.0
    return n, a, b, ad, bd


@njit(cache=True)
def actuator_project(xa, u, p, k):
    """After a step (spec 6), the actuator part xa = x[13:]: lag-free actuators set to their
    command (clipped), joints clipped to their limits, a fixed thruster's joints at 0."""
    lim = p[P_ALIM]
    for i in range(k):
        t = P_UNITS + 6 * k + UNIT_TAIL * i
        if p[t] > 0.5:  # a fixed thruster: thrust without lag is its command; no joints
            if p[ON_MOTOR] < 0.5:
                xa[i] = min(max(u[i], p[t + 2]), p[t + 3])
            xa[k + i] = 0.0
            xa[2 * k + i] = 0.0
            continue
        if p[ON_MOTOR] < 0.5:
            xa[i] = min(max(u[i], 0.0), p[P_NMAX])
        for j in (k + i, 2 * k + i):
            if p[ON_SERVO] < 0.5:
                xa[j] = min(max(u[j], -lim), lim)
            else:
                xa[j] = min(max(xa[j], -lim), lim)


def actuator_param_indices(k: int) -> np.ndarray:
    """Indices of everything `actuator` and `actuator_project` read from the packed parameters
    (k units): two parameter vectors equal there give the same actuator run under one command."""
    idx = [ON_MOTOR, P_TAU_M, P_NMAX, ON_SERVO, P_ALIM, P_RLIM, P_TAU_S, ON_TRANSIENT, P_GAIN_T]
    idx += range(P_TF, P_TF + 8 * len(TRANSIENT_ROWS))
    idx += range(P_UNITS + 6 * k, P_UNITS + 6 * k + UNIT_TAIL * k)
    return np.array(idx, np.int64)


@njit(cache=True)
def jets_and_transients(x, u, p, nu_r, k, xdot, tau, thrust_out):
    """tau_jets + tau_transient of k units; writes actuator and filter derivatives into xdot.

    Per unit i (spec 3, 4 and 4.1): n_i (motor_lag), alpha_i, beta_i (servo_lag), axial inflow
    V_a = (v_r + w x r_i) . d_i, thrust T_i (seed 000 eq. 15), transient rows driven by the joint
    rates, force F_i = (T_i + dT_i) d_i + g T_i (F1y e_alpha + F2z e_beta) at r_i and the
    reaction moment -g T_i M1z about body z. Jets never push backwards: T_i + dT_i >= 0.
    """
    i_tf = 13 + 3 * k
    xa, xad = x[13:], xdot[13:]
    gain = p[P_GAIN_T] if p[ON_TRANSIENT] > 0.5 else 0.0
    for i in range(k):
        n, a, b, ad, bd = actuator(xa, u, p, k, i, xad)
        o = P_UNITS + 6 * i
        rx, ry, rz = p[o], p[o + 1], p[o + 2]
        if p[P_UNITS + 6 * k + UNIT_TAIL * i] > 0.5:  # a fixed thruster: F = T d at r (spec 3.1)
            add_force_at(tau, rx, ry, rz, n * p[o + 3], n * p[o + 4], n * p[o + 5])
            thrust_out[i] = n
            continue
        # Geometry and inflow
        F = jet_frame(a, b, p[o + 3], p[o + 4])
        c0, c1, c2 = cross(nu_r[3], nu_r[4], nu_r[5], rx, ry, rz)
        v_axial = (nu_r[0] + c0) * F[0, 0] + (nu_r[1] + c1) * F[0, 1] + (nu_r[2] + c2) * F[0, 2]
        T = jet_thrust(n, v_axial, p)
        # Transient rows (seed 004 eq. 5-6), driven by the actual joint rates
        j = i_tf + N_TF_STATES * i
        f1x = f1y = m1z = f2x = f2z = 0.0
        if gain > 0.0:  # (their derivatives: `actuator`)
            f1x = filter_output(x[j:j + 4], p[P_TF:P_TF + 8])
            f1y = filter_output(x[j + 4:j + 8], p[P_TF + 8:P_TF + 16])
            m1z = filter_output(x[j + 8:j + 12], p[P_TF + 16:P_TF + 24])
            f2x = filter_output(x[j + 12:j + 16], p[P_TF + 24:P_TF + 32])
            f2z = filter_output(x[j + 16:j + 20], p[P_TF + 32:P_TF + 40])
        g_T = gain * T
        axial = max(T - g_T * (f1x + f2x), 0.0)
        lat_a, lat_b = g_T * f1y, g_T * f2z
        fx = axial * F[0, 0] + lat_a * F[1, 0] + lat_b * F[2, 0]
        fy = axial * F[0, 1] + lat_a * F[1, 1] + lat_b * F[2, 1]
        fz = axial * F[0, 2] + lat_a * F[1, 2] + lat_b * F[2, 2]
        add_force_at(tau, rx, ry, rz, fx, fy, fz, -g_T * m1z)
        thrust_out[i] = axial


@njit(cache=True)
def derivative(x, u, p, xdot):
    """x' = f(x, u; p) of spec 2-4; also returns the jet thrusts T_i (N) after transient loss.

    (M_RB + M_A) nu_r' + C(nu_r) nu_r + D(nu_r) nu_r + g(eta) = tau_jets + tau_transient,
    nu' = nu_r' + [-w x (R^T v_c), 0], p' = R v, q' = 1/2 q (x) [0, w].
    """
    k = (x.shape[0] - 13) // (3 + N_TF_STATES)
    q = x[3:7]
    nu = x[7:13]
    R = rotation(q)
    # Current: nu_c = [R^T v_c, 0] (spec 2, `current`)
    vc0 = vc1 = vc2 = 0.0
    if p[ON_CURRENT] > 0.5:
        c = p[P_CURRENT:P_CURRENT + 3]
        vc0 = R[0, 0] * c[0] + R[1, 0] * c[1] + R[2, 0] * c[2]
        vc1 = R[0, 1] * c[0] + R[1, 1] * c[1] + R[2, 1] * c[2]
        vc2 = R[0, 2] * c[0] + R[1, 2] * c[1] + R[2, 2] * c[2]
    nu_r = nu.copy()
    nu_r[0] -= vc0
    nu_r[1] -= vc1
    nu_r[2] -= vc2
    # Surface and wall proximity scale buoyancy and added mass
    depth = x[2] - p[P_SURF]
    s = submerged_fraction(depth, p[P_RADIUS]) if p[ON_SURFACE] > 0.5 else 1.0
    wall = wall_factor(x[2], p[P_FLOOR], p[P_RADIUS], p[P_KWALL]) if p[ON_WALL] > 0.5 else 1.0
    M = mass_matrix(p, s, wall)
    # Generalised forces
    tau = np.zeros(6)
    thrust = np.empty(k)
    jets_and_transients(x, u, p, nu_r, k, xdot, tau, thrust)
    rhs = tau - coriolis_times_nu(M, nu_r) - damping(nu_r, p) + restoring(R, p, s) + rig_spring(x, R, p)
    nu_r_dot = solve6(M, rhs)
    # nu' = nu_r' + nu_c', nu_c' = -w x nu_c
    w0, w1, w2 = nu[3], nu[4], nu[5]
    d0, d1, d2 = cross(w0, w1, w2, vc0, vc1, vc2)
    for i in range(6):
        xdot[7 + i] = nu_r_dot[i]
    xdot[7] -= d0
    xdot[8] -= d1
    xdot[9] -= d2
    # Kinematics: p' = R v, q' = 1/2 q (x) [0, w] (Fossen 2011 eq. 2.78)
    for i in range(3):
        xdot[i] = R[i, 0] * nu[0] + R[i, 1] * nu[1] + R[i, 2] * nu[2]
    qw, qx, qy, qz = q[0], q[1], q[2], q[3]
    xdot[3] = 0.5 * (-qx * w0 - qy * w1 - qz * w2)
    xdot[4] = 0.5 * (qw * w0 + qy * w2 - qz * w1)
    xdot[5] = 0.5 * (qw * w1 + qz * w0 - qx * w2)
    xdot[6] = 0.5 * (qw * w2 + qx * w1 - qy * w0)
    return thrust


@njit(cache=True)
def project(x, u, p):
    """After a step (spec 6): renormalise q, clip joints, and set lag-free actuators to command."""
    k = (x.shape[0] - 13) // (3 + N_TF_STATES)
    nq = math.sqrt(x[3] ** 2 + x[4] ** 2 + x[5] ** 2 + x[6] ** 2)
    for i in range(3, 7):
        x[i] /= nq
    actuator_project(x[13:], u, p, k)


@njit(cache=True)
def rk4_step(x, u, p, dt):
    """One classical Runge-Kutta step with u held over it, then `project` (spec 6)."""
    # One buffer for the stages and the stage state instead of a temporary array per operation;
    # each element is computed with the same operations in the same order as the array form
    # x + 0.5 dt k1, ..., x + dt/6 (k1 + 2 k2 + 2 k3 + k4), so the result is unchanged.
    n = x.shape[0]
    buf = np.empty((5, n))
    k1, k2, k3, k4, xs = buf[0], buf[1], buf[2], buf[3], buf[4]
    h = 0.5 * dt
    derivative(x, u, p, k1)
    for i in range(n):
        xs[i] = x[i] + h * k1[i]
    derivative(xs, u, p, k2)
    for i in range(n):
        xs[i] = x[i] + h * k2[i]
    derivative(xs, u, p, k3)
    for i in range(n):
        xs[i] = x[i] + dt * k3[i]
    derivative(xs, u, p, k4)
    out = np.empty(n)
    c = dt / 6.0
    for i in range(n):
        out[i] = x[i] + c * (k1[i] + 2.0 * k2[i] + 2.0 * k3[i] + k4[i])
    project(out, u, p)
    return out


@njit(cache=True)
def rk4_steps(x, u, p, dt, n_steps):
    """`n_steps` RK4 steps with u held; returns the final state."""
    for _ in range(n_steps):
        x = rk4_step(x, u, p, dt)
    return x


# ------------------------------------------------------------------------------------------------
# Outputs a sensor or a controller needs (pure functions of the state)

@njit(cache=True)
def quat_to_euler(q):
    """ZYX Euler angles (roll, pitch, yaw) of q = [w, x, y, z] (Fossen 2011 eq. 2.77)."""
    w, a, b, c = q[0], q[1], q[2], q[3]
    roll = math.atan2(2 * (w * a + b * c), 1 - 2 * (a * a + b * b))
    sp = min(max(2 * (w * b - c * a), -1.0), 1.0)
    pitch = math.asin(sp)
    yaw = math.atan2(2 * (w * c + a * b), 1 - 2 * (b * b + c * c))
    return roll, pitch, yaw


@njit(cache=True)
def euler_to_quat(roll, pitch, yaw):
    """q = q_z(yaw) q_y(pitch) q_x(roll), [w, x, y, z] (Fossen 2011 eq. 2.83); compiled, so the
    estimator's and controller's kernels call it too."""
    cr, sr = math.cos(roll / 2), math.sin(roll / 2)
    cp, sp = math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return np.array([
        cr * cp * cy + sr * sp * sy,
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
    ])


@njit(cache=True)
def specific_force(x, xdot, p):
    """Accelerometer truth R^T (a_ned - [0, 0, g]) = v' + w x v - R^T [0, 0, g] (spec 5)."""
    R = rotation(x[3:7])
    c0, c1, c2 = cross(x[10], x[11], x[12], x[7], x[8], x[9])
    g = p[P_G]
    return np.array([
        xdot[7] + c0 - g * R[2, 0],
        xdot[8] + c1 - g * R[2, 1],
        xdot[9] + c2 - g * R[2, 2],
    ])


def wrench_map(v: Vehicle, alpha=None, beta=None) -> np.ndarray:
    """The 6 x 3k force/moment map: tau = B f, f = per-unit force vectors [fx, fy, fz] (body).

    Column block i maps unit i's force to [F_i, r_i x F_i] (spec 3; PX4 control_allocator's
    effectiveness matrix for free force vectors).
    """
    k = v.n_units
    B = np.zeros((6, 3 * k))
    for i, position in enumerate(v.unit_positions):
        rx, ry, rz = position
        S = np.array([[0.0, -rz, ry], [rz, 0.0, -rx], [-ry, rx, 0.0]])
        B[0:3, 3 * i:3 * i + 3] = np.eye(3)
        B[3:6, 3 * i:3 * i + 3] = S
    return B


def thrust_direction(v: Vehicle, alpha, beta) -> np.ndarray:
    """d_i for every unit (k x 3) at joint angles alpha, beta (spec 3); a fixed thruster's own
    direction (spec 3.1), whatever its angles."""
    return np.array([
        jet_frame(float(alpha[i]), float(beta[i]), u.neutral[0], u.neutral[1])[0]
        for i, u in enumerate(v.units)
    ] + [np.asarray(f.direction, float) for f in v.fixed]).reshape(v.n_units, 3)


def effectiveness(v: Vehicle, alpha, beta) -> np.ndarray:
    """The 6 x k map from thrust magnitudes to the body wrench at given joint angles."""
    B = wrench_map(v)
    d = thrust_direction(v, alpha, beta)
    return np.column_stack([B[:, 3 * i:3 * i + 3] @ d[i] for i in range(v.n_units)])


def thrust_newton(v: Vehicle, n, v_axial=0.0, inflow: bool | None = None) -> float:
    """T(n, V_a) of one jet in newtons (seed 000 eq. 15), convenience for tests and tools."""
    p = pack_params(v)
    if inflow is not None:
        p[ON_INFLOW] = 1.0 if inflow else 0.0
    return float(jet_thrust(float(n), float(v_axial), p))


def faulty_command(v: Vehicle, command, thrust_fraction=None, curve_gain=None) -> np.ndarray:
    """Commands (rows of 3 k: speed or thrust per unit, then joints) as a faulty vehicle acts on
    them: the thruster faults the diagnosis tests and the benchmark conceals, in one place.

    `thrust_fraction` (per unit, 1 = healthy): a jet's propeller reaches sqrt(f) of its commanded
    speed, so its thrust is f of nominal (T ~ n^2, seed 000 eq. 15); a fixed thruster's command
    is its thrust (spec 3.1), so it is scaled by f itself, and f < 0 is a thruster that pushes
    the other way (a reversed motor or propeller). `curve_gain` = (forward, reverse): every fixed
    thruster's static curve scaled, its forward branch by the first and its reverse branch by the
    second (a thrust table measured at another voltage or for another propeller)."""
    c = np.array(command, float, ndmin=2)
    k, nj = v.n_units, v.n_jets
    if thrust_fraction is not None:
        f = np.asarray(thrust_fraction, float)
        c[:, :nj] *= np.sqrt(np.maximum(f[:nj], 0.0))
        c[:, nj:k] *= f[nj:k]
    if curve_gain is not None and k > nj:
        gf, gr = curve_gain
        t = c[:, nj:k]
        c[:, nj:k] = np.where(t > 0, t * gf, t * gr)
    return c
