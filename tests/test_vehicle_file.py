"""Vehicle files: the reference loads, and every kind of bad input is one clear VehicleFileError.

Each bad-file case edits one line of the reference file, so the error must name the file, the
dotted key of that one line and what the key must hold, and nothing else may be reported.
"""

from __future__ import annotations

import dataclasses
import math
import tomllib

import pytest

from conftest import SHARED_VEHICLE, shared_file
from onboard.vehicle import (
    DEFAULT_VEHICLE,
    EFFECT_IDS,
    VehicleFileError,
    fragment_toml,
    load_vehicle,
    parse_vehicle,
)


def edited(text: str, old: str, new: str) -> str:
    """`text` with the single occurrence of `old` replaced by `new` (fails if not exactly one)."""
    assert text.count(old) == 1, f"{old!r} occurs {text.count(old)} times in the reference file"
    return text.replace(old, new)


def load_error(tmp_path, text: str) -> tuple[str, str]:
    """Write `text` as a vehicle file, load it, return (path, message) of the one error raised."""
    path = tmp_path / "bad_vehicle.toml"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(VehicleFileError) as info:
        load_vehicle(path)
    assert type(info.value) is VehicleFileError
    return str(path), str(info.value)


def problem_lines(message: str) -> list[str]:
    """The per-key lines of a vehicle-file error: one problem is one line after the file's
    'invalid vehicle file: '; several follow a header line, one a line."""
    lines = message.splitlines()
    if len(lines) == 1:
        return [lines[0].split("invalid vehicle file: ", 1)[1]]
    return [ln.strip() for ln in lines[1:] if ln.strip()]


# --- the reference vehicle ------------------------------------------------------------------

def test_reference_vehicle_loads_with_its_numbers(vehicle):
    assert vehicle.name == "asr4"
    assert vehicle.source == str(DEFAULT_VEHICLE)
    assert vehicle.n_units == 4
    assert vehicle.body.mass == 6.5
    assert vehicle.body.cb == (0.0, 0.0, -0.02)
    assert vehicle.hydro.added_mass == (3.3, 3.3, 4.1, 0.006, 0.006, 0.002)
    assert vehicle.thruster.kt == (0.350165, -0.30192, 0.20207)
    assert vehicle.units[2].position == (-0.07778, -0.07778, 0.07)
    assert vehicle.pwm.elevation_channels == (9, 10, 11, 12)
    assert all(vehicle.effects.on(e) for e in EFFECT_IDS)
    assert vehicle.effects.wall_proximity.k_wall == 0.375
    assert vehicle.get("hydro.linear_damping") == (1.8, 1.8, 2.6, 0.08, 0.08, 0.05)


def test_packaged_default_equals_shared_reference_file():
    """onboard/data/asr4.toml (what the robot carries) holds the shared reference's values.

    Outside the project tree the shared file is absent; then the packaged file must still
    load (checked above), and this comparison has nothing to compare against.
    """
    shared_file(SHARED_VEHICLE)
    packaged = tomllib.loads(DEFAULT_VEHICLE.read_text(encoding="utf-8"))
    shared = tomllib.loads(SHARED_VEHICLE.read_text(encoding="utf-8"))
    assert packaged == shared
    assert dataclasses.replace(load_vehicle(SHARED_VEHICLE), source="x") == dataclasses.replace(
        load_vehicle(), source="x"
    )


# --- one bad line, one clear error ----------------------------------------------------------

