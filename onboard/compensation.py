"""Azimuth-transient compensation (seed 004): predict each jet's transient force and moment from its
planned joint motion and take it out of the demanded wrench before allocation.

Pure math plus one small stateful object. `TransientCompensator` holds, per unit, the five
seed-004 transfer functions of spec 4.1 (F1x, F1y, M1z, F2x, F2z; from
`onboard.model.transfer_function`) discretised at the control period with
`scipy.signal.cont2discrete` (zero-order hold: the joint rate is held over a step), and their
states, carried from step to step. It also carries the spec's `servo_lag` model (first-order lag
then rate limit) so the rates that drive the filters are the joints' actual rates, not the
commanded steps: with the servo's 30 ms lag and a 9 Hz F1x resonance the difference matters.

Per unit, over the next step, with thrust T, g = gain_per_newton * T and the rows' step-mean
outputs (spec 4.1, the same formula as `onboard.model.jets_and_transients`):

    axial change   dT = max(T - g (F1x + F2x), 0) - T      along d
    lateral        g F1y along e_alpha,  g F2z along e_beta
    moment         r x (force change) - g M1z about body z

`allocate_compensated` allocates demand - c_lat, c_lat the compensated share of the lateral
transient of the coming step, then makes up the compensated share of each unit's axial loss by
that unit's own speed at its planned angles (`_make_up`). With ZOH the rows are strictly proper (Dd = 0), so that transient is set by joint
motion already committed (the free response of the carried states, `free_rows`) plus a forced
part of at most C Bd / 2 <= 0.041 row units per rad/s of the step's own rate: no algebraic loop
and no fixed-point iteration over the plan (which formed a limit cycle at the joints' rate limit).
Only the rows that can be cancelled without turning the joints for it are (COMPENSATED_ROWS:
the axial loss in full, by speed only; half the lateral force, not on yaw): cancelling the reaction
moment or the lateral force by turning the azimuths excites them more than it cancels.

What the azimuths' turning does to yaw (the M1z reaction above all) is cancelled ahead instead,
by `YawPreview`: the map from a commanded to a made yaw moment has right-half-plane zeros
(`azimuth_yaw_map`), so its inverse needs the demand's future, and the controller's yaw
reference (third order, its own filter) gives that future (`Controller.yaw_preview`). The loop
adds its correction to the yaw demand before `allocate_compensated`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
from numba import njit
from scipy.signal import cont2discrete, tf2ss

from . import model
from .jit import MODEL_SOURCE, key_caches_on
from .allocation import Allocation, JetGeometry
from .allocation import _frozen, _owned, outcome as alloc_outcome
from .allocation import _speed1, axial_inflow, jet_frames, max_thrust
from .vehicle import Vehicle

ROWS = model.TRANSIENT_ROWS  # ("f1x", "f1y", "m1z", "f2x", "f2z")
# Share of each row (F1x, F1y, M1z, F2x, F2z) compensated (see allocate_compensated): the axial
# losses in full (made up by each unit's own speed after the plan, `_make_up`), the lateral forces
# half (taken out of the demand), the reaction moment not at all.
COMPENSATED_ROWS = (1.0, 0.5, 0.0, 1.0, 0.5)
# Wrench axes [X, Y, Z, K, M, N] on which the lateral rows are compensated: not yaw.
LATERAL_AXES = (1.0, 1.0, 1.0, 1.0, 1.0, 0.0)


def discretise_row(row: str, coeffs, dt_s: float, method: str = "zoh"):
    """(Ad, Bd, Cd, Dd) of one seed-004 row (eq. 5 or 6) at sample time dt_s."""
    num, den = model.transfer_function(row, coeffs)
    A, B, C, D = tf2ss(num, den)
    Ad, Bd, Cd, Dd, _ = cont2discrete((A, B, C, D), dt_s, method=method)
    return Ad, Bd.reshape(-1), Cd.reshape(-1), float(np.asarray(Dd).reshape(-1)[0])


@njit(cache=True)
def _servo_motion(angle, command, dt_s, time_constant, rate_limit, limit):
    k = angle.shape[0]
    a_end = np.empty(k)
    rate = np.empty(k)
    band = rate_limit * time_constant
    for i in range(k):
        target = min(max(command[i], -limit), limit)
        e0 = target - angle[i]
        mag = abs(e0)
        t_slew = max(mag - band, 0.0) / rate_limit  # time spent at the rate limit
        if t_slew >= dt_s:
            e_end = mag - rate_limit * dt_s
        else:
            e_end = min(mag, band) * math.exp(-(dt_s - t_slew) / time_constant)
        a_end[i] = target - (e_end if e0 >= 0.0 else -e_end)
        rate[i] = (a_end[i] - angle[i]) / dt_s
    return a_end, rate


def servo_motion(angle, command, dt_s, time_constant, rate_limit, limit):
    """Joint angle after dt_s and its mean rate, exactly, for spec `servo_lag`:

    a' = clip((clip(a_cmd) - a) / tau, +-rate_limit). While |error| > rate_limit * tau the joint
    slews at the rate limit; after that the error decays as exp(-t / tau).
    """
    return _servo_motion(np.array(angle, dtype=np.float64), np.array(command, dtype=np.float64),
                         float(dt_s), float(time_constant), float(rate_limit), float(limit))


@njit(cache=True)
def _predict(Ad, Bd, Cd, z0, ra, rb, T, gain, a_mid, b_mid, e1, pos):
    """One step of every unit's five rows and the spec-4.1 transient wrench of their step means.

    z1 = Ad z0 + Bd u (ZOH), y = (C z0 + C z1) / 2; drives u = (|a'|, a', a', |b'|, b');
    with g = gain T: force = (max(T - g (y1x + y2x), 0) - T) d + g y1y e_alpha + g y2z e_beta,
    moment r x force - g y1z about body z.
    """
    k = z0.shape[0]
    z1 = np.empty_like(z0)
    y = np.empty((k, 5))
    force = np.empty((k, 3))
    mz = np.empty(k)
    wrench = np.zeros(6)
    for i in range(k):
        drive = (abs(ra[i]), ra[i], ra[i], abs(rb[i]), rb[i])
        for r in range(5):
            y0 = 0.0
            y1 = 0.0
            for j in range(4):
                acc = Bd[r, j] * drive[r]
                for m in range(4):
                    acc += Ad[r, j, m] * z0[i, r, m]
                z1[i, r, j] = acc
                y0 += Cd[r, j] * z0[i, r, j]
                y1 += Cd[r, j] * acc
            y[i, r] = 0.5 * (y0 + y1)
        Ti = max(T[i], 0.0)
        g = gain * Ti
        F = model.jet_frame(a_mid[i], b_mid[i], e1[i, 0], e1[i, 1])
        dax = max(Ti - g * (y[i, 0] + y[i, 3]), 0.0) - Ti
        for c in range(3):
            force[i, c] = dax * F[0, c] + g * y[i, 1] * F[1, c] + g * y[i, 4] * F[2, c]
            wrench[c] += force[i, c]
        m0, m1, m2 = model.cross(pos[i, 0], pos[i, 1], pos[i, 2], force[i, 0], force[i, 1], force[i, 2])
        mz[i] = -g * y[i, 2]
        wrench[3] += m0
        wrench[4] += m1
        wrench[5] += m2 + mz[i]
    return wrench, force, mz, y, z1


@njit(cache=True)
def _rows_wrench(y, T, gain, weights, a, b, e1, pos):
    """Spec-4.1 transient wrench of given row outputs y (k x 5), each row scaled by weights[r].

    Same formula as `_predict` (force = (max(T - g (w0 y1x + w3 y2x), 0) - T) d + g w1 y1y e_alpha
    + g w4 y2z e_beta, moment r x force - g w2 y1z about body z), at the joint angles a, b.
    """
    k = y.shape[0]
    wrench = np.zeros(6)
    for i in range(k):
        Ti = max(T[i], 0.0)
        g = gain * Ti
        F = model.jet_frame(a[i], b[i], e1[i, 0], e1[i, 1])
        dax = max(Ti - g * (weights[0] * y[i, 0] + weights[3] * y[i, 3]), 0.0) - Ti
        f = np.empty(3)
        for c in range(3):
            f[c] = dax * F[0, c] + g * weights[1] * y[i, 1] * F[1, c] + g * weights[4] * y[i, 4] * F[2, c]
            wrench[c] += f[c]
        m0, m1, m2 = model.cross(pos[i, 0], pos[i, 1], pos[i, 2], f[0], f[1], f[2])
        wrench[3] += m0
        wrench[4] += m1
        wrench[5] += m2 - g * weights[2] * y[i, 2]
    return wrench


def azimuth_yaw_map(v: Vehicle, unit: int = 0, beta_rad: float = 0.0):
    """(num, den) of the net yaw moment per newton of thrust per rad of azimuth of one unit, the
    seed-004 transients included (spec 3 and 4.1, small azimuth about neutral):

        N / (T alpha) = L cos(beta) + g s (L H_F1y(s) - H_M1z(s))

    L = (r x e_alpha)_z, the lever of the tangential thrust (0.11 m on the reference vehicle);
    g = gain_per_newton; s H(s) because the rows are driven by the azimuth rate. The thrust T
    cancels: every unit and every thrust level has the same map, so no split of a yaw demand over
    azimuth turns escapes it. Its right-half-plane zeros (`np.roots(num)`) bound how fast an
    azimuth-made yaw moment can be shaped, the reaction included.
    """
    at = v.effects.azimuth_transient
    u = v.units[unit]
    F = model.jet_frame(0.0, 0.0, u.neutral[0], u.neutral[1])
    lever = float(u.position[0] * F[1, 1] - u.position[1] * F[1, 0])
    nF, dF = model.transfer_function("f1y", at.f1y)
    nM, dM = model.transfer_function("m1z", at.m1z)
    g = at.gain_per_newton
    den = np.polymul(dF, dM)
    cross = np.polysub(lever * np.polymul(nF, dM), np.polymul(nM, dF))
    num = np.polyadd(lever * math.cos(beta_rad) * den, g * np.polymul([1.0, 0.0], cross))
    return num, den


def azimuth_lever(num, den) -> float:
    """DC gain of `azimuth_yaw_map` (num, den): L cos(beta), the tangential thrust's lever (0.11 m
    on the reference vehicle at beta = 0); the transients have no DC part."""
    return float(np.polyval(num, 0.0) / np.polyval(den, 0.0))


# -- the yaw reaction, cancelled ahead along the controller's own reference ------------------------

# How far ahead the yaw correction plans. The commanded -> made yaw moment map has two RHP pairs,
# 21.4 +- 22.7j and 4.73 +- 57.8j rad/s (1/Re z = 0.05 and 0.21 s). Measured on the linearised
# reversal (tests/test_compensation.py): 0.3-0.8 s all give 0.59 mrad, 0.2 s 0.70, and at 0.15 s
# the plan diverges (`yaw_preview_gains` refuses it).
PREVIEW_HORIZON_S = 0.4
# weight of the correction's rate against the yaw error: J = int e^2 dt + MOVE_WEIGHT int c'^2 dt
PREVIEW_MOVE_WEIGHT = 1e-6  # rad^2 per (N m/s)^2


def yaw_loop_model(v: Vehicle, dt_s: float, yaw_bandwidth_rad_s: float, damping_ratio: float):
    """(A, b_ff, b_c, c_e) of the linearised yaw channel, discrete at dt_s (ZOH): the yaw error e
    that the azimuths' transients leave when the controller asks the feed-forward moment N0 and a
    correction c is added to the yaw demand:

        e = W S ((D - 1) N0 + D c),   x' = A x + b_ff N0 + b_c c,   e = c_e x

    D = `azimuth_yaw_map` / its DC gain (commanded -> made yaw moment, transients included, D(0) = 1;
    the same for every unit and thrust), S = 1 / (tau s + 1) the servo lag, W = s / (I_z (s^3 +
    2 z w s^2 + w^2 s + w^3 / 10) + d_r s^2) the closed yaw loop from a moment error to the yaw
    error (onboard.control eq. 1, its yaw PID at bandwidth w, damping z; I_z = I_zz + N_r',
    d_r the linear yaw damping). Realised block by block (a product of the polynomials, 12th
    order, is too badly conditioned).
    """
    num, den = azimuth_yaw_map(v)
    aD, bD, cD, dD = tf2ss(num / azimuth_lever(num, den), den)
    nD = aD.shape[0]
    tau = v.servo.time_constant
    izz = v.body.inertia[2] + v.hydro.added_mass[5]
    w, z = yaw_bandwidth_rad_s, damping_ratio
    W_den = np.polyadd(izz * np.array([1.0, 2 * z * w, w * w, w ** 3 / 10]), [v.hydro.linear_damping[5], 0.0, 0.0])
    aW, bW, cW, _ = tf2ss([1.0, 0.0], W_den)
    n = nD + 1 + aW.shape[0]
    A, B, C = np.zeros((n, n)), np.zeros((n, 2)), np.zeros((1, n))
    A[:nD, :nD] = aD
    B[:nD, 0] = B[:nD, 1] = bD[:, 0]  # D is driven by N0 + c
    d = float(np.asarray(dD).item())
    A[nD, :nD] = cD[0] / tau  # servo lag of D (N0 + c) - N0
    A[nD, nD] = -1.0 / tau
    B[nD, 0], B[nD, 1] = (d - 1.0) / tau, d / tau
    A[nD + 1:, nD + 1:] = aW
    A[nD + 1:, nD] = bW[:, 0]
    C[0, nD + 1:] = cW[0]
    Ad, Bd, Cd, _, _ = cont2discrete((A, B, C, np.zeros((1, 2))), dt_s, method="zoh")
    return Ad, np.ascontiguousarray(Bd[:, 0]), np.ascontiguousarray(Bd[:, 1]), Cd.reshape(-1)


@dataclass(frozen=True)
class YawPreviewGains:
    """c_k = kx x_k + kn N0[k:k+H] + kc c_(k-1): the first move of the least-squares plan over H steps.

    Plan: min sum_(j=1..H) e_(k+j)^2 + lam sum_(j=0..H-1) (c_(k+j) - c_(k+j-1))^2, lam =
    PREVIEW_MOVE_WEIGHT / dt^2 (the sums approximate the integrals of `PREVIEW_MOVE_WEIGHT`), on
    `yaw_loop_model` from its state x_k, the feed-forward N0 of the next H steps known.
    Unconstrained, so solved once: a receding-horizon plan that is a fixed linear filter.
    """

    A: np.ndarray
    b_ff: np.ndarray
    b_c: np.ndarray
    kx: np.ndarray
    kn: np.ndarray
    kc: float
    horizon: int
    radius: float  # spectral radius of the filter the plan makes (<= 1: checked when built)


def yaw_preview_gains(v: Vehicle, dt_s: float, yaw_bandwidth_rad_s: float, damping_ratio: float,
                      horizon_s: float = PREVIEW_HORIZON_S, move_weight: float = PREVIEW_MOVE_WEIGHT) -> YawPreviewGains:
    """The `YawPreviewGains` of the vehicle's yaw channel at control period dt_s."""
    A, b_ff, b_c, c_e = yaw_loop_model(v, dt_s, yaw_bandwidth_rad_s, damping_ratio)
    H = max(int(round(horizon_s / dt_s)), 1)
    nx = A.shape[0]
    Phi = np.empty((H, nx))  # e_(k+j) = c A^j x + sum_(i<j) c A^(j-1-i) (b_ff N_i + b_c c_i)
    h_ff, h_c = np.empty(H), np.empty(H)
    M = np.eye(nx)
    for j in range(H):
        h_ff[j], h_c[j] = c_e @ M @ b_ff, c_e @ M @ b_c
        M = A @ M
        Phi[j] = c_e @ M
    idx = np.arange(H)
    lower = idx[:, None] - idx[None, :]
    G_ff = np.where(lower >= 0, h_ff[np.clip(lower, 0, H - 1)], 0.0)
    G_c = np.where(lower >= 0, h_c[np.clip(lower, 0, H - 1)], 0.0)
    lam = move_weight / dt_s ** 2
    Dm = np.eye(H) - np.eye(H, k=-1)
    first = np.linalg.solve(G_c.T @ G_c + lam * Dm.T @ Dm, np.eye(H)[:, 0])  # row 0 of the inverse (symmetric)
    kx, kn, kc = -(first @ G_c.T) @ Phi, -(first @ G_c.T) @ G_ff, float(lam * first @ Dm.T[:, 0])
    # the filter [x; c] -> [A x + b_c c; c] with c = kx x + kc c_prev (+ the preview): its spectral
    # radius. One eigenvalue is 1 (a constant c has no yaw effect, W(0) = 0, so nothing moves it);
    # a horizon too short for the RHP zeros puts one outside (0.15 s at 100 Hz: 1.09).
    F = np.block([[A + np.outer(b_c, kx), (b_c * kc)[:, None]], [kx[None, :], np.array([[kc]])]])
    radius = float(np.max(np.abs(np.linalg.eigvals(F))))
    if not radius <= 1.0 + 1e-6:
        raise ValueError(f"horizon_s: the yaw preview's plan over {horizon_s} s at dt {dt_s} s is unstable "
                         f"(spectral radius {radius:.4f}); plan further ahead (default {PREVIEW_HORIZON_S} s)")
    return YawPreviewGains(A=_frozen(A), b_ff=_frozen(b_ff), b_c=_frozen(b_c), kx=_frozen(kx), kn=_frozen(kn),
                           kc=kc, horizon=H, radius=radius)


