"""Fixed two-way thrusters (spec 3.1, issue 17): the thrust curve, the model's force, the motor
lag, the PWM maps, the heavy-layout allocation against a hand-written mixing matrix, compensation
off, and the vehicle file's checks. Every expectation is computed by hand or read independently
from ../shared/data/t200/T200_PWM_N.csv."""

from __future__ import annotations

import csv
import math

import numpy as np
import pytest

from conftest import SHARED, shared_file
from hil.plant import Plant
from onboard import model
from onboard.allocation import AllocationConfig, FixedGeometry, FixedQpAllocator, allocator_for
from onboard.compensation import TransientCompensator, allocate_compensated
from onboard.fixed import pwm_of_thrust, thrust_limits, thrust_of_pwm
from onboard.pwm import command_to_pwm, pwm_to_command
from onboard.vehicle import DEFAULT_VEHICLE, VehicleFileError, load_vehicle, parse_vehicle

HEAVY = load_vehicle("bluerov2_heavy")
FT = HEAVY.fixed_thruster
HEAVY_TEXT = (DEFAULT_VEHICLE.parent / "bluerov2_heavy.toml").read_text()
S = 0.70711


def t200_16v() -> dict[int, float]:
    rows = csv.DictReader(open(shared_file(SHARED / "data" / "t200" / "T200_PWM_N.csv")))
    return {int(r["pwm_us"]): float(r["force_N_16V"]) for r in rows}


# --- the thrust curve ----------------------------------------------------------------------------

def test_t200_curve_gives_every_table_point_exactly():
    table = t200_16v()
    assert len(table) == 201
    pwm = np.array(sorted(table))
    assert np.array_equal(thrust_of_pwm(FT, pwm), np.array([table[p] for p in pwm]))


def test_t200_curve_between_points_dead_band_and_reverse():
    # 1602 us: halfway between 1600 (5.916129922443999 N) and 1604 (6.271987361388 N)
    assert thrust_of_pwm(FT, [1602])[0] == pytest.approx(0.5 * (5.916129922443999 + 6.271987361388), abs=1e-12)
    # 1601 us: a quarter of the way
    assert thrust_of_pwm(FT, [1601])[0] == pytest.approx(5.916129922443999 + 0.25 * (6.271987361388 - 5.916129922443999))
    # the 16 V dead band: 1472..1528 us give nothing; 1468 already pushes backwards
    assert np.all(thrust_of_pwm(FT, [1472, 1490, 1500, 1510, 1528]) == 0.0)
    assert thrust_of_pwm(FT, [1468])[0] == pytest.approx(-0.355857438944)
    # reverse: 1300 us and full reverse; reverse is weaker than forward (T200: 39.9 N against 51.4 N)
    assert thrust_of_pwm(FT, [1300])[0] == pytest.approx(-14.100851018156)
    assert thrust_of_pwm(FT, [1100])[0] == pytest.approx(-39.9079290382407)
    assert thrust_limits(FT) == pytest.approx((-39.9079290382407, 51.4362273206973))
    # beyond the ESC's range a width is clipped
    assert thrust_of_pwm(FT, [1000, 2000]) == pytest.approx([-39.9079290382407, 51.4362273206973])


def test_inverse_curve_round_trips_and_zero_is_neutral():
    T = np.array([-39.0, -14.100851018156, -1.0, 0.0, 0.5, 5.916129922443999, 50.0])
    pwm = pwm_of_thrust(FT, T)
    assert pwm[3] == 1500.0 and pwm[1] == pytest.approx(1300.0) and pwm[5] == pytest.approx(1600.0)
    assert thrust_of_pwm(FT, pwm) == pytest.approx(T, abs=1e-9)
    assert pwm_of_thrust(FT, [100.0, -100.0]) == pytest.approx([1900.0, 1100.0])  # beyond reach: the ends


