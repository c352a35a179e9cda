"""A data-driven term for a residual no known effect explains (PySINDy-style STLSQ).

Sequentially thresholded least squares (Brunton, Proctor & Kutz 2016, PNAS 113(15), Alg. 1):
fit the residual force of each axis on a library of state and input features, zero every
coefficient whose contribution is below `threshold` of the residual's spread, refit on the
survivors, repeat. The library and the optimiser are plain arguments, as PySINDy injects them.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from . import replay


def feature_library(traj: replay.Trajectory, vehicle, act: np.ndarray) -> tuple[np.ndarray, list[str]]:
    """(N, F) features and their names: 1, nu, |nu| nu, gravity direction, position in body axes,
    depth terms, thrust."""
    nu = traj.nu
    names = ["1"]
    cols = [np.ones(len(nu))]
    sym = ("u", "v", "w", "p", "q", "r")
    for i, s in enumerate(sym):
        cols.append(nu[:, i])
        names.append(s)
    for i, s in enumerate(sym):
        cols.append(np.abs(nu[:, i]) * nu[:, i])
        names.append(f"{s}|{s}|")
    R = replay.rotation_rows(traj.quat)
    for i, s in enumerate(("gx", "gy")):  # R^T e3: gravity direction in body axes (gz ~ 1: the constant)
        cols.append(R[:, 2, i])
        names.append(s)
    pb = np.einsum("nji,nj->ni", R, traj.pos_ned_m)  # R^T p: a position-dependent force (tether, spring)
    for i, s in enumerate(("xb", "yb", "zb")):
        cols.append(pb[:, i])
        names.append(s)
    depth = traj.pos_ned_m[:, 2] - vehicle.environment.surface_depth
    cols.append(depth)
    names.append("depth")
    cols.append(1.0 / np.maximum(vehicle.environment.floor_depth - traj.pos_ned_m[:, 2], 0.05))
    names.append("1/floor_gap")
    k = vehicle.n_units
    n = act[:, :k]
    for i in range(k):
        cols.append((n[:, i] / vehicle.thruster.n_max) ** 2)
        names.append(f"n{i + 1}^2")
    return np.column_stack(cols), names


@dataclass(frozen=True)
class SparseTerm:
    coefficients_: np.ndarray  # (F, 6) force per feature per axis
    names: tuple
    formula: str


def stlsq(X: np.ndarray, y: np.ndarray, threshold: float = 0.05, max_iter: int = 10, ridge: float = 1e-6):
    """Sequentially thresholded least squares with columns standardised, per output column;
    `ridge` is per sample (the penalty is ridge * N on standardised coefficients)."""
    scale = np.sqrt(np.mean(X ** 2, axis=0))
    scale[scale == 0] = 1.0
    Xs = X / scale
    coef = np.zeros((X.shape[1], y.shape[1]))
    for j in range(y.shape[1]):
        keep = np.ones(X.shape[1], bool)
        spread = np.sqrt(np.mean(y[:, j] ** 2))
        c = np.zeros(X.shape[1])
        for _ in range(max_iter):
            A = Xs[:, keep]
            sol = np.linalg.solve(A.T @ A + ridge * len(A) * np.eye(A.shape[1]), A.T @ y[:, j])
            c = np.zeros(X.shape[1])
            c[keep] = sol
            small = np.abs(c) < threshold * spread
            if not (keep & small).any():
                break
            keep &= ~small
            if not keep.any():
                break
        coef[:, j] = c / scale
    return coef


def fit_sparse(traj, vehicle, act, force_residual: np.ndarray, idx: np.ndarray, threshold: float = 0.1) -> SparseTerm:
    X, names = feature_library(traj, vehicle, act)
    coef = stlsq(X[idx], force_residual[idx], threshold, ridge=1e-2)
    parts = []
    for j, axis in enumerate(replay.AXES):
        terms = [f"{coef[i, j]:+.4g} {names[i]}" if names[i] != "1" else f"{coef[i, j]:+.4g}"
                 for i in range(len(names)) if coef[i, j] != 0.0]
        if terms:
            unit = "N" if j < 3 else "N m"
            parts.append(f"{axis} += ({' '.join(terms)}) {unit}")
    return SparseTerm(coef, tuple(names), "; ".join(parts) if parts else "(no term)")


def sparse_force(term: SparseTerm, traj, vehicle, act) -> np.ndarray:
    X, _ = feature_library(traj, vehicle, act)
    return X @ term.coefficients_

