"""The setpoint envelope and command parameters: may a ground setpoint or command act? (pure)

A ground setpoint is checked against the vehicle's `[envelope]` (onboard.vehicle.Envelope)
before it replaces the setpoint in force; a refused one leaves the previous setpoint flying.
Each check returns None (acceptable) or the reason, worded for a 50-character STATUSTEXT:
"setpoint refused: depth 12.0 m > max 2.0 m".

- SET_POSITION_TARGET_LOCAL_NED (common.xml, POSITION_TARGET_TYPEMASK): the frame must be one
  the loop reads (MAV_FRAME_LOCAL_NED, or a body frame: BODY_NED, BODY_OFFSET_NED, BODY_FRD);
  any other (LOCAL_OFFSET_NED's z is an offset, not a depth; a global frame; an unknown number)
  is refused, never read as NED. Then only the fields the onboard loop uses
  (onboard.loop.apply_position_target) are checked: z as a depth in a non-body frame within
  [min_depth_m, max_depth_m]; the horizontal speed hypot(vx, vy) (a rotation by yaw keeps it, so
  the frame does not matter) <= max_speed_m_s; |vz| <= max_heave_speed_m_s; |yaw| <= 2 pi (a
  heading, not 3.4e38); |yaw_rate| <= max_yaw_rate_rad_s.
- MANUAL_CONTROL: the axes' own range in common.xml, x, y, r in -1000..1000 and z in 0..1000
  (ArduSub's 500-neutral heave); the loop scales full stick to the controller's manual speeds.
- COMMAND_LONG MAV_CMD_COMPONENT_ARM_DISARM: param1 exactly 0 (disarm) or 1 (arm);
  MAV_CMD_DO_SET_MODE: param1 with MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, param2 a whole number
  (which modes exist is the loop's check, answered MAV_RESULT_DENIED there).

Non-finite numbers are not this module's business: the loop's decoders refuse and count them
(`rejected_inputs`) and say so in a STATUSTEXT, so they pass here unchanged.
"""

from __future__ import annotations

import math

from pymavlink.dialects.v20 import ardupilotmega as mavlink

BODY_FRAMES = (mavlink.MAV_FRAME_BODY_NED, mavlink.MAV_FRAME_BODY_OFFSET_NED, mavlink.MAV_FRAME_BODY_FRD)
IGNORE_Z = mavlink.POSITION_TARGET_TYPEMASK_Z_IGNORE
IGNORE_VX = mavlink.POSITION_TARGET_TYPEMASK_VX_IGNORE
IGNORE_VY = mavlink.POSITION_TARGET_TYPEMASK_VY_IGNORE
IGNORE_VZ = mavlink.POSITION_TARGET_TYPEMASK_VZ_IGNORE
IGNORE_YAW = mavlink.POSITION_TARGET_TYPEMASK_YAW_IGNORE
IGNORE_YAW_RATE = mavlink.POSITION_TARGET_TYPEMASK_YAW_RATE_IGNORE
FRAMES = (mavlink.MAV_FRAME_LOCAL_NED,) + BODY_FRAMES  # the frames apply_position_target reads
MAX_YAW_RAD = 2 * math.pi
MANUAL_RANGES = {"x": (-1000, 1000), "y": (-1000, 1000), "z": (0, 1000), "r": (-1000, 1000)}


def _finite(*values) -> bool:
    try:
        return all(math.isfinite(float(v)) for v in values)
    except (TypeError, ValueError, OverflowError):
        return False


def _f(v: float, decimals: int) -> str:
    """A refused value, short enough for a STATUSTEXT: fixed decimals, or 3 digits when huge."""
    return f"{v:.{decimals}f}" if abs(v) < 1000 else f"{v:.3g}"


def _num(v) -> str:
    try:
        return f"{float(v):.6g}"
    except (TypeError, ValueError, OverflowError):
        return repr(v)[:12]


def position_target_violation(env, msg) -> str | None:
    """SET_POSITION_TARGET_LOCAL_NED against the envelope `env`: None, or why it is refused."""
    mask = int(msg.type_mask)
    if msg.coordinate_frame not in FRAMES:
        return f"setpoint refused: frame {_num(msg.coordinate_frame)[:8]} not LOCAL_NED or body"
    body = msg.coordinate_frame in BODY_FRAMES
    if not mask & IGNORE_Z and not body and _finite(msg.z):
        depth = float(msg.z)
        if depth > env.max_depth_m:
            return f"setpoint refused: depth {_f(depth, 1)} m > max {env.max_depth_m:.1f} m"
        if depth < env.min_depth_m:
            return f"setpoint refused: depth {_f(depth, 1)} m < min {env.min_depth_m:.1f} m"
    if not (mask & IGNORE_VX and mask & IGNORE_VY):
        vx = 0.0 if mask & IGNORE_VX else msg.vx
        vy = 0.0 if mask & IGNORE_VY else msg.vy
        if _finite(vx, vy):
            speed = math.hypot(float(vx), float(vy))
            if speed > env.max_speed_m_s:
                return f"setpoint refused: speed {_f(speed, 2)} > max {env.max_speed_m_s:.2f} m/s"
    if not mask & IGNORE_VZ and _finite(msg.vz) and abs(float(msg.vz)) > env.max_heave_speed_m_s:
        return f"setpoint refused: heave {_f(abs(float(msg.vz)), 2)} > max {env.max_heave_speed_m_s:.2f} m/s"
    if not mask & IGNORE_YAW and _finite(msg.yaw) and abs(float(msg.yaw)) > MAX_YAW_RAD:
        return f"setpoint refused: |yaw| {_f(abs(float(msg.yaw)), 2)} > {MAX_YAW_RAD:.2f} rad"
    if not mask & IGNORE_YAW_RATE and _finite(msg.yaw_rate) and abs(float(msg.yaw_rate)) > env.max_yaw_rate_rad_s:
        return f"setpoint refused: yaw rate {_f(abs(float(msg.yaw_rate)), 2)} > max {env.max_yaw_rate_rad_s:.2f} rad/s"
    return None


def manual_violation(msg) -> str | None:
    """MANUAL_CONTROL axes outside their common.xml range: why it is refused, else None."""
    for axis, (lo, hi) in MANUAL_RANGES.items():
        v = getattr(msg, axis)
        if _finite(v) and v > hi:
            return f"setpoint refused: manual {axis} {v:g} > {hi}"
        if _finite(v) and v < lo:
            return f"setpoint refused: manual {axis} {v:g} < {lo}"
    return None


def command_violation(msg) -> str | None:
    """COMMAND_LONG arm/disarm or set-mode with parameters the loop must not guess at: why it is
    denied (MAV_RESULT_DENIED), else None. Other commands pass (the loop answers them)."""
    cmd = int(msg.command)
    if cmd == mavlink.MAV_CMD_COMPONENT_ARM_DISARM:
        p1 = msg.param1
        if not (_finite(p1) and float(p1) in (0.0, 1.0)):
            return f"command denied: arm param1 {_num(p1)} not 0 or 1"
    elif cmd == mavlink.MAV_CMD_DO_SET_MODE:
        p1, p2 = msg.param1, msg.param2
        if not (_finite(p1) and float(p1).is_integer() and int(p1) & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED):
            return f"command denied: mode param1 {_num(p1)} not custom"
        if not (_finite(p2) and float(p2).is_integer() and p2 >= 0):
            return f"command denied: mode param2 {_num(p2)} not a mode"
    return None