def _with_curve(curve: str) -> str:
    """bluerov2_heavy.toml with its [fixed_thruster] replaced."""
    head, rest = HEAVY_TEXT.split("\n[fixed_thruster]", 1)
    tail = rest[rest.index("\n[[fixed]]"):]
    return head + "\n[fixed_thruster]\n" + curve + "\n" + tail


def test_voltage_column_is_interpolated_between_columns():
    v = parse_vehicle(_with_curve(
        "time_constant = 0.05\npwm_range = [1100, 1900]\nvoltage = 16.0\ntable_voltages = [14.0, 18.0]\n"
        "table_pwm = [1100, 1500, 1900]\ntable_thrust = [[-30.0, 0.0, 40.0], [-46.0, 0.0, 60.0]]"))
    # 16 V is halfway: -38 N, 0, 50 N; 1700 us halfway again: 25 N
    assert thrust_of_pwm(v.fixed_thruster, [1100, 1500, 1900, 1700]) == pytest.approx([-38.0, 0.0, 50.0, 25.0])


def test_coefficient_model_hand_computed():
    v = parse_vehicle(_with_curve(
        "time_constant = 0.05\npwm_range = [1100, 1900]\ndead_band = [1480, 1520]\n"
        "forward = [10.0, 30.0]\nreverse = [8.0, 20.0]"))
    ft = v.fixed_thruster
    # 1710 us: s = (1710 - 1520) / (1900 - 1520) = 0.5 -> 10 * 0.5 + 30 * 0.25 = 12.5 N
    # 1290 us: s = (1480 - 1290) / (1480 - 1100) = 0.5 -> -(8 * 0.5 + 20 * 0.25) = -9 N
    assert thrust_of_pwm(ft, [1710, 1290, 1500, 1900, 1100]) == pytest.approx([12.5, -9.0, 0.0, 40.0, -28.0])
    assert pwm_of_thrust(ft, [12.5, -9.0, 0.0]) == pytest.approx([1710.0, 1290.0, 1500.0], abs=0.5)


# --- the model -------------------------------------------------------------------------------------

def test_one_thruster_pushes_and_turns_the_heavy_as_computed_by_hand():
    """Thruster 1 (front right, d = (-1, 1, 0)/sqrt 2 at r = (0.14, 0.092, 0.011)) at 10 N, at rest,
    level, no lag: u' = F_x / (m + X_udot), r' = N / (I_z + N_rdot), N = r_x F_y - r_y F_x."""
    v = HEAVY.with_effects(motor_lag=False)
    p = model.pack_params(v)
    u = np.zeros(3 * 8)
    u[0] = 10.0
    x = model.initial_state(v, 1.0, u)
    model.project(x, u, p)
    xdot = np.zeros_like(x)
    thrust = model.derivative(x, u, p, xdot)
    assert thrust == pytest.approx([10.0] + [0.0] * 7)
    Fx, Fy = -10 * S, 10 * S
    assert xdot[7] == pytest.approx(Fx / (13.5 + 6.3567), rel=1e-5)
    assert xdot[8] == pytest.approx(Fy / (13.5 + 7.1206), rel=1e-5)
    Mz = 0.14 * Fy - 0.092 * Fx  # 1.6405 N m
    assert xdot[12] == pytest.approx(Mz / (0.37 + 0.2215), rel=1e-5)
    # roll and pitch from the 11 mm the thruster sits below the CG: K = -r_z F_y, M = r_z F_x
    assert xdot[10] == pytest.approx(-0.011 * Fy / (0.26 + 0.1858), rel=1e-4)
    assert xdot[11] == pytest.approx(0.011 * Fx / (0.23 + 0.1348), rel=1e-4)