BAD_LINES = [
    # (case, old line, new line, dotted key named, words of the expectation)
    ("unknown top-level key", 'name = "asr4"', 'name = "asr4"\ncolour = "yellow"',
     "colour", "unknown key"),
    ("unknown section key", "mass = 6.5 ", "mass = 6.5\nmasss = 6.5 ",
     "body.masss", "unknown key"),
    ("unknown effect", "[effects.current]", "[effects.magic]\nenabled = true\n\n[effects.current]",
     "effects.magic", "unknown key"),
    ("unknown key inside an effect", "k_wall = 0.375", "k_wall = 0.375\nk_wal = 0.2",
     "effects.wall_proximity.k_wal", "unknown key"),
    ("missing key", "radius = 0.16 ", "# radius removed ",
     "body.radius", "missing"),
    ("missing effect key", "k_wall = 0.375", "# k_wall removed",
     "effects.wall_proximity.k_wall", "missing"),
    ("wrong vector length", "inertia = [0.060, 0.060, 0.075]", "inertia = [0.060, 0.060]",
     "body.inertia", "a list of 3 values"),
    ("negative mass", "mass = 6.5 ", "mass = -6.5 ",
     "body.mass", "> 0"),
    ("NaN", "rho = 1000.0 ", "rho = nan ",
     "environment.rho", "finite"),
    ("inf", "n_max = 83.3 ", "n_max = inf ",
     "thruster.n_max", "finite"),
    ("NaN inside a vector", "current = [0.0, 0.0, 0.0]", "current = [0.0, nan, 0.0]",
     "environment.current", "finite"),
    ("angle limit given in degrees", "angle_limit = 1.3963 ", "angle_limit = 80 ",
     "servo.angle_limit", "radians"),
    ("string for a number", "mass = 6.5 ", 'mass = "6.5" ',
     "body.mass", "a finite number"),
    ("boolean as number", "rate_limit = 5.0 ", "rate_limit = true ",
     "servo.rate_limit", "a finite number"),
    ("boolean for enabled given as number", "[effects.motor_lag]\nenabled = true",
     "[effects.motor_lag]\nenabled = 1", "effects.motor_lag.enabled", "true or false"),
    ("non-unit neutral", "neutral = [-0.70711, 0.70711, 0.0]", "neutral = [-1.0, 1.0, 0.0]",
     "unit[1].neutral", "unit vector"),
    ("pwm channel count mismatch", "jet_channels = [1, 2, 3, 4]", "jet_channels = [1, 2, 3]",
     "pwm.jet_channels", "4 channels"),
    ("duplicate channel", "elevation_channels = [9, 10, 11, 12]",
     "elevation_channels = [9, 10, 11, 4]", "pwm.elevation_channels", "once"),
]


@pytest.mark.parametrize("case,old,new,key,expect", BAD_LINES, ids=[c[0] for c in BAD_LINES])
def test_one_bad_line_gives_one_error_naming_file_key_and_expectation(
    tmp_path, reference_text, case, old, new, key, expect
):
    path, msg = load_error(tmp_path, edited(reference_text, old, new))
    assert path in msg.splitlines()[0], msg
    lines = problem_lines(msg)
    assert len(lines) == 1, f"{case}: expected one problem, got:\n{msg}"
    assert lines[0].startswith(key + ":"), f"{case}: key {key!r} not named first in {lines[0]!r}"
    assert expect in lines[0], f"{case}: expectation {expect!r} not in {lines[0]!r}"


def test_angle_limit_error_says_the_allowed_range(tmp_path, reference_text):
    _, msg = load_error(tmp_path, edited(reference_text, "angle_limit = 1.3963 ", "angle_limit = 80 "))
    assert "<= pi" in msg and "80" in msg


def test_every_problem_of_a_file_is_reported_at_once(tmp_path, reference_text):
    text = edited(reference_text, "mass = 6.5 ", "mass = -1.0 ")
    text = edited(text, "rate_limit = 5.0 ", 'rate_limit = "fast" ')
    _, msg = load_error(tmp_path, text)
    lines = problem_lines(msg)
    assert len(lines) == 2
    assert lines[0].startswith("body.mass:") and lines[1].startswith("servo.rate_limit:")


def test_invalid_toml_names_file_and_place(tmp_path, reference_text):
    path, msg = load_error(tmp_path, edited(reference_text, "mass = 6.5 ", "mass = = 6.5 "))
    assert path in msg
    assert "not valid TOML" in msg
    # tomllib reports the line: the edited line is the one holding `mass`
    line_no = reference_text.splitlines().index(
        next(ln for ln in reference_text.splitlines() if ln.startswith("mass = 6.5"))
    ) + 1
    assert f"line {line_no}" in msg


