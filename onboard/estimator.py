"""Model-aided state estimation: a filterpy EKF over attitude, rates, gyro bias, body velocity, depth.

There is no DVL, so body velocity is observable only through the vehicle model: the process
model is `onboard.model` itself (spec/vehicle-model.md sections 2-4), driven by the commanded
jets, and the accelerometer is fused as the specific force that model predicts
(f = v' + w x v - R^T [0, 0, g], spec 5): the accelerometer then tells about attitude (through
gravity) AND about velocity (through the damping and thrust-inflow terms of v').

Filter state (16, additive, `X_*` offsets below):
    [roll, pitch, yaw (rad, ZYX), p, q, r (rad/s), b_gx, b_gy, b_gz (rad/s), u, v, w (m/s),
     depth (m), d_x, d_y, d_z (m/s^2)]
d is the unmodelled body acceleration, a first-order Gauss-Markov process (v' = f(x, u) + d):
the accelerometer measures it directly (f_spec = v' + w x v - R^T g), so the velocity integrates
what the model misses instead of random-walking; with a perfect model d stays near zero.
Euler angles rather than a quaternion keep the filter additive, as filterpy's EKF assumes; the
one wrap (yaw) is handled by taking the measured yaw on the branch nearest its prediction
(innovation wrapped to [-pi, pi)) and by re-wrapping after each step, and the
ZYX singularity at pitch +-90 deg is out of reach of this bottom-heavy vehicle (cb 2 cm above
cg). The quaternion is reported next to the Euler angles.

The actuator states (propeller speeds, joint angles) and the seed-004 transient filters are not
estimated: they are propagated deterministically from the commands, with the same model, in a
full-size "nominal" state whose rigid-body part is overwritten by the filter mean before each
use. Depth rate is the kinematic z' = R[2, :] v of the estimate.

Why an EKF and not a UKF: a UKF on these 16 states has 33 sigma points, each one RK4 of the full
model per predict, plus filterpy's per-point numpy bookkeeping; measured here (filterpy
UnscentedKalmanFilter, same model, same machine) it costs ~2.5 ms per predict and ~0.9 ms per
update, beyond the whole 1 ms onboard step. The EKF linearises by forward differences inside one
numba-compiled call (10 model evaluations; the bias and disturbance columns are analytic, and
so is the yaw column in still water, where it is zero) and costs ~60-90 us per predict.
The mean is propagated with the full nonlinear model by RK4 (the transient filters have lightly
damped 57 rad/s poles that explicit Euler would excite); only the covariance uses
F = I + A dt + (A dt)^2 / 2.

Backends: "filterpy" (default) runs predict and update through filterpy's ExtendedKalmanFilter;
"compiled" runs the same gate and the same Joseph-form update in numba, and a test checks the
two give the same state and covariance on the same samples.

One update per instant: the samples of one instant (IMU, depth, ATTITUDE stamped alike, the
`update_*` calls between two `predict`s) fill fixed measurement slots and are fused in ONE
Kalman update when the filter moves on or is read. Each sample is still gated on its own
marginal S; with R diagonal the joint update equals the sequential one. Per 100 Hz tick that is
one filterpy update instead of up to three: filterpy's EKF.update cost ~0.1-0.25 ms per call in
the loop (half of it scipy.linalg.inv of S, the rest its generic numpy bookkeeping; with the
compiled `small_inverse` and without the deepcopy, about 21 us now), the numbers it works on
cost microseconds. Gating and row selection are one compiled call (`_gate_slots`)
whose output (H, z, h(x), R of the accepted rows) goes to `ExtendedKalmanFilter.update` as it is.

Robustness: NaN/inf inputs are rejected before touching the filter and counted; every update is
gated by its Mahalanobis distance d^2 = y^T S^-1 y against a chi-square bound and counted when
rejected. Divergence (non-finite state, a covariance past its bound, a run of consecutive gated
rejections, or a windowed normalised innovation far above its expectation) sets a latched
`diverged` flag with its reason; `reset()` is the explicit recovery.

Depth jumps (issue #7): a depth sensor that jumped and stays is gated sample after sample; once
the gated run has lasted `depth_reset_after_s` (1 s), depth is re-anchored on the sensor (state :=
reading, its covariance row and column zeroed, variance := R_depth) and counted in
`health.depth_resets`, as ArduPilot's NavEKF2/3 reset the height to the baro when its innovations
have failed for longer than a retry time. A shorter spike stays rejected. Depth is therefore not
in the consecutive-rejection divergence test (its remedy is the reset).
"""

from __future__ import annotations

import math
from copy import deepcopy
from dataclasses import dataclass, field

import numpy as np
from filterpy.kalman import ExtendedKalmanFilter
from numba import njit
from scipy.stats import chi2

from . import model
from .jit import MODEL_SOURCE, key_caches_on
from .model import P_CURRENT, P_G, P_SURF, derivative, euler_to_quat, quat_to_euler, rk4_step, specific_force
from .sensors import AttitudeSample, ImuSample
from .vehicle import Vehicle

# Filter state offsets
X_EULER, X_RATES, X_BIAS, X_VEL, X_DEPTH, X_DIST = 0, 3, 6, 9, 12, 13
N_X = 16
STREAMS = ("gyro", "accel", "depth", "attitude")
_GYRO, _ACCEL, _DEPTH, _ATT = range(4)


# ------------------------------------------------------------------------------------------------
# Domain types

@dataclass(frozen=True)
class EstimatorHealth:
    """What the estimator did with its inputs, per stream in `STREAMS` order (for telemetry)."""

    accepted: tuple = (0, 0, 0, 0)
    rejected_nonfinite: tuple = (0, 0, 0, 0)  # NaN/inf inputs dropped before the filter
    rejected_gated: tuple = (0, 0, 0, 0)  # innovation outside the chi-square gate
    nis_average: tuple = (0.0, 0.0, 0.0, 0.0)  # windowed NIS / dim (expected ~1)
    diverged: bool = False
    diverged_reason: str = ""
    depth_resets: int = 0  # depth re-anchored on the sensor after a sustained gated run (a jump)

    @property
    def rejected_total(self) -> int:
        return int(sum(self.rejected_nonfinite) + sum(self.rejected_gated))

    def as_dict(self) -> dict:
        """Flat name -> number, names <= 10 chars (NAMED_VALUE_FLOAT), e.g. `rejg_accel`."""
        out = {}
        for i, s in enumerate(STREAMS):
            out[f"rejn_{s[:5]}"] = float(self.rejected_nonfinite[i])
            out[f"rejg_{s[:5]}"] = float(self.rejected_gated[i])
        out["est_div"] = 1.0 if self.diverged else 0.0
        out["depth_rst"] = float(self.depth_resets)
        return out


