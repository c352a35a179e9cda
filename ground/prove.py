"""`jetloop prove`: the diagnosis proven on recordings where one effect is concealed.

Each case makes a recording with the plant (`hil.plant.Plant`) from a TRUE vehicle in which one
effect is present, and hands `diagnose` a NOMINAL vehicle file in which that effect is absent or
wrong. The excitation is a scripted pool session flown by a simple pilot (depth and heading
PD loops on the plant's true state, scripted surge and sway forces, allocation to the four
vectored jets; the commands reach the plant as integer PWM and are recorded as such): dives,
runs, turns, sway runs, heave work near the floor, a surfacing. The effects are concealed:
small enough that their imprint on the raw signals is a few times the sensor noise, or acting
in only part of the run (the floor, the surface), or with a second effect masking them.
Control cases have nothing missing. Every case is checked (named first, windows overlap the
effect, parameter within 15 %, held-out NRMSE down >= 40 %, controls give no finding) and the
table is printed and written to prove.json. Nothing is tuned per case: the recordings come
from the plant, the verdicts from `diagnose`; failures stay in the table.
"""

from __future__ import annotations

import json
import math
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hil.plant import Plant
from onboard import model
from onboard.pwm import command_to_pwm, pwm_to_command
from onboard.vehicle import Vehicle, load_vehicle

CONTROL_HZ = 50.0
MOCAP_HZ = 50.0
MOCAP_NOISE_M = 0.001
MOCAP_NOISE_RAD = 0.002


# ------------------------------------------------------------------------------------------------
# The pool session: setpoints and a pilot


def session_setpoints(duration_s: float, seed: int):
    """Piecewise setpoints (t0, depth_m, yaw_rad, surge_N, sway_N) of a scripted pool session.

    Phases scale with `duration_s` (reference 120 s): hold, dive toward the floor, runs forward
    and back with turns, sway runs, heave work near the floor, depth sweeps, a surfacing and a
    dive back. A seeded jitter varies magnitudes and times so sessions are not identical.
    """
    rng = np.random.default_rng(seed)
    s = duration_s / 120.0
    j = lambda a: a * (1.0 + 0.15 * rng.uniform(-1, 1))  # noqa: E731
    plan = [
        (0, 0.50, 0.0, 0.0, 0.0),
        (6, 0.95, 0.0, 0.0, 0.0),  # dive toward the floor (1.2 m)
        (14, 0.70, 0.0, j(1.6), 0.0),  # run forward
        (22, 0.70, math.pi / 2, j(0.8), 0.0),  # turn while running
        (30, 0.60, math.pi / 2, j(-1.4), 0.0),  # run back
        (37, 0.60, -math.pi / 4, 0.0, 0.0),  # turn
        (44, 0.55, -math.pi / 4, 0.0, j(1.3)),  # sway run
        (51, 0.55, 0.3, 0.0, j(-1.3)),  # sway back while turning
        (58, 1.00, 0.3, 0.0, 0.0),  # down to the floor
        (63, 0.90, 0.3, j(0.6), 0.0),  # heave work near the floor
        (66, 1.02, 0.3, 0.0, 0.0),
        (69, 0.92, -0.6, 0.0, 0.0),
        (72, 1.03, -0.6, j(-0.6), 0.0),
        (76, 0.40, -0.6, 0.0, 0.0),  # depth sweeps
        (81, 0.85, 1.2, j(1.0), 0.0),
        (87, 0.35, 1.2, 0.0, j(-0.8)),
        (93, 0.75, 0.0, j(1.8), 0.0),  # fast run
        (100, -0.10, 0.0, 0.0, 0.0),  # surfacing
        (110, 0.45, 0.4, j(0.8), 0.0),  # dive back
    ]
    return [(t0 * s, d, y, fx, fy) for t0, d, y, fx, fy in plan]


def legs_setpoints(duration_s: float, seed: int):
    """Randomised legs: every 3-9 s a new depth, heading, surge and sway, drawn at random."""
    rng = np.random.default_rng(seed + 7001)
    out, t = [], 0.0
    while t < duration_s:
        out.append((t, float(rng.uniform(0.3, 1.05)), float(rng.uniform(-math.pi, math.pi)),
                    float(rng.choice([0.0, 1.0]) * rng.uniform(-1.8, 1.8)),
                    float(rng.choice([0.0, 1.0]) * rng.uniform(-1.4, 1.4))))
        t += float(rng.uniform(3.0, 9.0))
    return out


def joystick_setpoints(duration_s: float, seed: int):
    """Manual flying with human timing: stick deflections held 0.4-3 s, pauses of 0.2-2 s between
    them, one axis at a time mostly; depth changed in small steps, heading by a held yaw-rate
    stick (integrated), the way a pilot flies ArduSub's ALT_HOLD."""
    rng = np.random.default_rng(seed + 7002)
    out, t, depth, yaw = [], 0.0, 0.6, 0.0
    while t < duration_s:
        hold = float(rng.uniform(0.4, 3.0))
        axis = rng.choice(["surge", "sway", "yaw", "depth", "mixed"], p=[0.3, 0.2, 0.25, 0.15, 0.1])
        fx = float(rng.uniform(-1.8, 1.8)) if axis in ("surge", "mixed") else 0.0
        fy = float(rng.uniform(-1.4, 1.4)) if axis in ("sway", "mixed") else 0.0
        if axis in ("yaw", "mixed"):
            yaw += float(rng.uniform(-0.6, 0.6)) * hold
        if axis == "depth":
            depth = float(np.clip(depth + rng.uniform(-0.3, 0.3), 0.25, 1.05))
        out.append((t, depth, yaw, fx, fy))
        t += hold
        out.append((t, depth, yaw, 0.0, 0.0))  # the stick released
        t += float(rng.uniform(0.2, 2.0))
    return out


def sweep_setpoints(duration_s: float, seed: int):
    """The held-out pilot (never looked at while tuning): 3-2-1-1 multistep inputs on surge, sway
    and heading in turn around a slowly wandering depth (flight-test identification practice)."""
    rng = np.random.default_rng(seed + 7003)
    out, t = [], 0.0
    unit = float(rng.uniform(0.6, 1.2))
    k = 0
    while t < duration_s:
        axis = k % 3
        depth = 0.55 + 0.35 * math.sin(0.05 * t + seed)
        amp = float(rng.uniform(0.8, 1.6))
        for n, sign in ((3, 1), (2, -1), (1, 1), (1, -1)):
            fx = sign * amp if axis == 0 else 0.0
            fy = sign * amp * 0.8 if axis == 1 else 0.0
            yaw = sign * 0.5 * amp if axis == 2 else 0.0
            out.append((t, depth, yaw, fx, fy))
            t += n * unit
        out.append((t, depth, 0.0, 0.0, 0.0))
        t += float(rng.uniform(1.0, 3.0))
        k += 1
    return out


PILOTS = {"scripted": session_setpoints, "legs": legs_setpoints, "joystick": joystick_setpoints,
          "sweep": sweep_setpoints}
HIDDEN_PILOT = "sweep"  # evaluation only: thresholds and rules were tuned without looking at it