@pytest.mark.parametrize("kind", ["missing file", "directory"])
def test_unreadable_path_is_a_vehicle_file_error(tmp_path, kind):
    path = tmp_path / "nowhere.toml" if kind == "missing file" else tmp_path
    with pytest.raises(VehicleFileError) as info:
        load_vehicle(path)
    assert str(path) in str(info.value)
    assert "cannot read" in str(info.value)


def test_parse_vehicle_names_its_source(reference_text):
    with pytest.raises(VehicleFileError) as info:
        parse_vehicle(edited(reference_text, "mass = 6.5 ", "mass = 0.0 "), source="fitted.toml")
    assert str(info.value).startswith("fitted.toml:")
    assert "body.mass" in str(info.value)


# --- effects switched off, with_effects, with_values ------------------------------------------

@pytest.mark.parametrize("effect_id", EFFECT_IDS)
def test_each_effect_switches_off_in_the_file(tmp_path, reference_text, effect_id):
    head = f"[effects.{effect_id}]"
    start = reference_text.index(head)
    at = reference_text.index("enabled = true", start)
    text = reference_text[:at] + "enabled = false" + reference_text[at + len("enabled = true"):]
    path = tmp_path / "off.toml"
    path.write_text(text, encoding="utf-8")
    v = load_vehicle(path)
    assert not v.effects.on(effect_id)
    assert all(v.effects.on(e) for e in EFFECT_IDS if e != effect_id)


@pytest.mark.parametrize("effect_id", EFFECT_IDS)
def test_with_effects_switches_one_and_keeps_the_rest(vehicle, effect_id):
    off = vehicle.with_effects(**{effect_id: False})
    assert not off.effects.on(effect_id)
    assert all(off.effects.on(e) for e in EFFECT_IDS if e != effect_id)
    assert vehicle.effects.on(effect_id), "with_effects must not change the original"
    assert off.with_effects(**{effect_id: True}) == vehicle


def test_with_effects_rejects_an_unknown_effect(vehicle):
    with pytest.raises(VehicleFileError, match="effects.magic"):
        vehicle.with_effects(magic=False)


def test_with_values_replaces_dotted_keys(vehicle):
    v = vehicle.with_values({
        "body.mass": 7.25,
        "hydro.added_mass": [3.0, 3.1, 4.0, 0.01, 0.01, 0.003],
        "effects.wall_proximity.k_wall": 0.5,
        "unit[2].position": [-0.08, -0.08, 0.06],
    })
    assert v.body.mass == 7.25
    assert v.hydro.added_mass == (3.0, 3.1, 4.0, 0.01, 0.01, 0.003)
    assert v.effects.wall_proximity.k_wall == 0.5
    assert v.units[2].position == (-0.08, -0.08, 0.06)
    assert v.units[1] == vehicle.units[1]
    assert vehicle.body.mass == 6.5


@pytest.mark.parametrize("key,value,expect", [
    ("body.mass", -1.0, "> 0"),
    ("body.inertia", [0.06, 0.06], "3 values"),
    ("hydro.added_mass", [float("nan")] * 6, "finite"),
    ("servo.angle_limit", 80.0, "radians"),
    ("thruster.n_max", True, "a finite number"),
    ("effects.motor_lag.enabled", "yes", "true or false"),
])
def test_with_values_validates_like_a_file(vehicle, key, value, expect):
    with pytest.raises(VehicleFileError) as info:
        vehicle.with_values({key: value})
    assert key in str(info.value) and expect in str(info.value)


def test_with_values_rejects_an_unknown_key(vehicle):
    with pytest.raises(VehicleFileError, match="hydro.added_mas"):
        vehicle.with_values({"hydro.added_mas": [0.0] * 6})


@pytest.mark.parametrize("key,value,expect", [
    ("unit[0].neutral", [2.0, 0.0, 0.0], "unit vector"),
    ("pwm.jet_channels", [1, 2, 3], "4 channels"),
    ("thruster.j_range", [0.5, 0.1], "min < max"),
])
def test_with_values_checks_consistency_like_a_file(vehicle, key, value, expect):
    with pytest.raises(VehicleFileError) as info:
        vehicle.with_values({key: value})
    assert key in str(info.value) and expect in str(info.value)


# --- fragments --------------------------------------------------------------------------------