@dataclass(frozen=True)
class EstimatedState:
    """The estimator's output at `time_s`; body FRD, NED, ZYX Euler; covariance diagonal of X."""

    time_s: float
    quat_wxyz: tuple
    euler_rad: tuple  # roll, pitch, yaw (yaw in [-pi, pi))
    rates_rad_s: tuple  # p, q, r (gyro bias removed)
    gyro_bias_rad_s: tuple
    velocity_body_m_s: tuple  # u, v, w
    depth_m: float  # below the free surface (NED z - surface_depth)
    depth_rate_m_s: float  # NED z' = R[2, :] v
    accel_disturbance_m_s2: tuple  # d: body acceleration the model does not explain
    covariance_diag: tuple  # 16 variances in the X_* layout
    health: EstimatorHealth = field(default_factory=EstimatorHealth)

    @property
    def nu(self) -> np.ndarray:
        """[u, v, w, p, q, r] as an array."""
        return np.array(self.velocity_body_m_s + self.rates_rad_s)


@dataclass(frozen=True)
class EstimatorTuning:
    """Noise densities and thresholds; the defaults suit the reference vehicle.

    Process noise is white in continuous time; Q = diag(q^2) dt (Van Loan, first order).
    """

    q_attitude_rad_sqrt_s: float = 2e-3  # kinematics are exact; room for linearisation error
    q_rates_rad_s2_sqrt_hz: float = 0.3  # unmodelled moment / inertia
    q_bias_rad_s_sqrt_s: float = 2e-4  # gyro bias random walk
    q_velocity_m_s2_sqrt_hz: float = 0.005  # residual, d carries the unmodelled force
    disturbance_sigma_m_s2: float = 0.2  # steady-state std of d (Gauss-Markov)
    disturbance_time_s: float = 2.0  # correlation time of d
    q_depth_m_sqrt_s: float = 2e-3
    accel_model_sigma_m_s2: float = 0.08  # model error in predicted specific force, added to R
    init_attitude_sigma_rad: float = 0.4
    init_yaw_sigma_rad: float = 3.2  # heading unknown until an ATTITUDE arrives
    init_rates_sigma_rad_s: float = 0.1
    init_bias_sigma_rad_s: float = 0.05
    init_velocity_sigma_m_s: float = 0.2
    init_depth_sigma_m: float = 1.0
    init_disturbance_sigma_m_s2: float = 0.2
    gate_probability: float = 0.9999  # chi-square gate P(accept | consistent filter)
    max_consecutive_rejections: int = 50  # gated rejections in a row of one stream -> diverged (not depth)
    depth_reset_after_s: float = 1.0  # depth gated this long without a pass -> re-anchor on the sensor
    nis_window: int = 100  # samples in the NIS moving average
    nis_limit: float = 4.0  # windowed NIS / dim of accepted samples above this -> diverged (expected 1)
    max_sigma_attitude_rad: float = 0.8  # roll/pitch std above this -> diverged
    max_sigma_velocity_m_s: float = 2.0
    max_sigma_depth_m: float = 3.0


# ------------------------------------------------------------------------------------------------
# Compiled core: the model seen through the 16 filter states

@njit(cache=True)
def _embed(xr, full, surface):
    """Full model state with the rigid-body part taken from the filter state xr (in place)."""
    full[0] = 0.0
    full[1] = 0.0
    full[2] = surface + xr[12]
    full[3:7] = model.euler_to_quat(xr[0], xr[1], xr[2])
    for i in range(3):
        full[7 + i] = xr[9 + i]  # u, v, w
        full[10 + i] = xr[3 + i]  # p, q, r


@njit(cache=True)
def _reduced_rates(xr, full, u, p, xdot, out, fspec, tau_d):
    """x_r' of the filter state and the specific force at xr; `full` is overwritten by the embedding.

    Euler rates: [phi', theta', psi'] = T(phi, theta) w (Fossen 2011 eq. 2.29);
    w' and v' from the vehicle model, v' + d; bias' = 0; depth' = z' = R[2, :] v; d' = -d / tau_d.
    """
    _embed(xr, full, p[P_SURF])
    derivative(full, u, p, xdot)
    phi, theta = xr[0], xr[1]
    sphi, cphi = math.sin(phi), math.cos(phi)
    cth = math.cos(theta)
    cth = cth if abs(cth) > 1e-6 else 1e-6
    tth = math.sin(theta) / cth
    pr, qr, rr = xr[3], xr[4], xr[5]
    out[0] = pr + sphi * tth * qr + cphi * tth * rr  # phi' = p + s(phi) t(theta) q + c(phi) t(theta) r
    out[1] = cphi * qr - sphi * rr  # theta' = c(phi) q - s(phi) r
    out[2] = (sphi * qr + cphi * rr) / cth  # psi' = (s(phi) q + c(phi) r) / c(theta)
    for i in range(3):
        out[3 + i] = xdot[10 + i]  # w' (model)
        out[6 + i] = 0.0  # b_g' = 0 (random walk in Q)
        out[9 + i] = xdot[7 + i] + xr[13 + i]  # v' = f_v(x, u) + d
        out[13 + i] = -xr[13 + i] / tau_d  # d' = -d / tau_d (+ white noise)
    out[12] = xdot[2]  # z' = R[2, :] v
    f = specific_force(full, xdot, p)  # f = v' + w x v - R^T [0, 0, g] (spec 5)
    for i in range(3):
        fspec[i] = f[i] + xr[13 + i]


