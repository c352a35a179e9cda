"""Fault injection in the HIL (issue #7 part 1): the joint-angle codec, the link, actuator and
sensor faults, their marks in the recording, the `jetloop hil` flags, and the closed loop."""

from __future__ import annotations

import math

import numpy as np
import pytest

from onboard import mavlink_codec as codec


def wire(*msgs):
    """Pack with one MAVLink object, parse with another: what a receiver gets."""
    tx, rx = codec.make_mavlink(), codec.make_mavlink(255, 190)
    out = codec.parse(rx, b"".join(codec.encode(tx, m) for m in msgs))
    assert len(out) == len(msgs)
    return out


# --- joint angle feedback codec ----------------------------------------------------------------

def test_joint_angles_round_trip_float32_exact():
    # values exactly representable in float32, so the wire returns them unchanged
    alpha = (0.5, -0.25, 1.5, -3.0)
    beta = (0.125, 0.0, -0.75, 0.0625)
    (m,) = wire(codec.encode_joint_angles(2.5, alpha, beta))
    assert m.get_type() == "ACTUATOR_OUTPUT_STATUS"
    assert m.time_usec == 2_500_000
    assert m.active == 0b1111_1111  # 2 x 4 joints
    assert list(m.actuator[:8]) == list(alpha + beta)
    assert list(m.actuator[8:]) == [0.0] * 24
    assert codec.decode_joint_angles(m, 4) == (2.5, alpha, beta)


def test_joint_angles_float32_rounding_of_arbitrary_values():
    alpha, beta = (0.1, 0.2), (-0.3, 0.4)
    (m,) = wire(codec.encode_joint_angles(0.01, alpha, beta))
    t, a, b = codec.decode_joint_angles(m, 2)
    assert t == 0.01 and m.active == 0b1111
    for got, want in zip(a + b, alpha + beta):
        assert abs(got - want) <= float(np.spacing(np.float32(abs(want)))) / 2  # half a float32 step


def test_joint_angles_refuse_nan_wrong_message_and_missing_joints():
    with pytest.raises(codec.CodecError, match=r"alpha\[1\].*finite"):
        codec.encode_joint_angles(1.0, (0.0, math.nan), (0.0, 0.0))
    with pytest.raises(codec.CodecError, match="2 azimuths but 3 elevations"):
        codec.encode_joint_angles(1.0, (0.0, 0.0), (0.0, 0.0, 0.0))
    with pytest.raises(codec.CodecError, match="carries 32 values"):
        codec.encode_joint_angles(1.0, (0.0,) * 17, (0.0,) * 17)
    m = codec.encode_joint_angles(1.0, (0.0, 0.0), (0.0, 0.0))
    m.actuator[3] = math.inf
    with pytest.raises(codec.CodecError, match=r"actuator\[3\]"):
        codec.decode_joint_angles(m, 2)
    with pytest.raises(codec.CodecError, match="lacks joints of 3 units"):
        codec.decode_joint_angles(codec.encode_joint_angles(1.0, (0.0,) * 2, (0.0,) * 2), 3)
    with pytest.raises(codec.CodecError, match="not ACTUATOR_OUTPUT_STATUS"):
        codec.decode_joint_angles(codec.heartbeat(), 4)