@dataclass(frozen=True)
class Pilot:
    """Depth and heading PD loops plus scripted horizontal force, allocated to k vectored jets.

    Each unit gets a baseline outward force (squeeze) plus its share of the wanted body wrench
    from the pseudo-inverse of the force map (spec 3), so every direction stays reachable with
    jets that only push outward; the unit's force vector gives its n, azimuth and elevation.
    """

    vehicle: Vehicle
    squeeze_n: float = 0.6
    kp_depth: float = 12.0
    kd_depth: float = 10.0
    kp_yaw: float = 0.35
    kd_yaw: float = 0.25

    def command(self, x: np.ndarray, sp) -> np.ndarray:
        v = self.vehicle
        k = v.n_units
        _, depth_ref, yaw_ref, fx_w, fy_b = sp
        R = model.rotation(x[3:7])
        roll, pitch, yaw = model.quat_to_euler(x[3:7])
        z = x[2] - v.environment.surface_depth
        w_ned = (R @ x[7:10])[2]
        e = v.environment
        trim = (e.rho * v.body.volume - v.body.mass) * e.g  # net buoyancy to cancel (N, up)
        fz_ned = self.kp_depth * (depth_ref - z) - self.kd_depth * w_ned + trim
        fz_ned = float(np.clip(fz_ned, -3.0, 4.0))
        e_yaw = (yaw_ref - yaw + math.pi) % (2 * math.pi) - math.pi
        mz = float(np.clip(self.kp_yaw * e_yaw - self.kd_yaw * x[12], -0.25, 0.25))
        f_body = R.T @ np.array([0.0, 0.0, fz_ned]) + np.array([fx_w, fy_b, 0.0])
        wrench = np.array([f_body[0], f_body[1], f_body[2], 0.0, 0.0, mz])
        B = model.wrench_map(v)
        rows = [0, 1, 2, 5]
        share = np.linalg.pinv(B[rows]) @ wrench[rows]
        cmd = np.zeros(3 * k)
        lim = v.servo.angle_limit
        thrust_coef = v.environment.rho * v.thruster.diameter ** 4 * v.thruster.kt[0]
        for i, u in enumerate(v.units):
            e1 = np.array(u.neutral)
            e2 = np.array([-e1[1], e1[0], 0.0])
            f = self.squeeze_n * e1 + share[3 * i:3 * i + 3]
            T = float(np.linalg.norm(f))
            alpha = math.atan2(f @ e2, f @ e1)
            beta = -math.asin(max(-1.0, min(1.0, f[2] / max(T, 1e-9))))
            cmd[i] = min(math.sqrt(T / thrust_coef), v.thruster.n_max)
            cmd[k + i] = float(np.clip(alpha, -lim, lim))
            cmd[2 * k + i] = float(np.clip(beta, -lim, lim))
        return cmd


# ------------------------------------------------------------------------------------------------
# Making a recording


@dataclass(frozen=True)
class SessionTruth:
    """What the plant did: for checking a diagnosis against the truth."""

    time_s: np.ndarray
    depth_m: np.ndarray
    speed_m_s: np.ndarray
    control_time_s: np.ndarray = None  # at each control step:
    joint_rate_rad_s: np.ndarray = None  # largest |joint rate| over the step (k units, both joints)
    speed_change_rev_s: np.ndarray = None  # largest |n - n_cmd| (propeller catching up)


def record_session(truth: Vehicle, path, duration_s: float = 120.0, seed: int = 0,
                   thrust_fraction=None, mocap: bool = True, noise: bool = True,
                   rig_stiffness=None, pilot: str = "scripted", ardusub: bool = False) -> SessionTruth:
    """Fly the pool session on the plant with the TRUE vehicle and write a .tlog at `path`.

    `thrust_fraction` (per unit, 1 = healthy) models a degraded thruster as
    `model.faulty_command` does (a jet's thrust is `fraction` of nominal). The recorded PWM is
    what the pilot commanded.
    `pilot` names the setpoint generator (PILOTS); `ardusub` records the sensors as ArduSub sends
    them: SCALED_IMU2 (mG, mrad/s integers) and SCALED_PRESSURE2 at the vehicle file's rates.
    """
    from pymavlink.dialects.v20 import ardupilotmega as mav

    k = truth.n_units
    plant = Plant(truth, seed=seed, depth_m=0.5, noise=noise, rig_stiffness=rig_stiffness,
                  rig_anchor=None if rig_stiffness is None else (0.0, 0.0, 0.6))
    flyer = Pilot(truth)
    sps = PILOTS[pilot](duration_s, seed)
    link = mav.MAVLink(None, srcSystem=1, srcComponent=1)
    rng = np.random.default_rng(seed + 1000)
    out = []  # (time_s, order, packet)
    t_ctrl = 1.0 / CONTROL_HZ
    n_ctrl = int(round(duration_s * CONTROL_HZ))
    times, depths, speeds = [], [], []
    c_times, j_rates, n_gaps = [], [], []
    lay = model.StateLayout(k)
    for step in range(n_ctrl):
        t = step * t_ctrl
        sp = next(s for s in reversed(sps) if s[0] <= t + 1e-9)
        pwm = command_to_pwm(truth, flyer.command(plant.state, sp))
        cmd = pwm_to_command(truth, pwm)
        plant.set_command(cmd if thrust_fraction is None else model.faulty_command(truth, cmd, thrust_fraction)[0])
        us = int(round(t * 1e6))
        out.append((t, 0, mav.MAVLink_servo_output_raw_message(
            us & 0xFFFFFFFF, 0, *[int(c) for c in pwm]).pack(link)))
        if step % int(CONTROL_HZ) == 0:
            out.append((t, -1, mav.MAVLink_heartbeat_message(
                mav.MAV_TYPE_SUBMARINE, mav.MAV_AUTOPILOT_GENERIC, 128, 0, mav.MAV_STATE_ACTIVE, 3).pack(link)))
        joints0 = plant.state[lay.alpha.start:lay.beta.stop].copy()
        samples = plant.advance(t + t_ctrl)
        c_times.append(t)
        j_rates.append(float(np.abs(plant.state[lay.alpha.start:lay.beta.stop] - joints0).max()) / t_ctrl)
        n_gaps.append(float(np.abs(plant.state[lay.n] - plant.command[:k]).max()))
        if t + t_ctrl > duration_s - 1e-9:  # the session ends before the sample at duration_s
            for name in ("imu", "pressure", "attitude", "truth"):
                setattr(samples, name, [x for x in getattr(samples, name) if x.time_s < duration_s - 1e-9])
        for s in samples.imu:
            if ardusub:  # ArduPilot GCS_Common send_scaled_imu: mG and mrad/s, int16
                acc = [int(np.clip(round(a / 9.80665 * 1000), -32768, 32767)) for a in s.accel_frd_m_s2]
                gyr = [int(np.clip(round(g * 1000), -32768, 32767)) for g in s.gyro_frd_rad_s]
                out.append((s.time_s, 1, mav.MAVLink_scaled_imu2_message(
                    int(round(s.time_s * 1e3)), *acc, *gyr, 0, 0, 0).pack(link)))
                continue
            out.append((s.time_s, 1, mav.MAVLink_highres_imu_message(
                int(round(s.time_s * 1e6)), *s.accel_frd_m_s2, *s.gyro_frd_rad_s,
                0, 0, 0, 0, 0, 0, 0, 0b111111, 0).pack(link)))
        for s in samples.pressure:
            out.append((s.time_s, 2, mav.MAVLink_scaled_pressure2_message(
                int(round(s.time_s * 1e3)), s.press_abs_pa / 100.0, 0.0, 2000, 0).pack(link)))
        for s in samples.attitude:
            out.append((s.time_s, 3, mav.MAVLink_attitude_message(
                int(round(s.time_s * 1e3)), s.roll_rad, s.pitch_rad, s.yaw_rad,
                s.rollspeed_rad_s, s.pitchspeed_rad_s, s.yawspeed_rad_s).pack(link)))
        for s in samples.truth:
            times.append(s.time_s)
            depths.append(s.pos_ned_m[2] - truth.environment.surface_depth)
            speeds.append(float(np.linalg.norm(s.nu[:3])))
            if mocap and round(s.time_s * MOCAP_HZ, 6).is_integer():
                nz = 1.0 if noise else 0.0
                e = np.array(s.euler_rad) + nz * rng.normal(0, MOCAP_NOISE_RAD, 3)
                q = model.euler_to_quat(*e)
                p = np.array(s.pos_ned_m) + nz * rng.normal(0, MOCAP_NOISE_M, 3)
                out.append((s.time_s, 4, mav.MAVLink_att_pos_mocap_message(
                    int(round(s.time_s * 1e6)), [float(c) for c in q], *[float(c) for c in p]).pack(link)))
    out.sort(key=lambda r: (r[0], r[1]))
    epoch = 1_767_225_600 * 1_000_000
    with open(path, "wb") as f:
        for t, _, pkt in out:
            f.write(int(epoch + round(t * 1e6)).to_bytes(8, "big"))
            f.write(pkt)
    return SessionTruth(np.array(times), np.array(depths), np.array(speeds), np.array(c_times),
                        np.array(j_rates), np.array(n_gaps))


