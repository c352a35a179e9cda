"""MAVLink 2 <-> domain samples: the one translation every link, log and endpoint shares (pure).

Codec separate from transport, as in pymavlink: this module builds and reads MAVLink message
objects; packing them onto a socket, a serial line or a .tlog is the caller's business (it
calls `encode`). The dialect is imported directly, never chosen by pymavlink's process-wide
MAVLINK_DIALECT / MAVLINK20 environment variables.

Conventions (spec/recording.md section 1):
- The vehicle is system 1, component 1.
- Vehicle time t (s since the plant / autopilot booted) goes into `time_usec` = round(t * 1e6)
  and `time_boot_ms` = round(t * 1e3). SERVO_OUTPUT_RAW.time_usec is a uint32 in MAVLink and
  wraps every 2^32 us (71.6 min); `decode_actuators` cannot undo the wrap, so callers reading
  long recordings unwrap it against the log time.
- Pressure travels in hPa (SCALED_PRESSURE2.press_abs, as ArduSub sends its depth sensor),
  temperature in cdegC; everything else in SI units, body FRD.
- Propeller rpm travels in ESC_TELEMETRY_1_TO_4 (ardupilotmega; units 1-4, then 5_TO_8, ...):
  the pymavlink dialects (2.4.50) have no ESC_STATUS, and ArduSub itself sends its rpm this way.
  `decode_rpm` reads ESC_STATUS too, when a dialect has it.
- Joint angle feedback (smart servos) travels in ACTUATOR_OUTPUT_STATUS: `active` = bitmask of
  the 2k joints, actuator[0:k] = azimuths, actuator[k:2k] = elevations (rad).
- Decoding rejects NaN / inf (a sensor reading nothing is not a reading) with `CodecError`,
  naming the message and field; so does encoding.
"""

from __future__ import annotations

import math

import pymavlink.dialects.v20.ardupilotmega as mavlink2

from .sensors import ActuatorSample, AttitudeSample, ImuSample, PressureSample

SYSTEM_ID = 1
COMPONENT_ID = 1
G0_M_S2 = 9.80665  # standard gravity: the "G" of the mG unit of SCALED_IMU / RAW_IMU
N_SERVO_CHANNELS = 16
HIGHRES_IMU_ACCEL_GYRO = 0b111111  # fields_updated bits 0-5: xacc..zgyro are valid
ESC_GROUPS = ("ESC_TELEMETRY_1_TO_4", "ESC_TELEMETRY_5_TO_8", "ESC_TELEMETRY_9_TO_12")
N_ACTUATOR_STATUS = 32  # ACTUATOR_OUTPUT_STATUS.actuator[32]: joint angle feedback


class CodecError(ValueError):
    """A message or sample that cannot be translated; the text names the message and field."""


def make_mavlink(system_id: int = SYSTEM_ID, component_id: int = COMPONENT_ID) -> mavlink2.MAVLink:
    """A MAVLink 2 packer/parser with no transport (its sequence number is its only state)."""
    return mavlink2.MAVLink(file=None, srcSystem=system_id, srcComponent=component_id)


def encode(mav: mavlink2.MAVLink, msg) -> bytes:
    """The packed MAVLink 2 packet of `msg` (advances `mav`'s sequence number)."""
    return msg.pack(mav)


def parse(mav: mavlink2.MAVLink, data: bytes) -> list:
    """Messages found in `data` (bytes may split packets across calls; `mav` keeps the rest)."""
    return mav.parse_buffer(data) or []


# --- time ------------------------------------------------------------------------------------

def time_usec(t_s: float) -> int:
    """Vehicle time (s since boot) -> MAVLink time_usec (us)."""
    _finite("time", "t_s", t_s)
    if t_s < 0:
        raise CodecError(f"vehicle time must be >= 0 s, got {t_s}")
    return int(round(t_s * 1e6))


MAX_TIME_S = 0xFFFFFFFF / 1e3  # time_boot_ms's range (49.7 days): the loop stamps its outputs with it


def _vehicle_time(message: str, t_s: float) -> float:
    """A received sample's time (s since boot), refused beyond what the loop can stamp its answers
    with (a time_usec near 2^64 moved the loop's clock to 1.8e13 s and its outputs failed to pack)."""
    if not t_s <= MAX_TIME_S:
        raise CodecError(f"{message}: time {t_s:.6g} s since boot is beyond time_boot_ms's range ({MAX_TIME_S:.0f} s)")
    return t_s


