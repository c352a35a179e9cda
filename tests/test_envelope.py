"""The setpoint envelope: the optional [envelope] section of the vehicle file and the pure checks
of onboard.envelope on SET_POSITION_TARGET_LOCAL_NED, MANUAL_CONTROL and arm/mode COMMAND_LONG."""

from __future__ import annotations

import math

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from conftest import SHARED_VEHICLE, shared_file
from onboard.control import Gains
from onboard.envelope import command_violation, manual_violation, position_target_violation
from onboard.loop import arm_command, body_velocity_target, depth_yaw_target, mode_command
from onboard.vehicle import Envelope, VehicleFileError, load_vehicle, parse_vehicle

ENV = Envelope(max_depth_m=2.0, min_depth_m=0.0, max_speed_m_s=1.0, max_heave_speed_m_s=0.5,
               max_yaw_rate_rad_s=1.0)
M = mavlink.POSITION_TARGET_TYPEMASK_X_IGNORE | mavlink.POSITION_TARGET_TYPEMASK_Y_IGNORE | 0b111000000


def _target(frame=mavlink.MAV_FRAME_LOCAL_NED, mask=0, z=0.0, vx=0.0, vy=0.0, vz=0.0, yaw_rate=0.0, yaw=0.0):
    return mavlink.MAVLink_set_position_target_local_ned_message(0, 1, 1, frame, M | mask, 0, 0, z, vx, vy, vz,
                                                                 0, 0, 0, yaw, yaw_rate)


# -- the vehicle file --------------------------------------------------------------------------------

def test_envelope_is_optional_and_defaults_for_the_asr4_sphere(reference_text):
    """Both reference files have no [envelope] table; the defaults are the docstring's figures:
    2.0 m depth, surface, 1.0 m/s (seed 000: largest ASR-IV velocity), 0.5 m/s heave, 1.0 rad/s."""
    for v in (load_vehicle(), load_vehicle(shared_file(SHARED_VEHICLE))):
        assert v.envelope == ENV
    assert "\n[envelope]" not in reference_text  # documented as a commented-out table only


def test_envelope_keys_are_read_and_partly_defaulted(reference_text):
    v = parse_vehicle(reference_text + "\n[envelope]\nmax_depth_m = 5.0\nmax_yaw_rate_rad_s = 0.5\n")
    assert v.envelope == Envelope(max_depth_m=5.0, max_yaw_rate_rad_s=0.5)
    assert v.envelope.max_speed_m_s == 1.0  # left out: its default
    assert v.with_values({"envelope.max_speed_m_s": 0.3}).envelope.max_speed_m_s == 0.3


@pytest.mark.parametrize("line, words", [
    ("max_depth_m = -1.0", "envelope.max_depth_m: expected a finite number > 0, got -1.0"),
    ("max_speed_m_s = nan", "envelope.max_speed_m_s: expected a finite number > 0"),
    ("max_speed = 1.0", "envelope.max_speed: unknown key"),
    ("min_depth_m = 3.0", "envelope.min_depth_m: expected a depth above max_depth_m (2 m), got 3.0"),
    ('max_yaw_rate_rad_s = "fast"', "envelope.max_yaw_rate_rad_s: expected a finite number > 0"),
])
def test_bad_envelope_keys_are_named(reference_text, line, words):
    with pytest.raises(VehicleFileError) as exc:
        parse_vehicle(reference_text + f"\n[envelope]\n{line}\n", source="v.toml")
    assert "v.toml: invalid vehicle file" in str(exc.value) and words in str(exc.value)


def test_envelope_not_a_table_is_named(reference_text):
    with pytest.raises(VehicleFileError, match="envelope: expected a table with keys max_depth_m"):
        parse_vehicle("envelope = 3\n" + reference_text)