# ------------------------------------------------------------------------------------------------
# The cases


@dataclass(frozen=True)
class Case:
    """One proof: a TRUE vehicle for the plant, a NOMINAL one for diagnose, what must be found."""

    name: str
    expect: tuple  # effect ids the findings must name (first finding = expect[0] or any of a pair); () = control
    truth_values: dict = field(default_factory=dict)  # dotted keys changed in the true vehicle
    nominal_values: dict = field(default_factory=dict)  # dotted keys changed in the nominal vehicle
    check: dict = field(default_factory=dict)  # reported key (or key[index]) -> true value
    acts: str = "everywhere"  # where the effect acts: everywhere, surface, floor, slews
    concealment: str = ""
    thrust_fraction: tuple | None = None
    rig_stiffness: tuple | None = None
    seed: int = 1


def cases() -> list[Case]:
    """Every effect id, every misestimated parameter, two pairs, an unknown term, controls."""
    off = lambda e: {f"effects.{e}.enabled": False}  # noqa: E731
    return [
        Case("thrust_inflow missing", ("thrust_inflow",), nominal_values=off("thrust_inflow"),
             concealment="thrust loss <= 15 % at the run speeds: under the accelerometer noise per sample"),
        Case("motor_lag missing", ("motor_lag",), nominal_values=off("motor_lag"),
             check={"thruster.motor_time_constant": 0.08}, acts="thrust changes",
             concealment="acts only while propeller speed changes"),
        Case("servo_lag missing", ("servo_lag",), nominal_values=off("servo_lag"),
             check={"servo.time_constant": 0.03}, acts="slews", concealment="acts only while joints slew"),
        Case("azimuth_transient missing", ("azimuth_transient",), nominal_values=off("azimuth_transient"),
             check={"effects.azimuth_transient.gain_per_newton": 0.0126}, acts="slews",
             concealment="acts only in joint slews, moment ~2x gyro-derivative noise"),
        Case("surface_proximity missing", ("surface_proximity",), nominal_values=off("surface_proximity"),
             acts="surface", concealment="acts only in the surfacing (about 10 % of the run)"),
        Case("wall_proximity missing", ("wall_proximity",), nominal_values=off("wall_proximity"),
             check={"effects.wall_proximity.k_wall": 0.375}, acts="floor",
             concealment="acts only near the floor, on heave acceleration"),
        Case("current missing", ("current",), truth_values={"environment.current": [0.04, -0.03, 0.0]},
             check={"environment.current": [0.04, -0.03, 0.0]},
             concealment="4-5 cm/s: drag change below the accelerometer noise"),
        Case("added_mass heave -25 %", ("added_mass",), nominal_values={"hydro.added_mass": [3.3, 3.3, 3.075, 0.006, 0.006, 0.002]},
             check={"hydro.added_mass[2]": 4.1}, concealment="heave force error ~1 N at peak acceleration only"),
        Case("linear_damping surge/sway +40 %", ("linear_damping",), truth_values={"hydro.linear_damping": [2.52, 2.52, 2.6, 0.08, 0.08, 0.05]},
             check={"hydro.linear_damping[0]": 2.52, "hydro.linear_damping[1]": 2.52},
             concealment="0.2 N at run speed"),
        Case("quadratic_damping heave +30 %", ("quadratic_damping",), truth_values={"hydro.quadratic_damping": [18.0, 18.0, 31.2, 0.05, 0.05, 0.03]},
             check={"hydro.quadratic_damping[2]": 31.2}, concealment="acts at heave speed only"),
        Case("buoyancy +0.5 %", ("buoyancy",), truth_values={"body.volume": 0.00665 * 1.005},
             check={"body.volume": 0.00665 * 1.005}, concealment="0.33 N: 1x accelerometer noise in heave"),
        Case("restoring_moment cb -25 %", ("restoring_moment",), truth_values={"body.cb": [0.0, 0.0, -0.015]},
             check={"body.cb[2]": -0.015}, concealment="righting moment error at small angles"),
        Case("imu_bias gyro", ("imu_bias",), truth_values={"sensors.gyro_bias": [0.006, -0.005, 0.004]},
             check={"sensors.gyro_bias": [0.006, -0.005, 0.004]}, concealment="bias 1.3-2x the gyro noise"),
        Case("sensor_delay 30 ms", ("sensor_delay",), truth_values={"sensors.delay": 0.03},
             check={"sensors.delay": 0.03}, concealment="30 ms latency of every vehicle sensor stream"),
        Case("thruster_fault unit 3 at 75 %", ("thruster_fault",), thrust_fraction=(1.0, 1.0, 0.75, 1.0),
             check={"thruster_fault.unit[2].thrust_fraction": 0.75}, concealment="0.25 x one jet's thrust"),
        Case("azimuth_transient masked by current", ("azimuth_transient", "current"),
             nominal_values=off("azimuth_transient"), truth_values={"environment.current": [0.05, 0.04, 0.0]},
             check={"effects.azimuth_transient.gain_per_newton": 0.0126}, acts="slews",
             concealment="a steady current masks the transient's imprint"),
        Case("wall_proximity masked by heave damping", ("wall_proximity", "linear_damping"),
             nominal_values={**off("wall_proximity"), "hydro.linear_damping": [1.8, 1.8, 2.0, 0.08, 0.08, 0.05]},
             check={"effects.wall_proximity.k_wall": 0.375}, acts="floor",
             concealment="a heave damping error masks the floor effect"),
        Case("unknown: tether spring", ("unknown",), rig_stiffness=(0.6, 0.6, 0.0),
             concealment="a 0.6 N/m horizontal tether: no known effect has its shape"),
        Case("control (seed 1)", (), seed=1),
        Case("control (seed 2)", (), seed=2),
        Case("control (seed 3)", (), seed=3),
    ]