class YawPreview:
    """The correction of the yaw demand that cancels, ahead, what the azimuths' transients (the
    M1z reaction above all) will do to the yaw of the moment the controller is about to ask.

    Why ahead: the map from a commanded yaw moment to the moment the turning azimuths make has
    right-half-plane zeros (`azimuth_yaw_map`: 21.4 +- 22.7j rad/s): a correction from the current
    demand alone, or fed back from the predicted reaction, cannot cancel it (measured: chatter, or
    a third at best); its inverse needs the demand's future. The controller's yaw reference is its
    own filter, so that future is known (`Controller.yaw_preview`) until the setpoint changes.

    `step(n0_future)` -> c (N m, to add to the yaw demand this step), the model advanced with what
    the step asks (n0_future[0] + c). A fixed linear filter of the feed-forward (`YawPreviewGains`):
    it reads no measurement, so it cannot destabilise the loop, and its own stability is checked
    when it is built (spectral radius <= 1; the one eigenvalue at 1 is a constant c, which leaves
    a few 1e-5 N m after a turn for the yaw integrator). c is held within the jets' yaw capacity
    (k T_max L); a preview of the wrong length or holding NaN/inf gives c = 0 and starts the model
    over.
    """

    def __init__(self, v: Vehicle, dt_s: float, yaw_bandwidth_rad_s: float, damping_ratio: float,
                 horizon_s: float = PREVIEW_HORIZON_S, move_weight: float = PREVIEW_MOVE_WEIGHT):
        self.gains = yaw_preview_gains(v, dt_s, yaw_bandwidth_rad_s, damping_ratio, horizon_s, move_weight)
        self.horizon = self.gains.horizon
        # the most yaw the jets can make by turning: every unit at bollard T_max (seed 000 eq. 15)
        # at the tangential lever
        self.limit_nm = float(np.sum(JetGeometry(v).thrust_max(np.zeros(v.n_units)))) * abs(
            azimuth_lever(*azimuth_yaw_map(v)))
        self.reset()
        self.step(np.zeros(self.horizon))  # load the compiled kernel now, not in the first step

    def reset(self) -> None:
        self.x = np.zeros(self.gains.A.shape[0])
        self.c = 0.0

    def step(self, n0_future) -> float:
        """c for this step from the feed-forward of this step and the horizon - 1 after it."""
        g = self.gains
        n0 = np.asarray(n0_future, dtype=np.float64)
        c = math.nan
        if n0.shape == (self.horizon,):
            c = _preview_step(self.x, self.c, n0, g.kx, g.kn, g.kc, g.A, g.b_ff, g.b_c, self.limit_nm)
        if not math.isfinite(c):
            self.reset()
            return 0.0
        self.c = c
        return c


