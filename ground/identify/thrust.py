"""Thrust model identification (seed 000 sections 5-6): fit K(J) and report residuals per condition.

Pure math: arrays in, frozen dataclasses out. The thrust of one water-jet at propeller speed n
(rev/s), flow speed V (m/s) and oblique angle theta (rad) is (seed 000 eq. 11, 15)

    J = V cos(theta) / (n D),      T = rho D^4 n^2 (kt0 + kt1 J + kt2 J^2).

The coefficients enter linearly, so the fit is an ordinary least squares on the thrust itself
(N, where the load-cell noise lives) rather than on K_T = T / (rho D^4 n^2) (eq. 13), which would
blow the noise up at low n. Residuals are reported the way seed 000 section 6.3 does: the
absolute difference between measured and model thrust, its maximum (with the speed where it
occurs and its share of the measured thrust) and its mean, per flow speed and oblique angle.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ResidualGroup:
    """Residual statistics of one test condition (one flow speed and oblique angle)."""

    v_m_s: float
    angle_rad: float
    n_points: int
    max_residual_n: float  # max |T_meas - T_model|
    mean_residual_n: float  # mean |T_meas - T_model|
    max_at_n_rev_s: float  # propeller speed where the max occurs
    max_relative: float  # max residual / measured thrust at that point


@dataclass(frozen=True)
class ThrustFit:
    """Fitted K(J) = kt0 + kt1 J + kt2 J^2 (seed 000 eq. 14) with its uncertainty and residuals."""

    kt: tuple  # (kt0, kt1, kt2)
    kt_std: tuple  # 1-sigma standard errors of kt
    rmse_n: float
    r2: float
    j_min: float
    j_max: float
    groups: tuple  # ResidualGroup per (flow speed, angle), sorted
    residual_n: np.ndarray  # signed T_meas - T_model per point (same order as the input)


def advance_ratio(n_rev_s, v_m_s, angle_rad, diameter_m):
    """J = V cos(theta) / (n D) (seed 000 eq. 11, the oblique flow enters through its axial part)."""
    n = np.asarray(n_rev_s, float)
    return np.asarray(v_m_s, float) * np.cos(np.asarray(angle_rad, float)) / (n * diameter_m)


def thrust_model(n_rev_s, v_m_s, angle_rad, kt, rho, diameter_m):
    """T = rho D^4 n^2 K(J) (seed 000 eq. 15), no clipping of J."""
    n = np.asarray(n_rev_s, float)
    J = advance_ratio(n, v_m_s, angle_rad, diameter_m)
    K = kt[0] + kt[1] * J + kt[2] * J * J
    return rho * diameter_m ** 4 * n * n * K


def thrust_coefficient(n_rev_s, thrust_n, rho, diameter_m):
    """K_T = T / (rho D^4 n^2) (seed 000 eq. 13, with the nozzle factor folded in as in eq. 15)."""
    n = np.asarray(n_rev_s, float)
    return np.asarray(thrust_n, float) / (rho * diameter_m ** 4 * n * n)


def fit_thrust(n_rev_s, v_m_s, angle_rad, thrust_n, rho: float, diameter_m: float) -> ThrustFit:
    """Least-squares K(J) from thrust measurements (seed 000 eq. 13-15) and section 6.3 residuals."""
    n = np.asarray(n_rev_s, float)
    v = np.asarray(v_m_s, float)
    ang = np.asarray(angle_rad, float)
    T = np.asarray(thrust_n, float)
    if not (n.shape == v.shape == ang.shape == T.shape) or n.ndim != 1:
        raise ValueError("n, v, angle and thrust must be 1-D arrays of one length")
    if n.size < 3:
        raise ValueError(f"need at least 3 measurements to fit 3 coefficients, got {n.size}")
    if np.any(n <= 0):
        raise ValueError("every propeller speed n must be > 0 rev/s (J = V cos(theta) / (n D))")
    J = advance_ratio(n, v, ang, diameter_m)
    scale = rho * diameter_m ** 4 * n * n
    # T = scale * [1, J, J^2] . kt : linear in kt
    A = np.column_stack([scale, scale * J, scale * J * J])
    kt, *_ = np.linalg.lstsq(A, T, rcond=None)
    model = A @ kt
    res = T - model
    dof = max(n.size - 3, 1)
    sigma2 = float(res @ res) / dof
    try:
        cov = sigma2 * np.linalg.inv(A.T @ A)
        kt_std = tuple(float(s) for s in np.sqrt(np.clip(np.diag(cov), 0.0, None)))
    except np.linalg.LinAlgError:
        kt_std = (float("inf"),) * 3
    ss_tot = float(np.sum((T - T.mean()) ** 2))
    r2 = 1.0 - float(res @ res) / ss_tot if ss_tot > 0 else 1.0
    return ThrustFit(
        kt=tuple(float(k) for k in kt),
        kt_std=kt_std,
        rmse_n=float(np.sqrt(np.mean(res ** 2))),
        r2=r2,
        j_min=float(J.min()),
        j_max=float(J.max()),
        groups=residual_groups(n, v, ang, T, res),
        residual_n=res,
    )


def residual_groups(n, v, angle, thrust, residual, decimals: int = 6) -> tuple:
    """Max and mean |residual| per (flow speed, oblique angle), as seed 000 Figures 24 and 26."""
    keys = np.round(np.column_stack([v, angle]), decimals)
    out = []
    for key in sorted({tuple(k) for k in keys}):
        sel = np.all(keys == key, axis=1)
        r = np.abs(residual[sel])
        i = int(np.argmax(r))
        t_at = float(thrust[sel][i])
        out.append(ResidualGroup(
            v_m_s=float(key[0]),
            angle_rad=float(key[1]),
            n_points=int(sel.sum()),
            max_residual_n=float(r[i]),
            mean_residual_n=float(r.mean()),
            max_at_n_rev_s=float(n[sel][i]),
            max_relative=float(r[i] / abs(t_at)) if t_at != 0 else float("inf"),
        ))
    return tuple(out)


def synthesize_thrust_data(kt, rho: float, diameter_m: float, conditions, n_rev_s,
                           noise_rel: float = 0.03, noise_abs_n: float = 0.02, seed: int = 0):
    """Measurements from eq. 15 at each (V, theta) in `conditions` and each speed in `n_rev_s`.

    Noise is Gaussian with sigma = noise_abs_n + noise_rel * T (a load cell read to a few per
    cent, as the scatter of seed 000 Figures 23-26). Returns (n, v, angle, thrust) arrays.
    """
    rng = np.random.default_rng(seed)
    n_all, v_all, a_all = [], [], []
    for v, a in conditions:
        for n in n_rev_s:
            n_all.append(n)
            v_all.append(v)
            a_all.append(a)
    n_arr, v_arr, a_arr = (np.array(x, float) for x in (n_all, v_all, a_all))
    T = thrust_model(n_arr, v_arr, a_arr, kt, rho, diameter_m)
    T = T + rng.standard_normal(T.size) * (noise_abs_n + noise_rel * np.abs(T))
    return n_arr, v_arr, a_arr, T


# Seed 000 section 6.3: 15 speeds at each of three axial flow speeds, then 15 speeds at three
# oblique angles with the flow at 0.22 m/s. The speeds span the jets' working range (rev/s).
SEED000_FLOW_SPEEDS_M_S = (0.1, 0.22, 0.35)
SEED000_OBLIQUE_ANGLES_RAD = tuple(np.deg2rad([10.0, 30.0, 50.0]))
SEED000_OBLIQUE_FLOW_M_S = 0.22


def seed000_conditions() -> tuple:
    """(V, theta) pairs of seed 000 section 6.3.1 and 6.3.2."""
    axial = tuple((v, 0.0) for v in SEED000_FLOW_SPEEDS_M_S)
    oblique = tuple((SEED000_OBLIQUE_FLOW_M_S, a) for a in SEED000_OBLIQUE_ANGLES_RAD)
    return axial + oblique