def _reported(findings: list, effect: str, key: str):
    """The fitted value of `key` (optionally `key[i]`) in the first finding naming `effect`."""
    base, _, idx = key.partition("[")
    for f in findings:
        if f["effect"] != effect:
            continue
        params = f["parameters"]
        if key in params:
            return params[key]
        if base in params and idx:
            return params[base][int(idx.rstrip("]"))]
    return None


def _param_error(case: Case, findings: list) -> float | None:
    """Largest relative error of the checked parameters (vector: norm of difference / norm)."""
    if not case.check:
        return None
    errs = []
    for key, truth in case.check.items():
        got = _reported(findings, case.expect[0], key)
        if got is None:
            return float("inf")
        t = np.atleast_1d(np.asarray(truth, float))
        g = np.atleast_1d(np.asarray(got, float))
        errs.append(float(np.linalg.norm(g - t) / max(np.linalg.norm(t), 1e-12)))
    return max(errs)


def _acts_mask(case: Case, truth: SessionTruth, vehicle: Vehicle):
    """(times, mask): where the case's effect acts, from the plant's truth."""
    e = vehicle.environment
    R = vehicle.body.radius
    if case.acts == "surface":
        return truth.time_s, truth.depth_m < 1.5 * R
    if case.acts == "floor":
        return truth.time_s, (e.floor_depth - e.surface_depth - truth.depth_m) < 2.0 * R
    if case.acts == "slews":
        return truth.control_time_s, truth.joint_rate_rad_s > 1.0
    if case.acts == "thrust changes":
        return truth.control_time_s, truth.speed_change_rev_s > 2.0
    return truth.time_s, np.ones(len(truth.time_s), bool)


def run_case(case: Case, out_dir: Path, reference: Vehicle, duration_s: float = 120.0, progress=None) -> dict:
    """Record, diagnose and check one case; returns its prove.json row."""
    from ground.diagnose import diagnose
    from ground.diagnose.report import write_html, write_json
    from ground.recording import read_recording

    t0 = time.perf_counter()
    truth_v = reference.with_values(case.truth_values) if case.truth_values else reference
    nominal = reference.with_values(case.nominal_values) if case.nominal_values else reference
    slug = "".join(c if c.isalnum() else "_" for c in case.name).strip("_")
    rec_path = out_dir / f"{slug}.tlog"
    truth = record_session(truth_v, rec_path, duration_s, seed=case.seed,
                           thrust_fraction=case.thrust_fraction, rig_stiffness=case.rig_stiffness)
    (out_dir / f"{slug}.nominal.toml").write_text(vehicle_toml(nominal, _vehicle_note(case)))
    rec = read_recording(rec_path)
    diag = diagnose(rec, nominal, progress=progress)
    rep = diag.report
    write_json(rep, out_dir / f"{slug}.json")
    try:
        write_html(diag, out_dir / f"{slug}_report")
    except Exception as exc:  # a plot must not lose the verdict
        print(f"report plots for {case.name} failed: {exc}", file=sys.stderr)
    findings = rep["findings"]
    named = [f["effect"] for f in findings]
    before = rep["fit"]["holdout"]["before"]["total"]
    after = rep["fit"]["holdout"]["after"]["total"]
    drop = (before - after) / before if before > 0 else 0.0
    row = {"case": case.name, "expect": list(case.expect), "named": named,
           "concealment": case.concealment, "nrmse_before": before, "nrmse_after": after,
           "nrmse_drop": round(drop, 3),
           "nrmse_raw_before": rep["fit"]["holdout"]["raw"]["before"],
           "nrmse_raw_after": rep["fit"]["holdout"]["raw"]["after"]}
    if not case.expect:
        row["checks"] = {"no_finding": not findings}
        row["param_error"] = None
    else:
        perr = _param_error(case, findings)
        t_all, acts = _acts_mask(case, truth, reference)
        t_act = t_all[acts]
        overlap = any(((t_act >= w["t0"]) & (t_act <= w["t1"])).any() for w in rep["mismatch"]["windows"])
        first_ok = bool(findings) and (findings[0]["effect"] == case.expect[0]
                                        or (len(case.expect) > 1 and findings[0]["effect"] in case.expect))
        row["param_error"] = None if perr is None or not math.isfinite(perr) else round(perr, 4)
        row["param_reported"] = perr is None or math.isfinite(perr)
        row["checks"] = {
            "named_first": first_ok,
            "windows_overlap": bool(overlap),
            "parameter_within_15pct": perr is None or (math.isfinite(perr) and perr <= 0.15),
            "nrmse_drop_40pct": drop >= 0.40,
        }
        if len(case.expect) > 1:
            row["checks"]["both_named"] = set(case.expect) <= set(named)
    row["passed"] = all(row["checks"].values())
    row["time_s"] = round(time.perf_counter() - t0, 1)
    row["diagnose_s"] = rep["elapsed_s"]
    return row


def vehicle_toml(v: Vehicle, header: str = "") -> str:
    """A complete vehicle file for `v` (loads back to an equal vehicle), so every proof
    recording can be re-diagnosed by hand: jetloop diagnose REC --vehicle NOMINAL.toml."""
    import dataclasses

    from onboard.vehicle import SECTIONS, _toml_value

    def table(name: str, obj) -> list[str]:  # an optional key at its default is left out, as a user would
        # (TOML has no null for jet_neutral = None; an empty fixed_channels means no fixed thrusters)
        return [f"[{name}]"] + [f"{f.name} = {_toml_value(getattr(obj, f.name))}" for f in dataclasses.fields(obj)
                                if f.default is dataclasses.MISSING or getattr(obj, f.name) != f.default] + [""]

    lines = [header.rstrip(), f'name = "{v.name}"', ""] if header else [f'name = "{v.name}"', ""]
    for sec in SECTIONS:
        lines += table(sec, getattr(v, sec))
    for u in v.units:
        lines += ["[[unit]]", f"position = {_toml_value(u.position)}", f"neutral = {_toml_value(u.neutral)}", ""]
    for u in v.fixed:
        lines += ["[[fixed]]", f"position = {_toml_value(u.position)}", f"direction = {_toml_value(u.direction)}", ""]
    if v.fixed_thruster is not None:
        lines += table("fixed_thruster", v.fixed_thruster)
    for f in dataclasses.fields(v.effects):
        eff = getattr(v.effects, f.name)
        lines.append(f"[effects.{f.name}]")
        lines += [f"{g.name} = {_toml_value(getattr(eff, g.name))}" for g in dataclasses.fields(eff)]
        lines.append("")
    return "\n".join(lines)


