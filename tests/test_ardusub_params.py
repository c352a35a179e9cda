"""The shipped ArduSub parameter files (issue 17): each motor output lands on the unit that pushes
the way ArduSub's mixer means it to, the joints ArduSub does not drive stay centred, and what
ArduSub can and cannot control on asr4 with its joints centred (the README's claim) is the model's."""

from __future__ import annotations

import numpy as np
import pytest

from onboard import model
from onboard.pwm import pwm_to_command
from onboard.vehicle import DEFAULT_VEHICLE, load_vehicle

PARAMS = DEFAULT_VEHICLE.parent / "ardusub"
# AP_Motors6DOF.cpp SUB_FRAME_VECTORED, motors 1-4: (forward, lateral) factors
VECTORED_HORIZONTAL = {1: (-1, 1), 2: (-1, -1), 3: (1, 1), 4: (1, -1)}
MOTOR1 = 33  # SERVOn_FUNCTION of Motor1; Motor m is 32 + m


def parm(name: str) -> dict[str, float]:
    out = {}
    for line in (PARAMS / name).read_text().splitlines():
        line = line.split("#", 1)[0].strip()
        if line:
            key, value = line.split()
            out[key] = float(value)
    return out


def test_asr4_parm_puts_each_jet_on_the_motor_that_pushes_its_way(vehicle):
    p = parm("asr4.parm")
    assert p["FRAME_CONFIG"] == 1
    for i, ch in enumerate(vehicle.pwm.jet_channels):
        motor = int(p[f"SERVO{ch}_FUNCTION"]) - MOTOR1 + 1
        e1 = vehicle.units[i].neutral
        assert VECTORED_HORIZONTAL[motor] == (np.sign(e1[0]), np.sign(e1[1])), (i + 1, motor)
    assert sorted(int(p[f"SERVO{c}_FUNCTION"]) for c in vehicle.pwm.jet_channels) == [33, 34, 35, 36]


def test_asr4_parm_leaves_every_joint_at_its_trim_the_centre(vehicle):
    p = parm("asr4.parm")
    pwm = np.zeros(16)
    for ch in vehicle.pwm.azimuth_channels + vehicle.pwm.elevation_channels:
        assert p[f"SERVO{ch}_FUNCTION"] == 0  # disabled: ArduSub outputs the trim
        pwm[ch - 1] = p[f"SERVO{ch}_TRIM"]
    k = vehicle.n_units
    assert pwm_to_command(vehicle, pwm)[k:] == pytest.approx(np.zeros(2 * k))


def test_what_ardusub_can_control_on_asr4_with_its_joints_centred(vehicle):
    """Surge and sway only (each with its roll or pitch): the radial jets have no yaw moment and,
    level, no heave; rank 2 of 6."""
    E = model.effectiveness(vehicle, np.zeros(4), np.zeros(4))
    assert np.linalg.matrix_rank(E) == 2
    assert np.abs(E[2]).max() < 1e-12 and np.abs(E[5]).max() < 1e-12  # heave, yaw
    assert E[4] == pytest.approx(0.07 * E[0], abs=1e-4)  # pitch = r_z F_x, 7 cm below the CG
    assert E[3] == pytest.approx(-0.07 * E[1], abs=1e-4)  # roll = -r_z F_y


def test_bluerov_parm_is_the_stock_heavy_frame_on_the_vehicle_channels():
    p = parm("bluerov2_heavy.parm")
    v = load_vehicle("bluerov2_heavy")
    assert p["FRAME_CONFIG"] == 2
    assert [int(p[f"SERVO{c}_FUNCTION"]) for c in v.pwm.fixed_channels] == list(range(33, 41))