@njit(cache=True)
def _preview_step(x, c_prev, n0, kx, kn, kc, A, b_ff, b_c, limit):
    """c = kx x + kn n0 + kc c_prev within +-limit, then x <- A x + b_ff n0[0] + b_c c in place;
    NaN (x left alone) if n0 holds a non-finite value."""
    c = kc * c_prev
    for j in range(n0.shape[0]):
        if not math.isfinite(n0[j]):
            return math.nan
        c += kn[j] * n0[j]
    m = x.shape[0]
    for j in range(m):
        c += kx[j] * x[j]
    if not math.isfinite(c):
        return math.nan
    c = min(max(c, -limit), limit)
    new = np.empty(m)
    for i in range(m):
        acc = b_ff[i] * n0[0] + b_c[i] * c
        for j in range(m):
            acc += A[i, j] * x[j]
        new[i] = acc
    x[:] = new
    return c


@dataclass(frozen=True)
class TransientPrediction:
    """Predicted transient over one control step (step means), per unit and summed.

    `wrench_n` = [X, Y, Z (N), K, M, N (N m)] body FRD; `rows` (k x 5) the filter outputs
    F1x, F1y, M1z, F2x, F2z (before the gain * T scaling).
    """

    wrench_n: np.ndarray
    force_body_n: np.ndarray  # (k, 3)
    moment_z_nm: np.ndarray  # (k,) reaction moments -g M1z
    rows: np.ndarray  # (k, 5)
    alpha_rate_rad_s: np.ndarray
    beta_rate_rad_s: np.ndarray
    next_state: np.ndarray  # (k, 5, 4) filter states at the end of the step
    next_alpha_rad: np.ndarray  # the joints' (estimated) angles at the end of the step
    next_beta_rad: np.ndarray