@njit(cache=True)
def _linearise(xr, full, u, p, tau_d):
    """Forward-difference A = df/dx_r (16x16) and H_acc = d f_spec / d x_r (3x16) at xr.

    Returns (A, H_acc, f_spec(xr)); `full` keeps the actuator/transient part, its rigid-body
    part is restored from xr on return.
    """
    n = xr.shape[0]
    xdot = np.zeros(full.shape[0])
    f0 = np.empty(n)
    s0 = np.empty(3)
    _reduced_rates(xr, full, u, p, xdot, f0, s0, tau_d)
    A = np.empty((n, n))
    H = np.empty((3, n))
    f1 = np.empty(n)
    s1 = np.empty(3)
    xp = xr.copy()
    # with no water current nothing in the body-frame model, the Euler rates or z' depends on yaw
    # (gravity and buoyancy act through R^T e3, a function of roll and pitch): that column is 0
    still = p[P_CURRENT] == 0.0 and p[P_CURRENT + 1] == 0.0 and p[P_CURRENT + 2] == 0.0
    for j in range(n):
        if 6 <= j < 9 or j >= 13 or (j == 2 and still):
            # analytic columns: the gyro bias enters neither model nor accelerometer; d enters
            # v' and f_spec with unit gain and decays at 1 / tau_d; yaw in still water, above
            for i in range(n):
                A[i, j] = 0.0
            for i in range(3):
                H[i, j] = 0.0
            if j >= 13:
                A[j - 4, j] = 1.0
                A[j, j] = -1.0 / tau_d
                H[j - 13, j] = 1.0
            continue
        h = 1e-6 * max(1.0, abs(xr[j]))
        xp[j] = xr[j] + h
        _reduced_rates(xp, full, u, p, xdot, f1, s1, tau_d)
        for i in range(n):
            A[i, j] = (f1[i] - f0[i]) / h
        for i in range(3):
            H[i, j] = (s1[i] - s0[i]) / h
        xp[j] = xr[j]
    _embed(xr, full, p[P_SURF])
    return A, H, s0


@njit(cache=True)
def _propagate(xr, full, u, p, dt, tau_d):
    """Mean by RK4 of the full model (yaw in [-pi, pi)); F = I + A dt + (A dt)^2 / 2 at the prior mean.

    Also returns H_acc, the accelerometer Jacobian at the prior mean, for the next IMU update.
    """
    A, H_acc, _ = _linearise(xr, full, u, p, tau_d)
    nxt = rk4_step(full, u, p, dt)
    xn = xr.copy()
    roll, pitch, yaw = quat_to_euler(nxt[3:7])
    xn[0], xn[1], xn[2] = roll, pitch, (yaw + math.pi) % (2.0 * math.pi) - math.pi
    for i in range(3):
        xn[3 + i] = nxt[10 + i]
        xn[9 + i] = nxt[7 + i]
    xn[12] = nxt[2] - p[P_SURF]
    # d enters v' additively: v += d dt (first order), d decays exactly over dt
    decay = math.exp(-dt / tau_d)
    for i in range(3):
        xn[9 + i] += xr[13 + i] * dt
        xn[13 + i] = xr[13 + i] * decay
        nxt[7 + i] = xn[9 + i]
    Ad = A * dt
    F = np.eye(xr.shape[0]) + Ad + 0.5 * (Ad @ Ad)
    return xn, nxt, F, H_acc


def _vector3(v):
    """A finite 3-vector as a tuple of floats, or None (NaN, inf, wrong length or not numbers)."""
    try:
        if len(v) != 3:
            return None
        x0, x1, x2 = float(v[0]), float(v[1]), float(v[2])
    except (TypeError, ValueError):
        return None
    if not (math.isfinite(x0) and math.isfinite(x1) and math.isfinite(x2)):
        return None
    return (x0, x1, x2)


def _wrap(a: float) -> float:
    """Angle in [-pi, pi)."""
    return (a + math.pi) % (2.0 * math.pi) - math.pi


# Measurement slots of one instant, STREAMS order: gyro rows 0:3, accelerometer 3:6, depth 6:7,
# attitude 7:10 (roll, pitch, yaw; the yaw row's innovation wraps)
_SLOT = np.array([0, 3, 6, 7, 10])
_YAW_ROW = 9
N_ROWS = 10
_LINEAR_SLOTS = np.array([False, False, True, True])  # depth and attitude: h(x) linear in x
_NO_SLOTS = np.zeros(4, dtype=bool)


def _given(_x, value):
    """filterpy's HJacobian / Hx callback for a value computed beforehand (passed in `args`)."""
    return value


@njit(cache=True)
def _mahalanobis2(P, H, R, y):
    """d^2 = y^T S^-1 y with S = H P H^T + R (innovation covariance); inf if S is singular."""
    S = H @ P @ H.T + R
    if not np.all(np.isfinite(S)):
        return np.inf
    L = np.linalg.cholesky(S)  # S = L L^T; d^2 = |L^-1 y|^2
    m = y.shape[0]
    w = np.empty(m)
    for i in range(m):
        s = y[i]
        for j in range(i):
            s -= L[i, j] * w[j]
        w[i] = s / L[i, i]
    return float(np.sum(w * w))


@njit(cache=True)
def _specific_force_at(xr, full, u, p):
    """h_acc(x) = f_spec = v' + w x v - R^T [0, 0, g] (spec 5), v' = f_v(x, u) + d, at the mean."""
    xdot = np.zeros(full.shape[0])
    _embed(xr, full, p[P_SURF])
    derivative(full, u, p, xdot)
    f = specific_force(full, xdot, p)
    for i in range(3):
        f[i] += xr[13 + i]
    return f


@njit(cache=True)
def _accel_rows(xr, P, full, u, p, a, H_acc, r_accel, z, hx, H, r):
    """Fill the accelerometer slot: z = a, h(x) = f_spec(x, u), H = H_acc (linearised at the
    prior), r = sigma^2 + (g (P_roll + P_pitch) / 2)^2: the second-order term of gravity's
    projection, g (1 - cos d) ~ g d^2 / 2 for an attitude error d, large while the attitude is
    uncertain, so a big initial error is not mistaken for an outlier by the gate (second-order
    EKF, Gelb 1974 sec. 6.1)."""
    f = _specific_force_at(xr, full, u, p)
    lin = 0.5 * p[P_G] * (P[0, 0] + P[1, 1])
    for i in range(3):
        z[3 + i] = a[i]
        hx[3 + i] = f[i]
        r[3 + i] = r_accel + lin * lin
        for j in range(xr.shape[0]):
            H[3 + i, j] = H_acc[i, j]