def _vehicle_note(case: Case) -> str:
    lines = [f"# Nominal vehicle of proof case '{case.name}': the reference with these keys changed:"]
    lines += [f"#   {k} = {v}" for k, v in case.nominal_values.items()] or ["#   (none)"]
    lines.append("# The TRUE vehicle (the plant that made the recording) differs from the reference by:")
    lines += [f"#   {k} = {v}" for k, v in case.truth_values.items()]
    if case.thrust_fraction:
        lines.append(f"#   unit thrust fractions = {list(case.thrust_fraction)}")
    if case.rig_stiffness:
        lines.append(f"#   a tether spring (N/m, NED x y z) = {list(case.rig_stiffness)}")
    if lines[-1].startswith("# The TRUE"):
        lines.append("#   (nothing: the plant flies the reference vehicle)")
    return "\n".join(lines)


def table(rows: list[dict]) -> str:
    head = f"{'case':40s} {'named':32s} {'param err':>9s} {'NRMSE before':>12s} {'after':>7s} {'drop':>6s} {'time':>6s}  verdict"
    lines = [head, "-" * len(head)]
    for r in rows:
        named = ",".join(r["named"]) or "-"
        pe = ("-" if r.get("param_reported", True) else "n/a") if r["param_error"] is None else f"{100 * r['param_error']:.1f}%"
        failed = [k for k, ok in r["checks"].items() if not ok]
        verdict = "PASS" if r["passed"] else "FAIL (" + ", ".join(failed) + ")"
        lines.append(f"{r['case'][:40]:40s} {named[:32]:32s} {pe:>9s} {r['nrmse_before']:12.3f} "
                     f"{r['nrmse_after']:7.3f} {100 * r['nrmse_drop']:5.0f}% {r['time_s']:5.0f}s  {verdict}")
    n_pass = sum(r["passed"] for r in rows)
    lines.append(f"{n_pass}/{len(rows)} cases pass")
    return "\n".join(lines)


# ------------------------------------------------------------------------------------------------
# The benchmark: cases drawn from a family (pilots, sensor sets, durations, effects, magnitudes)

SPLITS = {"dev": 101, "eval": 202}  # seed salts: thresholds and rules are tuned on dev only
SENSOR_SETS = ("mocap", "imu", "ardusub")
CONTROL_FRACTION = 0.35
MASK_FRACTION = 0.2


def _effect_family():
    """(name, expect id, builder(m) -> case fields) of every effect at magnitude multiplier m (1-5x
    the classic case's, which sits near the detectability of a 120 s pool session)."""
    off = lambda e: {f"effects.{e}.enabled": False}  # noqa: E731
    cap = lambda x, lo, hi: float(min(max(x, lo), hi))  # noqa: E731
    return [
        ("thrust_inflow", lambda m: dict(nominal_values=off("thrust_inflow"))),
        ("motor_lag", lambda m: dict(nominal_values=off("motor_lag"),
                                     truth_values={"thruster.motor_time_constant": cap(0.08 * m, 0.08, 0.3)},
                                     check={"thruster.motor_time_constant": cap(0.08 * m, 0.08, 0.3)})),
        ("servo_lag", lambda m: dict(nominal_values=off("servo_lag"),
                                     truth_values={"servo.time_constant": cap(0.03 * m, 0.03, 0.12)},
                                     check={"servo.time_constant": cap(0.03 * m, 0.03, 0.12)})),
        ("azimuth_transient", lambda m: dict(nominal_values=off("azimuth_transient"),
                                             truth_values={"effects.azimuth_transient.gain_per_newton": 0.0126 * m},
                                             check={"effects.azimuth_transient.gain_per_newton": 0.0126 * m})),
        ("surface_proximity", lambda m: dict(nominal_values=off("surface_proximity"))),
        ("wall_proximity", lambda m: dict(nominal_values=off("wall_proximity"),
                                          truth_values={"effects.wall_proximity.k_wall": 0.375 * m},
                                          check={"effects.wall_proximity.k_wall": 0.375 * m})),
        ("current", lambda m: dict(truth_values={"environment.current": [0.04 * m, -0.03 * m, 0.0]},
                                   check={"environment.current": [0.04 * m, -0.03 * m, 0.0]})),
        ("added_mass", lambda m: dict(nominal_values={"hydro.added_mass": [3.3, 3.3, 4.1 * cap(1 - 0.25 * m, 0.2, 1), 0.006, 0.006, 0.002]},
                                      check={"hydro.added_mass[2]": 4.1})),
        ("linear_damping", lambda m: dict(truth_values={"hydro.linear_damping": [1.8 * (1 + 0.4 * m), 1.8 * (1 + 0.4 * m), 2.6, 0.08, 0.08, 0.05]},
                                          check={"hydro.linear_damping[0]": 1.8 * (1 + 0.4 * m)})),
        ("quadratic_damping", lambda m: dict(truth_values={"hydro.quadratic_damping": [18.0, 18.0, 24.0 * (1 + 0.3 * m), 0.05, 0.05, 0.03]},
                                             check={"hydro.quadratic_damping[2]": 24.0 * (1 + 0.3 * m)})),
        ("buoyancy", lambda m: dict(truth_values={"body.volume": 0.00665 * (1 + 0.005 * m)},
                                    check={"body.volume": 0.00665 * (1 + 0.005 * m)})),
        ("restoring_moment", lambda m: dict(truth_values={"body.cb": [0.0, 0.0, -0.02 * cap(1 - 0.25 * m, 0.1, 1)]},
                                            check={"body.cb[2]": -0.02 * cap(1 - 0.25 * m, 0.1, 1)})),
        ("imu_bias", lambda m: dict(truth_values={"sensors.gyro_bias": [0.006 * m, -0.005 * m, 0.004 * m]},
                                    check={"sensors.gyro_bias": [0.006 * m, -0.005 * m, 0.004 * m]})),
        ("sensor_delay", lambda m: dict(truth_values={"sensors.delay": cap(0.03 * m, 0.03, 0.12)},
                                        check={"sensors.delay": cap(0.03 * m, 0.03, 0.12)})),
        ("thruster_fault", lambda m, unit=2: dict(
            thrust_fraction=tuple(cap(1 - 0.25 * m, 0.2, 1) if i == unit else 1.0 for i in range(4)),
            check={f"thruster_fault.unit[{unit}].thrust_fraction": cap(1 - 0.25 * m, 0.2, 1)})),
    ]


# The family's flight durations (s) and their probabilities (family_case; bench/bench_campaign.py)
DURATIONS_S = (60.0, 90.0, 120.0, 180.0, 300.0, 600.0)
DURATION_P = (0.3, 0.2, 0.25, 0.1, 0.1, 0.05)


@dataclass(frozen=True)
class Flight:
    """How a benchmark case is flown and sensed."""

    pilot: str
    sensors: str  # mocap, imu (no motion capture), ardusub (SCALED_IMU2 and ArduSub rates, no mocap)
    imu_hz: float
    duration_s: float


