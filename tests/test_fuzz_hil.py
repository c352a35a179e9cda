"""Fuzzing the HIL side's inputs (issue 7 part 2): the actuator commands HilEndpoint takes from the
controller (HIL_ACTUATOR_CONTROLS, SERVO_OUTPUT_RAW with hostile values, through a real Link), and
the binary servo frames of ArduPilot's SITL JSON interface (hil/json_sitl.py: random bytes, wrong
magic, short and long frames, any frame rate and frame count, any PWM).

Properties: nothing raises; the plant's command stays finite and inside the vehicle's limits; a
command that cannot be used is counted (stats.bad_commands, stale_replies; backend.bad_packets)
and every reply SITL gets is a JSON frame of finite numbers.
"""

from __future__ import annotations

import json
import math
from datetime import timedelta

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from hil.endpoint import HilEndpoint
from hil.json_sitl import HEADER, MAGIC_16, MAGIC_32, PACKET_16, PACKET_32, JsonSitlBackend
from hil.plant import Plant
from onboard.link import Link
from test_fuzz_messages import HOSTILE_FLOATS, hostile, pack

FUZZ = settings(max_examples=80, deadline=timedelta(seconds=30),
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])


def _within_limits(command, vehicle) -> None:
    c = np.asarray(command, dtype=float)
    k = vehicle.n_units
    assert np.all(np.isfinite(c))
    assert np.all(c[:k] >= -1e-9) and np.all(c[:k] <= vehicle.thruster.n_max + 1e-9)
    assert np.all(np.abs(c[k:]) <= vehicle.servo.angle_limit + 1e-9)


@pytest.fixture(scope="module")
def endpoints(vehicle):
    links = {}
    for mode in ("hil", "pwm"):
        links[mode] = Link("udpin:127.0.0.1:0")
    made = {mode: HilEndpoint(vehicle, links[mode], Plant(vehicle, dt_s=0.001, seed=0, noise=False),
                              actuators=mode, history=False) for mode in links}
    yield made
    for lk in links.values():
        lk.close()


def _through_link(msgs) -> list:
    with Link("udpin:127.0.0.1:0") as lk:
        lk.feed(b"".join(pack(m, seq=i) for i, m in enumerate(msgs)), datagram=True)
        return [lk._ready.popleft() for _ in range(len(lk._ready))]


@FUZZ
@given(msgs=st.lists(st.one_of(hostile("HIL_ACTUATOR_CONTROLS"), hostile("SERVO_OUTPUT_RAW")), min_size=1, max_size=8),
       mode=st.sampled_from(["hil", "pwm"]), t=st.floats(0, 1e5))
@example(msgs=[mavlink.MAVLink_hil_actuator_controls_message(2 ** 64 - 1, [math.nan] * 16, 0, 0)], mode="hil", t=0.0)
@example(msgs=[mavlink.MAVLink_servo_output_raw_message(2 ** 32 - 1, 255, *([65535] * 8))], mode="pwm", t=0.0)
def test_endpoint_takes_any_actuator_command(endpoints, vehicle, msgs, mode, t):
    ep = endpoints[mode]
    before = (ep.stats.commands_applied, ep.stats.bad_commands, ep.stats.stale_replies)
    received = _through_link(msgs)
    assert len(received) == len(msgs)
    for m in received:
        ep._handle(m, t, record=False)
    _within_limits(ep.plant.command, vehicle)
    wanted = sum(m.get_type() == ("HIL_ACTUATOR_CONTROLS" if mode == "hil" else "SERVO_OUTPUT_RAW") for m in received)
    after = (ep.stats.commands_applied, ep.stats.bad_commands, ep.stats.stale_replies)
    assert sum(a - b for a, b in zip(after, before)) == wanted  # each one applied, or counted as refused


@FUZZ
@given(controls=st.lists(st.sampled_from(HOSTILE_FLOATS), min_size=16, max_size=16))
def test_non_finite_controls_are_counted_never_applied(endpoints, vehicle, controls):
    ep = endpoints["hil"]
    k = vehicle.n_units
    bad = not all(math.isfinite(c) for c in controls[:3 * k])
    before_cmd = np.array(ep.plant.command, dtype=float)
    before_bad = ep.stats.bad_commands
    ep._answered_us = 0  # not stale
    (m,) = _through_link([mavlink.MAVLink_hil_actuator_controls_message(1, controls, 0, 0)])
    ep._handle(m, 0.0, record=False)
    assert ep.stats.bad_commands - before_bad == int(bad)
    if bad:
        assert np.array_equal(np.array(ep.plant.command, dtype=float), before_cmd)
    _within_limits(ep.plant.command, vehicle)


# -- SITL JSON backend ------------------------------------------------------------------------------

def _check_reply(reply) -> None:
    assert reply.startswith(b"\n") and reply.endswith(b"\n")
    frame = json.loads(reply)
    values = [frame["timestamp"], *frame["imu"]["gyro"], *frame["imu"]["accel_body"], *frame["position"],
              *frame["velocity"], *frame["attitude"], *frame["quaternion"]]
    assert all(math.isfinite(v) for v in values)


@pytest.fixture(scope="module")
def backend(vehicle):
    return JsonSitlBackend(vehicle)


FRAME = st.one_of(
    st.binary(max_size=100),  # anything
    st.tuples(st.sampled_from([MAGIC_16, MAGIC_32, 0, 18459, 0xFFFF]), st.integers(0, 0xFFFF),
              st.integers(0, 2 ** 32 - 1), st.binary(max_size=70)).map(lambda h: HEADER.pack(*h[:3]) + h[3]),
    st.tuples(st.integers(0, 0xFFFF), st.integers(0, 2 ** 32 - 1),
              st.lists(st.integers(0, 0xFFFF), min_size=16, max_size=16)).map(lambda p: PACKET_16.pack(MAGIC_16, *p[:2], *p[2])),
    st.tuples(st.integers(0, 0xFFFF), st.integers(0, 2 ** 32 - 1),
              st.lists(st.integers(0, 0xFFFF), min_size=32, max_size=32)).map(lambda p: PACKET_32.pack(MAGIC_32, *p[:2], *p[2])),
)


@settings(max_examples=40, deadline=timedelta(seconds=30),
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(frames=st.lists(FRAME, min_size=1, max_size=6))
@example(frames=[PACKET_16.pack(MAGIC_16, 400, 0, *([1500] * 16)), PACKET_16.pack(MAGIC_16, 400, 2 ** 32 - 1, *([65535] * 16))])
@example(frames=[PACKET_16.pack(MAGIC_16, 1, 5, *([0] * 16)), PACKET_16.pack(MAGIC_16, 65535, 6, *([1] * 16))])
def test_sitl_backend_takes_any_frame(backend, frames):
    for data in frames:
        before = backend.bad_packets
        reply = backend.handle(data)
        if reply is None:
            assert backend.bad_packets == before + 1  # every refusal counted
        else:
            _check_reply(reply)
            assert np.all(np.isfinite(backend.plant.state))