class TransientCompensator:
    """Seed-004 transient predictor for every unit, discretised at `dt_s`, state carried over steps.

    `predict(alpha_cmd, beta_cmd, thrust)` (through the servo model) or
    `predict_rates(alpha_rate, beta_rate, thrust, alpha, beta)` return a `TransientPrediction`
    without changing anything; `commit(prediction)` advances the filters and joint estimates.
    With `azimuth_transient` or `servo_lag` off the prediction is zero, as in the spec.
    """

    def __init__(self, v: Vehicle, dt_s: float, alpha_rad=None, beta_rad=None, row_weights=COMPENSATED_ROWS):
        w = np.asarray(row_weights, dtype=float).reshape(-1) if np.ndim(row_weights) else np.array([np.nan])
        if w.shape != (len(ROWS),) or not np.all(np.isfinite(w)) or np.any(w < 0) or np.any(w > 1):
            raise ValueError(f"row_weights: expected {len(ROWS)} weights in [0, 1] for the rows {ROWS}, "
                             f"got {row_weights!r}")
        self.row_weights = w
        if not (isinstance(dt_s, (int, float)) and np.isfinite(dt_s) and dt_s > 0):
            raise ValueError(f"dt_s: expected the control period in seconds (> 0), got {dt_s!r}")
        self.vehicle = v
        self.dt_s = float(dt_s)
        self.k = v.n_units
        # No joint moves on a vehicle of fixed thrusters (spec 3.1): nothing to predict or cancel.
        self.jointless = bool(v.fixed)
        if self.jointless:
            self.active, self.gain = False, 0.0
            self.reset(alpha_rad, beta_rad)
            return
        self.geo = JetGeometry(v)
        at = v.effects.azimuth_transient
        self.active = bool(at.enabled and v.effects.on("servo_lag"))
        self.gain = at.gain_per_newton if self.active else 0.0
        # ZOH: the rates are held over a step, and the rows are strictly proper, so Dd = 0.
        mats = [discretise_row(r, getattr(at, r), self.dt_s, "zoh") for r in ROWS]
        self.Ad = np.ascontiguousarray(np.stack([m[0] for m in mats]))  # (5, 4, 4)
        self.Bd = np.ascontiguousarray(np.stack([m[1] for m in mats]))  # (5, 4)
        self.Cd = np.ascontiguousarray(np.stack([m[2] for m in mats]))  # (5, 4)
        # free response y = (C z0 + C Ad z0) / 2 = C_free z0: the fixed row map, formed once here
        self._C_free = 0.5 * (self.Cd + np.einsum("rj,rjm->rm", self.Cd, self.Ad))  # (5, 4)
        s = v.servo
        self.servo = (s.time_constant, s.rate_limit, s.angle_limit)
        self._zeros6, self._ones, self._eye6 = np.zeros(6), np.ones(self.k), np.eye(6)
        self.reset(alpha_rad, beta_rad)
        z = np.zeros(self.k)
        self.predict(z, z, z)  # loads the compiled kernels now rather than in the first step
        self.rows_wrench(np.zeros((self.k, len(ROWS))), z)
        ro = _frozen(z)  # the allocator's plans are read-only arrays: that kind of signature
        _make_up_speeds(ro, ro, np.zeros((self.k, len(ROWS))), 0.0, 1.0, 1.0, LOSS_CAP, ro, ro, self._zeros6,
                        self.geo.position, self.geo.e1, self.geo.tp, self._ones)

    def reset(self, alpha_rad=None, beta_rad=None) -> None:
        """Zero the filters (spec 6: transient states start at zero) and set the joint estimates."""
        self.state = np.zeros((self.k, len(ROWS), 4))
        self.alpha = np.zeros(self.k) if alpha_rad is None else np.asarray(alpha_rad, float).copy()
        self.beta = np.zeros(self.k) if beta_rad is None else np.asarray(beta_rad, float).copy()

    # -- prediction -------------------------------------------------------------------------------
    def predict(self, alpha_cmd, beta_cmd, thrust_n) -> TransientPrediction:
        """Transient of the next step if the joints are commanded to alpha_cmd, beta_cmd."""
        if self.jointless:
            return self._predict(None, None, thrust_n, None, None, None, None)
        tau_s, rate, lim = self.servo
        a1, ra = servo_motion(self.alpha, alpha_cmd, self.dt_s, tau_s, rate, lim)
        b1, rb = servo_motion(self.beta, beta_cmd, self.dt_s, tau_s, rate, lim)
        return self._predict(ra, rb, thrust_n, self.alpha, self.beta, a1, b1)

    def predict_rates(self, alpha_rate, beta_rate, thrust_n, alpha_rad=None, beta_rad=None) -> TransientPrediction:
        """Transient of the next step for given joint rates held over it (from angles alpha, beta)."""
        a0 = self.alpha if alpha_rad is None else np.asarray(alpha_rad, float)
        b0 = self.beta if beta_rad is None else np.asarray(beta_rad, float)
        ra, rb = np.asarray(alpha_rate, float), np.asarray(beta_rate, float)
        return self._predict(ra, rb, thrust_n, a0, b0, a0 + ra * self.dt_s, b0 + rb * self.dt_s)

    def _predict(self, ra, rb, thrust_n, a0, b0, a1, b1) -> TransientPrediction:
        k = self.k
        if self.jointless:
            z = np.zeros(k)
            return TransientPrediction(
                wrench_n=np.zeros(6), force_body_n=np.zeros((k, 3)), moment_z_nm=z, rows=np.zeros((k, len(ROWS))),
                alpha_rate_rad_s=z, beta_rate_rad_s=z, next_state=np.zeros((k, len(ROWS), 4)),
                next_alpha_rad=z, next_beta_rad=z)
        ra = np.array(ra, dtype=np.float64)  # writable copies: one compiled signature
        rb = np.array(rb, dtype=np.float64)
        if not self.active:
            ra, rb = np.zeros(k), np.zeros(k)
        a_mid = 0.5 * (np.asarray(a0, float) + a1)
        b_mid = 0.5 * (np.asarray(b0, float) + b1)
        T = np.array(thrust_n, dtype=np.float64)
        wrench, force, mz, y, z1 = _predict(self.Ad, self.Bd, self.Cd, self.state, ra, rb, T, self.gain,
                                            a_mid, b_mid, self.geo.e1, self.geo.position)
        return TransientPrediction(
            wrench_n=wrench, force_body_n=force, moment_z_nm=mz, rows=y, alpha_rate_rad_s=ra,
            beta_rate_rad_s=rb, next_state=z1, next_alpha_rad=np.asarray(a1, float),
            next_beta_rad=np.asarray(b1, float),
        )

    def free_rows(self) -> np.ndarray:
        """Step-mean row outputs (k x 5) over the coming step with the joints held: the free response.

        ZOH and strictly proper rows (Dd = 0): y over the step is (C z0 + C Ad z0) / 2 plus a forced
        part (C Bd / 2) u of the step's own rate u. C Bd / 2 is 0.017..0.040 here (rows at 10 ms),
        so at the 5 rad/s rate limit the forced part of a row is under 0.3 % of T: what acts
        during the coming step is set by the joint motion already committed.
        """
        if not self.active:
            return np.zeros((self.k, len(ROWS)))
        return np.einsum("rm,irm->ir", self._C_free, self.state)

    def rows_wrench(self, rows, thrust_n, alpha_rad=None, beta_rad=None, weights=None) -> np.ndarray:
        """Spec-4.1 transient wrench of row outputs `rows` (k x 5) at thrust T and joint angles
        (default: the current estimates), each row scaled by `weights` (default: this compensator's
        `row_weights`)."""
        a = self.alpha if alpha_rad is None else np.asarray(alpha_rad, float)
        b = self.beta if beta_rad is None else np.asarray(beta_rad, float)
        w = self.row_weights if weights is None else np.asarray(weights, float)
        return _rows_wrench(np.ascontiguousarray(rows, dtype=np.float64), np.array(thrust_n, dtype=np.float64),
                            self.gain, np.array(w, dtype=np.float64), np.array(a, dtype=np.float64),
                            np.array(b, dtype=np.float64), self.geo.e1, self.geo.position)

    def commit(self, prediction: TransientPrediction) -> None:
        """Advance to the end of the step the prediction was made for."""
        self.state = np.array(prediction.next_state)
        self.alpha = np.array(prediction.next_alpha_rad)
        self.beta = np.array(prediction.next_beta_rad)


