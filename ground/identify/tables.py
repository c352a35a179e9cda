"""Added mass vs depth and damping vs speed tables into vehicle-file keys (seed 003 section 3.2).

Pure math: arrays in, frozen dataclasses out. A user supplies tables from CFD/BEM runs (AQWA,
Fluent) or from tests:
- added mass at several water-entry depths for each attitude (pitch) and degree of freedom;
  seed 003 fits a first-order polynomial per attitude and DOF (Figure 5):
      M_A(l) = m0 + m1 l;
- damping force (moment) at several speeds (rates) for each attitude and DOF; seed 003 fits a
  second-order polynomial (Figure 8 level, Figure 9 surge at 10-40 deg):
      F(v) = c0 + c1 v + c2 v^2.
The vehicle file (spec/vehicle-model.md 2) holds D(v) v = (D_l + D_q |v|) v, which is the
second-order polynomial through the origin, so that form is fitted too and gives the keys
`hydro.linear_damping` and `hydro.quadratic_damping`; `hydro.added_mass` takes each line at
the depth where the body is fully submerged (the spec scales it by the submerged fraction).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

DOFS = ("surge", "sway", "heave", "roll", "pitch", "yaw")


@dataclass(frozen=True)
class AddedMassLine:
    """M_A(depth) = intercept + slope * depth for one attitude and DOF (seed 003 Figure 5)."""

    attitude_rad: float
    dof: str
    intercept: float  # kg or kg m^2 at depth 0
    slope: float  # per metre of depth
    r2: float
    n_points: int
    depth_min_m: float
    depth_max_m: float

    def at(self, depth_m: float) -> float:
        return self.intercept + self.slope * depth_m


@dataclass(frozen=True)
class DampingCurve:
    """F(v) = c0 + c1 v + c2 v^2 (seed 003 Figures 8-9) and the through-origin D_l v + D_q |v| v."""

    attitude_rad: float
    dof: str
    c0: float
    c1: float
    c2: float
    r2: float
    linear: float  # D_l (N s/m or N m s/rad)
    quadratic: float  # D_q (N s^2/m^2 or N m s^2/rad^2)
    r2_origin: float
    n_points: int
    speed_max: float


def _r2(y, model) -> float:
    ss = float(np.sum((y - np.mean(y)) ** 2))
    return 1.0 - float(np.sum((y - model) ** 2)) / ss if ss > 0 else 1.0


def _groups(attitude, dof, decimals: int = 9):
    att = np.round(np.asarray(attitude, float), decimals)
    dof = np.asarray(dof, dtype=object)
    bad = sorted({str(d) for d in dof if d not in DOFS})
    if bad:
        raise ValueError(f"unknown degree(s) of freedom {bad}; expected one of {', '.join(DOFS)}")
    keys = sorted({(float(a), str(d)) for a, d in zip(att, dof)}, key=lambda k: (DOFS.index(k[1]), k[0]))
    for a, d in keys:
        yield a, d, (att == a) & (dof == d)


def fit_added_mass_lines(attitude_rad, depth_m, dof, added_mass) -> tuple:
    """First-order line of added mass vs depth per (attitude, DOF) (seed 003 Figure 5)."""
    depth = np.asarray(depth_m, float)
    ma = np.asarray(added_mass, float)
    if not (depth.shape == ma.shape == np.shape(attitude_rad) == np.shape(dof)):
        raise ValueError("attitude, depth, dof and added_mass must be columns of one length")
    out = []
    for a, d, sel in _groups(attitude_rad, dof):
        x, y = depth[sel], ma[sel]
        if np.unique(x).size < 2:
            raise ValueError(f"attitude {a:.4g} rad, {d}: need added mass at two depths or more, got {x.size} row(s)")
        slope, intercept = np.polyfit(x, y, 1)
        out.append(AddedMassLine(
            attitude_rad=a, dof=d, intercept=float(intercept), slope=float(slope),
            r2=_r2(y, intercept + slope * x), n_points=int(x.size),
            depth_min_m=float(x.min()), depth_max_m=float(x.max()),
        ))
    return tuple(out)


def fit_damping(attitude_rad, dof, speed, force) -> tuple:
    """Second-order damping polynomial per (attitude, DOF) (seed 003 Figures 8-9)."""
    v = np.asarray(speed, float)
    f = np.asarray(force, float)
    if not (v.shape == f.shape == np.shape(attitude_rad) == np.shape(dof)):
        raise ValueError("attitude, dof, speed and force must be columns of one length")
    out = []
    for a, d, sel in _groups(attitude_rad, dof):
        x, y = v[sel], f[sel]
        if np.unique(x).size < 3:
            raise ValueError(f"attitude {a:.4g} rad, {d}: need damping at three speeds or more, got {np.unique(x).size}")
        c2, c1, c0 = np.polyfit(x, y, 2)
        # through the origin, odd in v: F = D_l v + D_q |v| v (spec 2)
        A = np.column_stack([x, np.abs(x) * x])
        (dl, dq), *_ = np.linalg.lstsq(A, y, rcond=None)
        out.append(DampingCurve(
            attitude_rad=a, dof=d, c0=float(c0), c1=float(c1), c2=float(c2),
            r2=_r2(y, c0 + c1 * x + c2 * x * x), linear=float(dl), quadratic=float(dq),
            r2_origin=_r2(y, A @ np.array([dl, dq])), n_points=int(x.size), speed_max=float(np.abs(x).max()),
        ))
    return tuple(out)


def vehicle_values(current: dict, lines=(), curves=(), full_depth_m: float = None,
                   attitude_rad: float = 0.0) -> dict:
    """Vehicle-file keys from the fits at one attitude (default level), other entries kept.

    `current` holds the vehicle's present `hydro.added_mass`, `hydro.linear_damping` and
    `hydro.quadratic_damping` (6-vectors). Added mass takes each line at `full_depth_m`;
    damping takes the through-origin coefficients, clipped at zero (the spec's keys are >= 0).
    """
    out = {k: list(current[k]) for k in ("hydro.added_mass", "hydro.linear_damping", "hydro.quadratic_damping")}
    changed = set()
    for ln in lines:
        if abs(ln.attitude_rad - attitude_rad) < 1e-9:
            if full_depth_m is None:
                raise ValueError("full_depth_m is needed to read the added mass off the depth lines")
            out["hydro.added_mass"][DOFS.index(ln.dof)] = max(ln.at(full_depth_m), 0.0)
            changed.add("hydro.added_mass")
    for c in curves:
        if abs(c.attitude_rad - attitude_rad) < 1e-9:
            i = DOFS.index(c.dof)
            out["hydro.linear_damping"][i] = max(c.linear, 0.0)
            out["hydro.quadratic_damping"][i] = max(c.quadratic, 0.0)
            changed.update({"hydro.linear_damping", "hydro.quadratic_damping"})
    return {k: v for k, v in out.items() if k in changed}
