"""`jetloop prove`: the checks themselves, a representative case fast, every case slow."""

from __future__ import annotations

import json
import math

import pytest

from ground.cli import main
from ground.prove import (Case, _param_error, cases, family_case, family_table, run_case, run_family_case,
                          session_setpoints, table)
from onboard.vehicle import load_vehicle

V = load_vehicle()


def test_cases_cover_every_effect_and_parameter_and_controls():
    expected = {c.expect[0] for c in cases() if c.expect}
    assert expected >= {"thrust_inflow", "motor_lag", "servo_lag", "azimuth_transient", "surface_proximity",
                        "wall_proximity", "current", "added_mass", "linear_damping", "quadratic_damping",
                        "buoyancy", "restoring_moment", "imu_bias", "sensor_delay", "thruster_fault", "unknown"}
    assert sum(1 for c in cases() if not c.expect) >= 3
    assert any(len(c.expect) == 2 for c in cases())  # a second effect masking the first
    # every case's vehicles are valid vehicle files
    for c in cases():
        V.with_values(c.truth_values)
        V.with_values(c.nominal_values)


def test_nominal_vehicle_file_loads_back_equal():
    import dataclasses

    from ground.prove import vehicle_toml
    from onboard.vehicle import parse_vehicle

    for c in cases()[:8]:
        nominal = V.with_values(c.nominal_values)
        back = parse_vehicle(vehicle_toml(nominal, "# note"))
        assert dataclasses.replace(back, source="") == dataclasses.replace(nominal, source="")


def test_session_has_dives_runs_turns_and_a_surfacing():
    sp = session_setpoints(120.0, 0)
    depths = [s[1] for s in sp]
    assert min(depths) < 0.0 < 0.9 < max(depths)  # a surfacing and the floor (1.2 m)
    assert any(abs(s[2]) > 1.0 for s in sp)  # turns
    assert any(abs(s[3]) > 1.0 for s in sp) and any(abs(s[4]) > 1.0 for s in sp)  # surge and sway runs


def test_parameter_error_is_relative_and_missing_parameters_fail():
    case = Case("x", ("buoyancy",), check={"body.volume": 0.0067})
    found = [{"effect": "buoyancy", "parameters": {"body.volume": 0.0067 * 1.1}}]
    assert _param_error(case, found) == pytest.approx(0.1)
    vec = Case("y", ("added_mass",), check={"hydro.added_mass[2]": 4.0})
    got = [{"effect": "added_mass", "parameters": {"hydro.added_mass": [3.3, 3.3, 3.0, 0, 0, 0]}}]
    assert _param_error(vec, got) == pytest.approx(0.25)
    assert math.isinf(_param_error(case, [{"effect": "current", "parameters": {}}]))


def test_table_keeps_failures():
    rows = [
        {"case": "a", "named": ["buoyancy"], "param_error": 0.01, "nrmse_before": 0.2, "nrmse_after": 0.05,
         "nrmse_drop": 0.75, "time_s": 10, "checks": {"named_first": True}, "passed": True},
        {"case": "b", "named": [], "param_error": None, "param_reported": False, "nrmse_before": 0.2,
         "nrmse_after": 0.2, "nrmse_drop": 0.0, "time_s": 10, "checks": {"named_first": False}, "passed": False},
    ]
    text = table(rows)
    assert "1/2 cases pass" in text and "FAIL (named_first)" in text


def test_buoyancy_case_passes(tmp_path):
    """Representative: a 0.5 % volume error (0.33 N, about the accelerometer noise in heave)."""
    case = next(c for c in cases() if c.expect == ("buoyancy",))
    row = run_case(case, tmp_path, V, duration_s=60.0)
    assert row["named"][0] == "buoyancy"
    assert row["param_error"] < 0.15
    assert row["checks"]["windows_overlap"]
    assert row["nrmse_after"] < row["nrmse_before"]  # (the 40 % is a benchmark median, README)
    assert (tmp_path / f"{case.name.replace(' ', '_').replace('+', '_').replace('.', '_').replace('%', '_')}.tlog").exists() or \
        any(p.suffix == ".tlog" for p in tmp_path.iterdir())


@pytest.mark.slow
def test_control_case_gives_no_finding(tmp_path):
    case = next(c for c in cases() if not c.expect)
    row = run_case(case, tmp_path, V, duration_s=60.0)
    assert row["named"] == [] and row["passed"]


@pytest.mark.slow
def test_a_tether_no_known_effect_has_is_named_unknown(tmp_path):
    """The classic `unknown` case (a 0.6 N/m horizontal tether) at 60 s: its fitting windows'
    held-out chi-square stands above the null draws' median by more than the Z_GATE margin
    (2501 against 1650, gate 265 on 2026-11-26), and the sparse term finds the spring."""
    case = next(c for c in cases() if c.expect == ("unknown",))
    row = run_case(case, tmp_path, V, duration_s=60.0)
    assert row["named"] == ["unknown"] and row["nrmse_after"] < row["nrmse_before"]