def compensate(wrench_demand, prediction: TransientPrediction) -> np.ndarray:
    """The wrench to ask the jets for so that jets + transient = demand: demand - prediction."""
    return np.asarray(wrench_demand, float) - prediction.wrench_n


@dataclass(frozen=True)
class CompensatedAllocation:
    """An allocation made against demand - c (c: the compensated part of the predicted transient),
    and the full predicted transient of that plan."""

    allocation: Allocation
    prediction: TransientPrediction
    wrench_demand: np.ndarray
    wrench_total: np.ndarray  # achieved by the jets + predicted transient
    iterations: int  # re-plans made (step 2 of allocate_compensated)
    correction_n: np.ndarray | None = None  # the compensated part c taken out of the demand


def allocate_compensated(allocator, compensator: TransientCompensator, wrench_demand, nu_r=None,
                         iterations: int = 2, commit: bool = True) -> CompensatedAllocation:
    """Allocate demand - c_lat, then make up the axial loss by speed: jets + transient ~ demand.

    1. c_lat from the coming step's free response (`free_rows`: what the joint motion already
       committed leaves in the filters; with ZOH the rows' Dd is 0, so no algebraic loop) at the
       last plan's thrust and the current joint angles (`_correction`: rows F1y, F2z, not on yaw);
       plan demand - c_lat.
    2. `iterations` times (any integer >= 0; 0 = step 1 only): c_lat again from the plan's own
       thrust and joint motion (free + forced part, `predict`); re-plan demand - c_lat; stop once
       it moves by under REPLAN_TOL_N (1 mN). Through the plan c_lat changes only with T (g F ~
       0.0126 T per unit of row output) and with the forced part (C Bd / 2 <= 0.041, so under
       0.3 % of T at the rate limit): a contraction, not the re-plan against the plan's own full
       transient that chattered at the rate limit.
    3. The axial loss (spec 4.1: a unit commanded to T gives (T - g (F1x + F2x)) along its own d,
       g = gain T) is made up by that unit's speed at the planned joint angles (`_make_up`,
       `make_up_thrust`: T_cmd = T / (1 - L), L = gain (w0 F1x + w3 F2x) <= LOSS_CAP), within
       each unit's T_max(J) and with what is left undone balanced in yaw
       (`yaw_balanced_make_up`); n from the inverse of seed-000 eq. 15. No allocator call, no
       joint motion for it.
    4. The full prediction (every row) of the plan at the commanded thrust is returned as
       `prediction`; `allocation` is the plan at the made-up speeds (what is sent), `correction_n`
       = c_lat + c_ax (the jets give demand - c). With `commit` the allocator advances with its own
       plan (its change reference stays the QP's sequence) and the compensator with the prediction.

    Why the axial loss is not taken out of the demand (as it was until the sway measurement): a
    wrench handed to the QP is realised however the QP likes, and with 12 force components for 6
    wrench axes and a change penalty it re-vectors for it. F1x is driven by |azimuth rate| (eq. 5,
    57 rad/s mode): the re-vectoring made more loss, the loss more make-up, and at 0.3 m/s the loop
    closed into a ~9 Hz limit cycle at the azimuths' rate limit (HIL, sway +-0.3 m/s: 24 % of the
    azimuth commands at the limit, yaw disturbance x8). Measured in HIL, sway +-0.3 m/s: no axial
    make-up: no chatter (3.8 %), yaw x0.89; make-up in the demand capped at each unit's headroom
    T_max(J) - T: chatter stays (10.5 %), yaw x12 (so not the jets' saturation); make-up by speed:
    chatter gone (3.5 %), yaw x1.35, the rest from the units at full speed (n_max 4 % of the
    time) leaving their loss undone while the others made theirs up: a lopsided force with yaw.
    With that remainder balanced in yaw (`yaw_balanced_make_up`): yaw x0.72, position x0.155.
    The four translation scenarios (surge, sway +-0.3, surge <-> sway 0.3, surge +-0.2 m/s): yaw
    x0.49, 0.72, 0.82, 0.97; position x0.15, 0.155, 0.12, 0.14 (were x1.52, 8.0, 2.94, 0.83).
    The price, yaw reversals with these rows alone (tests/test_closed_loop.py, `yaw_preview`
    off): yaw x1.44 (0.111 -> 0.007 m in position), which the yaw preview takes to x0.28.

    Not every row is cancelled (`COMPENSATED_ROWS`, `LATERAL_AXES`). Cancelling a transient that
    needs the azimuths to turn excites the transient again through the same turn: for the yaw
    moment the loop gain is g K_M1z / (r cos beta), about 8 / cos(beta) near M1z's 29 rad/s mode,
    and F1y's 49 rad/s resonance does the same on the lateral force. `azimuth_yaw_map` gives the
    net azimuth -> yaw map with the transients: right-half-plane zeros at 21.4 +- 22.7j rad/s,
    the same for every unit and thrust, so neither a split over units nor more thrust helps. Measured open loop (demand
    [0, 0, 2, 0, 0, 0] N then [0.5, 0, 2, 0, 0, 0.1]): cancelling M1z or F1y/F2z in full, or all
    rows at 0.3, ends in rate-limit chatter even from the free response alone; the axial losses
    in full (made up by thrust, no turning needed) plus half the lateral forces without their yaw
    moment settle. The rest is left to the controller as a disturbance.

    That yaw rest is not for a per-step correction of the current demand: thrust at fixed joint
    angles has no yaw to give in a yaw turn (heave 8 N per N m of yaw), and a correction that
    turns the azimuths needs the demand ahead. `YawPreview` has it (the controller's yaw reference)
    and corrects the yaw demand before it reaches this function: HIL yaw reversals 4.84 -> 1.33
    mrad RMS, where the rows here alone give 6.99 (tests/test_closed_loop.py).
    """
    if isinstance(iterations, bool) or not isinstance(iterations, (int, np.integer)):
        raise ValueError(f"iterations: expected an integer >= 0 (re-plans per step), got {iterations!r}")
    n_iter = max(int(iterations), 0)
    tau = np.asarray(wrench_demand, float)
    if compensator.jointless:  # fixed thrusters: compensation is off, the plan is what is sent
        alloc = allocator.allocate(tau, nu_r=nu_r, commit=commit)
        pred = compensator.predict(alloc.alpha_rad, alloc.beta_rad, alloc.thrust_n)
        return CompensatedAllocation(alloc, pred, tau, np.asarray(alloc.wrench_achieved), 0, np.zeros(6))
    prev = getattr(allocator, "previous", None)
    thrust_ref = np.zeros(compensator.k) if prev is None else np.asarray(prev.thrust_n, float)
    corr = _correction(compensator, compensator.free_rows(), thrust_ref, compensator.alpha, compensator.beta)
    alloc = allocator.allocate(tau - corr, nu_r=nu_r, commit=False)
    pred = compensator.predict(alloc.alpha_rad, alloc.beta_rad, alloc.thrust_n)
    done = 0
    for _ in range(n_iter):
        a_mid = 0.5 * (compensator.alpha + pred.next_alpha_rad)
        b_mid = 0.5 * (compensator.beta + pred.next_beta_rad)
        new = _correction(compensator, pred.rows, alloc.thrust_n, a_mid, b_mid)
        if not np.all(np.isfinite(new)) or np.max(np.abs(new - corr)) < REPLAN_TOL_N:
            break
        corr = new
        alloc = allocator.allocate(tau - corr, nu_r=nu_r, commit=False)
        pred = compensator.predict(alloc.alpha_rad, alloc.beta_rad, alloc.thrust_n)
        done += 1
    sent, pred, axial = _make_up(allocator, compensator, alloc, pred, nu_r)
    if commit:
        allocator.commit(alloc)
        compensator.commit(pred)
    return CompensatedAllocation(sent, pred, tau, np.asarray(sent.wrench_achieved) + pred.wrench_n, done,
                                 corr + axial)