@njit(cache=True)
def _accel_after(xr, P, full, u, p, H, r, z, hx, before, gates, r_accel):
    """Rewrite the accelerometer's h(x) for samples that arrived BEFORE it in the instant (slots
    `before`): fused one after another, the accelerometer's prediction would be f_spec at x1, the
    posterior of those samples (x1 = x + K1 y1, K1 = P H1^T S1^-1, each sample gated as in
    `_gate_slots`), linearised there with H_acc. In the joint update at the prior x the same
    result needs h_eff = f_spec(x1) - H_acc (x1 - x): then z - h_eff - H_acc (x_post - x) is that
    sequential innovation (the update is linear in everything else). The second-order variance
    term of `_accel_rows` is taken at that posterior too, P1 = P - K1 H1 P (an ATTITUDE sample
    shrinks the roll/pitch variance it is made of). `full` is left embedding xr."""
    y = z - hx
    y[_YAW_ROW] = (y[_YAW_ROW] + math.pi) % (2.0 * math.pi) - math.pi
    rows = np.empty(z.shape[0], dtype=np.int64)
    m = 0
    for b in range(before.shape[0]):
        if not before[b]:
            continue
        lo, hi = _SLOT[b], _SLOT[b + 1]
        d2 = _mahalanobis2(P, H[lo:hi], np.diag(r[lo:hi]), y[lo:hi])
        if math.isfinite(d2) and d2 <= gates[b]:
            for i in range(lo, hi):
                rows[m] = i
                m += 1
    if m == 0:
        return
    H1 = np.empty((m, xr.shape[0]))
    y1 = np.empty(m)
    R1 = np.zeros((m, m))
    for i in range(m):
        H1[i] = H[rows[i]]
        y1[i] = y[rows[i]]
        R1[i, i] = r[rows[i]]
    PHT = P @ H1.T
    S1 = H1 @ PHT + R1
    x1 = xr + PHT @ np.linalg.solve(S1, y1)
    v0 = P[0, 0] - PHT[0] @ np.linalg.solve(S1, PHT[0])  # P1[0, 0], P1[1, 1]
    v1 = P[1, 1] - PHT[1] @ np.linalg.solve(S1, PHT[1])
    lin = 0.5 * p[P_G] * (v0 + v1)
    f = _specific_force_at(x1, full, u, p)
    for i in range(3):
        s = f[i] + 0.0
        for j in range(xr.shape[0]):
            s -= H[3 + i, j] * (x1[j] - xr[j])
        hx[3 + i] = s
        r[3 + i] = r_accel + lin * lin
    _embed(xr, full, p[P_SURF])


@njit(cache=True)
def _gate_slots(P, H, r, z, hx, present, gates):
    """Gate each present slot b on its own marginal innovation covariance S_b = H_b P H_b^T + R_b:
    d2_b = y_b^T S_b^-1 y_b <= gates[b] (chi-square), y = z - h(x) with the yaw row wrapped.

    R is diagonal (independent sensor axes), so the accepted slots stay separable and are fused
    in one update. Returns the accepted rows ready for it, (H, z, h(x), R), the measured yaw
    taken on the branch nearest its prediction (z = h + wrap(z - h)), and d2 and acceptance per slot.
    """
    nb = present.shape[0]
    y = z - hx
    y[_YAW_ROW] = (y[_YAW_ROW] + math.pi) % (2.0 * math.pi) - math.pi
    d2 = np.full(nb, np.nan)
    ok = np.zeros(nb, dtype=np.bool_)
    rows = np.empty(z.shape[0], dtype=np.int64)
    m = 0
    for b in range(nb):
        if not present[b]:
            continue
        lo, hi = _SLOT[b], _SLOT[b + 1]
        d2[b] = _mahalanobis2(P, H[lo:hi], np.diag(r[lo:hi]), y[lo:hi])
        if math.isfinite(d2[b]) and d2[b] <= gates[b]:
            ok[b] = True
            for i in range(lo, hi):
                rows[m] = i
                m += 1
    Hs = np.empty((m, H.shape[1]))
    zs = np.empty(m)
    hxs = np.empty(m)
    Rs = np.zeros((m, m))
    for i in range(m):
        k = rows[i]
        Hs[i] = H[k]
        hxs[i] = hx[k]
        zs[i] = hx[k] + y[k] if k == _YAW_ROW else z[k]
        Rs[i, i] = r[k]
    return Hs, zs, hxs, Rs, d2, ok


@njit(cache=True)
def _covariance_predict(F, P, Q):
    """P = F P F^T + Q (filterpy EKF.predict, compiled)."""
    return F @ P @ F.T + Q


@njit(cache=True)
def _gauss_jordan_inverse(S):
    """(S^-1, ok) of a small square S by Gauss-Jordan elimination with partial pivoting (the
    exact inverse up to rounding, as LAPACK's getrf + getri); ok is False, and the first result
    meaningless, if a pivot is zero or not finite (S singular or not finite)."""
    n = S.shape[0]
    A = np.empty((n, n))
    X = np.eye(n)
    for i in range(n):
        for j in range(n):
            A[i, j] = S[i, j]
            if not math.isfinite(S[i, j]):
                return X, False
    for c in range(n):
        p, best = c, abs(A[c, c])
        for r in range(c + 1, n):
            if abs(A[r, c]) > best:
                p, best = r, abs(A[r, c])
        if not (best > 0.0 and math.isfinite(best)):
            return X, False
        if p != c:
            for j in range(n):
                A[p, j], A[c, j] = A[c, j], A[p, j]
                X[p, j], X[c, j] = X[c, j], X[p, j]
        d = A[c, c]
        for j in range(n):
            A[c, j] /= d
            X[c, j] /= d
        for r in range(n):
            f = A[r, c]
            if r != c and f != 0.0:
                for j in range(n):
                    A[r, j] -= f * A[c, j]
                    X[r, j] -= f * X[c, j]
    return X, True


@njit(cache=True)
def _joseph_update(x, P, H, R, y):
    """The EKF update of filterpy's EKF.update, compiled:
    S = H P H^T + R; K = P H^T S^-1; x = x + K y; P = (I - K H) P (I - K H)^T + K R K^T.
    S^-1 by `_gauss_jordan_inverse`, as the filterpy backend's `small_inverse`."""
    PHT = P @ H.T
    S = H @ PHT + R
    S_inv, ok = _gauss_jordan_inverse(S)
    if not ok:
        raise ValueError("singular or non-finite innovation covariance")
    K = PHT @ S_inv
    xn = x + K @ y
    I_KH = np.eye(x.shape[0]) - K @ H
    Pn = I_KH @ P @ I_KH.T + K @ R @ K.T
    return xn, Pn


@njit(cache=True)
def _gated_fuse(x, P, H, r, z, hx, present, gates):
    """The compiled backend's whole update: `_gate_slots`, then `_joseph_update` with the
    accepted rows (the filterpy backend hands the same rows to ExtendedKalmanFilter.update).
    Returns (x, P, d2 per slot, accepted per slot)."""
    Hs, zs, hxs, Rs, d2, ok = _gate_slots(P, H, r, z, hx, present, gates)
    if zs.shape[0] == 0:
        return x, P, d2, ok
    xn, Pn = _joseph_update(x, P, Hs, Rs, zs - hxs)
    return xn, Pn, d2, ok


