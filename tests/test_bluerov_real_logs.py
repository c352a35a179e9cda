"""The three real ArduSub recordings with their real vehicle, `--vehicle bluerov2_heavy` (issue 17):
`plot` draws the eight T200s' commanded thrust through the vehicle file's curve, `identify` says in
one line what these rates and this little motion do not allow, and nothing ends in a traceback."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from conftest import ARDUSUB
from ground.plot import make_plots
from ground.recording import read_recording
from onboard.fixed import thrust_of_pwm
from onboard.pwm import pwm_to_command
from onboard.vehicle import load_vehicle

ROOT = Path(__file__).resolve().parents[1]
HEAVY = load_vehicle("bluerov2_heavy")
needs_ardusub = pytest.mark.usefixtures("ardusub_data")


def jetloop(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "ground.cli", *args], cwd=ROOT, capture_output=True,
                          text=True, timeout=600)


@needs_ardusub
def test_recorded_servo_outputs_through_the_t200_curve():
    """small.tlog's armed stretch: SERVO_OUTPUT_RAW rows read as thrust per thruster, by hand."""
    rec = read_recording(ARDUSUB / "small.tlog")
    pwm = rec.servo.pwm_us
    u = pwm_to_command(HEAVY, np.asarray(pwm, float).T).T  # the (channels, samples) form diagnose uses
    assert u.shape == (len(pwm), 24)
    for row, cmd in zip(pwm, u):
        want = np.where(row[:8] >= 500, thrust_of_pwm(HEAVY.fixed_thruster, row[:8]), 0.0)
        assert cmd[:8] == pytest.approx(want)
    assert np.abs(u[:, :8]).max() > 5.0  # the pilot did drive it: some thruster above 5 N
    assert np.all(u[:, 8:] == 0.0)  # no joints


@needs_ardusub
@pytest.mark.slow
@pytest.mark.parametrize("name", ["small.tlog", "small.BIN", "2023-04-18_11-03-34.tlog"])
def test_plot_with_the_bluerov(tmp_path, name):
    s = make_plots(ARDUSUB / name, tmp_path, vehicle=HEAVY)
    assert s["panels"]["attitude"] == "" and s["panels"]["jets"] == ""
    assert "bluerov2_heavy has fixed thrusters only" in s["panels"]["joints"]
    assert (tmp_path / "jets.png").stat().st_size > 5000


@needs_ardusub
@pytest.mark.slow
@pytest.mark.parametrize("name", ["small.tlog", "small.BIN", "2023-04-18_11-03-34.tlog"])
def test_identify_says_what_the_recording_cannot_give(name):
    p = jetloop("identify", "free-decay", "--spring", "50", str(ARDUSUB / name), "--vehicle", "bluerov2_heavy")
    assert p.returncode == 2 and "Traceback" not in p.stderr
    assert "clear extrema in the trace; a free decay needs at least 3" in p.stderr
    assert p.stderr.count("\n") == 1


def test_identify_of_a_jet_method_names_the_vehicle_without_jets():
    for method in ("thrust", "azimuth"):
        p = jetloop("identify", method, "--vehicle", "bluerov2_heavy")
        assert p.returncode == 2 and "Traceback" not in p.stderr
        assert "bluerov2_heavy has no vectored water-jets" in p.stderr, p.stderr


@needs_ardusub
def test_replay_starts_from_the_recorded_attitude_and_depth_and_turns_on_the_recorded_burst():
    """small.tlog: at 903.7 s motors 1-4 all ran above neutral for ~1 s; through the model, with
    the log's own motor directions (MOT_1/2/5/8_DIRECTION = -1), the model turns tens of degrees,
    the recording under 3 (README: what these logs allow to conclude)."""
    from ground.plot import replay_fixed
    from onboard.sensors import depth_from_pressure

    rec = read_recording(ARDUSUB / "small.tlog")
    t, euler, depth = replay_fixed(rec, HEAVY, 900.0, 906.0)
    a, pr = rec.attitude, rec.pressure
    for i in range(3):
        assert euler[0, i] == pytest.approx(np.interp(900.0, a.time_s, np.unwrap(a.euler_rad[:, i])), abs=1e-9)
    assert depth[0] == pytest.approx(np.interp(900.0, pr.time_s, depth_from_pressure(pr.press_abs_pa, HEAVY)))
    yaw_model = np.degrees(np.unwrap(euler[:, 2]))
    m = (a.time_s >= 900.0) & (a.time_s <= 906.0)
    yaw_rec = np.degrees(np.unwrap(a.euler_rad[m, 2]))
    assert yaw_model[0] - yaw_model.min() > 20.0
    assert np.ptp(yaw_rec) < 3.0


@needs_ardusub
@pytest.mark.slow
def test_plot_page_has_the_replay_for_the_bluerov(tmp_path):
    s = make_plots(ARDUSUB / "small.tlog", tmp_path, vehicle=HEAVY)
    assert s["panels"]["replay"] == ""
    assert (tmp_path / "replay.png").stat().st_size > 5000
    assert 'src="replay.png"' in (tmp_path / "index.html").read_text()


@needs_ardusub
def test_the_logs_carry_the_autopilots_motor_directions():
    """PARAM_VALUE (tlog) and PARM (dataflash) are kept; ArduSub's MOT_n_DIRECTION = -1 reverses
    the thrusters on those motors in the model (onboard.fixed.ardusub_directions)."""
    from onboard.fixed import ardusub_directions

    tl = read_recording(ARDUSUB / "small.tlog").parameters
    assert len(tl) == 887 and tl["FRAME_CONFIG"] == 2.0 and tl["MOT_1_DIRECTION"] == -1.0
    assert ardusub_directions(tl, HEAVY) == (-1.0, -1.0, 1.0, 1.0, -1.0, 1.0, 1.0, -1.0)
    df = read_recording(ARDUSUB / "small.BIN").parameters
    assert df["FRAME_CONFIG"] == 1.0 and df["SERVO7_FUNCTION"] == 0.0  # a six-thruster BlueROV2
    assert ardusub_directions(df, HEAVY) == (-1.0, -1.0, 1.0, -1.0, -1.0, 1.0, 1.0, 1.0)