@pytest.mark.slow
@pytest.mark.parametrize("index", [2232, 2259])
def test_a_long_perfect_model_recording_gets_no_unknown_term(index, tmp_path):
    """Eval controls 2232 (600 s, 25 Hz ArduSub rates) and 2259 (600 s, 50 Hz IMU): the smoother's
    slow drift left a whole-recording chi2/dof of 1.23-1.26 and a sparse `unknown` term fitted
    58-66 % of it; the windows' chi-square against the null draws' median gates it (core.diagnose)."""
    row = run_family_case("eval", index, tmp_path)
    assert row["expect"] == [] and row["named"] == []


@pytest.mark.slow
def test_prove_command_writes_prove_json(tmp_path, capsys):
    assert main(["prove", "--out", str(tmp_path), "--only", "wall_proximity missing", "--duration", "60", "--quiet"]) == 0
    out = capsys.readouterr().out
    assert "wall_proximity missing" in out and "cases pass" in out
    data = json.loads((tmp_path / "prove.json").read_text())
    assert len(data["cases"]) == 1 and data["cases"][0]["case"] == "wall_proximity missing"


def test_family_table_has_wilson_intervals_and_the_confusion_matrix():
    rows = [
        {"case": "c", "expect": [], "named": [], "sensors": "imu", "pilot": "legs"},
        {"case": "f", "expect": [], "named": ["current"], "sensors": "mocap", "pilot": "legs"},
        {"case": "b", "expect": ["buoyancy"], "named": ["buoyancy"], "sensors": "imu", "pilot": "legs",
         "testable": True, "top1": True, "top2": True, "param_error": 0.02, "within_3sd": True, "nrmse_drop": 0.5,
         "nrmse_before": 0.1, "nrmse_after": 0.05},
        {"case": "x", "expect": ["current"], "error": "ValueError: boom", "sensors": "imu", "pilot": "legs"},
    ]
    text = family_table(rows)
    assert "4 cases (1 raised), 2 controls" in text
    assert "| all | 3 | 1/2 (50 %, 9-91) |" in text  # false findings on controls, Wilson 95 %
    assert "| control | (none) |" not in text and "| control |" in text and "| buoyancy |" in text
    assert "first force finding in the model" not in text
    assert "effects the recording cannot test" not in text
    # an effect the report lists untestable with its first finding in the model: a tested miss
    # (prove._testable keeps the first pass's verdict), and the rate without it printed apart
    rows.append({"case": "m", "index": 7, "expect": ["added_mass", "restoring_moment"], "named": ["restoring_moment"],
                 "sensors": "imu", "pilot": "legs", "testable": True, "masked_by": "restoring_moment",
                 "top1": False, "top2": False, "nrmse_before": 0.1, "nrmse_after": 0.05})
    text = family_table(rows)
    assert "| all | 4 | 1/2 (50 %, 9-91) | 2/2 (100 %, 34-100) | 1/2 (50 %, 9-91) |" in text
    # the masked cases apart from the rest, each row counted like "all". Wilson 95 % by hand
    # (z = 1.96, z^2 = 3.8416): 1/1 -> centre (1 + z^2/2) / (1 + z^2) = 0.603, half-width
    # z (z/2) / (1 + z^2) = 0.397: 0.21-1; 0/1 -> 0-0.79; 1/2 -> 0.5 -+ 0.405: 0.09-0.91
    assert "| effects: one (and controls) | 3 | 1/2 (50 %, 9-91) | 1/1 (100 %, 21-100) | 1/1 (100 %, 21-100) |" in text
    assert "| effects: masked by a second | 1 | - | 1/1 (100 %, 21-100) | 0/1 (0 %, 0-79) |" in text
    assert "1 tested effect(s) the report lists untestable with its first force finding in the model (7), counted as " \
           "misses above; without them: top-1 1/1 (100 %, 21-100), top-2 1/1 (100 %, 21-100)" in text
    # an effect the recording cannot test, and a finding named that is not there: the controls'
    # rate does not see it, this line does (the concealed masking second named is no such finding)
    rows += [{"case": "u", "index": 8, "expect": ["current"], "named": ["sensor_delay"], "sensors": "ardusub",
              "pilot": "legs", "testable": False},
             {"case": "v", "index": 9, "expect": ["wall_proximity", "motor_lag"], "named": ["motor_lag"],
              "sensors": "imu", "pilot": "legs", "testable": False}]
    assert "effects the recording cannot test: 1/2 (50 %, 9-91) named an effect that is not there (8)" in \
        family_table(rows)
    assert "not testable held out" not in family_table(rows)
    # significant on the fitting blocks but out of the held-out blocks' reach (core._unconfirmable):
    # left out as untestable, and the rate with it counted as a miss printed apart
    rows.append({"case": "q", "index": 10, "expect": ["quadratic_damping"], "named": [], "sensors": "mocap",
                 "pilot": "joystick", "testable": False, "unconfirmed": True, "top1": False, "top2": False})
    text = family_table(rows)
    assert "| all | 7 | 1/2 (50 %, 9-91) | 2/5 (40 %, 12-77) | 1/2 (50 %, 9-91) |" in text
    assert "1 effect(s) significant on the fitting blocks that the report lists not testable held out (10), left " \
           "out above; counted as misses: top-1 1/3 (33 %, 6-79), top-2 1/3 (33 %, 6-79); with motion capture " \
           "top-1 0/1 (0 %, 0-79), top-2 0/1 (0 %, 0-79); without top-1 1/2 (50 %, 9-91), top-2 1/2 (50 %, 9-91)" in text


