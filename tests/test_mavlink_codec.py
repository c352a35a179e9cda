"""The MAVLink codec: domain samples survive the wire, units are converted, NaN/inf is refused."""

from __future__ import annotations

import math
import os
import subprocess
import sys

import numpy as np
import pytest

import pymavlink.dialects.v20.ardupilotmega as mavlink2
from onboard import mavlink_codec as codec
from onboard.sensors import ActuatorSample, AttitudeSample, ImuSample, PressureSample


def wire(*msgs):
    """Pack with one MAVLink object, parse with another: what a receiver gets."""
    tx, rx = codec.make_mavlink(), codec.make_mavlink(255, 190)
    data = b"".join(codec.encode(tx, m) for m in msgs)
    out = codec.parse(rx, data)
    assert len(out) == len(msgs)
    return out


def test_imu_round_trip_float32_exact_values():
    # values exactly representable in float32, so the wire returns them unchanged
    s = ImuSample(1.25, (0.5, -0.25, -9.75), (0.125, -0.0625, 2.0))
    (m,) = wire(codec.encode_imu(s))
    assert m.get_type() == "HIGHRES_IMU"
    assert m.get_srcSystem() == 1 and m.get_srcComponent() == 1
    assert m.time_usec == 1_250_000
    assert m.fields_updated == 0b111111  # accel and gyro valid, nothing else
    assert codec.decode(m) == s


def test_pressure_round_trip_in_hpa():
    s = PressureSample(0.02, 106230.5, 21.37)
    (m,) = wire(codec.encode_pressure(s))
    assert m.get_type() == "SCALED_PRESSURE2"
    assert m.time_boot_ms == 20
    # 106230.5 Pa = 1062.305 hPa, stored as float32: error at most half a float32 step (in Pa)
    half_ulp_pa = float(np.spacing(np.float32(1062.305))) * 100 / 2
    assert abs(m.press_abs - 1062.305) <= half_ulp_pa / 100
    assert m.temperature == 2137  # cdegC
    back = codec.decode(m)
    assert back.time_s == 0.02
    assert abs(back.press_abs_pa - 106230.5) <= half_ulp_pa
    assert back.temperature_c == 21.37


def test_attitude_round_trip():
    s = AttitudeSample(3.5, 0.25, -0.5, 3.0, 0.125, -1.5, 0.75)
    (m,) = wire(codec.encode_attitude(s))
    assert m.time_boot_ms == 3500
    assert codec.decode(m) == s


def test_time_conventions():
    assert codec.time_usec(0.0) == 0
    assert codec.time_usec(12.345678) == 12_345_678
    assert codec.time_boot_ms(0.0206) == 21  # 20.6 ms rounds to 21
    assert codec.time_boot_ms(4000.0) == 4_000_000
    with pytest.raises(codec.CodecError, match=">= 0"):
        codec.time_usec(-0.001)
    with pytest.raises(codec.CodecError, match="finite"):
        codec.time_usec(math.nan)


def test_actuators_channels_9_to_16_travel_in_the_mavlink2_extensions():
    pwm = tuple(1000 + 10 * c for c in range(1, 13)) + (0, 0, 0, 0)  # distinct per channel
    s = ActuatorSample(2.5, pwm, (0.0, 1000.4, 2999.6, 4998.0))
    servo, esc = wire(*codec.encode_actuators(s))
    assert servo.get_type() == "SERVO_OUTPUT_RAW" and esc.get_type() == "ESC_TELEMETRY_1_TO_4"
    assert servo.time_usec == 2_500_000
    assert [getattr(servo, f"servo{c}_raw") for c in range(9, 13)] == [1090, 1100, 1110, 1120]
    assert list(esc.rpm) == [0, 1000, 3000, 4998]  # rounded to the uint16 field
    back = codec.decode_actuators(servo, [esc])
    assert back.pwm_us == pwm
    assert back.rpm == (0.0, 1000.0, 3000.0, 4998.0)
    assert back.time_s == 2.5


def test_servo_time_usec_wraps_at_uint32():
    s = ActuatorSample(4300.0, (1500,) * 12, (0.0,) * 4)  # 4300 s > 2^32 us = 4294.967296 s
    servo = codec.encode_actuators(s)[0]
    assert servo.time_usec == 4_300_000_000 - 2**32


def test_actuators_five_units_use_two_esc_messages():
    s = ActuatorSample(0.0, (1500,) * 15, (1.0, 2.0, 3.0, 4.0, 5.0))
    msgs = wire(*codec.encode_actuators(s))
    assert [m.get_type() for m in msgs] == ["SERVO_OUTPUT_RAW", "ESC_TELEMETRY_1_TO_4", "ESC_TELEMETRY_5_TO_8"]
    assert codec.decode(msgs[2]) == (4, (5.0, 0.0, 0.0, 0.0))
    assert codec.decode_actuators(msgs[0], msgs[1:], n_units=5).rpm == (1.0, 2.0, 3.0, 4.0, 5.0)