def test_motor_lag_is_first_order_with_the_files_time_constant():
    pwm = [1500] * 16
    pwm[4] = 1700  # thruster 5 (vertical)
    cmd = pwm_to_command(HEAVY, pwm)
    t_cmd = cmd[4]
    assert t_cmd == pytest.approx(float(thrust_of_pwm(FT, [1700])[0]))
    plant = Plant(HEAVY, dt_s=0.001, depth_m=2.0, noise=False, command=cmd)
    for t in (0.05, 0.1, 0.2):
        plant.advance(t)
        assert plant.state[13 + 4] == pytest.approx(t_cmd * (1 - math.exp(-t / 0.05)), rel=1e-6)
    assert np.all(plant.state[13:21][[0, 1, 2, 3, 5, 6, 7]] == 0.0)
    lay = model.StateLayout(8)
    assert np.all(plant.state[lay.alpha] == 0) and np.all(plant.state[lay.transient] == 0)


def test_neutral_pwm_means_no_thrust_and_no_pulse_means_the_esc_stops():
    assert np.all(pwm_to_command(HEAVY, [1500] * 16) == 0.0)
    assert np.all(pwm_to_command(HEAVY, [0] * 16) == 0.0)
    c = pwm_to_command(HEAVY, [1900, 1100] + [1500] * 14)
    assert c[:2] == pytest.approx([51.4362273206973, -39.9079290382407])
    assert list(command_to_pwm(HEAVY, c)[:8]) == [1900, 1100] + [1500] * 6


# --- allocation: the heavy layout against a hand-written mixing matrix -----------------------------

# Columns thrusters 1-8; rows X, Y, Z (N per N), K, M, N (N m per N). Horizontal thrusters at
# (+-0.14 or -0.15, +-0.092, 0.011), d = (-+1, +-1, 0)/sqrt 2; vertical at (+-0.118, +-0.215, -0.053),
# d = (0, 0, 1). Moment r x d = (r_y d_z - r_z d_y, r_z d_x - r_x d_z, r_x d_y - r_y d_x).
B_HEAVY = np.array([
    [-S, -S, S, S, 0, 0, 0, 0],
    [S, -S, S, -S, 0, 0, 0, 0],
    [0, 0, 0, 0, 1, 1, 1, 1],
    [-0.011 * S, 0.011 * S, -0.011 * S, 0.011 * S, 0.215, -0.215, 0.215, -0.215],
    [-0.011 * S, -0.011 * S, 0.011 * S, 0.011 * S, -0.118, -0.118, 0.118, 0.118],
    [(0.14 + 0.092) * S, -(0.14 + 0.092) * S, -(0.15 + 0.092) * S, (0.15 + 0.092) * S, 0, 0, 0, 0],
])
# ArduSub's heavy frame, libraries/AP_Motors/AP_Motors6DOF.cpp SUB_FRAME_VECTORED_6DOF, per motor:
# (roll, pitch, yaw, throttle, forward, lateral). Throttle up is -Z; pitch up is +M.
ARDUSUB_VECTORED_6DOF = [
    (0, 0, 1, 0, -1, 1), (0, 0, -1, 0, -1, -1), (0, 0, -1, 0, 1, 1), (0, 0, 1, 0, 1, -1),
    (1, -1, 0, -1, 0, 0), (-1, -1, 0, -1, 0, 0), (1, 1, 0, -1, 0, 0), (-1, 1, 0, -1, 0, 0),
]


def test_heavy_effectiveness_is_the_hand_written_mixing_matrix():
    E = FixedGeometry(HEAVY).E
    assert E == pytest.approx(B_HEAVY, abs=1e-5)
    assert np.linalg.matrix_rank(E) == 6
    assert model.effectiveness(HEAVY, np.zeros(8), np.zeros(8)) == pytest.approx(B_HEAVY, abs=1e-5)


def test_ardusub_mixing_pushes_the_model_the_way_it_means():
    """Every nonzero factor of ArduSub's heavy-frame matrix has the sign of our column for that
    axis, so stock ArduSub's mixing flies this vehicle file."""
    E = FixedGeometry(HEAVY).E
    axes = {"roll": E[3], "pitch": E[4], "yaw": E[5], "throttle": -E[2], "forward": E[0], "lateral": E[1]}
    for i, factors in enumerate(ARDUSUB_VECTORED_6DOF):
        for name, f in zip(("roll", "pitch", "yaw", "throttle", "forward", "lateral"), factors):
            if f:
                assert np.sign(axes[name][i]) == f, (i + 1, name)