REPLAN_TOL_N = 1e-3  # re-plan only if c moved by more (1 mN: far below what the loop can track)
LOSS_CAP = 0.2  # at most this fraction of a unit's thrust is made up for (T_cmd <= T / 0.8)


def _correction(comp: TransientCompensator, rows, thrust_n, alpha_rad, beta_rad) -> np.ndarray:
    """The part of the transient of row outputs `rows` (k x 5) at thrust T, angles a, b that is
    taken out of the demand before allocation: the lateral rows F1y, M1z, F2z at weights w1, w2,
    w4, on the axes of LATERAL_AXES only (not yaw), as a spec-4.1 wrench (`rows_wrench`).

    The axial rows are not here: their loss is made up per unit by thrust after the plan
    (`_make_up`), never handed to the allocator as a wrench (see allocate_compensated).
    """
    w = comp.row_weights
    lateral = comp.rows_wrench(rows, thrust_n, alpha_rad, beta_rad, weights=(0.0, w[1], w[2], 0.0, w[4]))
    return lateral * _LATERAL_AXES


_LATERAL_AXES = np.asarray(LATERAL_AXES, dtype=float)


def make_up_thrust(thrust_n, rows, gain: float, weights=COMPENSATED_ROWS, loss_cap: float = LOSS_CAP) -> np.ndarray:
    """Thrust to command so that, after the seed-004 axial loss of `rows`, each unit gives thrust_n.

    Spec 4.1: a unit commanded to T gives T (1 - L) along its own d, L = gain (F1x + F2x) (the rows'
    step means; g = gain T). The compensated loss is L = gain (w0 F1x + w3 F2x), capped at
    loss_cap, so T_cmd = T / (1 - L): the same direction, only more speed (L < 0, a gain, asks
    for less). Pure math; units at T <= 0 stay at 0.
    """
    return _made_up(np.asarray(thrust_n, np.float64), np.asarray(rows, np.float64), float(gain),
                    float(weights[0]), float(weights[3]), float(loss_cap))