@njit(cache=True)
def _settle(xr, full, surface):
    """After an update: yaw back to [-pi, pi), the full model state's rigid-body part from xr."""
    xr[2] = (xr[2] + math.pi) % (2.0 * math.pi) - math.pi
    _embed(xr, full, surface)


@njit(cache=True)
def _covariance_check(x, P, limits):
    """0 if healthy; 1 non-finite x or P; 2, 3, 4: roll/pitch, velocity, depth variance past limits."""
    for i in range(x.shape[0]):
        if not math.isfinite(x[i]):
            return 1
        for j in range(x.shape[0]):
            if not math.isfinite(P[i, j]):
                return 1
    if max(P[0, 0], P[1, 1]) > limits[0]:
        return 2
    if max(P[9, 9], P[10, 10], P[11, 11]) > limits[1]:
        return 3
    if P[12, 12] > limits[2]:
        return 4
    return 0


def small_inverse(S) -> np.ndarray:
    """S^-1 of the innovation covariance (at most 10 x 10 here), compiled: scipy.linalg.inv, which
    filterpy's EKF.update calls, spends ~20 us per call on its checks and dispatch (half of that
    update's cost in the onboard loop, measured) for an inversion worth a microsecond. Raises
    numpy.linalg.LinAlgError as numpy.linalg.inv does for a singular (or non-finite) S."""
    S = np.asarray(S, dtype=np.float64)
    if S.ndim != 2 or S.shape[0] != S.shape[1]:
        raise np.linalg.LinAlgError(f"small_inverse: expected a square matrix, got shape {S.shape}")
    X, ok = _gauss_jordan_inverse(S)
    if not ok:
        raise np.linalg.LinAlgError("small_inverse: singular or non-finite matrix")
    return X


class _ModelAidedEKF(ExtendedKalmanFilter):
    """filterpy's EKF with the nonlinear mean propagation of the vehicle model.

    `predict_x` is filterpy's documented override point for a nonlinear f(x, u); here u is the
    (mean, F) pair computed by `_propagate`, so predict() does x = f(x, u), P = F P F^T + Q.
    `update` is filterpy's EKF.update with S^-1 taken by `self.inv`, the hook filterpy's own
    KalmanFilter has (its EKF calls scipy.linalg.inv directly): here the compiled `small_inverse`.
    """

    inv = staticmethod(small_inverse)

    def predict_x(self, u=0):
        self.x, self.F = u

    def update(self, z, HJacobian, Hx, R=None, args=(), hx_args=(), residual=np.subtract):
        """filterpy.kalman.ExtendedKalmanFilter.update (filterpy 2.0.0), statement for statement,
        but S^-1 = self.inv(S): K = P H^T S^-1, x = x + K (z - h(x)),
        P = (I - K H) P (I - K H)^T + K R K^T (Joseph form)."""
        if z is None:
            return super().update(z, HJacobian, Hx, R, args, hx_args, residual)
        if not isinstance(args, tuple):
            args = (args,)
        if not isinstance(hx_args, tuple):
            hx_args = (hx_args,)
        if R is None:
            R = self.R
        elif not isinstance(R, np.ndarray) and np.isscalar(R):  # (an array is never a scalar: skip the test)
            R = np.eye(self.dim_z) * R
        if not isinstance(z, np.ndarray) and np.isscalar(z) and self.dim_z == 1:
            z = np.asarray([z], float)
        H = HJacobian(self.x, *args)
        PHT = np.dot(self.P, H.T)
        self.S = np.dot(H, PHT) + R
        self.SI = self.inv(self.S)
        self.K = PHT.dot(self.SI)
        hx = Hx(self.x, *hx_args)
        self.y = residual(z, hx)
        self.x = self.x + np.dot(self.K, self.y)
        I_KH = self._I - np.dot(self.K, H)
        self.P = np.dot(I_KH, self.P).dot(I_KH.T) + np.dot(self.K, R).dot(self.K.T)
        self._log_likelihood = None
        self._likelihood = None
        self._mahalanobis = None
        self.z = z.copy() if type(z) is np.ndarray else deepcopy(z)  # (the same copy, without deepcopy's dispatch)
        self.x_post = self.x.copy()
        self.P_post = self.P.copy()


# ------------------------------------------------------------------------------------------------