def time_boot_ms(t_s: float) -> int:
    """Vehicle time (s since boot) -> MAVLink time_boot_ms (uint32 ms, 49.7 days of range)."""
    ms = int(round(time_usec(t_s) / 1000.0))
    if ms > 0xFFFFFFFF:
        raise CodecError(f"vehicle time {t_s} s does not fit time_boot_ms (uint32 ms)")
    return ms


# --- domain sample -> message -----------------------------------------------------------------

def heartbeat(armed: bool = True) -> mavlink2.MAVLink_heartbeat_message:
    """HEARTBEAT of a submarine (MAV_TYPE_SUBMARINE), generic autopilot, active."""
    return mavlink2.MAVLink_heartbeat_message(
        type=mavlink2.MAV_TYPE_SUBMARINE,
        autopilot=mavlink2.MAV_AUTOPILOT_GENERIC,
        base_mode=mavlink2.MAV_MODE_FLAG_SAFETY_ARMED if armed else 0,
        custom_mode=0,
        system_status=mavlink2.MAV_STATE_ACTIVE,
        mavlink_version=3,
    )


def encode_imu(s: ImuSample) -> mavlink2.MAVLink_highres_imu_message:
    """ImuSample -> HIGHRES_IMU (specific force m/s^2, body rates rad/s, FRD)."""
    a = _finite_all("HIGHRES_IMU", ("xacc", "yacc", "zacc"), s.accel_frd_m_s2)
    w = _finite_all("HIGHRES_IMU", ("xgyro", "ygyro", "zgyro"), s.gyro_frd_rad_s)
    return mavlink2.MAVLink_highres_imu_message(
        time_usec(s.time_s), a[0], a[1], a[2], w[0], w[1], w[2],
        0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, HIGHRES_IMU_ACCEL_GYRO, 0,
    )


def encode_pressure(s: PressureSample) -> mavlink2.MAVLink_scaled_pressure2_message:
    """PressureSample -> SCALED_PRESSURE2 (press_abs hPa = Pa / 100, temperature cdegC)."""
    p = _finite("SCALED_PRESSURE2", "press_abs", s.press_abs_pa)
    c = _finite("SCALED_PRESSURE2", "temperature", s.temperature_c)
    return mavlink2.MAVLink_scaled_pressure2_message(
        time_boot_ms(s.time_s), p / 100.0, 0.0, int(round(c * 100.0)), 0,
    )


def encode_attitude(s: AttitudeSample) -> mavlink2.MAVLink_attitude_message:
    """AttitudeSample -> ATTITUDE (ZYX Euler rad, body rates rad/s)."""
    names = ("roll", "pitch", "yaw", "rollspeed", "pitchspeed", "yawspeed")
    v = _finite_all("ATTITUDE", names, (
        s.roll_rad, s.pitch_rad, s.yaw_rad, s.rollspeed_rad_s, s.pitchspeed_rad_s, s.yawspeed_rad_s,
    ))
    return mavlink2.MAVLink_attitude_message(time_boot_ms(s.time_s), *v)


def encode_actuators(s: ActuatorSample) -> list:
    """ActuatorSample -> [SERVO_OUTPUT_RAW, ESC_TELEMETRY_1_TO_4, (5_TO_8, ...)].

    PWM channels 1..16 (9..16 are MAVLink 2 extension fields); rpm rounded to the uint16 field.
    """
    if len(s.pwm_us) > N_SERVO_CHANNELS:
        raise CodecError(f"SERVO_OUTPUT_RAW carries {N_SERVO_CHANNELS} channels, got {len(s.pwm_us)}")
    pwm = list(s.pwm_us) + [0] * (N_SERVO_CHANNELS - len(s.pwm_us))
    for i, c in enumerate(pwm):
        if not (isinstance(c, int) or float(c).is_integer()) or not 0 <= c <= 0xFFFF:
            raise CodecError(f"SERVO_OUTPUT_RAW.servo{i + 1}_raw must be an integer 0..65535 us, got {c!r}")
    servo = mavlink2.MAVLink_servo_output_raw_message(
        time_usec(s.time_s) & 0xFFFFFFFF, 0, *(int(c) for c in pwm)
    )
    rpm = _finite_all("ESC_TELEMETRY", [f"rpm[{i}]" for i in range(len(s.rpm))], s.rpm)
    if len(rpm) > 4 * len(ESC_GROUPS):
        raise CodecError(f"ESC telemetry carries at most {4 * len(ESC_GROUPS)} units, got {len(rpm)}")
    out = [servo]
    for g in range(0, len(rpm), 4):
        group = [min(max(int(round(abs(r))), 0), 0xFFFF) for r in rpm[g:g + 4]]
        group += [0] * (4 - len(group))
        cls = getattr(mavlink2, f"MAVLink_{ESC_GROUPS[g // 4].lower()}_message")
        out.append(cls([0] * 4, [0] * 4, [0] * 4, [0] * 4, group, [0] * 4))
    return out