def test_fragment_toml_parses_back_to_the_same_values(vehicle):
    import numpy as np

    values = {
        "hydro.added_mass": np.array([3.31, 3.29, 4.6, 0.0061, 0.006, 0.0021]),
        "hydro.linear_damping": (1.8, 1.8, 2.6, 0.08, 0.08, 0.05),
        "body.mass": np.float64(6.75),
        "effects.wall_proximity.k_wall": 0.4125,
        "effects.motor_lag.enabled": False,
        "thruster.motor_time_constant": 0.0912345,
    }
    text = fragment_toml(values)
    doc = tomllib.loads(text)
    flat = {}
    for table, body in doc.items():
        stack = [(table, body)]
        while stack:
            prefix, node = stack.pop()
            for k, val in node.items():
                if isinstance(val, dict):
                    stack.append((f"{prefix}.{k}", val))
                else:
                    flat[f"{prefix}.{k}"] = val
    assert set(flat) == set(values)
    for key, want in values.items():
        got = flat[key]
        if isinstance(want, bool):
            assert got is want
        elif np.ndim(want):
            assert np.allclose(got, want, rtol=1e-6, atol=0)
        else:
            assert math.isclose(got, float(want), rel_tol=1e-6)
    # ... and the parsed fragment goes back into a vehicle
    v = vehicle.with_values(flat)
    assert v.body.mass == 6.75
    assert not v.effects.on("motor_lag")
    assert v.hydro.added_mass[2] == 4.6


def test_fragment_with_a_unit_key_stays_valid_toml_and_names_the_table():
    import tomllib

    from onboard.vehicle import fragment_toml

    text = fragment_toml({"hydro.added_mass": [1, 2, 3, 4, 5, 6], "unit[2].position": [0.1, 0.2, 0.3]})
    doc = tomllib.loads(text)
    assert doc["hydro"]["added_mass"] == [1, 2, 3, 4, 5, 6]
    assert "# unit[2].position = [0.1, 0.2, 0.3]" in text and "[[unit]] number 3" in text


# --- issue 15 item 10: files that parse but make no sense --------------------------------------