def test_heartbeat_is_a_submarine():
    (m,) = wire(codec.heartbeat())
    assert m.type == mavlink2.MAV_TYPE_SUBMARINE
    assert m.base_mode & mavlink2.MAV_MODE_FLAG_SAFETY_ARMED
    assert codec.decode(m) is None  # no domain sample in a heartbeat


def test_scaled_imu_is_read_in_mg_and_mrad_s():
    m = mavlink2.MAVLink_scaled_imu2_message(1500, 1000, -500, -1000, 500, 0, -250, 0, 0, 0, 0)
    s = codec.decode(wire(m)[0])
    assert s.time_s == 1.5
    assert s.accel_frd_m_s2 == pytest.approx((9.80665, -4.903325, -9.80665), abs=1e-12)
    assert s.gyro_frd_rad_s == pytest.approx((0.5, 0.0, -0.25), abs=1e-12)


def test_parse_across_split_buffers():
    tx, rx = codec.make_mavlink(), codec.make_mavlink()
    data = codec.encode(tx, codec.heartbeat()) + codec.encode(tx, codec.encode_attitude(
        AttitudeSample(1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)))
    got = []
    for i in range(len(data)):  # one byte at a time
        got += codec.parse(rx, data[i:i + 1])
    assert [m.get_type() for m in got] == ["HEARTBEAT", "ATTITUDE"]
    assert data[0] == 0xFD  # MAVLink 2 start byte


# --- NaN / inf are refused, both ways -----------------------------------------------------------

def raw_packet_roundtrip(msg):
    """Pack with pymavlink directly (which lets NaN through) and parse: what a sick sender sends."""
    tx, rx = mavlink2.MAVLink(None, 1, 1), mavlink2.MAVLink(None, 255, 0)
    return rx.parse_buffer(msg.pack(tx))[0]


@pytest.mark.parametrize("field", ["xacc", "zgyro"])
def test_decode_rejects_nan_imu(field):
    vals = dict(xacc=0.0, yacc=0.0, zacc=-9.8, xgyro=0.0, ygyro=0.0, zgyro=0.0)
    vals[field] = math.nan
    m = raw_packet_roundtrip(mavlink2.MAVLink_highres_imu_message(
        10, vals["xacc"], vals["yacc"], vals["zacc"], vals["xgyro"], vals["ygyro"], vals["zgyro"],
        0, 0, 0, 0, 0, 0, 0, 63, 0))
    with pytest.raises(codec.CodecError, match=rf"HIGHRES_IMU\.{field} is nan"):
        codec.decode(m)


def test_decode_rejects_inf_pressure_and_nan_attitude():
    p = raw_packet_roundtrip(mavlink2.MAVLink_scaled_pressure2_message(10, math.inf, 0.0, 2000, 0))
    with pytest.raises(codec.CodecError, match=r"SCALED_PRESSURE2\.press_abs is inf"):
        codec.decode(p)
    a = raw_packet_roundtrip(mavlink2.MAVLink_attitude_message(10, 0.0, math.nan, 0.0, 0.0, 0.0, 0.0))
    with pytest.raises(codec.CodecError, match=r"ATTITUDE\.pitch is nan"):
        codec.decode(a)


def test_encode_rejects_nan():
    with pytest.raises(codec.CodecError, match=r"HIGHRES_IMU\.ygyro is nan"):
        codec.encode_imu(ImuSample(0.0, (0.0, 0.0, -9.8), (0.0, math.nan, 0.0)))
    with pytest.raises(codec.CodecError, match=r"press_abs is -inf"):
        codec.encode_pressure(PressureSample(0.0, -math.inf))
    with pytest.raises(codec.CodecError, match=r"rpm\[2\] is nan"):
        codec.encode_actuators(ActuatorSample(0.0, (1500,) * 12, (0.0, 0.0, math.nan, 0.0)))


def test_decode_refuses_the_wrong_message():
    with pytest.raises(codec.CodecError, match="HEARTBEAT is not an IMU message"):
        codec.decode_imu(codec.heartbeat())


def test_codec_ignores_pymavlink_environment_dialect():
    # mavutil picks its dialect and version from MAVLINK_DIALECT / MAVLINK20; the codec must not.
    code = (
        "from onboard import mavlink_codec as c\n"
        "from onboard.sensors import ImuSample\n"
        "b = c.encode(c.make_mavlink(), c.encode_imu(ImuSample(0.0, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0))))\n"
        "print(b[0], b[7] | b[8] << 8 | b[9] << 16)\n"
    )
    env = dict(os.environ, MAVLINK_DIALECT="minimal")
    env.pop("MAVLINK20", None)
    out = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["253", "105"]  # MAVLink 2 start byte, HIGHRES_IMU id