def encode_joint_angles(t_s: float, alpha_rad, beta_rad) -> mavlink2.MAVLink_actuator_output_status_message:
    """Measured joint angles -> ACTUATOR_OUTPUT_STATUS (smart servos report their position).

    With k units: `active` = (1 << 2k) - 1, actuator[0:k] = azimuths alpha (rad),
    actuator[k:2k] = elevations beta (rad), the rest 0; time_usec = sample time.
    """
    a = _finite_all("ACTUATOR_OUTPUT_STATUS", [f"alpha[{i}]" for i in range(len(alpha_rad))], alpha_rad)
    b = _finite_all("ACTUATOR_OUTPUT_STATUS", [f"beta[{i}]" for i in range(len(beta_rad))], beta_rad)
    k = len(a)
    if len(b) != k:
        raise CodecError(f"ACTUATOR_OUTPUT_STATUS: {k} azimuths but {len(b)} elevations")
    if 2 * k > N_ACTUATOR_STATUS:
        raise CodecError(f"ACTUATOR_OUTPUT_STATUS carries {N_ACTUATOR_STATUS} values, {k} units need {2 * k}")
    values = list(a) + list(b) + [0.0] * (N_ACTUATOR_STATUS - 2 * k)
    return mavlink2.MAVLink_actuator_output_status_message(time_usec(t_s), (1 << (2 * k)) - 1, values)


# --- message -> domain sample -----------------------------------------------------------------

def decode_imu(msg) -> ImuSample:
    """HIGHRES_IMU, SCALED_IMU(2,3) or RAW_IMU -> ImuSample.

    SCALED_IMU* carry mG and mrad/s; RAW_IMU is read with ArduPilot's scaling, the same.
    """
    name = msg.get_type()
    if name == "HIGHRES_IMU":
        a = _finite_all(name, ("xacc", "yacc", "zacc"), (msg.xacc, msg.yacc, msg.zacc))
        w = _finite_all(name, ("xgyro", "ygyro", "zgyro"), (msg.xgyro, msg.ygyro, msg.zgyro))
        return ImuSample(_vehicle_time(name, msg.time_usec / 1e6), a, w)
    if name in ("SCALED_IMU", "SCALED_IMU2", "SCALED_IMU3", "RAW_IMU"):
        t = _vehicle_time(name, msg.time_usec / 1e6) if name == "RAW_IMU" else msg.time_boot_ms / 1e3
        a = tuple(c * G0_M_S2 / 1000.0 for c in (msg.xacc, msg.yacc, msg.zacc))
        w = tuple(c / 1000.0 for c in (msg.xgyro, msg.ygyro, msg.zgyro))
        return ImuSample(t, a, w)
    raise CodecError(f"{name} is not an IMU message")


def decode_pressure(msg) -> PressureSample:
    """SCALED_PRESSURE(2,3) -> PressureSample (Pa = hPa * 100)."""
    name = msg.get_type()
    if name not in ("SCALED_PRESSURE", "SCALED_PRESSURE2", "SCALED_PRESSURE3"):
        raise CodecError(f"{name} is not a pressure message")
    p = _finite(name, "press_abs", msg.press_abs)
    return PressureSample(msg.time_boot_ms / 1e3, p * 100.0, msg.temperature / 100.0)


def decode_attitude(msg) -> AttitudeSample:
    """ATTITUDE -> AttitudeSample."""
    name = msg.get_type()
    if name != "ATTITUDE":
        raise CodecError(f"{name} is not an ATTITUDE message")
    names = ("roll", "pitch", "yaw", "rollspeed", "pitchspeed", "yawspeed")
    v = _finite_all(name, names, tuple(getattr(msg, n) for n in names))
    return AttitudeSample(msg.time_boot_ms / 1e3, *v)


def decode_rpm(msg) -> tuple[int, tuple]:
    """ESC_TELEMETRY_x_TO_y or ESC_STATUS -> (index of its first unit, 0-based; rpm of 4 units)."""
    name = msg.get_type()
    if name in ESC_GROUPS:
        first = 4 * ESC_GROUPS.index(name)
    elif name == "ESC_STATUS":
        first = int(msg.index)
    else:
        raise CodecError(f"{name} is not an ESC telemetry message")
    return first, _finite_all(name, [f"rpm[{i}]" for i in range(4)], tuple(msg.rpm))