ABSURD = [
    # (old line, new line, the one problem line expected, word by word)
    ("mass = 6.5 ", "mass = 6500.0 ", "body.mass 6500 kg: expected 0.1-1000 kg; grams?"),
    ("mass = 6.5 ", "mass = " + "9" * 400 + " ", "body.mass: expected a finite number > 0, got an integer of 400 digits"),
    ("g = 9.81 ", "g = 1e300 ", "environment.g 1e+300 m/s^2: expected 1-30 m/s^2"),
    ("gyro_noise = 0.003 ", "gyro_noise = 1e300 ", "sensors.gyro_noise 1e+300 rad/s: expected 0-1 rad/s; deg/s?"),
    ("imu_rate = 100.0 ", "imu_rate = 1e-6 ", "sensors.imu_rate 1e-06 Hz: expected 1-4000 Hz"),
    ("imu_rate = 100.0 ", "imu_rate = 1e7 ", "sensors.imu_rate 1e+07 Hz: expected 1-4000 Hz"),
    ("j_range = [0.0, 0.54]", "j_range = [0.0, 1e300]", "thruster.j_range 1e+300: expected -10 to 10 for each element (advance ratio [min, max])"),
    ("gain_per_newton = 0.0126 ", "gain_per_newton = 1e300 ",
     "effects.azimuth_transient.gain_per_newton 1e+300 1/N: expected 0-1 1/N"),
    ("n_max = 83.3 ", "n_max = 5000.0 ", "thruster.n_max 5000 rev/s: expected 0.1-2000 rev/s; rpm? expected rev/s"),
    ("volume = 0.00665 ", "volume = 6.65 ", "body.volume 6.65 m^3: expected 1e-05-2 m^3; litres?"),
    # issue 15, second pass: each key in its range, together absurd
    ("mass = 6.5 ", "mass = 1000.0 ", "body.mass 1000 kg with body.volume 0.00665 m^3: buoyancy/weight rho V / m "
     "0.00665: expected 0.5-2 (near neutral); grams? litres?"),
    # a hostile user's find (2026-12-02): a radius its volume could not fill, or overfills a
    # thousandfold (hand: 0.00665 / (4/3 pi 5^3) = 1.27e-5; / (4/3 pi 0.01^3) = 1588)
    ("radius = 0.16 ", "radius = 5.0 ", "body.radius 5 m with body.volume 0.00665 m^3: the volume fills 1.27e-05 of "
     "the radius' sphere (under the limit): expected 0.01-20 (the hull sphere's radius); a length? cm?"),
    ("radius = 0.16 ", "radius = 0.01 ", "body.radius 0.01 m with body.volume 0.00665 m^3: the volume fills 1.59e+03 "
     "of the radius' sphere (over the limit): expected 0.01-20 (the hull sphere's radius); a length? cm?"),
    # just over the limit, printed "20" at .3g: the words say which side (hand: radius 0.04297 m,
    # 0.00665 / (4/3 pi 0.04297^3) = 20.01)
    ("radius = 0.16 ", "radius = 0.04297 ", "body.radius 0.04297 m with body.volume 0.00665 m^3: the volume fills 20 "
     "of the radius' sphere (over the limit): expected 0.01-20 (the hull sphere's radius); a length? cm?"),
    ("kt = [0.350165, -0.30192, 0.20207]", "kt = [0.0, 0.0, 0.0]",
     "thruster.kt [0, 0, 0]: K(J) 0 at J = 0: expected K(J) > 0 over j_range [0, 0.54] (a jet that pushes "
     "nothing, or backwards)"),
    ("kt = [0.350165, -0.30192, 0.20207]", "kt = [0.350165, -1.30192, 0.20207]",
     "thruster.kt [0.350165, -1.30192, 0.20207]: K(J) -0.294 at J = 0.54: expected K(J) > 0 over j_range [0, 0.54] "
     "(a jet that pushes nothing, or backwards)"),
    # a fuzz example (2026-11-25): positive but nothing (hand: 1000 x 83.3^2 x 0.0365^4 x 1e-300 = 1.23e-299 N)
    ("kt = [0.350165, -0.30192, 0.20207]", "kt = [1e-300, 0.0, 0.0]",
     "thruster.kt [1e-300, 0, 0]: a jet's thrust at n_max is 1.23e-299 N at J = 0: expected at least 0.001 N "
     "(a jet that pushes nothing)"),
    # issue 15, adversarial re-run: seed-004 rows whose denominator is zero or unstable passed
    # (onboard died on a LinAlgError / an unstable yaw-preview plan; the plant diverged)
    ("m1z = [711.34, 15.20, 839.31, 4751.00, 229.90]", "m1z = [711.34, 0.0, 0.0, 0.0, 0.0]",
     "effects.azimuth_transient.m1z [711.34, 0, 0, 0, 0]: a pole with Re >= 0: expected a stable transient (seed 004), "
     "or enabled = false"),
    ("m1z = [711.34, 15.20, 839.31, 4751.00, 229.90]", "m1z = [711.34, 1.0, 1.0, 4751.0, 229.9]",
     "effects.azimuth_transient.m1z [711.34, 1, 1, 4751, 229.9]: a pole with Re >= 0: expected a stable transient (seed 004), "
     "or enabled = false"),
    ("f1x = [1035.34, 76.51, 127.9, 9.88, 1.00, 6.40, 3228.49]", "f1x = [1035.34, 76.51, 127.9, -9.88, 1.0, 6.4, 3228.49]",
     "effects.azimuth_transient.f1x [1035.34, 76.51, 127.9, -9.88, 1, 6.4, 3228.49]: a pole with Re >= 0: "
     "expected a stable transient (seed 004), or enabled = false"),
]


@pytest.mark.parametrize("old,new,expect", ABSURD, ids=[a[1][:30] for a in ABSURD])
def test_absurd_values_are_refused_with_the_range_and_units(tmp_path, reference_text, old, new, expect):
    """A 400-digit integer was an OverflowError traceback; 1e300 noise or g, imu_rate 1e-6 or 1e7,
    j_range 1e300 were accepted and crashed or hung later. The message says the range in the
    key's units and the likely slip, and echoes at most a few dozen characters."""
    path, msg = load_error(tmp_path, edited(reference_text, old, new))
    assert problem_lines(msg) == [expect]
    assert len(msg) < len(path) + 200