# A small stratified subset of the benchmark's development split, run in CI, chosen by a rule, not
# by its outcome: for each sensor set, the first control and the first effect case among the dev
# cases of at most 90 s. Failures stay visible as strict xfails (measured, README benchmark).
def _subset():
    picked, seen = [], set()
    for i in range(200):
        case, flight, _ = family_case("dev", i)
        key = (flight.sensors, bool(case.expect))
        if flight.duration_s <= 90.0 and key not in seen:
            seen.add(key)
            picked.append(i)
    return picked


SUBSET_FAILS = {  # measured on the dev split (README benchmark): below their calibrated thresholds
    6: "wall_proximity at 1.2x from 60 s at ArduSub rates (25 Hz IMU): not detected",
    7: "quadratic damping named linear since the fitting windows tile the recording (2ef7a6f, 2026-11-28; "
       "named right with whole 10 s windows from the start; the change also reshuffles the null draws)",
}  # 27, a heave added mass -33 % (1.3x) without motion capture, is named since the tiled windows (which also
# reshuffle the null draws); 29, a control at ArduSub rates named a 5.4 ms delay since bd15df1, is clean since
# the smoother's settling start (076b2ab)


@pytest.mark.slow
@pytest.mark.parametrize("index", [pytest.param(i, marks=pytest.mark.xfail(reason=SUBSET_FAILS[i], strict=True))
                                   if i in SUBSET_FAILS else i for i in _subset()])
def test_benchmark_subset(index, tmp_path):
    row = run_family_case("dev", index, tmp_path)
    assert "error" not in row, row.get("error")
    if not row["expect"]:
        assert row["named"] == [], f"false finding on a control: {row['named']}"
    else:
        assert row["top2"], f"expected {row['expect']}, named {row['named']}"
        assert row["nrmse_after"] <= row["nrmse_before"]