def decode_actuators(servo_msg, esc_msgs=(), n_units: int = 4) -> ActuatorSample:
    """SERVO_OUTPUT_RAW (+ the ESC telemetry of the same instant) -> ActuatorSample.

    Time comes from SERVO_OUTPUT_RAW.time_usec (uint32: see the module note on its wrap).
    `rpm` holds units 1, 2, ... for as far as the given ESC messages cover them without a gap,
    at most `n_units` (empty when no ESC message is given).
    """
    name = servo_msg.get_type()
    if name != "SERVO_OUTPUT_RAW":
        raise CodecError(f"{name} is not SERVO_OUTPUT_RAW")
    pwm = tuple(int(getattr(servo_msg, f"servo{i}_raw", 0) or 0) for i in range(1, N_SERVO_CHANNELS + 1))
    rpm: dict[int, float] = {}
    for m in esc_msgs:
        first, values = decode_rpm(m)
        for i, r in enumerate(values):
            rpm[first + i] = float(r)
    covered = 0
    while covered < n_units and covered in rpm:
        covered += 1
    return ActuatorSample(servo_msg.time_usec / 1e6, pwm, tuple(rpm[i] for i in range(covered)))


def decode_joint_angles(msg, n_units: int) -> tuple[float, tuple, tuple]:
    """ACTUATOR_OUTPUT_STATUS -> (t_s, azimuths alpha (rad) x n_units, elevations beta x n_units).

    Rejects another message, an `active` mask missing one of the 2 n_units joints, and NaN/inf.
    """
    name = msg.get_type()
    if name != "ACTUATOR_OUTPUT_STATUS":
        raise CodecError(f"{name} is not ACTUATOR_OUTPUT_STATUS")
    k = int(n_units)
    if not 0 < 2 * k <= N_ACTUATOR_STATUS:
        raise CodecError(f"ACTUATOR_OUTPUT_STATUS carries 1..{N_ACTUATOR_STATUS // 2} units, asked for {n_units}")
    need = (1 << (2 * k)) - 1
    if (int(msg.active) & need) != need:
        raise CodecError(f"ACTUATOR_OUTPUT_STATUS.active = {int(msg.active):#x} lacks joints of {k} units "
                         f"(expected bits {need:#x})")
    v = _finite_all(name, [f"actuator[{i}]" for i in range(2 * k)], tuple(msg.actuator)[:2 * k])
    return _vehicle_time(name, msg.time_usec / 1e6), v[:k], v[k:]


def decode(msg):
    """Any sensor or actuator message -> its domain sample; None for messages with no sample.

    ESC telemetry decodes to `(first_unit, rpm)` (it has no time of its own in ardupilotmega).
    """
    name = msg.get_type()
    reader = _DECODERS.get(name)
    return reader(msg) if reader is not None else None


_DECODERS = {
    "HIGHRES_IMU": decode_imu,
    "SCALED_IMU": decode_imu,
    "SCALED_IMU2": decode_imu,
    "SCALED_IMU3": decode_imu,
    "RAW_IMU": decode_imu,
    "SCALED_PRESSURE": decode_pressure,
    "SCALED_PRESSURE2": decode_pressure,
    "SCALED_PRESSURE3": decode_pressure,
    "ATTITUDE": decode_attitude,
    "SERVO_OUTPUT_RAW": decode_actuators,
    "ESC_STATUS": decode_rpm,
    **{g: decode_rpm for g in ESC_GROUPS},
}


# --- checks -----------------------------------------------------------------------------------

def _finite(message: str, field: str, value) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise CodecError(f"{message}.{field} must be a number, got {value!r}") from None
    if not math.isfinite(v):
        raise CodecError(f"{message}.{field} is {v}: expected a finite number")
    return v


def _finite_all(message: str, fields, values) -> tuple:
    values = tuple(values)
    if len(values) != len(fields):
        raise CodecError(f"{message}: expected {len(fields)} values ({', '.join(fields)}), got {len(values)}")
    try:  # fast path (this runs for every sample): all finite numbers
        out = tuple(map(float, values))
        if all(map(math.isfinite, out)):
            return out
    except (TypeError, ValueError):
        pass
    return tuple(_finite(message, f, v) for f, v in zip(fields, values))  # names the bad field