@njit(cache=True)
def _made_up(T, rows, gain, w0, w3, loss_cap):
    """`make_up_thrust` compiled (what `_make_up_speeds` calls)."""
    out = np.empty(T.shape[0])
    for i in range(T.shape[0]):
        out[i] = max(T[i], 0.0) / (1.0 - min(gain * (w0 * rows[i, 0] + w3 * rows[i, 3]), loss_cap))
    return out


def yaw_balanced_make_up(grow_n, room_n, yaw_lever_m) -> np.ndarray:
    """Thrust increments (k) to command: each unit's make-up `grow_n` within its headroom `room_n`
    (T_max(J) - T), then, if some unit ran out of room, the make-up of units on the other side of
    the yaw axis cut so that what is left undone has no yaw moment.

    Left undone r_i = grow_i - dT_i along d_i has yaw sum(r_i l_i), l_i = (r_i x d_i)_z the
    unit's yaw lever. A unit at full speed while the others make up in full would leave its own
    loss alone: a lopsided force whose yaw moment (measured, sway +-0.3 m/s, jets at n_max 4 %
    of the time: yaw disturbance x1.35) the heading loop then chases. Units with l_j of the
    other sign give up the fraction f of their make-up with f sum(dT_j |l_j|) = |sum(r_i l_i)|,
    f <= 1. Only yaw is balanced: the rest of the remainder is a small force the position loop
    takes (a common share for all units instead was measured, while this was built, to cost the
    yaw-reversal flight part of its position gain).
    """
    return _balance(np.asarray(grow_n, np.float64), np.asarray(room_n, np.float64),
                    np.asarray(yaw_lever_m, np.float64))


