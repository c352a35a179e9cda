"""Thrust identification (seed 000 sections 5-6): eq. 15 data back to eq. 14, residuals as sec. 6.3."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ground.identify import thrust as th
from onboard.model import thrust_newton

# Seed 000 eq. 14: pi alpha^2 / 4 K_T = 0.20207 J^2 - 0.30192 J + 0.350165
KT_EQ14 = (0.350165, -0.30192, 0.20207)
RHO = 1000.0
D = 0.0365  # m, the ASR-IV water-jet propeller (vehicle file)


def eq15(n, v, angle, kt=KT_EQ14):
    """T = rho D^4 n^2 (kt0 + kt1 J + kt2 J^2), J = V cos(theta) / (n D), written out here."""
    J = v * np.cos(angle) / (n * D)
    return RHO * D ** 4 * n ** 2 * (kt[0] + kt[1] * J + kt[2] * J ** 2)


def figure9_grid():
    """Seed 000 sec. 4.2.1: up to 1 m/s inflow at >= 3000 rpm keeps J within 0..0.54."""
    n = np.repeat(np.array([3000.0, 3500.0, 4000.0, 4500.0, 5000.0]) / 60.0, 6)
    v = np.tile(np.linspace(0.0, 1.0, 6), 5)
    return n, v, np.zeros_like(n)


def test_noise_free_data_give_eq14_exactly():
    n, v, a = figure9_grid()
    fit = th.fit_thrust(n, v, a, eq15(n, v, a), RHO, D)
    assert fit.kt == pytest.approx(KT_EQ14, abs=1e-10)
    assert fit.rmse_n < 1e-12
    assert fit.j_max == pytest.approx(1.0 / (50.0 * D))  # 0.548, the paper's 0.54


def test_noisy_figure9_data_return_eq14_coefficients():
    n, v, a = figure9_grid()
    rng = np.random.default_rng(7)
    T = eq15(n, v, a)
    T_meas = T * (1 + 0.01 * rng.standard_normal(T.size))  # 1 % scatter, as CFD vs test
    fit = th.fit_thrust(n, v, a, T_meas, RHO, D)
    for k, k_true, s in zip(fit.kt, KT_EQ14, fit.kt_std):
        assert abs(k - k_true) < 3 * s
    # the K(J) curve within 1 % over the paper's J range
    J = np.linspace(0.0, 0.54, 55)
    K_fit = fit.kt[0] + fit.kt[1] * J + fit.kt[2] * J ** 2
    K_true = KT_EQ14[0] + KT_EQ14[1] * J + KT_EQ14[2] * J ** 2
    assert np.max(np.abs(K_fit / K_true - 1)) < 0.01


def test_section63_residual_statistics_fall_in_the_papers_ranges():
    # 15 speeds at 0.1 / 0.22 / 0.35 m/s axial, then 10 / 30 / 50 deg at 0.22 m/s (sec. 6.3.1-6.3.2)
    speeds = np.linspace(2000.0, 4900.0, 15) / 60.0
    conds = [(0.1, 0.0), (0.22, 0.0), (0.35, 0.0)] + [(0.22, math.radians(d)) for d in (10, 30, 50)]
    n = np.repeat(speeds[None, :], len(conds), axis=0).ravel()
    v = np.repeat([c[0] for c in conds], speeds.size)
    a = np.repeat([c[1] for c in conds], speeds.size)
    rng = np.random.default_rng(3)
    T = eq15(n, v, a)
    T_meas = T * (1 + 0.03 * rng.standard_normal(T.size))  # a load cell read to 3 %
    fit = th.fit_thrust(n, v, a, T_meas, RHO, D)
    assert len(fit.groups) == 6 and all(g.n_points == 15 for g in fit.groups)
    for g in fit.groups:
        # paper: max residual 0.28 N (7 %), mean residuals 0.06-0.18 N
        assert g.max_residual_n <= 0.28
        assert 0.02 <= g.mean_residual_n <= 0.18
        assert g.max_relative <= 0.10
    # the statistics are those of |measured - eq. 15 with the fitted kt|
    g = next(g for g in fit.groups if g.v_m_s == 0.35)
    sel = v == 0.35
    r = np.abs(T_meas[sel] - eq15(n[sel], v[sel], a[sel], fit.kt))
    assert g.max_residual_n == pytest.approx(r.max())
    assert g.mean_residual_n == pytest.approx(r.mean())


def test_residual_groups_by_hand():
    n = np.array([10.0, 20.0, 30.0, 10.0, 20.0])
    v = np.array([0.1, 0.1, 0.1, 0.2, 0.2])
    a = np.zeros(5)
    T = np.array([1.0, 2.0, 4.0, 1.0, 2.0])
    res = np.array([0.1, -0.3, 0.2, -0.05, 0.05])
    g1, g2 = th.residual_groups(n, v, a, T, res)
    assert (g1.v_m_s, g1.n_points) == (0.1, 3)
    assert g1.max_residual_n == pytest.approx(0.3)
    assert g1.mean_residual_n == pytest.approx(0.2)
    assert g1.max_at_n_rev_s == 20.0
    assert g1.max_relative == pytest.approx(0.3 / 2.0)
    assert g2.mean_residual_n == pytest.approx(0.05)


def test_fit_model_agrees_with_the_onboard_thrust_model(vehicle):
    # the identification's eq. 15 and the plant's jet_thrust are the same formula inside j_range
    for n, va in ((40.0, 0.0), (60.0, 0.3), (80.0, 0.9)):
        expect = thrust_newton(vehicle, n, va, inflow=True)
        got = th.thrust_model(n, va, 0.0, vehicle.thruster.kt, vehicle.environment.rho, vehicle.thruster.diameter)
        assert got == pytest.approx(expect, rel=1e-12)


def test_bad_input_is_named():
    with pytest.raises(ValueError, match="n must be > 0|propeller speed n"):
        th.fit_thrust(np.array([0.0, 1.0, 2.0]), np.zeros(3), np.zeros(3), np.ones(3), RHO, D)
    with pytest.raises(ValueError, match="at least 3"):
        th.fit_thrust(np.ones(2), np.zeros(2), np.zeros(2), np.ones(2), RHO, D)