def test_a_family_json_that_is_not_a_file_is_one_line(tmp_path, capsys):
    """Resuming reads family.json bounded: a FIFO there (or a device) is one line, exit 2, never a
    hang or memory filled (issue 15 hardening, found by its second adversarial run)."""
    import os

    from ground.cli import main

    os.mkfifo(tmp_path / "family.json")
    assert main(["prove", "--split", "dev", "--cases", "1", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"jetloop prove: cannot resume from {tmp_path / 'family.json'}: not a regular file (a device, pipe or directory)"


def _family_json(path, split, indices, named):
    rows = [{"case": f"{split}-{i}", "split": split, "index": i, "expect": ["buoyancy"], "named": named,
             "sensors": "mocap", "pilot": "legs", "testable": True, "top1": named == ["buoyancy"],
             "top2": "buoyancy" in named} for i in indices]
    path.write_text(json.dumps({"split": split, "cases": rows}))
    return str(path)


def test_prove_table_pools_family_jsons_once_each_and_one_split(tmp_path, capsys):
    """`jetloop prove --table A B`: two blocks as one benchmark (two fresh blocks at the same
    commit, or a block split over machines): 2 hits of 3 and 1 of 1 are 3 of 4, Wilson 30-95 %."""
    a = _family_json(tmp_path / "a.json", "eval", [10, 11, 12], ["buoyancy"])
    b = _family_json(tmp_path / "b.json", "eval", [13], ["buoyancy"])
    miss = json.loads((tmp_path / "a.json").read_text())
    miss["cases"][0].update(named=[], top1=False, top2=False)
    (tmp_path / "a.json").write_text(json.dumps(miss))
    assert main(["prove", "--table", a, b]) == 0
    out = capsys.readouterr().out
    assert out.startswith("4 cases (0 raised), 0 controls")
    assert "| all | 4 | - | 4/4 (100 %, 51-100) | 3/4 (75 %, 30-95) | 3/4 (75 %, 30-95) |" in out
    # each case once, one split, and a file that is not a family.json: one line each, exit 2
    dev = _family_json(tmp_path / "dev.json", "dev", [14], ["buoyancy"])
    (tmp_path / "junk.json").write_text("{\"cases\": [{\"split\": \"eval\"}]}")
    for args, err in ((["--table", a, a], f"jetloop prove: eval case 10 is in both {a} and {a}: pool each case once"),
                      (["--table", a, dev], "jetloop prove: cannot pool cases of different splits (dev, eval): "
                                            "development cases were looked at while tuning"),
                      (["--table", str(tmp_path / "junk.json")],
                       f"jetloop prove: {tmp_path / 'junk.json'} is not a benchmark family.json (KeyError: 'index')"),
                      (["--table", str(tmp_path / "none.json")],
                       f"jetloop prove: cannot read {tmp_path / 'none.json'}: No such file or directory")):
        assert main(["prove", *args]) == 2
        assert capsys.readouterr().err.strip() == err
    # hostile rows (a review's finds: each had ended in a traceback): one line each, exit 2
    good = {"case": "eval-1", "split": "eval", "index": 1, "expect": ["buoyancy"], "named": [], "sensors": "imu",
            "pilot": "legs", "testable": True, "top1": False, "top2": False}
    for i, bad in enumerate([dict(good, index=1e999), dict(good, split=[]), dict(good, expect=[[1]]),
                             dict(good, named=5), dict(good, named="abc"), dict(good, param_error="x", top2=True),
                             dict(good, nrmse_drop="a"), {k: v for k, v in good.items() if k != "sensors"}]):
        path = tmp_path / f"bad{i}.json"
        path.write_text(json.dumps({"split": "eval", "cases": [bad]}).replace("1e+999", "1e999"))
        assert main(["prove", "--table", str(path)]) == 2, bad
        err = capsys.readouterr().err.strip()
        assert err.startswith(f"jetloop prove: {path} is not a benchmark family.json (") and "\n" not in err, err
    deep = tmp_path / "deep.json"
    deep.write_text('{"cases": ' + "[" * 200000)
    assert main(["prove", "--table", str(deep)]) == 2
    assert capsys.readouterr().err.strip().startswith(f"jetloop prove: {deep} is not a benchmark family.json (")


def test_a_reader_that_leaves_early_ends_the_command_quietly(tmp_path):
    """`jetloop prove --table ... | head`: the reader closes the pipe before the table is written;
    the command ends with the shell's SIGPIPE status (141) and nothing on stderr, not a
    BrokenPipeError traceback (the real entry point, the real pipe)."""
    import os
    import shutil
    import subprocess

    # 400 effects: a confusion table of 400 x 400 cells, far beyond the pipe's 64 kB buffer
    rows = [{"case": f"eval-{i}", "split": "eval", "index": i, "expect": [f"effect_{i}"], "named": [f"effect_{i}"],
             "sensors": "imu", "pilot": "legs", "testable": True, "top1": True, "top2": True} for i in range(400)]
    path = tmp_path / "family.json"
    path.write_text(json.dumps({"split": "eval", "cases": rows}))
    proc = subprocess.Popen([shutil.which("jetloop"), "prove", "--table", str(path)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE)
    assert proc.stdout.read(20).startswith(b"400 cases")
    proc.stdout.close()
    err = proc.stderr.read()
    assert proc.wait(timeout=120) == 141 and err == b"", err
    # a table that fits the buffer, stdout buffered as usual, the reader gone before it is written
    # (`| true`): the final flush fails inside the command, not at the interpreter's exit, where
    # it had returned 0 with the output lost (a review's find; this machine sets PYTHONUNBUFFERED)
    small = _family_json(tmp_path / "small.json", "eval", [1], ["buoyancy"])
    env = {k: v for k, v in os.environ.items() if k != "PYTHONUNBUFFERED"}
    proc = subprocess.Popen([shutil.which("jetloop"), "prove", "--table", small], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, env=env)
    proc.stdout.close()  # long before the command has imported what it needs
    err = proc.stderr.read()
    assert proc.wait(timeout=120) == 141 and err == b"", err


@pytest.mark.slow
@pytest.mark.parametrize("index, first", [(1854, ["added_mass", "imu_bias"]), (1441, ["imu_bias", "buoyancy"])])
def test_an_imu_bias_named_with_a_force_is_listed_by_what_it_explains(index, first, tmp_path):
    """An IMU bias named with forces is listed first only when its held-out NRMSE alone beats
    the forces' together (core.diagnose); the expected orders are those the dev runs gave. Dev cases (eval block 1696-1995 and earlier, now development): added
    mass 3.9x with a 1x gyro bias masking it, the bias first until 2026-11-26 because it stood
    further above its threshold; and a 4.3x gyro bias with a 1x buoyancy error, the bias first."""
    row = run_family_case("eval", index, tmp_path)
    assert row["named"][:2] == first