def family_case(split: str, index: int) -> tuple[Case, Flight, float]:
    """Case `index` of the benchmark's `split` ("dev" or "eval"): (case, flight, magnitude)."""
    rng = np.random.default_rng([SPLITS[split], index])
    pilots = [p for p in PILOTS if p != HIDDEN_PILOT or split == "eval"]
    sensors = str(rng.choice(SENSOR_SETS))
    flight = Flight(str(rng.choice(pilots)), sensors,
                    float(rng.choice([25.0, 50.0]) if sensors == "ardusub" else rng.choice([50.0, 100.0, 200.0])),
                    float(rng.choice(list(DURATIONS_S), p=list(DURATION_P))))
    seed = int(rng.integers(1, 1_000_000))
    fam = _effect_family()
    if rng.random() < CONTROL_FRACTION:
        return Case(f"{split}-{index:03d} control", (), seed=seed), flight, 0.0
    name, build = fam[int(rng.integers(len(fam)))]
    m = float(np.exp(rng.uniform(0.0, math.log(5.0))))
    # which jet is faulty comes from the case's seed (it was always the third before 2026-11-25)
    fields = build(m, seed % 4) if name == "thruster_fault" else build(m)
    expect = (name,)
    if rng.random() < MASK_FRACTION:  # a masking second effect at its classic magnitude
        others = [f for f in fam if f[0] != name and f[0] not in ("thruster_fault",) and name != "thruster_fault"]
        if others:
            oname, obuild = others[int(rng.integers(len(others)))]
            o = obuild(1.0)
            fields = dict(fields)
            for key in ("truth_values", "nominal_values"):
                fields[key] = {**o.get(key, {}), **fields.get(key, {})}
            expect = (name, oname)
    case = Case(f"{split}-{index:03d} {'+'.join(expect)} x{m:.1f}", expect, seed=seed, **fields)
    return case, flight, m


def wilson(k: int, n: int, z: float = 1.96) -> tuple[float, float]:
    """95 % Wilson score interval of a proportion k/n (Wilson 1927)."""
    if n == 0:
        return (float("nan"), float("nan"))
    p = k / n
    den = 1 + z * z / n
    mid = (p + z * z / (2 * n)) / den
    half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / den
    return (max(0.0, mid - half), min(1.0, mid + half))


def run_family_case(split: str, index: int, out_dir, reference: Vehicle | None = None, draws: int | None = None) -> dict:
    """Record and diagnose benchmark case `index` of `split`; its row for family.json."""
    from ground.diagnose import diagnose
    from ground.diagnose.core import NULL_DRAWS
    from ground.diagnose.report import write_json
    from ground.recording import read_recording

    t0 = time.perf_counter()
    reference = reference or load_vehicle(None)
    case, flight, m = family_case(split, index)
    out_dir = Path(out_dir)
    rates = {"sensors.imu_rate": flight.imu_hz}
    if flight.sensors == "ardusub":
        rates.update({"sensors.attitude_rate": 10.0, "sensors.pressure_rate": 10.0})
    truth_v = reference.with_values({**rates, **case.truth_values})
    nominal = reference.with_values(case.nominal_values) if case.nominal_values else reference
    slug = "".join(c if c.isalnum() else "_" for c in case.name.split(" ")[0])
    rec_path = out_dir / f"{slug}.tlog"
    row = {"case": case.name, "split": split, "index": index, "expect": list(case.expect), "magnitude": round(m, 3),
           "pilot": flight.pilot, "sensors": flight.sensors, "imu_hz": flight.imu_hz, "duration_s": flight.duration_s}
    try:
        record_session(truth_v, rec_path, flight.duration_s, seed=case.seed, thrust_fraction=case.thrust_fraction,
                       mocap=flight.sensors == "mocap", pilot=flight.pilot, ardusub=flight.sensors == "ardusub")
        (out_dir / f"{slug}.nominal.toml").write_text(vehicle_toml(nominal, _vehicle_note(case)))
        rep = diagnose(read_recording(rec_path), nominal, draws=NULL_DRAWS if draws is None else draws).report
        write_json(rep, out_dir / f"{slug}.json")
    except Exception as exc:  # a case that breaks is a row with its error, never the end of the run
        row.update(error=f"{type(exc).__name__}: {exc}", time_s=round(time.perf_counter() - t0, 1))
        return row
    findings = rep["findings"]
    named = [f["effect"] for f in findings]
    before, after = rep["fit"]["holdout"]["before"]["total"], rep["fit"]["holdout"]["after"]["total"]
    row.update(named=named, untestable=[u["effect"] for u in rep.get("untestable", [])],
               nrmse_before=before, nrmse_after=after, diagnose_s=rep["elapsed_s"],
               time_s=round(time.perf_counter() - t0, 1))
    if case.expect:
        primary = case.expect[0]
        row["top1"] = bool(named) and named[0] == primary
        row["top2"] = primary in named[:2]
        row["testable"] = _testable(case, rep.get("untestable", []), nominal)
        # listed untestable with the report's first finding in the model (core._masked_untestable):
        # counted by the first pass's verdict all the same, the table says how many
        row["masked_by"] = next((u["with"] for u in rep.get("untestable", [])
                                 if u["effect"] == primary and u.get("with")), None)
        # significant on the fitting blocks, but out of the held-out blocks' reach (core._unconfirmable):
        # left out as untestable, the table prints the rate with them counted as misses
        row["unconfirmed"] = any(u["effect"] == primary and u.get("significant") for u in rep.get("untestable", []))
        perr = _param_error(case, findings)
        row["param_error"] = None if perr is None or not math.isfinite(perr) else round(perr, 4)
        row["within_3sd"] = _within_sd(case, findings, 3.0)
        row["nrmse_drop"] = round((before - after) / before, 3) if named and before and before > 0 else None
    return row


def _testable(case: Case, untestable: list, nominal: Vehicle | None = None) -> bool:
    """Whether the report can test the case's primary effect: not listed as untestable, or
    listed for parameters (a family tested by some of them) none of which the case checks
    (`hydro.linear_damping[0]`; of a whole vector key, the elements whose true value differs
    from the `nominal` vehicle's, or any element without it). An entry untestable only `"with"`
    the report's first finding in the model does not count: that verdict rests on the
    diagnosis's own first finding, which may be the wrong one (a quadratic damping named for a
    linear one soaks up its signal), so the benchmark keeps the first pass's."""
    primary = case.expect[0]
    for u in untestable:
        if u["effect"] != primary or u.get("with"):
            continue
        names = u.get("parameters")
        if not names or not case.check:
            return False
        for key, truth in case.check.items():
            if key in names:
                return False
            moved = range(len(np.atleast_1d(truth)))
            if nominal is not None and "[" not in key:
                try:
                    moved = np.flatnonzero(np.atleast_1d(np.asarray(truth, float))
                                           != np.atleast_1d(np.asarray(nominal.get(key), float)))
                except (AttributeError, KeyError, ValueError, TypeError):
                    pass
            if any(f"{key}[{i}]" in names for i in moved):
                return False
    return True


def _within_sd(case: Case, findings: list, k: float):
    """Whether every checked parameter is within k reported standard deviations of the truth."""
    if not case.check:
        return None
    f = next((f for f in findings if f["effect"] == case.expect[0]), None)
    if f is None or "std" not in f:
        return None
    as_sd = [dict(f, parameters=f["std"])]
    for key, truth in case.check.items():
        got, sd = _reported([f], case.expect[0], key), _reported(as_sd, case.expect[0], key)
        if got is None or sd is None:
            return None
        t, g, s = (np.atleast_1d(np.asarray(v, float)) for v in (truth, got, sd))
        if not np.isfinite(s).all():  # a checked element the finding did not estimate
            return None
        if np.any(np.abs(g - t) > k * np.maximum(s, 1e-300)):
            return False
    return True


