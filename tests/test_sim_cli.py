"""`jetloop sim` end to end: the recording's rates, contents, determinism, readers, bad input."""

from __future__ import annotations

import contextlib
import io
import math
import re
import shutil
import struct
import subprocess
import sys
from collections import Counter
from pathlib import Path

import numpy as np
import pytest

from ground import cli
from hil import sim
from hil.tlog import FIXED_EPOCH_US
from onboard import mavlink_codec as codec
from onboard.vehicle import DEFAULT_VEHICLE, load_vehicle

DEMO = sim.DEMO_COMMANDS
HEADER = "t," + ",".join(f"pwm{c}" for c in range(1, 13))

# Distinct PWM on every channel, so a swapped channel shows. Row times are deliberately not all
# on the 0.1 s grid (2.05 s).
ROWS = [
    (0.0, [1100] * 4 + [1500, 1510, 1520, 1530] + [1490, 1480, 1470, 1460]),
    (1.0, [1700] * 4 + [1500, 1510, 1520, 1530] + [1490, 1480, 1470, 1460]),
    (2.05, [1700] * 4 + [1550, 1560, 1570, 1580] + [1450, 1440, 1430, 1420]),
    (3.0, [1100] * 4 + [1500] * 8),
]
RATES = {"imu_rate": 200.0, "pressure_rate": 20.0, "attitude_rate": 25.0}  # not the reference ones
DEPTH0 = 0.8


def csv_text(rows) -> str:
    return HEADER + "\n" + "".join(f"{t}," + ",".join(str(p) for p in pwm) + "\n" for t, pwm in rows)


def run_cli(*argv) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = cli.main(["sim", *map(str, argv)])
    return rc, out.getvalue(), err.getvalue()


def read_tlog(path: Path) -> list:
    """(timestamp_us, message) of every packet, read by hand: 8-byte big-endian time, MAVLink 2."""
    data = path.read_bytes()
    rx = codec.make_mavlink(255, 0)
    out, i = [], 0
    while i < len(data):
        (ts,) = struct.unpack(">Q", data[i:i + 8])
        assert data[i + 8] == 0xFD, f"packet at byte {i + 8} is not MAVLink 2"
        n = 8 + 12 + data[i + 9]  # timestamp + MAVLink 2 header/CRC + payload
        (msg,) = codec.parse(rx, data[i + 8:i + n])
        out.append((ts, msg))
        i += n
    return out


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    d = tmp_path_factory.mktemp("sim")
    text = DEFAULT_VEHICLE.read_text()
    for key, value in RATES.items():
        text, n = re.subn(rf"^{key} = [0-9.]+", f"{key} = {value}", text, flags=re.M)
        assert n == 1, key
    (d / "v.toml").write_text(text)
    (d / "cmds.csv").write_text(csv_text(ROWS))
    common = ["--vehicle", d / "v.toml", "--commands", d / "cmds.csv", "--depth", DEPTH0]
    res = {}
    for name, seed in (("a", 1), ("b", 1), ("c", 2)):
        truth = ["--truth", d / f"truth_{name}.csv"] if name == "a" else []
        rc, out, err = run_cli(*common, "--out", d / f"{name}.tlog", "--seed", seed, *truth)
        assert rc == 0, err
        res[name] = d / f"{name}.tlog"
        res[name + "_stdout"] = out
    res["truth"] = d / "truth_a.csv"
    res["vehicle"] = load_vehicle(d / "v.toml")
    res["packets"] = read_tlog(res["a"])
    res["dir"] = d
    return res


def held_messages(times_s, period_s=0.1, dt_s=0.001):
    """Actuator reports: each row at its step, then every period while held; the last row once."""
    steps = [math.ceil(t / dt_s - 1e-9) for t in times_s]
    per = round(period_s / dt_s)
    return sum(math.ceil((b - a) / per) for a, b in zip(steps, steps[1:])) + 1


# --- the recording ------------------------------------------------------------------------------

