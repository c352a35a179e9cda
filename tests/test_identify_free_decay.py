"""Free decay (seed 001 sec. 3.2-3.3): Table 7 from its omega_n and zeta, pendulum eq. 14-16, HIL rig."""

from __future__ import annotations

import math

import numpy as np
import pytest

from ground.identify import free_decay as fd
from hil.plant import Plant
from onboard.sensors import depth_from_pressure

# Seed 001 Table 2 (spring-rig model) and Table 7 (results): omega_n rad/s, zeta, C_m
K_SPRING = 63.6  # N/m
M_MODEL = 0.97  # kg
V_MODEL = 344868e-9  # m^3 (344,868 mm^3)
TABLE7 = {"x": (7.1142, 0.1971, 0.8172), "y": (7.8268, 0.109, 0.1945), "z": (6.8188, 0.1418, 1.1564)}
ENCODER_STEP = 1e-3 / 2.45  # m, LX-EP-40 resolution 2.45 count/mm


def quantised_trace(omega_n, zeta, amplitude=0.04, duration=8.0, rate=100.0):
    """y = A exp(-zeta w t) cos(w_d t) read by the seed's linear encoder (quantised)."""
    t = np.arange(int(duration * rate) + 1) / rate
    wd = omega_n * math.sqrt(1 - zeta ** 2)
    y = amplitude * np.exp(-zeta * omega_n * t) * np.cos(wd * t)
    return t, np.round(y / ENCODER_STEP) * ENCODER_STEP


@pytest.mark.parametrize("axis", ["x", "y", "z"])
def test_table7_added_mass_from_its_omega_n_and_zeta(axis):
    w, z, cm_printed = TABLE7[axis]
    t, y = quantised_trace(w, z)
    fit = fd.spring_free_decay(t, y, M_MODEL, K_SPRING, V_MODEL, 0.1)
    assert fit.omega_n_rad_s == pytest.approx(w, rel=5e-4)
    assert fit.zeta == pytest.approx(z, rel=5e-3)
    # eq. 7 and eq. 3 with Table 2's m, V and K
    cm_eq7 = (K_SPRING / w ** 2 - M_MODEL) / (1000.0 * V_MODEL)
    assert fit.cm == pytest.approx(cm_eq7, rel=0.01)
    # The printed C_m: z agrees with eq. 7 to 0.3 %; the printed x and y values both sit 1.70 %
    # below eq. 7 (they imply rho V = 0.3507 kg instead of Table 2's 0.3449 kg), so they are
    # reproduced within 2 %, not 1 %.
    tol = 0.01 if axis == "z" else 0.02
    assert fit.cm == pytest.approx(cm_printed, rel=tol)


def test_log_decrement_is_exact_on_a_linear_decay():
    t, y = fd.synthesize_linear_decay(5.0, 0.08, 0.03, 10.0, 200.0, offset=0.2)
    dec = fd.log_decrement(t, y, offset=0.2)
    assert dec.omega_n_rad_s == pytest.approx(5.0, rel=1e-4)
    assert dec.zeta == pytest.approx(0.08, rel=1e-3)
    # delta = 2 pi zeta / sqrt(1 - zeta^2)
    assert dec.delta == pytest.approx(2 * math.pi * 0.08 / math.sqrt(1 - 0.08 ** 2), rel=1e-3)


def test_eq6_fit_recovers_added_mass_k_l_k_q_and_cd():
    m, K, m_add, D = 0.97, 63.6, 0.35, 0.08
    cd = 1.2
    k_q = 0.5 * 1000.0 * cd * D ** 2  # (1/2) rho C_D D^2
    k_l = 0.3
    t, y = fd.synthesize_spring_decay(m + m_add, K, k_l, k_q, 0.04, 8.0, 100.0, noise=2e-4, seed=1)
    fit = fd.spring_free_decay(t, y, m, K, V_MODEL, D)
    assert fit.chin_added_mass_kg == pytest.approx(m_add, rel=0.01)
    assert fit.k_l_n_s_m == pytest.approx(k_l, rel=0.05)
    assert fit.k_q_n_s2_m2 == pytest.approx(k_q, rel=0.03)
    assert fit.chin_cd == pytest.approx(cd, rel=0.03)
    # eq. 7 through omega_n is close too (damping barely moves the frequency)
    assert fit.added_mass_kg == pytest.approx(m_add, rel=0.02)


def test_eq9_cd_is_the_energy_equivalent_of_quadratic_damping():
    # pure quadratic damping: eq. 9 over the first period gives C_D within 3 %
    m, K, m_add, D, cd = 1.0, 100.0, 0.5, 0.1, 1.0
    k_q = 0.5 * 1000.0 * cd * D ** 2
    t, y = fd.synthesize_spring_decay(m + m_add, K, 0.0, k_q, 0.03, 10.0, 200.0)
    fit = fd.spring_free_decay(t, y, m, K, 1e-3, D)
    assert fit.cd == pytest.approx(cd, rel=0.03)
    assert fit.chin_cd == pytest.approx(cd, rel=1e-3)