def family_table(rows: list[dict]) -> str:
    """The benchmark's markdown table: rates with 95 % Wilson intervals, by sensor set and by
    effect, and the confusion matrix (expected primary effect -> first finding)."""
    ok = [r for r in rows if "error" not in r]
    lines = [f"{len(rows)} cases ({len(rows) - len(ok)} raised), "
             f"{sum(1 for r in ok if not r['expect'])} controls", ""]

    def rate(sel, key):
        vals = [r[key] for r in sel if r.get(key) is not None]
        k = sum(bool(v) for v in vals)
        lo, hi = wilson(k, len(vals))
        return f"{k}/{len(vals)} ({100 * k / len(vals):.0f} %, {100 * lo:.0f}-{100 * hi:.0f})" if vals else "-"

    def block(sel):
        ctrl = [r for r in sel if not r["expect"]]
        eff = [r for r in sel if r["expect"]]
        test = [r for r in eff if r.get("testable")]
        false = [dict(r, false=bool(r["named"])) for r in ctrl]
        pe = [dict(r, ok15=r.get("param_error") is not None and r["param_error"] <= 0.15)
              for r in test if r.get("top2") and r.get("param_error") is not None]
        drops = [r["nrmse_drop"] for r in test if r.get("nrmse_drop") is not None]
        worse = sum(1 for r in sel if r.get("named") and r.get("nrmse_after", 0) > r.get("nrmse_before", 0))
        return (rate(false, "false"), rate(eff, "testable"), rate(test, "top1"), rate(test, "top2"),
                rate(pe, "ok15"), rate([r for r in test if r.get("within_3sd") is not None], "within_3sd"),
                f"{100 * float(np.median(drops)):.0f} %" if drops else "-", str(worse))

    head = ("| set | cases | controls: false findings | effects testable | top-1 (testable) | top-2 (testable) "
            "| param within 15 % | param within 3 sd | median NRMSE drop | worse fits |")
    lines += [head, "|" + "---|" * 10]
    # the masked cases apart: a primary beside a second effect at its classic magnitude, where a
    # right report may name the second first (top-1 counts the primary only)
    groups = [("all", ok)] + [(f"sensors: {s}", [r for r in ok if r["sensors"] == s]) for s in SENSOR_SETS] + \
             [(f"pilot: {p}", [r for r in ok if r["pilot"] == p]) for p in PILOTS] + \
             [("effects: one (and controls)", [r for r in ok if len(r["expect"]) < 2]),
              ("effects: masked by a second", [r for r in ok if len(r["expect"]) > 1])]
    for name, sel in groups:
        if sel:
            lines.append(f"| {name} | {len(sel)} | " + " | ".join(block(sel)) + " |")
    masked = [r for r in ok if r["expect"] and r.get("testable") and r.get("masked_by")]
    if masked:  # counted as tested (and missed) above; the rate without them, for what the report says
        test = [r for r in ok if r["expect"] and r.get("testable") and not r.get("masked_by")]
        lines += ["", f"{len(masked)} tested effect(s) the report lists untestable with its first force finding in the "
                      f"model ({', '.join(str(r.get('index', r['case'])) for r in masked)}), counted as misses above; "
                      f"without them: top-1 {rate(test, 'top1')}, top-2 {rate(test, 'top2')}"]
    unconfirmed = [r for r in ok if r["expect"] and not r.get("testable") and r.get("unconfirmed")]
    if unconfirmed:  # left out above (every row) as untestable; the rates with them counted as misses
        test = [r for r in ok if r["expect"] and (r.get("testable") or r.get("unconfirmed"))]
        parts = [(name, [r for r in test if (r["sensors"] == "mocap") == mocap])
                 for name, mocap in (("with motion capture", True), ("without", False))]
        lines += ["", f"{len(unconfirmed)} effect(s) significant on the fitting blocks that the report lists not testable "
                      f"held out ({', '.join(str(r.get('index', r['case'])) for r in unconfirmed)}), left out above; "
                      f"counted as misses: top-1 {rate(test, 'top1')}, top-2 {rate(test, 'top2')}; "
                      + "; ".join(f"{name} top-1 {rate(sel, 'top1')}, top-2 {rate(sel, 'top2')}" for name, sel in parts)]
    # the controls' rate does not see these: a finding that is not there, named while the concealed
    # effect is one the recording cannot test
    blind = [dict(r, wrong=bool(set(r.get("named") or []) - set(r["expect"])))
             for r in ok if r["expect"] and not r.get("testable")]
    if blind:
        wrong = [str(r.get("index", r["case"])) for r in blind if r["wrong"]]
        lines += ["", f"effects the recording cannot test: {rate(blind, 'wrong')} named an effect that is not there"
                      + (f" ({', '.join(wrong)})" if wrong else "")]
    lines += ["", "| effect | cases | testable | top-1 (testable) | top-2 (testable) | param within 15 % |", "|---|---|---|---|---|---|"]
    for eff in sorted({r["expect"][0] for r in ok if r["expect"]}):
        sel = [r for r in ok if r["expect"] and r["expect"][0] == eff]
        b = block(sel)
        lines.append(f"| {eff} | {len(sel)} | {b[1]} | {b[2]} | {b[3]} | {b[4]} |")
    truths = sorted({r["expect"][0] if r["expect"] else "control" for r in ok})
    firsts = sorted({(r["named"] or ["(none)"])[0] for r in ok})
    lines += ["", "confusion (rows: concealed primary effect; columns: first finding)", "",
              "| | " + " | ".join(firsts) + " |", "|" + "---|" * (len(firsts) + 1)]
    for tname in truths:
        sel = [r for r in ok if (r["expect"][0] if r["expect"] else "control") == tname]
        cnt = [sum(1 for r in sel if (r["named"] or ["(none)"])[0] == f) for f in firsts]
        lines.append(f"| {tname} | " + " | ".join(str(c) if c else "" for c in cnt) + " |")
    return "\n".join(lines)


MAX_FAMILY_JSON_BYTES = 256 * 1024 * 1024  # ~1 kB a case: far beyond any run


class ProveError(ValueError):
    """A benchmark run that cannot start; the message is the one line the user sees."""