def test_controller_full_stick_lies_inside_the_default_envelope():
    """A full MANUAL_CONTROL stick is scaled by the controller's gains: those must not exceed what
    the envelope allows from a setpoint, or the joystick would fly what a setpoint may not ask."""
    g = Gains()
    assert g.manual_speed_m_s <= ENV.max_speed_m_s
    assert g.manual_heave_m_s <= ENV.max_heave_speed_m_s
    assert g.manual_yaw_rate_rad_s <= ENV.max_yaw_rate_rad_s
    assert g.max_yaw_rate_rad_s <= ENV.max_yaw_rate_rad_s and g.max_depth_rate_m_s <= ENV.max_heave_speed_m_s


# -- SET_POSITION_TARGET_LOCAL_NED ------------------------------------------------------------------

def test_depth_inside_is_accepted_and_outside_refused_with_the_numbers():
    assert position_target_violation(ENV, depth_yaw_target(2.0, 0.3)) is None  # the bound itself
    assert position_target_violation(ENV, depth_yaw_target(0.0)) is None
    assert position_target_violation(ENV, depth_yaw_target(12.0)) == "setpoint refused: depth 12.0 m > max 2.0 m"
    assert position_target_violation(ENV, depth_yaw_target(-0.5)) == "setpoint refused: depth -0.5 m < min 0.0 m"
    assert position_target_violation(ENV, depth_yaw_target(None, 3.0)) is None  # yaw only: any angle


def test_z_is_not_a_depth_in_a_body_frame_or_when_ignored():
    assert position_target_violation(ENV, _target(mavlink.MAV_FRAME_BODY_FRD, z=50.0)) is None
    assert position_target_violation(ENV, _target(mask=mavlink.POSITION_TARGET_TYPEMASK_Z_IGNORE, z=50.0)) is None


def test_horizontal_speed_is_the_norm_of_vx_vy():
    # 0.6 and 0.8 m/s: each under 1.0, together hypot = 1.0 exactly (accepted); 0.61, 0.8 -> 1.006 (refused)
    assert position_target_violation(ENV, body_velocity_target(0.6, 0.8)) is None
    assert position_target_violation(ENV, body_velocity_target(0.61, 0.8)) == \
        f"setpoint refused: speed {math.hypot(0.61, 0.8):.2f} > max 1.00 m/s"
    assert position_target_violation(ENV, body_velocity_target(3.0)) == "setpoint refused: speed 3.00 > max 1.00 m/s"
    # vx ignored: only vy counts
    assert position_target_violation(ENV, _target(mask=mavlink.POSITION_TARGET_TYPEMASK_VX_IGNORE, vx=9.0, vy=0.9)) is None


def test_heave_and_yaw_rate_limits():
    assert position_target_violation(ENV, _target(vz=0.5)) is None
    assert position_target_violation(ENV, _target(vz=-0.7)) == "setpoint refused: heave 0.70 > max 0.50 m/s"
    assert position_target_violation(ENV, _target(yaw_rate=-2.0)) == "setpoint refused: yaw rate 2.00 > max 1.00 rad/s"
    ignored = mavlink.POSITION_TARGET_TYPEMASK_VZ_IGNORE | mavlink.POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE
    assert position_target_violation(ENV, _target(mask=ignored, vz=9.0, yaw_rate=9.0)) is None


def test_non_finite_fields_are_left_to_the_decoder():
    """inf/NaN are the loop decoder's to count as rejected inputs, not envelope refusals."""
    assert position_target_violation(ENV, depth_yaw_target(float("inf"))) is None
    assert position_target_violation(ENV, _target(vx=float("nan"))) is None


def test_a_yaw_beyond_a_turn_is_refused():
    """Issue 15: yaw 3.4e38 was accepted as a heading. Within +-2 pi (0..2 pi and -pi..pi senders) passes."""
    assert position_target_violation(ENV, depth_yaw_target(None, 2 * math.pi)) is None
    assert position_target_violation(ENV, depth_yaw_target(None, -3.0)) is None
    assert position_target_violation(ENV, depth_yaw_target(None, 3.4e38)) == \
        "setpoint refused: |yaw| 3.4e+38 > 6.28 rad"
    assert position_target_violation(ENV, depth_yaw_target(0.5, 7.0)) == "setpoint refused: |yaw| 7.00 > 6.28 rad"
    assert position_target_violation(ENV, _target(mask=mavlink.POSITION_TARGET_TYPEMASK_YAW_IGNORE, yaw=1e9)) is None