class Estimator:
    """Model-aided EKF, ready to use from a vehicle: `predict`, `update_*`, read `estimate`.

    Samples of one instant (the `update_*` calls between two `predict`s) are gated each on its
    own and fused together in ONE Kalman update, when the filter next moves on or is read
    (`predict`, `estimate`, `health`, `diverged`): R is diagonal, so with the gate passed this is
    the same posterior as fusing them one after another (sequential processing of independent
    measurements, Bar-Shalom et al. 2001 sec. 7.2), for one filterpy update per tick instead of
    one per sample.
    """

    def __init__(
        self,
        vehicle: Vehicle,
        depth_m: float = 0.0,
        euler_rad=(0.0, 0.0, 0.0),
        gyro_bias_rad_s=(0.0, 0.0, 0.0),
        tuning: EstimatorTuning | None = None,
        backend: str = "filterpy",
    ):
        """backend: "filterpy" runs predict and update through filterpy's ExtendedKalmanFilter;
        "compiled" runs the same equations (same gate, same Joseph form) in numba, cross-checked
        against filterpy in the tests."""
        if backend not in ("filterpy", "compiled"):
            raise ValueError(f"Estimator: backend must be 'filterpy' or 'compiled', got {backend!r}")
        self.backend = backend
        self._compiled = backend == "compiled"
        self.vehicle = vehicle
        self.tuning = tuning or EstimatorTuning()
        self.params = model.pack_params(vehicle)
        self.layout = model.StateLayout(vehicle.n_units)
        s, e = vehicle.sensors, vehicle.environment
        t = self.tuning
        # Measurement noise variances (spec 5), floored so S stays invertible when a file says 0;
        # every sensor axis is independent, so R is diagonal and kept as its diagonal
        self._r_gyro = np.full(3, max(s.gyro_noise, 1e-4) ** 2)
        self._r_accel = np.full(3, max(s.accel_noise, 1e-3) ** 2 + t.accel_model_sigma_m_s2 ** 2)
        self._r_depth = np.full(1, max(s.pressure_noise / (e.rho * e.g), 1e-3) ** 2)
        self._r_att = np.full(3, max(s.attitude_noise, 1e-4) ** 2)
        # Continuous process noise densities, X_* order
        self._q = np.array(
            [t.q_attitude_rad_sqrt_s] * 3 + [t.q_rates_rad_s2_sqrt_hz] * 3
            + [t.q_bias_rad_s_sqrt_s] * 3 + [t.q_velocity_m_s2_sqrt_hz] * 3 + [t.q_depth_m_sqrt_s]
            # Gauss-Markov: q_d^2 = 2 sigma_d^2 / tau_d keeps the steady-state std at sigma_d
            + [t.disturbance_sigma_m_s2 * math.sqrt(2.0 / t.disturbance_time_s)] * 3
        ) ** 2
        self._tau_d = float(t.disturbance_time_s)
        self._Qc = np.diag(self._q)
        self._sigma_limits = np.array(
            [t.max_sigma_attitude_rad, t.max_sigma_velocity_m_s, t.max_sigma_depth_m]) ** 2
        self._gate = {m: float(chi2.ppf(t.gate_probability, m)) for m in (1, 3)}
        self._H_gyro = np.zeros((3, N_X))
        self._H_gyro[:, X_RATES:X_RATES + 3] = np.eye(3)  # h = w + b_g
        self._H_gyro[:, X_BIAS:X_BIAS + 3] = np.eye(3)
        self._H_depth = np.zeros((1, N_X))
        self._H_depth[0, X_DEPTH] = 1.0  # h = depth
        self._H_att = np.zeros((3, N_X))
        self._H_att[:, X_EULER:X_EULER + 3] = np.eye(3)  # h = [roll, pitch, yaw]
        # The instant's measurement slots (_SLOT), fused together by _fuse_pending: H of the
        # gyro, depth and attitude slots is constant, the accelerometer's is written per sample
        self._zb, self._hxb = np.zeros(N_ROWS), np.zeros(N_ROWS)
        self._rb = np.concatenate([self._r_gyro, self._r_accel, self._r_depth, self._r_att])
        self._Hb = np.vstack([self._H_gyro, np.zeros((3, N_X)), self._H_depth, self._H_att])
        self._slot_gates = np.array([self._gate[3], self._gate[3], self._gate[1], self._gate[3]])
        self._present = np.zeros(len(STREAMS), dtype=bool)
        self._init = (float(depth_m), tuple(map(float, euler_rad)), tuple(map(float, gyro_bias_rad_s)))
        self.reset()
        small_inverse(np.eye(1))  # loads the compiled inverse now, not in the first update

    # -- lifecycle ---------------------------------------------------------------------------
    def reset(self, depth_m: float | None = None, euler_rad=None, gyro_bias_rad_s=None) -> None:
        """Back to the initial estimate and covariance; clears counters and the diverged latch."""
        d0, e0, b0 = self._init
        d0 = d0 if depth_m is None else float(depth_m)
        e0 = e0 if euler_rad is None else tuple(map(float, euler_rad))
        b0 = b0 if gyro_bias_rad_s is None else tuple(map(float, gyro_bias_rad_s))
        t = self.tuning
        ekf = _ModelAidedEKF(dim_x=N_X, dim_z=3)
        x = np.zeros(N_X)
        x[X_EULER:X_EULER + 3] = e0
        x[X_BIAS:X_BIAS + 3] = b0
        x[X_DEPTH] = d0
        ekf.x = x
        ekf.P = np.diag(np.array(
            [t.init_attitude_sigma_rad] * 2 + [t.init_yaw_sigma_rad] + [t.init_rates_sigma_rad_s] * 3
            + [t.init_bias_sigma_rad_s] * 3 + [t.init_velocity_sigma_m_s] * 3 + [t.init_depth_sigma_m]
            + [t.init_disturbance_sigma_m_s2] * 3
        ) ** 2)
        self._ekf = ekf
        self._full = model.initial_state(self.vehicle, d0)
        _embed(x, self._full, self.params[P_SURF])
        self._command = np.zeros(3 * self.vehicle.n_units)
        self._H_acc = _linearise(x, self._full, self._command, self.params, self._tau_d)[1]
        self._Q_dt = math.nan  # dt of the cached Q = diag(q^2) dt
        self.time_s = 0.0
        self._accepted = [0, 0, 0, 0]
        self._rej_nonfinite = [0, 0, 0, 0]
        self._rej_gated = [0, 0, 0, 0]
        self._consecutive = [0, 0, 0, 0]
        self._nis = [0.0, 0.0, 0.0, 0.0]
        self._nis_n = [0, 0, 0, 0]
        self._diverged = ""
        self._depth_rejected_since = None  # time_s of the first gated depth sample of the current run
        self._depth_resets = 0
        self._present[:] = False  # slots holding a sample of this instant
        self._surface_reading = False  # a depth reading of 0 in this instant (see update_depth)
        self._acc_after = _NO_SLOTS  # slots filled before the accelerometer's (see _accel_after)
        self._pending = False
        self._version = 0  # bumped by every change: the estimate / health objects are built once per change
        self._health_cache = (-1, None)
        self._estimate_cache = (-1, math.nan, None)

    # -- prediction --------------------------------------------------------------------------
    def predict(self, dt: float, command) -> None:
        """Advance by dt (s) with the command u = [n_cmd x k, alpha_cmd x k, beta_cmd x k] held.

        x_k+1 = f(x_k, u_k) by RK4 of the vehicle model; P = F P F^T + Q, Q = diag(q^2) dt.
        """
        dt = float(dt)
        if not (math.isfinite(dt) and 0.0 < dt <= 1.0):
            raise ValueError(f"Estimator.predict: dt must be a finite time step in (0, 1] s, got {dt!r}")
        try:
            u = np.asarray(command, dtype=float)
        except (TypeError, ValueError):
            u = np.full(1, np.nan)
        if u.shape != self._command.shape or not math.isfinite(u.sum()):
            raise ValueError(
                f"Estimator.predict: command must be {self._command.shape[0]} finite values "
                f"[n_cmd, alpha_cmd, beta_cmd per unit], got {command!r}"
            )
        self._fuse_pending()  # the samples of the instant being left
        self._version += 1
        if self._diverged and not np.all(np.isfinite(self._ekf.x)):
            self.time_s += dt  # nothing sane to propagate; wait for reset()
            return
        self._command = u.copy()
        ekf = self._ekf
        xn, self._full, F, self._H_acc = _propagate(ekf.x, self._full, u, self.params, dt, self._tau_d)
        if dt != self._Q_dt:
            self._Q_dt, self._Q = dt, self._Qc * dt  # Q = diag(q^2) dt
        ekf.Q = self._Q
        if self._compiled:
            ekf.x, ekf.P = xn, _covariance_predict(F, ekf.P, ekf.Q)
        else:
            ekf.predict(u=(xn, F))  # x = f(x, u); P = F P F^T + Q
        # Heading without a heading sensor is a random walk: cap, do not call it divergence
        cap = math.pi ** 2
        if ekf.P[2, 2] > cap:
            s = math.sqrt(cap / ekf.P[2, 2])
            ekf.P[2, :] *= s
            ekf.P[:, 2] *= s
        self.time_s += dt
        self._check_divergence()

    # -- updates (buffered for the instant, fused by _fuse_pending) --------------------------
    def update_imu(self, sample: ImuSample) -> None:
        """An IMU sample: gyro z = w + b_g, accelerometer z = f_spec(x, u) (spec 5).

        Each half is checked for NaN/inf and gated on its own; the accelerometer Jacobian is the
        one linearised at the prior (predict).
        """
        self._version += 1
        g = _vector3(sample.gyro_frd_rad_s)
        a = _vector3(sample.accel_frd_m_s2)
        if g is None:
            self._rej_nonfinite[_GYRO] += 1
        else:
            self._claim(_GYRO)
            x, z, hx = self._ekf.x, self._zb, self._hxb
            for i in range(3):
                z[i] = g[i]
                hx[i] = x[X_RATES + i] + x[X_BIAS + i]  # h = w + b_g
        if a is None:
            self._rej_nonfinite[_ACCEL] += 1
        else:
            self._claim(_ACCEL)
            # depth / attitude samples fused before it in this instant (see _accel_after)
            self._acc_after = self._present & _LINEAR_SLOTS
            _accel_rows(self._ekf.x, self._ekf.P, self._full, self._command, self.params, a, self._H_acc,
                        self._r_accel[0], self._zb, self._hxb, self._Hb, self._rb)

    def update_depth(self, depth_m: float) -> None:
        """A depth (m, from `sensors.depth_from_pressure`); z = max(depth, 0) as the sensor reads."""
        self._version += 1
        try:
            z = float(depth_m)
        except (TypeError, ValueError):
            z = math.nan
        if not math.isfinite(z):
            self._rej_nonfinite[_DEPTH] += 1
            return
        if z <= 0.0 and self._pending:
            # the sensor reads max(depth, 0): a 0 says something only if the estimate is below the
            # surface, which the samples before it in this instant may change: decided after them
            if self._present[_DEPTH] or self._surface_reading:
                self._fuse_pending()
            else:
                self._surface_reading = True
                return
        if z <= 0.0 and self._ekf.x[X_DEPTH] <= 0.0:
            self._accepted[_DEPTH] += 1  # at or above the surface, and so is the estimate: nothing more
            self._depth_rejected_since = None
            return
        # h = depth, H = e_depth: a reading > 0 says the vehicle is that deep whatever the estimate;
        # a reading of 0 with the estimate below the surface pulls it up to 0
        self._claim(_DEPTH)
        row = _SLOT[_DEPTH]
        self._zb[row] = max(z, 0.0)
        self._hxb[row] = self._ekf.x[X_DEPTH]

    def update_attitude(self, sample: AttitudeSample) -> None:
        """An ATTITUDE (roll, pitch, yaw); h = [roll, pitch, yaw], yaw innovation wrapped to [-pi, pi)."""
        self._version += 1
        try:
            z = (float(sample.roll_rad), float(sample.pitch_rad), float(sample.yaw_rad))
        except (TypeError, ValueError):
            z = (math.nan,) * 3
        if not (math.isfinite(z[0]) and math.isfinite(z[1]) and math.isfinite(z[2])):
            self._rej_nonfinite[_ATT] += 1
            return
        self._claim(_ATT)
        x, lo = self._ekf.x, _SLOT[_ATT]
        for i in range(3):
            self._zb[lo + i] = z[i]
            self._hxb[lo + i] = x[X_EULER + i]

    def _claim(self, k: int) -> None:
        """Slot k for a new sample; a second sample of a stream in one instant fuses the first."""
        if self._present[k]:
            self._fuse_pending()
        self._present[k] = True
        self._pending = True

    def _fuse_pending(self) -> None:
        """Gate each pending sample by d^2 = y^T S^-1 y (S = H P H^T + R on its own rows), then ONE
        update with the accepted rows: filterpy's ExtendedKalmanFilter.update (or its compiled
        twin), K = P H^T S^-1; x += K y; P = (I - K H) P (I - K H)^T + K R K^T (Joseph)."""
        if not self._pending:
            return
        present = self._present.copy()
        self._present[:] = False
        self._pending = False
        self._version += 1
        if present.any():
            self._fuse(present)
        if self._surface_reading:  # a depth of 0 (at or above the surface), after the rest
            self._surface_reading = False
            d = float(self._ekf.x[X_DEPTH])
            if d <= 0.0:
                self._accepted[_DEPTH] += 1  # estimate at or above the surface too: nothing more
                self._depth_rejected_since = None
            else:  # estimate below the surface: z = 0 pulls it up to the surface
                self._zb[_SLOT[_DEPTH]], self._hxb[_SLOT[_DEPTH]] = 0.0, d
                present[:] = False
                present[_DEPTH] = True
                self._fuse(present)

    def _fuse(self, present) -> None:
        """The gated update of the slots `present` (see _fuse_pending)."""
        ekf = self._ekf
        if present[_ACCEL] and self._acc_after.any():
            _accel_after(ekf.x, ekf.P, self._full, self._command, self.params, self._Hb, self._rb,
                         self._zb, self._hxb, self._acc_after & present, self._slot_gates, self._r_accel[0])
        self._acc_after = _NO_SLOTS
        if self._compiled:
            ekf.x, ekf.P, d2, ok = _gated_fuse(ekf.x, ekf.P, self._Hb, self._rb, self._zb, self._hxb,
                                               present, self._slot_gates)
        else:
            H, z, hx, R, d2, ok = _gate_slots(ekf.P, self._Hb, self._rb, self._zb, self._hxb,
                                              present, self._slot_gates)
            if z.shape[0]:
                # K = P H^T S^-1; x += K y; P = (I - K H) P (I - K H)^T + K R K^T (Joseph)
                ekf.update(z, _given, _given, R=R, args=(H,), hx_args=(hx,))
        reanchor = None
        for k in range(len(STREAMS)):
            if not present[k]:
                continue
            if ok[k]:
                self._accepted[k] += 1
                self._consecutive[k] = 0  # (the NIS average sees accepted samples only)
                self._nis_push(k, d2[k] / (_SLOT[k + 1] - _SLOT[k]))
                if k == _DEPTH:
                    self._depth_rejected_since = None
                continue
            self._rej_gated[k] += 1
            self._consecutive[k] += 1
            if k == _DEPTH:
                if self._depth_rejected_since is None:
                    self._depth_rejected_since = self.time_s
                elif self.time_s - self._depth_rejected_since >= self.tuning.depth_reset_after_s - 1e-9:
                    reanchor = float(self._zb[_SLOT[_DEPTH]])
        if reanchor is not None:
            self._reset_depth(reanchor)
        if reanchor is not None or ok.any():
            _settle(ekf.x, self._full, self.params[P_SURF])
        self._check_divergence()

    def _reset_depth(self, depth_m: float) -> None:
        """Re-anchor depth on the sensor after `depth_reset_after_s` of gated depth samples (a
        sensor that jumped and stays): depth := z, its covariance row and column zeroed, variance
        := R_depth, as ArduPilot's NavEKF2/3 reset the height to the baro when the height
        innovations have failed for longer than their retry time (FuseVelPosNED -> ResetHeight)."""
        ekf = self._ekf
        x, P = ekf.x.copy(), ekf.P.copy()
        x[X_DEPTH] = depth_m
        P[X_DEPTH, :] = 0.0
        P[:, X_DEPTH] = 0.0
        P[X_DEPTH, X_DEPTH] = self._r_depth[0]
        ekf.x, ekf.P = x, P
        self._depth_resets += 1
        self._depth_rejected_since = None
        self._consecutive[_DEPTH] = 0

    def _nis_push(self, k: int, value: float) -> None:
        """Windowed mean of NIS/dim: exponential average with the window's time constant."""
        n = min(self._nis_n[k] + 1, self.tuning.nis_window)
        self._nis_n[k] = n
        self._nis[k] += (value - self._nis[k]) / n

    def _check_divergence(self) -> None:
        if self._diverged:
            return
        t = self.tuning
        x, P = self._ekf.x, self._ekf.P
        code = _covariance_check(x, P, self._sigma_limits)
        if code:
            d = np.diag(P)
            self._diverged = {
                1: "non-finite state or covariance",
                2: f"roll/pitch sigma {math.sqrt(max(d[0], d[1])):.2f} rad > {t.max_sigma_attitude_rad}",
                3: f"velocity sigma {math.sqrt(max(d[9:12])):.2f} m/s > {t.max_sigma_velocity_m_s}",
                4: f"depth sigma {math.sqrt(d[12]):.2f} m > {t.max_sigma_depth_m}",
            }[code]
        else:
            for k, s in enumerate(STREAMS):
                # depth is not in the run test: a sustained depth disagreement re-anchors (_reset_depth)
                if k != _DEPTH and self._consecutive[k] >= t.max_consecutive_rejections:
                    self._diverged = f"{s}: {self._consecutive[k]} consecutive gated rejections"
                    break
                if self._nis_n[k] >= t.nis_window // 2 and self._nis[k] > t.nis_limit:
                    self._diverged = f"{s}: windowed NIS/dim {self._nis[k]:.1f} > {t.nis_limit}"
                    break

    # -- output ------------------------------------------------------------------------------
    @property
    def diverged(self) -> bool:
        self._fuse_pending()
        return bool(self._diverged)

    @property
    def health(self) -> EstimatorHealth:
        self._fuse_pending()
        version, h = self._health_cache
        if version != self._version:
            h = EstimatorHealth(
                accepted=tuple(self._accepted),
                rejected_nonfinite=tuple(self._rej_nonfinite),
                rejected_gated=tuple(self._rej_gated),
                nis_average=tuple(self._nis),
                diverged=bool(self._diverged),
                diverged_reason=self._diverged,
                depth_resets=self._depth_resets,
            )
            self._health_cache = (self._version, h)
        return h

    @property
    def estimate(self) -> EstimatedState:
        health = self.health  # fuses what is pending
        version, time_s, s = self._estimate_cache
        if version != self._version or time_s != self.time_s:
            s = _make_state(self.time_s, self._ekf.x, self._ekf.P.diagonal(), health)
            self._estimate_cache = (self._version, self.time_s, s)
        return s