def test_message_counts_follow_the_vehicle_rates(runs):
    counts = Counter(m.get_type() for _, m in runs["packets"])
    dur = ROWS[-1][0]
    expected = {
        "HIGHRES_IMU": int(dur * RATES["imu_rate"]) + 1,  # first sample at t = 0, last at t = 3 s
        "SCALED_PRESSURE2": int(dur * RATES["pressure_rate"]) + 1,
        "ATTITUDE": int(dur * RATES["attitude_rate"]) + 1,
        "HEARTBEAT": int(dur) + 1,
        "SERVO_OUTPUT_RAW": held_messages([t for t, _ in ROWS]),  # 10 + 11 + 10 + 1
        "ESC_TELEMETRY_1_TO_4": held_messages([t for t, _ in ROWS]),
    }
    assert expected["SERVO_OUTPUT_RAW"] == 32
    assert dict(counts) == expected
    # the summary on stdout says the same
    out = runs["a_stdout"]
    for name, n in expected.items():
        assert f"{name} {n}" in out
    assert "3.000 s of vehicle time" in out and "x real time" in out


def test_sample_times_are_exact_periods(runs):
    imu = [m.time_usec for _, m in runs["packets"] if m.get_type() == "HIGHRES_IMU"]
    assert np.all(np.diff(imu) == round(1e6 / RATES["imu_rate"]))
    prs = [m.time_boot_ms for _, m in runs["packets"] if m.get_type() == "SCALED_PRESSURE2"]
    assert np.all(np.diff(prs) == round(1e3 / RATES["pressure_rate"]))
    att = [m.time_boot_ms for _, m in runs["packets"] if m.get_type() == "ATTITUDE"]
    assert np.all(np.diff(att) == round(1e3 / RATES["attitude_rate"]))
    servo = [m.time_usec for _, m in runs["packets"] if m.get_type() == "SERVO_OUTPUT_RAW"]
    assert max(np.diff(servo)) <= 100_000  # at least 10 Hz while held
    assert {1_000_000, 2_050_000, 3_000_000} <= set(servo)  # and at every row


def test_tlog_timestamps_are_the_fixed_epoch_plus_vehicle_time(runs):
    pk = runs["packets"]
    ts = [t for t, _ in pk]
    assert ts[0] == FIXED_EPOCH_US == 1_767_225_600_000_000  # 2026-01-01T00:00:00Z
    assert all(a <= b for a, b in zip(ts, ts[1:]))
    for t, m in pk:
        if hasattr(m, "time_usec"):
            assert t - FIXED_EPOCH_US == m.time_usec
        elif hasattr(m, "time_boot_ms"):
            assert t - FIXED_EPOCH_US == 1000 * m.time_boot_ms
    assert all(m.get_srcSystem() == 1 and m.get_srcComponent() == 1 for _, m in pk)
    assert all(m.type == 12 for _, m in pk if m.get_type() == "HEARTBEAT")  # MAV_TYPE_SUBMARINE


def test_servo_output_carries_the_csv_pwm(runs):
    row_steps = [math.ceil(t / 0.001 - 1e-9) for t, _ in ROWS]
    n = 0
    for _, m in runs["packets"]:
        if m.get_type() != "SERVO_OUTPUT_RAW":
            continue
        step = m.time_usec // 1000
        row = max(i for i, s in enumerate(row_steps) if s <= step)
        got = [getattr(m, f"servo{c}_raw") for c in range(1, 17)]
        assert got == ROWS[row][1] + [0, 0, 0, 0], m.time_usec
        n += 1
    assert n == held_messages([t for t, _ in ROWS]) == 32


def test_esc_rpm_follows_the_first_order_motor_lag(runs):
    v = runs["vehicle"]
    tau = v.thruster.motor_time_constant
    n_cmd = (1700 - 1100) / (1900 - 1100) * v.thruster.n_max  # rev/s, the linear PWM map
    pk = runs["packets"]
    checked = 0
    for k, (ts, m) in enumerate(pk):
        if m.get_type() != "ESC_TELEMETRY_1_TO_4":
            continue
        t = (ts - FIXED_EPOCH_US) / 1e6
        rpm = 0.0 if t < 1.0 else 60 * n_cmd * (1 - math.exp(-(t - 1.0) / tau))  # n' = (n_cmd - n)/tau
        assert list(m.rpm) == pytest.approx([rpm] * 4, abs=1.0), t  # the field is an integer rpm
        checked += 1
    assert checked == held_messages([t for t, _ in ROWS]) == 32


