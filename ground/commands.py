"""Ground commands as standard MAVLink (pure builders and the operator's command lines).

Commands (the onboard loop's own builders, onboard/loop.py, so both sides agree on the fields):
- arm / disarm: COMMAND_LONG MAV_CMD_COMPONENT_ARM_DISARM (param1 1 / 0)
- mode: COMMAND_LONG MAV_CMD_DO_SET_MODE (param1 MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, param2 mode)
- depth / yaw setpoint: SET_POSITION_TARGET_LOCAL_NED in MAV_FRAME_LOCAL_NED (z = depth, yaw)
- velocity setpoint: SET_POSITION_TARGET_LOCAL_NED in MAV_FRAME_BODY_FRD (vx, vy)
- joystick: MANUAL_CONTROL (x, y, r in +-1000; z 0..1000 with 500 neutral, as ArduSub)
- stream rates: COMMAND_LONG MAV_CMD_SET_MESSAGE_INTERVAL (param1 message id, param2 interval
  in us; -1 stops the stream, 0 restores the default) - MAVLink common.xml.

`parse_command("depth 1.5")` turns an operator's line into messages (`COMMAND_HELP` lists them).

Signing and stream rates are the robot's checks, so they live in `onboard.signing` and
`onboard.stream_rates`; the names the ground uses are re-exported here.
"""

from __future__ import annotations

import math

from pymavlink.dialects.v20 import ardupilotmega as mavlink

# The robot's side of signing and stream rates lives in onboard (the robot carries it).
from onboard.signing import SigningError, enable_signing, load_key
from onboard.stream_rates import StreamRates

__all__ = ["CommandError", "SigningError", "StreamRates", "enable_signing", "load_key"]

COMMAND_HELP = ("arm | disarm | mode NAME | depth M [yaw DEG] | yaw DEG | velocity U [V] | "
                "manual X Y Z R | rate MESSAGE HZ")


class CommandError(ValueError):
    """An operator command or key file that cannot be used; the message says what was expected."""


# ------------------------------------------------------------------------------------------------
# Command builders


def arm(armed: bool = True):
    from onboard.loop import arm_command

    return arm_command(armed)


def set_mode(name: str):
    from onboard.loop import MODES, mode_command

    if name not in MODES:
        raise CommandError(f"mode {name!r}: expected one of {', '.join(sorted(MODES))}")
    return mode_command(name)


def depth_yaw(depth_m: float | None = None, yaw_rad: float | None = None):
    from onboard.loop import depth_yaw_target

    for label, v in (("depth", depth_m), ("yaw", yaw_rad)):
        if v is not None and not math.isfinite(v):
            raise CommandError(f"{label} setpoint {v!r}: expected a finite number")
    return depth_yaw_target(depth_m, yaw_rad)


def velocity(u_m_s: float, v_m_s: float = 0.0):
    from onboard.loop import body_velocity_target

    if not (math.isfinite(u_m_s) and math.isfinite(v_m_s)):
        raise CommandError(f"velocity ({u_m_s!r}, {v_m_s!r}): expected finite numbers in m/s")
    return body_velocity_target(u_m_s, v_m_s)


def manual(x: int, y: int, z: int, r: int, target_system: int = 1):
    """MANUAL_CONTROL; axes clipped to their ranges (x, y, r: -1000..1000; z: 0..1000)."""
    c = lambda a, lo, hi: int(max(lo, min(hi, round(a))))  # noqa: E731
    return mavlink.MAVLink_manual_control_message(target_system, c(x, -1000, 1000), c(y, -1000, 1000),
                                                   c(z, 0, 1000), c(r, -1000, 1000), 0)