@pytest.mark.parametrize("demand", [
    [10, 0, 0, 0, 0, 0], [0, 8, 0, 0, 0, 0], [0, 0, -20, 0, 0, 0], [0, 0, 0, 1.0, 0, 0],
    [0, 0, 0, 0, 1.0, 0], [0, 0, 0, 0, 0, 2.0], [5, -3, 4, 0.2, -0.3, 0.5],
])
def test_qp_equals_weighted_pseudo_inverse_within_limits(demand):
    alloc = FixedQpAllocator(HEAVY, 0.01)
    a = alloc.allocate(demand, commit=False)
    assert a.status == "solved" and not a.fallback
    t = alloc.unconstrained(demand)
    assert a.thrust_n == pytest.approx(t, abs=2e-3)
    assert a.wrench_achieved == pytest.approx(B_HEAVY @ a.thrust_n, abs=1e-3)
    # the effort term costs a little: within 1 % of the demand's size
    assert np.abs(a.residual_wrench).max() < 0.01 * np.abs(demand).max() + 1e-3
    assert list(a.alpha_rad) == [0.0] * 8 and a.command[:8] == pytest.approx(a.thrust_n)


def test_qp_saturates_at_the_curves_ends():
    alloc = FixedQpAllocator(HEAVY, 0.01)
    a = alloc.allocate([200, 0, 0, 0, 0, 0], commit=False)
    assert a.thrust_n[:2] == pytest.approx([-39.9079290382407] * 2, abs=1e-3)  # reverse is the weak side
    assert np.all(a.thrust_n[2:4] <= 51.4362273206973 + 1e-6)
    assert a.wrench_achieved[0] == pytest.approx(2 * 39.9079 * S + S * a.thrust_n[2:4].sum(), abs=1e-2)
    assert list(a.pwm_us(HEAVY)[:2]) == [1100, 1100]


def test_a_dead_thruster_gets_nothing_and_the_rest_cover():
    alloc = FixedQpAllocator(HEAVY, 0.01)
    alloc.set_health([1, 1, 1, 1, 0, 1, 1, 1])
    a = alloc.allocate([0, 0, -20, 0, 0, 0], commit=False)
    assert a.thrust_n[4] == pytest.approx(0.0, abs=1e-6)
    assert a.wrench_achieved[2] == pytest.approx(-20, abs=0.5)


def test_compensation_is_off_where_no_joint_moves():
    alloc = allocator_for(HEAVY, 0.01)
    comp = TransientCompensator(HEAVY, 0.01)
    c = allocate_compensated(alloc, comp, [5, 0, -10, 0, 0, 0.5])
    plain = FixedQpAllocator(HEAVY, 0.01).allocate([5, 0, -10, 0, 0, 0.5])
    assert np.array_equal(c.prediction.wrench_n, np.zeros(6)) and c.iterations == 0
    assert c.allocation.thrust_n == pytest.approx(plain.thrust_n, abs=1e-9)
    assert np.array_equal(c.wrench_total, c.allocation.wrench_achieved)


def test_allocation_config_scales_from_the_thrusters():
    cfg = AllocationConfig.from_vehicle(HEAVY)
    assert cfg.force_scale_n == pytest.approx(51.4362273206973)
    arms = [math.dist((0, 0, 0), f.position) for f in HEAVY.fixed]
    assert cfg.moment_arm_m == pytest.approx(sum(arms) / 8)


# --- asr4 behind ArduSub: the [pwm] neutral option ------------------------------------------------