def test_units_that_cannot_make_every_wrench_are_refused(vehicle):
    """All units at the origin (or on one line) cannot turn the body about every axis: the
    allocation needs a rank-6 wrench map (today a LinAlgError in onboard, a hang in demo)."""
    at_origin = {f"unit[{i}].position": [0.0, 0.0, 0.0] for i in range(4)}
    on_a_line = {f"unit[{i}].position": [0.05 * i, 0.0, 0.07] for i in range(4)}
    for values in (at_origin, on_a_line):
        with pytest.raises(VehicleFileError, match="rank < 6"):
            vehicle.with_values(values)
    vehicle.with_values({f"unit[{i}].position": [0.05 * i, 0.01 * i * i, 0.07] for i in range(4)})


def test_transient_rows_are_checked_only_when_the_transient_is_on(vehicle):
    """bluerov2_heavy writes zeros with the effect off; the loop does not model them then."""
    zeros = {f"effects.azimuth_transient.{r}": [0.0] * (5 if r == "m1z" else 7) for r in ("f1x", "f1y", "m1z", "f2x", "f2z")}
    with pytest.raises(VehicleFileError, match="pole with Re >= 0"):
        vehicle.with_values(zeros)
    vehicle.with_values({**zeros, "effects.azimuth_transient.enabled": False})


def test_a_transient_the_yaw_preview_cannot_plan_for_flies_without_it(tmp_path, reference_text, capsys):
    """A stable transient unlike seed 004's (m1z's K ten times larger: one of 59 in 199 rows drawn
    within 10x of seed 004's) made the yaw preview's plan unstable, and `jetloop onboard` died at
    start with a ValueError traceback (issue 15, adversarial re-run). The preview is a refinement:
    the loop flies with the compensation alone and says why on one line."""
    from ground.cli import main
    from hil.sim import FIXED_EPOCH_US, parse_commands, simulate, vehicle_channels
    from hil.tlog import TlogWriter

    text = edited(reference_text, "m1z = [711.34, 15.20, 839.31, 4751.00, 229.90]",
                  "m1z = [7113.4, 15.20, 839.31, 4751.00, 229.90]")
    path = tmp_path / "strong_m1z.toml"
    path.write_text(text)
    v = load_vehicle(path)
    chans = vehicle_channels(v)
    rec = tmp_path / "r.tlog"
    with TlogWriter(rec) as w:  # a second of the vehicle's own sensor stream to fly on
        csv = "t," + ",".join(f"pwm{c}" for c in chans) + "\n0," + ",".join("1500" for _ in chans) + "\n1,"
        for chunk in simulate(v, parse_commands(csv + ",".join("1500" for _ in chans) + "\n", "c", chans)):
            for t_us, msg in chunk.messages:
                w.write(msg, FIXED_EPOCH_US + t_us)
    code = main(["onboard", "--vehicle", str(path), "--link", f"tlog:{rec}", "--lockstep",
                 "--params", str(tmp_path / "p.params")])
    out = capsys.readouterr()
    assert code == 0 and "Traceback" not in out.err, out.err[-2000:]
    lines = [x for x in out.out.splitlines() if "yaw preview off" in x]
    assert len(lines) == 1 and "unstable" in lines[0], out.out


def test_a_channel_used_four_times_is_one_problem_in_one_line(tmp_path, reference_text):
    """Issue 15 re-run: `jet_channels = [1, 1, 1, 1]` said the same line three times under "3
    problems", and a channel out of range read "a list of channel number 1..16s"."""
    path, msg = load_error(tmp_path, edited(reference_text, "jet_channels = [1, 2, 3, 4]", "jet_channels = [1, 1, 1, 1]"))
    assert msg == (f"{path}: invalid vehicle file: pwm.jet_channels: expected each channel used once "
                   "(channel 1 is already in pwm.jet_channels), got [1, 1, 1, 1]")
    path, msg = load_error(tmp_path, edited(reference_text, "jet_channels = [1, 2, 3, 4]", "jet_channels = [99, 2, 3, 4]"))
    assert problem_lines(msg) == ["pwm.jet_channels: expected a list of values, each a channel number 1..16, "
                                  "one per unit, got [99, 2, 3, 4]"]