def message_interval(message: str | int, rate_hz: float, target_system: int = 1, target_component: int = 1):
    """COMMAND_LONG MAV_CMD_SET_MESSAGE_INTERVAL: rate_hz > 0 sets, 0 stops (-1), < 0 default (0)."""
    msg_id = message_id(message)
    if not math.isfinite(rate_hz):
        raise CommandError(f"rate for {message}: expected a number of Hz, got {rate_hz!r}")
    interval_us = 1e6 / rate_hz if rate_hz > 0 else (-1.0 if rate_hz == 0 else 0.0)
    if interval_us > 2 ** 31 - 1:  # the autopilot reads it as int32 us; 1e-300 Hz did not even pack
        raise CommandError(f"rate for {message}: {rate_hz!r} Hz is slower than one message per 2^31 us, "
                           "the slowest MAVLink can ask")
    return mavlink.MAVLink_command_long_message(target_system, target_component,
                                                mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                                                float(msg_id), float(interval_us), 0, 0, 0, 0, 0)


def message_id(message: str | int) -> int:
    if isinstance(message, int) or (str(message).isascii() and str(message).isdigit()):
        if not 0 <= int(message) < 2 ** 24:  # a MAVLink 2 message id has 24 bits
            raise CommandError(f"message id {message}: expected 0..{2 ** 24 - 1}")
        return int(message)
    name = str(message).upper()
    ident = getattr(mavlink, f"MAVLINK_MSG_ID_{name}", None)
    if ident is None:
        raise CommandError(f"message {message!r}: not a MAVLink message name (e.g. ATTITUDE)")
    return int(ident)


def parse_rates(text: str) -> dict:
    """'ATTITUDE=10,NAMED_VALUE_FLOAT=5' -> {'ATTITUDE': 10.0, ...} (names checked)."""
    out = {}
    for item in filter(None, (s.strip() for s in str(text).split(","))):
        name, sep, value = item.partition("=")
        try:
            hz = float(value)
        except ValueError:
            hz = math.nan
        if not sep or not math.isfinite(hz) or hz < 0:
            raise CommandError(f"rate {item!r}: expected MESSAGE=HZ (HZ >= 0), e.g. ATTITUDE=10")
        message_id(name)
        out[name.strip().upper()] = hz
    return out


def parse_command(line: str) -> list:
    """One operator line -> the messages to send; CommandError naming the expected form."""
    words = str(line).split()
    if not words:
        raise CommandError(f"empty command: expected {COMMAND_HELP}")
    verb, args = words[0].lower(), words[1:]

    def nums(n_min, n_max):
        if not n_min <= len(args) <= n_max:
            raise CommandError(f"{line!r}: expected {COMMAND_HELP}")
        try:
            v = [float(a) for a in args]
        except ValueError:
            raise CommandError(f"{line!r}: arguments must be numbers; expected {COMMAND_HELP}") from None
        if not all(math.isfinite(x) and abs(x) < 3.4e38 for x in v):  # MAVLink floats are float32:
            raise CommandError(f"{line!r}: arguments must be finite float32 numbers")  # 7.7e117 did not pack
        return v

    if verb in ("arm", "disarm") and not args:
        return [arm(verb == "arm")]
    if verb == "mode" and len(args) == 1:
        return [set_mode(args[0].lower())]
    if verb == "depth":
        if len(args) == 3 and args[1].lower() == "yaw":
            args = [args[0], args[2]]
        v = nums(1, 2)
        return [depth_yaw(v[0], math.radians(v[1]) if len(v) > 1 else None)]
    if verb == "yaw":
        return [depth_yaw(None, math.radians(nums(1, 1)[0]))]
    if verb == "velocity":
        v = nums(1, 2)
        return [velocity(v[0], v[1] if len(v) > 1 else 0.0)]
    if verb == "manual":
        return [manual(*nums(4, 4))]
    if verb == "rate" and len(args) == 2:
        try:
            hz = float(args[1])
        except ValueError:
            raise CommandError(f"{line!r}: expected rate MESSAGE HZ") from None
        return [message_interval(args[0], hz)]
    raise CommandError(f"{line!r}: expected {COMMAND_HELP}")


# ------------------------------------------------------------------------------------------------