def test_jet_neutral_makes_ardusubs_1500_us_no_thrust(vehicle):
    v = vehicle.with_values({"pwm.jet_neutral": 1500})
    nmax = v.thruster.n_max
    c = pwm_to_command(v, [1500, 1900, 1700, 1300] + [1500] * 12)
    assert c[:4] == pytest.approx([0.0, nmax, 0.5 * nmax, 0.0])
    assert list(command_to_pwm(v, c)[:4]) == [1500, 1900, 1700, 1500]
    assert pwm_to_command(vehicle, [1500] * 16)[0] == pytest.approx(0.5 * nmax)  # without it: half speed


# --- the vehicle file's checks: one clear line each --------------------------------------------------

@pytest.mark.parametrize("old,new,says", [
    ("direction = [0.0, 0.0, 1.0]\n[[fixed]]   # 6", "direction = [0.0, 0.0, 2.0]\n[[fixed]]   # 6",
     "fixed[4].direction: expected a unit vector"),
    ("fixed_channels = [1, 2, 3, 4, 5, 6, 7, 8]", "fixed_channels = [1, 2, 3, 4, 5, 6, 7]",
     "pwm.fixed_channels: expected 8 channels, one per [[fixed]] thruster"),
    ("fixed_channels = [1, 2, 3, 4, 5, 6, 7, 8]", "fixed_channels = [1, 2, 3, 4, 5, 6, 7, 7]",
     "channel 7 is already in pwm.fixed_channels"),
    ("voltage = 16.0", "voltage = 12.0", "fixed_thruster.voltage: expected a supply within the table's 16-16 V"),
    ("table_voltages = [16.0]", "table_voltages = [16.0]\ndead_band = [1480, 1520]",
     "fixed_thruster: a table (table_pwm, table_thrust, table_voltages, voltage) or coefficients (dead_band), not both"),
    ("1100, 1104, 1108,", "1100, 1108, 1104,", "fixed_thruster.table_pwm: expected at least two widths, strictly increasing"),
    ("time_constant = 0.05 ", "time_constant = 50.0 ", "fixed_thruster.time_constant 50 s: expected 0.0001-10 s; ms?"),
])
def test_bad_fixed_thruster_files_say_one_clear_line(old, new, says):
    assert old in HEAVY_TEXT
    with pytest.raises(VehicleFileError) as exc:
        parse_vehicle(HEAVY_TEXT.replace(old, new, 1), source="heavy.toml")
    msg = str(exc.value)
    assert "\n" not in msg and msg.startswith("heavy.toml: invalid vehicle file: ") and says in msg, msg


def test_a_table_row_of_the_wrong_length_is_named():
    text = HEAVY_TEXT.replace("-39.9079290382407, ", "", 1)
    with pytest.raises(VehicleFileError, match=r"table_thrust\[0\]: expected 201 values, one per table_pwm entry"):
        parse_vehicle(text)


def test_thrusters_that_cannot_roll_are_refused():
    """All vertical thrusters on the centre line: no roll moment, rank 5."""
    text = HEAVY_TEXT
    for y in ("0.215", "-0.215"):
        text = text.replace(f"position = [0.118, {y}, -0.053]", "position = [0.118, 0.0, -0.053]")
        text = text.replace(f"position = [-0.118, {y}, -0.053]", "position = [-0.118, 0.0, -0.053]")
    with pytest.raises(VehicleFileError, match="rank < 6"):
        parse_vehicle(text)


def test_packaged_vehicle_by_name_and_its_sources_are_cited():
    assert HEAVY.name == "bluerov2_heavy" and HEAVY.n_units == 8 and HEAVY.n_jets == 0
    assert "10.3390/jmse10121898" in HEAVY_TEXT and "AP_Motors6DOF.cpp" in HEAVY_TEXT
    assert HEAVY.body.mass == 13.5 and HEAVY.hydro.added_mass[2] == 18.6863


def test_normalised_controls_span_each_thrusters_reverse_and_forward_reach():
    from onboard.pwm import command_to_normalised, normalised_to_command

    c = normalised_to_command(HEAVY, [1.0, -1.0, 0.5, -0.5, 0, 0, 0, 0] + [0.3] * 16)
    assert c[:4] == pytest.approx([51.4362273206973, -39.9079290382407, 0.5 * 51.4362273206973,
                                   -0.5 * 39.9079290382407])
    assert np.all(c[8:] == 0.0)  # no joints, whatever the controls say
    assert command_to_normalised(HEAVY, c)[:4] == pytest.approx([1.0, -1.0, 0.5, -0.5])