def _make_state(time_s: float, x, cov_diag, health: EstimatorHealth) -> EstimatedState:
    phi, theta, psi, p, q, r, bgx, bgy, bgz, u, v, w, depth, dx, dy, dz = np.asarray(x, dtype=float).tolist()
    # q = q_z(psi) q_y(theta) q_x(phi) (Fossen 2011 eq. 2.83)
    quat = tuple(euler_to_quat(phi, theta, psi).tolist())
    # z' = R[2, :] v = -s(theta) u + c(theta) s(phi) v + c(theta) c(phi) w (Fossen 2011 eq. 2.18)
    cth = math.cos(theta)
    zdot = -math.sin(theta) * u + cth * math.sin(phi) * v + cth * math.cos(phi) * w
    return EstimatedState(
        float(time_s), quat, (phi, theta, _wrap(psi)), (p, q, r), (bgx, bgy, bgz), (u, v, w), depth, zdot,
        (dx, dy, dz), tuple(np.asarray(cov_diag, dtype=float).tolist()), health,
    )


def state_from_truth(x_full, vehicle: Vehicle, time_s: float = 0.0) -> EstimatedState:
    """An `EstimatedState` holding a full model state exactly (zero covariance, zero bias).

    For closed-loop tests and the HIL's "perfect estimate" mode: the controller sees the truth.
    """
    x_full = np.asarray(x_full, float)
    roll, pitch, yaw = quat_to_euler(x_full[3:7])
    xr = np.zeros(N_X)
    xr[0:3] = roll, pitch, yaw
    xr[3:6] = x_full[10:13]
    xr[9:12] = x_full[7:10]
    xr[12] = x_full[2] - vehicle.environment.surface_depth
    return _make_state(time_s, xr, np.zeros(N_X), EstimatorHealth())


__all__ = [
    "Estimator",
    "EstimatedState",
    "EstimatorHealth",
    "EstimatorTuning",
    "STREAMS",
    "state_from_truth",
]


# Kernels above compile onboard.model functions into themselves: key their disk cache on it.
key_caches_on(globals(), MODEL_SOURCE)