def test_pressure_depth_matches_truth_within_the_pressure_noise(runs):
    v = runs["vehicle"]
    env = v.environment
    truth = np.loadtxt(runs["truth"], delimiter=",", skiprows=1)
    z_at = {round(row[0] * 1000): row[3] for row in truth}
    res = []
    for _, m in runs["packets"]:
        if m.get_type() == "SCALED_PRESSURE2":
            depth = (m.press_abs * 100.0 - env.p_atm) / (env.rho * env.g)  # p = p_atm + rho g depth
            res.append(depth - (z_at[m.time_boot_ms] - env.surface_depth))
    res = np.array(res)
    sigma = v.sensors.pressure_noise / (env.rho * env.g)  # 20 Pa -> 2.04 mm
    assert len(res) == int(ROWS[-1][0] * RATES["pressure_rate"]) + 1 == 61  # 20 Hz over 3 s, both ends
    assert np.max(np.abs(res)) < 5 * sigma
    assert abs(res.mean()) < 4 * sigma / math.sqrt(len(res))
    assert 0.6 * sigma < res.std() < 1.4 * sigma


def test_truth_csv(runs):
    lines = runs["truth"].read_text().splitlines()
    assert lines[0] == "t,x,y,z,roll,pitch,yaw,u,v,w,p,q,r"
    rows = np.array([[float(c) for c in ln.split(",")] for ln in lines[1:]])
    assert rows.shape == (int(3.0 * RATES["imu_rate"]) + 1, 13)
    assert np.allclose(np.diff(rows[:, 0]), 1 / RATES["imu_rate"])
    # at rest, level, at the --depth given, at t = 0
    assert list(rows[0]) == [0.0, 0.0, 0.0, DEPTH0] + [0.0] * 9
    assert rows[-1, 0] == 3.0


def test_same_seed_same_bytes_other_seed_other_bytes(runs):
    a, b, c = (runs[k].read_bytes() for k in "abc")
    assert a == b
    assert a != c
    assert len(a) > 10_000


def test_mavutil_reads_the_recording(runs, monkeypatch):
    from pymavlink import mavutil

    monkeypatch.delenv("MAVLINK20", raising=False)  # mavutil sets it; leave the process as found
    monkeypatch.delenv("MAVLINK_DIALECT", raising=False)
    conn = mavutil.mavlink_connection(str(runs["a"]))
    counts = Counter()
    first_ts = None
    while True:
        m = conn.recv_match()
        if m is None:
            break
        assert m.get_type() != "BAD_DATA"
        counts[m.get_type()] += 1
        first_ts = m._timestamp if first_ts is None else first_ts
    conn.close()
    assert counts == Counter(m.get_type() for _, m in runs["packets"])
    assert first_ts == pytest.approx(FIXED_EPOCH_US / 1e6)