@pytest.mark.parametrize("argv", [
    ["onboard", "--vehicle", "bluerov2_heavy", "--lockstep", "--link", "udpout:127.0.0.1:14999"],
    ["demo", "--vehicle", "bluerov2_heavy"],
    ["soak", "--vehicle", "bluerov2_heavy", "--duration", "200"],
    ["prove", "--vehicle", "bluerov2_heavy"],
])
def test_commands_that_run_the_onboard_loop_refuse_a_vehicle_without_jets_in_one_line(argv, capsys):
    from ground.cli import main

    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "bluerov2_heavy has fixed thrusters only" in err and "jetloop hil --json-sitl" in err


# --- a vehicle that mixes vectored jets and fixed thrusters: simulated, refused by the onboard loop --

def _mixed_vehicle_text() -> str:
    """asr4 with the heavy's first T200 added on channel 13 (jets 1-4, joints 5-12)."""
    asr4 = DEFAULT_VEHICLE.read_text()
    fixed = HEAVY_TEXT[HEAVY_TEXT.index("\n[fixed_thruster]"):HEAVY_TEXT.index("\n[[fixed]]   # 2")]
    text = asr4.replace("\n[pwm] ", fixed + "\n[pwm] ", 1)
    return text.replace("servo_range = [1100, 1900]", "servo_range = [1100, 1900]\nfixed_channels = [13]", 1)


def test_a_mixed_vehicle_loads_and_the_plant_flies_both_kinds():
    v = parse_vehicle(_mixed_vehicle_text(), source="mixed.toml")
    assert v.unit_kinds == ("jet",) * 4 + ("fixed",)
    speeds = {}
    for jet1, t200 in ((1100, 1500), (1100, 1700), (1900, 1500)):  # all off; the T200 alone; jet 1 alone
        pwm = [jet1, 1100, 1100, 1100] + [1500] * 8 + [t200]
        p = Plant(v, dt_s=0.01, depth_m=2.0, noise=False, command=pwm_to_command(v, pwm))
        p.advance(0.2)
        speeds[jet1, t200] = p.state[7:9]  # surge, sway (body), m/s
    assert np.abs(speeds[1100, 1500]).max() < 1e-9
    u, w = speeds[1100, 1700]  # the T200 pushes along its direction, -x +y at 45 deg
    assert u < -0.01 and w > 0.01, (u, w)
    assert abs(speeds[1900, 1500][0]) > 0.01  # and jet 1 at full speed still pushes along its neutral


def test_a_mixed_vehicle_is_refused_by_the_allocators_in_one_line():
    from onboard.allocation import PseudoInverseAllocator, QpAllocator

    v = parse_vehicle(_mixed_vehicle_text(), source="mixed.toml")
    for make in (QpAllocator, PseudoInverseAllocator, FixedQpAllocator, allocator_for):
        with pytest.raises(ValueError) as exc:
            make(v, 0.01)
        assert "\n" not in str(exc.value) and "a mixed vehicle is simulated but not allocated" in str(exc.value)


@pytest.mark.parametrize("command", [["onboard", "--lockstep", "--link", "udpout:127.0.0.1:14999"], ["demo"],
                                     ["soak", "--duration", "200"]])
def test_commands_that_run_the_onboard_loop_refuse_a_mixed_vehicle_in_one_line(command, tmp_path, capsys):
    from ground.cli import main

    path = tmp_path / "mixed.toml"
    path.write_text(_mixed_vehicle_text())
    assert main([command[0], "--vehicle", str(path), *command[1:]]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "mixes 4 vectored jets with 1 fixed thrusters" in err, err
    assert "can be simulated" in err