# Seed 001 Table 3 pendulum model (PVC, 22 % scale)
M_P, V_P, R_P, A_P = 0.146, 107597e-9, 0.5, 0.0045


def test_pendulum_eq14_to_16_on_a_morison_trace():
    m_add, k_d = 0.089, 0.6  # kg; K_D = (1/2) rho C_D A_wet
    t, th = fd.synthesize_pendulum(M_P, V_P, R_P, m_add, 0.0, k_d, math.radians(15), 20.0, 100.0)
    fit = fd.pendulum_free_decay(t, th, M_P, V_P, R_P, A_P)
    B = 1000.0 * V_P * 9.81
    a1 = (B - M_P * 9.81) / ((M_P + m_add) * R_P)  # eq. 12 divided by (m + m') r
    a2 = k_d * R_P / (M_P + m_add)
    assert fit.a1 == pytest.approx(a1, rel=1e-4)
    assert fit.a2 == pytest.approx(a2, rel=1e-3)
    assert fit.added_mass_kg == pytest.approx(m_add, rel=1e-3)  # eq. 15
    assert fit.cd == pytest.approx(2 * k_d / (1000.0 * A_P), rel=1e-3)  # eq. 16
    assert fit.cm == pytest.approx(m_add / (1000.0 * V_P), rel=1e-3)


def test_pendulum_chin_form_with_imu_noise():
    m_add, k_l, k_q = 0.089, 0.05, 0.6
    t, th = fd.synthesize_pendulum(M_P, V_P, R_P, m_add, k_l, k_q, math.radians(15), 20.0, 100.0,
                                   noise_rad=0.002, seed=4)
    fit = fd.pendulum_free_decay(t, th, M_P, V_P, R_P, A_P)
    assert fit.chin_added_mass_kg == pytest.approx(m_add, rel=0.01)
    assert fit.k_l_n_s_m == pytest.approx(k_l, rel=0.05)
    assert fit.k_q_n_s2_m2 == pytest.approx(k_q, rel=0.03)
    # the Morison-only form of eq. 14 cannot hold the linear term: it fits worse
    assert fit.rmse_rad > 2 * fit.chin_rmse_rad


@pytest.mark.parametrize("noise", [False, True])
def test_hil_spring_rig_gives_back_the_vehicle_heave_added_mass(vehicle, noise):
    v = vehicle.with_effects(surface_proximity=False, wall_proximity=False)
    K = 400.0
    plant = Plant(v, dt_s=0.002, depth_m=0.5, rig_stiffness=[0.0, 0.0, K], noise=noise, seed=2)
    plant.state[2] += 0.05  # launch 5 cm below the rest point
    s = plant.advance(20.0)
    t = np.array([p.time_s for p in s.pressure])
    y = np.array([depth_from_pressure(p.press_abs_pa, v) for p in s.pressure])
    fit = fd.spring_free_decay(t, y, v.body.mass, K, v.body.volume, 2 * v.body.radius, v.environment.rho)
    heave = v.hydro.added_mass[2]  # 4.1 kg
    assert fit.added_mass_kg == pytest.approx(heave, rel=0.02)  # eq. 7
    assert fit.chin_added_mass_kg == pytest.approx(heave, rel=0.01)  # eq. 6 fitted
    assert fit.k_q_n_s2_m2 == pytest.approx(v.hydro.quadratic_damping[2], rel=0.03)
    assert fit.k_l_n_s_m == pytest.approx(v.hydro.linear_damping[2], rel=0.01 if not noise else 0.15)
    # the rest point: buoyancy minus weight lifts the body by (rho V - m) g / K
    lift = (v.environment.rho * v.body.volume - v.body.mass) * v.environment.g / K
    assert fit.equilibrium_m == pytest.approx(0.5 - lift, abs=2e-4)


def test_bad_traces_are_named():
    with pytest.raises(ValueError, match="at least 20 samples"):
        fd.spring_free_decay(np.arange(5.0), np.zeros(5), 1.0, 1.0, 1.0, 1.0)
    t = np.arange(100) * 0.01
    with pytest.raises(ValueError, match="strictly increasing"):
        fd.spring_free_decay(t[::-1], np.sin(t), 1.0, 1.0, 1.0, 1.0)
    with pytest.raises(ValueError, match="extrema"):
        fd.spring_free_decay(t, np.zeros(100) + 1e-3 * t, 1.0, 1.0, 1.0, 1.0)
    with pytest.raises(ValueError, match="heavier than the water"):
        fd.pendulum_free_decay(t, np.sin(t), 0.1, 1e-3, 0.5, 0.01)
    with pytest.raises(ValueError, match="spring must be"):
        fd.spring_free_decay(t, np.sin(t), 1.0, -3.0, 1.0, 1.0)