def test_mavlogdump_parses_the_recording(runs):
    script = shutil.which("mavlogdump.py")
    cmd = [sys.executable, script] if script else [sys.executable, "-m", "pymavlink.tools.mavlogdump"]
    out = subprocess.run(cmd + [str(runs["a"])], capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    dumped = Counter(re.findall(r"^\S+ \S+: (\w+) \{", out.stdout, flags=re.M))
    assert "BAD_DATA" not in dumped
    assert dumped == Counter(m.get_type() for _, m in runs["packets"])


def test_real_command_line_runs_the_packaged_demo(tmp_path):
    out = subprocess.run(
        [sys.executable, "-m", "ground.cli", "sim", "--commands", str(DEMO), "--out", str(tmp_path / "d.tlog")],
        capture_output=True, text=True, timeout=300,
    )
    assert out.returncode == 0, out.stderr
    assert "14.000 s of vehicle time" in out.stdout
    assert "HIGHRES_IMU 1401" in out.stdout  # reference vehicle: 100 Hz for 14 s, both ends
    assert re.search(r"final \(t = 14\.000 s\): depth [0-9.]+ m", out.stdout)


# --- the commands file ----------------------------------------------------------------------------

def test_parse_commands_values():
    text = "# comment\n\n" + HEADER + ",pwm14\n0.5," + ",".join(["1500.0"] * 12) + ",1900\n2,1100" + ",1500" * 12 + "\n"
    s = sim.parse_commands(text, "x.csv")
    assert s.times_s == (0.5, 2.0)
    assert s.lines == (4, 5)
    assert s.pwm_us[0] == (1500,) * 12 + (0, 1900, 0, 0)
    assert s.pwm_us[1] == (1100,) + (1500,) * 11 + (0, 1500, 0, 0)
    assert s.duration_s == 2.0


def test_required_channels_come_from_the_vehicle():
    with pytest.raises(sim.CommandsFileError, match="missing column 'pwm13'"):
        sim.parse_commands(HEADER + "\n1," + ",".join(["1500"] * 12) + "\n", "x.csv", channels=[1, 2, 13])


def test_first_row_is_held_from_time_zero_and_rows_need_distinct_steps():
    s = sim.parse_commands(csv_text([(0.5, [1500] * 12), (1.0, [1600] * 12)]))
    ev = sim.event_steps(s, 0.001)
    assert ev[0].row == 0 and ev[0].heartbeat and ev[0].actuators
    assert ev[500].row == 0 and ev[1000].row == 1
    assert sorted(ev) == [0, 100, 200, 300, 400, 500, 600, 700, 800, 900, 1000]
    # 0.0002 s and 0.0008 s both apply from step 1 (the first step at or after them)
    close = sim.parse_commands(csv_text([(0.0, [1500] * 12), (0.0002, [1600] * 12), (0.0008, [1700] * 12),
                                         (1.0, [1600] * 12)]), "c.csv")
    with pytest.raises(sim.CommandsFileError, match=r"c\.csv:4: .*same integration step"):
        sim.event_steps(close, 0.001)


ROW = ",".join(["1500"] * 12)
BAD = {
    "missing column": (HEADER.replace(",pwm10", "") + "\n0," + ",".join(["1500"] * 11) + "\n", 1,
                       "missing column 'pwm10'"),
    "unknown column": (HEADER + ",pwm17\n0," + ROW + ",1500\n", 1, "unknown column 'pwm17'"),
    "non-numeric": (f"{HEADER}\n0,{ROW}\n1,1500,abc" + ",1500" * 10 + "\n", 3, "column pwm2: 'abc' is not a number"),
    "nan": (f"{HEADER}\n0,{ROW}\nnan,{ROW}\n", 3, "column t: 'nan' is not a finite number"),
    "non-monotonic": (f"{HEADER}\n0,{ROW}\n2,{ROW}\n1.5,{ROW}\n", 4, "t = 1.5 s does not increase"),
    "repeated time": (f"{HEADER}\n0,{ROW}\n1,{ROW}\n1,{ROW}\n", 4, "does not increase"),
    "negative time": (f"{HEADER}\n-1,{ROW}\n1,{ROW}\n", 2, "expected 0 <= t <= 86400 s"),
    "time beyond a day": (f"{HEADER}\n0,{ROW}\n1e300,{ROW}\n", 3, "t = 1e+300 s: expected 0 <= t <= 86400 s"),
    "pwm too low": (f"{HEADER}\n0,{ROW}\n1,799" + ",1500" * 11 + "\n", 3, "pwm1: 799 us is outside 800..2200"),
    "pwm too high": (f"{HEADER}\n0," + "1500," * 11 + "2201\n1,{ROW}\n", 2, "pwm12: 2201 us is outside"),
    "short row": (f"{HEADER}\n0,{ROW}\n1,1500,1500\n", 3, "expected 13 values"),
    "header only": (HEADER + "\n", 1, "no command rows"),
    "zero duration": (f"{HEADER}\n0,{ROW}\n", 2, "must be > 0"),
    "comments count": (f"# a comment\n\n{HEADER}\n0,{ROW}\n# another\n1,x{ROW}\n", 6, "is not a number"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_commands_name_file_and_line(case, tmp_path):
    text, line, phrase = BAD[case]
    with pytest.raises(sim.CommandsFileError) as e:
        sim.parse_commands(text, "cmds.csv")
    assert e.value.line == line
    assert str(e.value).startswith(f"cmds.csv:{line}: ")
    assert phrase in str(e.value)
    # and through the command line: exit 2, the message, no traceback, no recording
    path = tmp_path / "cmds.csv"
    path.write_text(text)
    rc, out, err = run_cli("--commands", path, "--out", tmp_path / "r.tlog")
    assert rc == 2
    assert f"{path}:{line}: " in err and phrase in err
    assert "Traceback" not in err
    assert not (tmp_path / "r.tlog").exists()


@pytest.mark.parametrize("text", ["", "\n\n  \n", "# only a comment\n"])
def test_empty_commands_file(text, tmp_path):
    path = tmp_path / "empty.csv"
    path.write_text(text)
    rc, _, err = run_cli("--commands", path, "--out", tmp_path / "r.tlog")
    assert rc == 2
    assert f"{path}: empty file: expected a header line with columns t, pwm1" in err


def test_bad_input_in_a_real_process_exits_2_without_traceback(tmp_path):
    path = tmp_path / "bad.csv"
    path.write_text(f"{HEADER}\n0,{ROW}\n1,1500,1500\n")
    out = subprocess.run(
        [sys.executable, "-m", "ground.cli", "sim", "--commands", str(path), "--out", str(tmp_path / "r.tlog")],
        capture_output=True, text=True, timeout=120,
    )
    assert out.returncode == 2
    assert f"{path}:3: expected 13 values" in out.stderr
    assert "Traceback" not in out.stderr


def test_bad_options_and_files(tmp_path):
    good = tmp_path / "c.csv"
    good.write_text(csv_text([(0.0, [1500] * 12), (0.2, [1500] * 12)]))
    cases = [
        (["--commands", tmp_path / "missing.csv"], "missing.csv: cannot read commands file"),
        (["--commands", good, "--vehicle", tmp_path / "nope.toml"], "nope.toml: cannot read vehicle file"),
        (["--commands", good, "--dt", "0"], "--dt 0.0: expected a step"),
        (["--commands", good, "--dt", "0.02"], "0 < dt <= 0.01"),  # IMU at 100 Hz
        (["--commands", good, "--depth", "nan"], "--depth nan"),
        (["--commands", good, "--seed", "-1"], "--seed -1"),
        (["--commands", good, "--out", tmp_path / "no" / "dir.tlog"], "cannot write"),
    ]
    for argv, phrase in cases:
        if "--out" not in argv:
            argv = argv + ["--out", tmp_path / "r.tlog"]
        rc, _, err = run_cli(*argv)
        assert rc == 2, argv
        assert phrase in err, (argv, err)
        assert "Traceback" not in err


def test_progress_goes_to_stderr(tmp_path, monkeypatch):
    monkeypatch.setattr(sim, "PROGRESS_AFTER_S", 0.0)  # report after every chunk instead of every 2 s
    path = tmp_path / "c.csv"
    path.write_text(csv_text([(0.0, [1500] * 12), (0.5, [1500] * 12)]))
    rc, out, err = run_cli("--commands", path, "--out", tmp_path / "r.tlog")
    assert rc == 0
    lines = [ln for ln in err.splitlines() if ln.startswith("  t = ")]
    assert lines and lines[-1].startswith("  t = 0.5 / 0.5 s (100 %)")
    assert not any(ln.startswith("  t = ") for ln in out.splitlines())
    assert "0.500 s of vehicle time" in out


def test_tlog_writer_layout_counts_and_order(tmp_path):
    from hil.tlog import TlogWriter

    path = tmp_path / "w.tlog"
    with TlogWriter(path) as w:
        w.write(codec.heartbeat(), 0x0102030405060708)
        w.write(codec.heartbeat(), 0x0102030405060708 + 1)
        with pytest.raises(ValueError, match="must not go back"):
            w.write(codec.heartbeat(), 5)
    data = path.read_bytes()
    pkt = codec.encode(codec.make_mavlink(), codec.heartbeat())  # seq 0, like the writer's first
    assert data[:8] == bytes([1, 2, 3, 4, 5, 6, 7, 8])  # big-endian microseconds
    assert data[8:8 + len(pkt)] == pkt
    assert len(data) == 2 * (8 + len(pkt)) == w.bytes_written
    assert w.counts == {"HEARTBEAT": 2}