@pytest.mark.parametrize("frame", [mavlink.MAV_FRAME_LOCAL_OFFSET_NED, mavlink.MAV_FRAME_GLOBAL,
                                   mavlink.MAV_FRAME_LOCAL_FRD, 200])
def test_a_frame_the_loop_does_not_read_is_refused_not_taken_as_ned(frame):
    """Issue 15: an unknown coordinate_frame was read as NED (z a depth). LOCAL_OFFSET_NED's z is an
    offset from where the vehicle is, a global frame's z an altitude: refused, and said so."""
    assert position_target_violation(ENV, _target(frame, z=0.5)) == \
        f"setpoint refused: frame {frame} not LOCAL_NED or body"
    for ok in (mavlink.MAV_FRAME_LOCAL_NED, mavlink.MAV_FRAME_BODY_NED, mavlink.MAV_FRAME_BODY_OFFSET_NED,
               mavlink.MAV_FRAME_BODY_FRD):
        assert position_target_violation(ENV, _target(ok, z=0.5)) is None


def test_every_refusal_text_fits_a_statustext():
    worst = [depth_yaw_target(-123456.0), body_velocity_target(1e6, 1e6), _target(vz=-1e6), _target(yaw_rate=1e6),
             depth_yaw_target(None, -3.4e38), _target(255)]
    for m in worst:
        assert len(position_target_violation(ENV, m)) <= 50


# -- MANUAL_CONTROL and COMMAND_LONG -------------------------------------------------------------------

def test_manual_axes_outside_their_range_are_refused():
    ok = mavlink.MAVLink_manual_control_message(1, 1000, -1000, 0, 1000, 0)
    assert manual_violation(ok) is None
    assert manual_violation(mavlink.MAVLink_manual_control_message(1, 1500, 0, 500, 0, 0)) == \
        "setpoint refused: manual x 1500 > 1000"
    assert manual_violation(mavlink.MAVLink_manual_control_message(1, 0, 0, -1, 0, 0)) == \
        "setpoint refused: manual z -1 < 0"
    assert manual_violation(mavlink.MAVLink_manual_control_message(1, 0, 0, 500, -32768, 0)) == \
        "setpoint refused: manual r -32768 < -1000"


def _long(cmd, p1=0.0, p2=0.0):
    return mavlink.MAVLink_command_long_message(1, 1, cmd, 0, p1, p2, 0, 0, 0, 0, 0)


def test_arm_and_mode_parameters():
    assert command_violation(arm_command(True)) is None and command_violation(arm_command(False)) is None
    assert command_violation(mode_command("depth_hold")) is None
    arm = mavlink.MAV_CMD_COMPONENT_ARM_DISARM
    assert command_violation(_long(arm, 2.0)) == "command denied: arm param1 2 not 0 or 1"
    assert command_violation(_long(arm, 0.5)) == "command denied: arm param1 0.5 not 0 or 1"
    assert command_violation(_long(arm, float("nan"))) == "command denied: arm param1 nan not 0 or 1"
    mode = mavlink.MAV_CMD_DO_SET_MODE
    assert command_violation(_long(mode, 0.0, 2.0)) == "command denied: mode param1 0 not custom"
    assert command_violation(_long(mode, 1.0, 2.5)) == "command denied: mode param2 2.5 not a mode"
    assert command_violation(_long(mode, 1.0, float("inf"))) == "command denied: mode param2 inf not a mode"
    assert command_violation(_long(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, float("nan"))) is None  # not ours