def test_a_huge_array_is_echoed_in_a_few_characters(tmp_path, reference_text):
    """A 3-million-element array made an 18 MB error message (a file of at most 1 MB, the vehicle
    file's bound, can still hold 150,000 values)."""
    big = "[" + ", ".join(["1.0"] * 150_000) + "]"
    path, msg = load_error(tmp_path, edited(reference_text, "inertia = [0.060, 0.060, 0.075]", f"inertia = {big}"))
    assert len(msg) < len(path) + 250 and "(150000 values)" in msg


def test_control_characters_in_the_name_are_refused(tmp_path, reference_text):
    """Issue 15 item 11: the name is printed on terminals; an escape sequence in it was printed raw."""
    path, msg = load_error(tmp_path, edited(reference_text, 'name = "asr4"', 'name = "asr4\\u001b[2J\\u0007"'))
    assert problem_lines(msg)[0].startswith("name: expected a non-empty string of at most 64 printable")
    assert "\x1b" not in msg and "\x07" not in msg


def test_a_utf8_byte_order_mark_is_accepted_like_the_commands_csv(tmp_path, reference_text):
    """Issue 15 item 11: a UTF-8 BOM (Notepad's) was refused as invalid TOML; the CSV reader accepts one."""
    path = tmp_path / "bom.toml"
    path.write_bytes(b"\xef\xbb\xbf" + reference_text.encode())
    assert load_vehicle(path).body.mass == 6.5


COMMANDS_WITH_VEHICLE = {
    "sim": ["--commands", "c.csv", "--out", "o.tlog"], "identify": ["free-decay"], "diagnose": ["r.tlog"],
    "prove": [], "demo": [], "onboard": ["--link", "udpin:127.0.0.1:1"], "hil": [], "ground": [], "soak": [],
    "plot": ["r.tlog", "--out", "o"],
}


@pytest.mark.parametrize("command", sorted(COMMANDS_WITH_VEHICLE))
def test_every_command_refuses_an_absurd_vehicle_with_exit_2_and_no_traceback(tmp_path, reference_text,
                                                                              command, capsys, monkeypatch):
    from ground.cli import main

    monkeypatch.chdir(tmp_path)
    (tmp_path / "r.tlog").write_bytes(b"")
    bad = tmp_path / "bad.toml"
    bad.write_text(edited(reference_text, "mass = 6.5 ", "mass = " + "7" * 400 + " "))
    assert main([command, *COMMANDS_WITH_VEHICLE[command], "--vehicle", str(bad)]) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and "body.mass" in err and len(err) < 600, err
    assert len(err.strip().splitlines()) == 1, err  # one clear line


def _leaves(obj, path=""):
    """Every (dotted path, value) of a vehicle, down to single numbers, strings and booleans."""
    if dataclasses.is_dataclass(obj):
        for f in dataclasses.fields(obj):
            yield from _leaves(getattr(obj, f.name), f"{path}.{f.name}" if path else f.name)
    elif isinstance(obj, (tuple, list)):
        for i, x in enumerate(obj):
            yield from _leaves(x, f"{path}[{i}]")
    else:
        yield path, obj


@pytest.mark.parametrize("name", ["bluerov2_heavy", "asr4"])
def test_vehicle_toml_round_trip_is_exact(name):
    """ground.prove.vehicle_toml writes a vehicle that loads back with every value the same double
    (the T200 table's -39.9079290382407 came back as -39.9079: six significant digits)."""
    from ground.prove import vehicle_toml

    v = load_vehicle(name)
    back = parse_vehicle(vehicle_toml(v), source=v.source)
    got, want = dict(_leaves(back)), dict(_leaves(v))
    assert got.keys() == want.keys()
    differ = {k: (want[k], got[k]) for k in want
              if type(got[k]) is not type(want[k]) or repr(got[k]) != repr(want[k])}
    assert not differ, f"{len(differ)} of {len(want)} values differ, e.g. {list(differ.items())[:3]}"
    assert len(want) > (500 if name == "bluerov2_heavy" else 100)  # the walk reached the tables
