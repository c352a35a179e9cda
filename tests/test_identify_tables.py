"""Seed 003 sec. 3.2 tables: added-mass lines over depth per attitude, damping polynomials, keys."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ground.identify import tables as tb

DEPTHS = np.linspace(0.05, 0.32, 6)
# (attitude deg, dof, intercept, slope): slopes fall as the pitch grows (seed 003 Fig. 5)
LINES = [(0, "heave", 0.4, 11.5), (15, "heave", 0.35, 9.8), (30, "heave", 0.27, 8.2),
         (0, "surge", 0.33, 9.3), (30, "surge", 0.22, 6.6)]


def line_table(noise=0.0, seed=0):
    rng = np.random.default_rng(seed)
    att, dep, dof, ma = [], [], [], []
    for a, d, c0, c1 in LINES:
        for h in DEPTHS:
            att.append(math.radians(a))
            dep.append(h)
            dof.append(d)
            ma.append((c0 + c1 * h) * (1 + noise * rng.standard_normal()))
    return np.array(att), np.array(dep), np.array(dof, dtype=object), np.array(ma)


def test_added_mass_lines_are_recovered_per_attitude_and_dof():
    fits = tb.fit_added_mass_lines(*line_table())
    assert len(fits) == len(LINES)
    for a, d, c0, c1 in LINES:
        ln = next(f for f in fits if f.dof == d and f.attitude_rad == pytest.approx(math.radians(a)))
        assert ln.intercept == pytest.approx(c0, abs=1e-12)
        assert ln.slope == pytest.approx(c1, rel=1e-12)
        assert ln.r2 == pytest.approx(1.0)
        assert ln.at(0.32) == pytest.approx(c0 + c1 * 0.32)


def test_noisy_lines_keep_the_papers_ordering():
    fits = tb.fit_added_mass_lines(*line_table(noise=0.01, seed=5))
    heave = sorted((f for f in fits if f.dof == "heave"), key=lambda f: f.attitude_rad)
    assert heave[0].slope > heave[1].slope > heave[2].slope  # 0 deg largest, 30 deg smallest
    for f, (_, _, c0, c1) in zip(heave, LINES[:3]):
        assert f.slope == pytest.approx(c1, rel=0.05)


def test_damping_polynomial_and_vehicle_form():
    dl, dq = 2.6, 24.0
    v = np.array([0.2, 0.4, 0.6, 0.8, 1.0])
    F = dl * v + dq * v * v
    (c,) = tb.fit_damping(np.zeros(5), np.array(["heave"] * 5, dtype=object), v, F)
    assert (c.c0, c.c1, c.c2) == pytest.approx((0.0, dl, dq), abs=1e-9)
    assert (c.linear, c.quadratic) == pytest.approx((dl, dq), rel=1e-12)
    # negative speeds: the vehicle form D_l v + D_q |v| v is odd, the fit follows it
    (c2,) = tb.fit_damping(np.zeros(10), np.array(["surge"] * 10, dtype=object),
                           np.concatenate([-v, v]), np.concatenate([-F, F]))
    assert (c2.linear, c2.quadratic) == pytest.approx((dl, dq), rel=1e-12)


def test_vehicle_values_replace_only_what_was_fitted(vehicle):
    lines = tb.fit_added_mass_lines(*line_table())
    v = np.array([0.2, 0.4, 0.6, 0.8, 1.0])
    curves = tb.fit_damping(np.zeros(5), np.array(["yaw"] * 5, dtype=object), v, 0.05 * v + 0.03 * v * v)
    current = {k: vehicle.get(k) for k in ("hydro.added_mass", "hydro.linear_damping", "hydro.quadratic_damping")}
    out = tb.vehicle_values(current, lines, curves, full_depth_m=0.32)
    ma = list(vehicle.hydro.added_mass)
    ma[2] = 0.4 + 11.5 * 0.32  # heave line at full depth, level attitude
    ma[0] = 0.33 + 9.3 * 0.32
    assert out["hydro.added_mass"] == pytest.approx(ma)
    assert out["hydro.linear_damping"][5] == pytest.approx(0.05)
    assert out["hydro.quadratic_damping"][5] == pytest.approx(0.03)
    assert out["hydro.linear_damping"][:5] == list(vehicle.hydro.linear_damping[:5])
    vehicle.with_values(out)  # valid vehicle keys


def test_bad_tables_are_named():
    with pytest.raises(ValueError, match="unknown degree"):
        tb.fit_added_mass_lines(np.zeros(2), np.array([0.1, 0.2]), np.array(["bob", "bob"], dtype=object), np.ones(2))
    with pytest.raises(ValueError, match="two depths"):
        tb.fit_added_mass_lines(np.zeros(2), np.array([0.1, 0.1]), np.array(["heave"] * 2, dtype=object), np.ones(2))
    with pytest.raises(ValueError, match="three speeds"):
        tb.fit_damping(np.zeros(2), np.array(["heave"] * 2, dtype=object), np.array([0.1, 0.2]), np.ones(2))