def run_family(split: str, n: int, out: Path, workers: int = 2, first: int = 0, progress=None) -> list[dict]:
    """Cases first..first+n-1 of `split`, on a process pool; family.json rewritten as each ends."""
    import concurrent.futures as cf
    import multiprocessing as mp

    out.mkdir(parents=True, exist_ok=True)
    path = out / "family.json"
    done = {}
    if path.exists():  # resume: cases already done are kept
        from onboard.files import read_text_bounded

        try:  # a regular file of a sane size (a FIFO or /dev/zero there must not hang or fill memory)
            text = read_text_bounded(path, MAX_FAMILY_JSON_BYTES)
        except (OSError, UnicodeDecodeError) as exc:
            raise ProveError(f"cannot resume from {path}: {getattr(exc, 'strerror', None) or exc}") from exc
        try:
            done = {(r["split"], r["index"]): r for r in json.loads(text)["cases"] if "error" not in r}
        except (ValueError, KeyError, TypeError):
            done = {}
    todo = [i for i in range(first, first + n) if (split, i) not in done]
    rows = [done[(split, i)] for i in range(first, first + n) if (split, i) in done]
    ctx = mp.get_context("spawn")  # numba's threads and fork do not mix (hil/batch.py)
    with cf.ProcessPoolExecutor(max_workers=max(1, workers), mp_context=ctx) as pool:
        futs = {pool.submit(run_family_case, split, i, str(out)): i for i in todo}
        for k, fut in enumerate(cf.as_completed(futs)):
            try:
                row = fut.result()
            except Exception as exc:  # a worker that died
                row = {"case": f"{split}-{futs[fut]:03d}", "split": split, "index": futs[fut], "expect": [],
                       "error": f"{type(exc).__name__}: {exc}"}
            rows.append(row)
            rows.sort(key=lambda r: r["index"])
            path.write_text(json.dumps({"split": split, "cases": rows}, indent=1) + "\n")
            if progress:
                progress(f"[{k + 1}/{len(todo)}] {row['case']}: named {row.get('named', row.get('error'))} "
                         f"({row.get('time_s', '?')} s)")
    return rows


def pooled_rows(paths) -> list[dict]:
    """The cases of several family.json files as one benchmark (blocks run apart: on two machines,
    or a second fresh block at the same code). One split only, each case once."""
    from onboard.files import read_text_bounded

    rows, seen, splits = [], {}, set()
    for path in map(Path, paths):
        try:
            data = json.loads(read_text_bounded(path, MAX_FAMILY_JSON_BYTES))
            cases = data["cases"]
            keys = [(r["split"], int(r["index"])) for r in cases]
            for r in cases:
                if not isinstance(r["split"], str) or not all(
                        isinstance(r.get(k, []), list) and all(isinstance(e, str) for e in r.get(k, []))
                        for k in ("expect", "named")):
                    raise TypeError(f"case {r['index']}: split, expected and named effects are not names")
            family_table(cases)  # every other field the table reads, read once here
        except (OSError, UnicodeDecodeError) as exc:
            raise ProveError(f"cannot read {path}: {getattr(exc, 'strerror', None) or exc}") from exc
        except (ValueError, KeyError, TypeError, AttributeError, OverflowError, RecursionError) as exc:
            raise ProveError(f"{path} is not a benchmark family.json ({type(exc).__name__}: {exc})") from exc
        for key, r in zip(keys, cases):
            if key in seen:
                raise ProveError(f"{key[0]} case {key[1]} is in both {seen[key]} and {path}: pool each case once")
            seen[key] = path
            splits.add(key[0])
            rows.append(r)
    if len(splits) > 1:
        raise ProveError(f"cannot pool cases of different splits ({', '.join(sorted(splits))}): "
                         "development cases were looked at while tuning")
    if not rows:
        raise ProveError("no cases in " + ", ".join(map(str, paths)))
    return sorted(rows, key=lambda r: int(r["index"]))


def configure(parser) -> None:
    parser.add_argument("--out", default="prove_out", help="directory for recordings, reports and prove.json")
    parser.add_argument("--vehicle", default=None, help="reference vehicle TOML (default asr4)")
    parser.add_argument("--duration", type=float, default=120.0, help="pool-session length, s (default 120)")
    parser.add_argument("--only", default=None, help="run only cases whose name contains this text")
    parser.add_argument("--split", choices=sorted(SPLITS), default=None,
                        help="run the benchmark family instead of the classic cases: dev (tuning) or eval seeds")
    parser.add_argument("--cases", type=int, default=30, help="benchmark: how many cases of the split (default 30)")
    parser.add_argument("--first", type=int, default=0, help="benchmark: index of the first case (default 0)")
    parser.add_argument("--workers", type=int, default=2, help="benchmark: worker processes (default 2)")
    parser.add_argument("--dask", action="store_true",
                        help="benchmark: run the cases on jetloop campaign's engine (a local Dask cluster of --workers "
                             "processes; results.parquet and index.html beside family.json)")
    parser.add_argument("--scheduler", default=None, metavar="tcp://HOST:PORT",
                        help="benchmark: run the cases on this existing Dask scheduler (implies --dask)")
    parser.add_argument("--table", nargs="+", default=None, metavar="FAMILY_JSON",
                        help="benchmark: print the table of these family.json files pooled (blocks run apart, "
                             "e.g. two fresh blocks at the same commit); runs nothing")
    parser.add_argument("--quiet", action="store_true")


def run(args) -> int:
    from onboard.vehicle import VehicleFileError, require_jets

    if args.table:
        try:
            print(family_table(pooled_rows(args.table)))
        except ProveError as exc:
            print(f"jetloop prove: {exc}", file=sys.stderr)
            return 2
        return 0

    try:
        reference = load_vehicle(args.vehicle)
        require_jets(reference, "prove")
    except VehicleFileError as exc:
        print(f"jetloop prove: {exc}", file=sys.stderr)
        return 2
    if args.duration < 60:
        print("jetloop prove: --duration must be at least 60 s (the session needs it)", file=sys.stderr)
        return 2
    from ground.cli import make_output_dir

    out = make_output_dir(args.out, "jetloop prove")
    if out is None:
        return 2
    if args.split is not None:
        if args.cases < 1 or args.first < 0 or args.workers < 1:
            print("jetloop prove: --cases and --workers must be at least 1, --first at least 0", file=sys.stderr)
            return 2
        say = None if args.quiet else (lambda msg: print(msg, file=sys.stderr, flush=True))
        if args.dask or args.scheduler:  # the campaign engine (issue 14)
            from ground.campaign.engine import run_prove_family

            rows = run_prove_family(args.split, args.cases, out, args.workers, args.first, args.scheduler,
                                    args.vehicle, quiet=args.quiet)
            (out / "family.json").write_text(json.dumps({"split": args.split, "cases": rows}, indent=1) + "\n")
        else:
            try:
                rows = run_family(args.split, args.cases, out, args.workers, args.first, say)
            except ProveError as exc:
                print(f"jetloop prove: {exc}", file=sys.stderr)
                return 2
        text = family_table(rows)
        (out / "family.md").write_text(text + "\n")
        print(text)
        return 0
    chosen = [c for c in cases() if args.only is None or args.only in c.name]
    if not chosen:
        print(f"jetloop prove: no case matches {args.only!r}", file=sys.stderr)
        return 2
    rows = []
    for i, case in enumerate(chosen):
        if not args.quiet:
            print(f"[{i + 1}/{len(chosen)}] {case.name} ...", file=sys.stderr, flush=True)
        rows.append(run_case(case, out, reference, args.duration))
        (out / "prove.json").write_text(json.dumps({"duration_s": args.duration, "cases": rows}, indent=2) + "\n")
        if not args.quiet:
            r = rows[-1]
            print(f"    named {r['named']}, {'PASS' if r['passed'] else 'FAIL'} ({r['time_s']} s)", file=sys.stderr)
    print(table(rows))
    return 0