@njit(cache=True)
def _make_up_speeds(n_plan, T_plan, rows, gain, w0, w3, loss_cap, alpha, beta, nu, pos, e1, tp, eff):
    """Commanded speeds of `_make_up` in one compiled call: `make_up_thrust`, the units' T_max(J)
    = T(eff n_max, V_a) (seed 000 eq. 15 at their axial inflow V_a), `yaw_balanced_make_up`, and
    n = (inverse of eq. 15 at V_a) / eff, at most n_max; a dead or idle unit keeps its speed."""
    k = n_plan.shape[0]
    F = jet_frames(alpha, beta, e1)
    va = axial_inflow(nu, pos, F)
    t_max = max_thrust(va, tp, eff)
    grow = _made_up(T_plan, rows, gain, w0, w3, loss_cap)
    room = np.empty(k)
    lever = np.empty(k)
    for i in range(k):
        T = max(T_plan[i], 0.0)
        grow[i] -= T
        room[i] = max(t_max[i], 0.0) - T
        lever[i] = pos[i, 0] * F[i, 0, 1] - pos[i, 1] * F[i, 0, 0]
    dT = _balance(grow, room, lever)
    n = np.empty(k)
    for i in range(k):
        n[i] = n_plan[i]
        if eff[i] > 0.0 and T_plan[i] > 0.0:
            nt = _speed1(T_plan[i] + dT[i], va[i], tp) / eff[i]
            if math.isfinite(nt):
                n[i] = min(nt, tp[7])
    return n


@njit(cache=True)
def _balance(grow, room, lever):
    k = grow.shape[0]
    dT = np.empty(k)
    n_left = 0.0
    for i in range(k):
        dT[i] = min(grow[i], max(room[i], 0.0)) if grow[i] > 0.0 else grow[i]
        n_left += (grow[i] - dT[i]) * lever[i]
    if n_left != 0.0:
        cap = 0.0
        for i in range(k):
            if dT[i] > 0.0 and lever[i] * n_left < 0.0:
                cap += dT[i] * abs(lever[i])
        if cap > 0.0:
            f = min(1.0, abs(n_left) / cap)
            for i in range(k):
                if dT[i] > 0.0 and lever[i] * n_left < 0.0:
                    dT[i] *= 1.0 - f
    return dT


def _make_up(allocator, comp: TransientCompensator, alloc: Allocation, pred: TransientPrediction, nu_r):
    """The plan with each unit's axial loss made up by its own speed, at the planned joint angles.

    Returns (allocation sent, prediction of it, axial wrench c_ax taken out of the demand). The
    speed of T_cmd (`make_up_thrust`) from the inverse of seed-000 eq. 15 at the unit's axial
    inflow, over its efficiency, at most n_max: a unit without headroom makes up only what it
    has left (`yaw_balanced_make_up`), and nothing is re-vectored for it (`_make_up_speeds`).
    c_ax = jets(plan) - jets(sent), so the jets deliver demand - c, c = c_lat + c_ax.
    """
    if not comp.active or comp.gain == 0.0:
        return alloc, pred, np.zeros(6)
    geo = comp.geo
    a, b = alloc.alpha_rad, alloc.beta_rad
    nu = comp._zeros6 if nu_r is None else np.asarray(nu_r, dtype=np.float64)
    if not (nu.shape == (6,) and np.isfinite(nu).all()):
        nu = comp._zeros6
    eff = getattr(allocator, "efficiency", None)
    eff = comp._ones if eff is None else eff
    w = comp.row_weights
    n = _make_up_speeds(alloc.n_rev_s, alloc.thrust_n, pred.rows, comp.gain, w[0], w[3], LOSS_CAP, a, b, nu,
                        geo.position, geo.e1, geo.tp, eff)
    W = getattr(allocator, "W", None)
    W = comp._eye6 if W is None else W
    tau_qp = alloc.wrench_demand
    T, force, achieved, _, _ = alloc_outcome(n, a, b, nu, geo.position, geo.e1, geo.tp, tau_qp, W, eff)
    axial = alloc.wrench_achieved - achieved  # c_ax: minus what the make-up adds
    pred = comp._predict(pred.alpha_rate_rad_s, pred.beta_rate_rad_s, T, comp.alpha, comp.beta,
                         pred.next_alpha_rad, pred.next_beta_rad)
    # against tau_qp - c_ax the sent command leaves the plan's own residual and weighted error
    sent = replace(alloc, n_rev_s=_owned(n), thrust_n=_owned(T), force_body_n=_owned(force),
                   wrench_demand=_owned(tau_qp - axial), wrench_achieved=_owned(achieved))
    return sent, pred, axial


__all__ = [
    "ROWS",
    "COMPENSATED_ROWS",
    "LOSS_CAP",
    "make_up_thrust",
    "yaw_balanced_make_up",
    "REPLAN_TOL_N",
    "LATERAL_AXES",
    "discretise_row",
    "azimuth_yaw_map",
    "azimuth_lever",
    "servo_motion",
    "TransientPrediction",
    "TransientCompensator",
    "compensate",
    "CompensatedAllocation",
    "allocate_compensated",
    "PREVIEW_HORIZON_S",
    "PREVIEW_MOVE_WEIGHT",
    "yaw_loop_model",
    "YawPreviewGains",
    "yaw_preview_gains",
    "YawPreview",
]


# Kernels above compile onboard.model functions into themselves: key their disk cache on it.
key_caches_on(globals(), MODEL_SOURCE, Path(__file__).with_name("allocation.py"))
