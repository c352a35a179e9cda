"""Fuzzing the onboard loop's MAVLink input (issue 7 part 2) through a real UDP onboard.link.Link.

Every message type OnboardLoop.handle reads is sent with hostile field values (NaN, inf, 3.4e38,
integer extremes, any frame, any type_mask, any target system) from the autopilot's system and from
the ground's, between well-formed sensor samples, while the loop polls in lock-step. Properties:
- nothing raises out of poll(); no example takes more than its deadline (no hang);
- the command sent stays finite and inside the vehicle's limits (0 <= n <= n_max, |angle| <= limit);
- a sensor sample with a non-finite value in a field the codec reads is counted
  (stats.rejected_inputs, or ignored_imu for a lower-ranked IMU), and never reaches the estimator;
- the loop goes on: well-formed samples after the hostile ones still make it step.
"""

from __future__ import annotations

import math
from datetime import timedelta

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from onboard import mavlink_codec as codec
from onboard.link import Link
from onboard.loop import IMU_RANK, LoopConfig, OnboardLoop, VehicleClock, arm_command
from onboard.sensors import AttitudeSample, ImuSample, PressureSample
from test_fuzz_messages import hostile, hostile_any

SENSORS = ("HIGHRES_IMU", "SCALED_IMU", "SCALED_IMU2", "SCALED_IMU3", "RAW_IMU", "SCALED_PRESSURE2",
           "SCALED_PRESSURE", "ATTITUDE", "SYSTEM_TIME", "ESC_TELEMETRY_1_TO_4", "ACTUATOR_OUTPUT_STATUS")
GROUND = ("SET_POSITION_TARGET_LOCAL_NED", "MANUAL_CONTROL", "COMMAND_LONG", "HEARTBEAT")
READ_FLOATS = {  # fields the codec decodes: a non-finite one must be refused
    "HIGHRES_IMU": ("xacc", "yacc", "zacc", "xgyro", "ygyro", "zgyro"),
    "SCALED_PRESSURE2": ("press_abs",),  # (SCALED_PRESSURE is passed over unread once SCALED_PRESSURE2 came)
    "ATTITUDE": ("roll", "pitch", "yaw", "rollspeed", "pitchspeed", "yawspeed"),
}
FUZZ = settings(max_examples=15, deadline=timedelta(seconds=60),  # a hang, not a loaded machine
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


def _good(t: float) -> list:
    """A well-formed frame of sensor messages at vehicle time t, then its SYSTEM_TIME marker."""
    wobble = 1e-3 * math.sin(100.0 * t)  # never exactly repeated: 10 identical samples are a frozen IMU
    return [codec.encode_imu(ImuSample(t, (wobble, 0.0, -9.80665), (0.0, wobble, 0.0))),
            codec.encode_pressure(PressureSample(t, 101325.0 + 1025 * 9.80665 * 0.5, 20.0)),
            codec.encode_attitude(AttitudeSample(t, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)),
            mavlink.MAVLink_system_time_message(0, codec.time_boot_ms(t))]


class Rig:
    """An onboard loop on a real udpin link, an autopilot (system 1) and a ground (255) sending to it
    through the autopilot's socket (the link's one peer, as a router forwards a ground's packets)."""

    def __init__(self, vehicle, key: bytes | None = None):
        self.link = Link("udpin:127.0.0.1:0")
        self.ground_link = Link("udpin:127.0.0.1:0")  # the robot's --ground link, a station behind it
        self.loop = OnboardLoop(vehicle, self.link, VehicleClock(block_s=0.005), LoopConfig(signing_key=key),
                                ground=self.ground_link)
        port = self.link.local_address[1]
        self.autopilot = Link(f"udpout:127.0.0.1:{port}", source_system=1, source_component=1)
        self.ground = Link(f"udpout:127.0.0.1:{port}", source_system=255, source_component=190)
        self.station = Link(f"udpout:127.0.0.1:{self.ground_link.local_address[1]}", 255, 190)
        if key is not None:  # the autopilot and the ground sign, as they must for a robot with a key
            from onboard.signing import enable_signing

            for lk in (self.autopilot, self.ground, self.station):
                enable_signing(lk.mav, key)

    def send(self, msgs, sender=None) -> None:
        sender = sender or self.autopilot
        data = b"".join(sender.pack(m) for m in msgs)  # one datagram, from the peer's socket
        self.autopilot.write_raw(data)

    def pump(self, polls: int = 60) -> None:
        """poll() until two polls in a row read nothing (a poll that steps reads nothing itself;
        bounded: a hang shows as the example's deadline)."""
        quiet = 0
        for _ in range(polls):
            before = self.link.bytes_in + self.ground_link.bytes_in + self.loop.link_foreign()
            self.loop.poll()
            idle = (self.link.bytes_in + self.ground_link.bytes_in + self.loop.link_foreign() == before
                    and not self.loop._tick_due() and not self.link._ready and not self.ground_link._ready)
            quiet = quiet + 1 if idle else 0
            if quiet >= 2:
                break

    def close(self) -> None:
        for lk in (self.link, self.ground_link, self.autopilot, self.ground, self.station):
            lk.close()


@pytest.fixture(scope="module")
def rigs(vehicle):
    """rigs(key=None) -> a fresh Rig (the previous one is closed: one example, one loop)."""
    made = []

    def make(key=None):
        while made:
            made.pop().close()
        made.append(Rig(vehicle, key))
        return made[-1]
    yield make
    while made:
        made.pop().close()


def _check_command(loop, vehicle) -> None:
    c = np.asarray(loop.command, dtype=float)
    k = vehicle.n_units
    assert np.all(np.isfinite(c))
    assert np.all(c[:k] >= -1e-9) and np.all(c[:k] <= vehicle.thruster.n_max + 1e-9)
    assert np.all(np.abs(c[k:]) <= vehicle.servo.angle_limit + 1e-9)


def _armed_rig(rigs, key=None):
    rig = rigs(key)
    rig.send(_good(0.01))
    rig.pump()
    rig.send([arm_command(True)], rig.ground)
    for i in range(2, 8):
        rig.send(_good(0.01 * i))
        rig.pump()
    assert rig.loop.armed  # the ground's command reached the loop: the hostile ones below do too
    return rig


def _fly(rig, msgs, from_ground: bool, t0: float = 0.08) -> None:
    rig.send(msgs, rig.ground if from_ground else rig.autopilot)
    rig.pump()
    for i in range(1, 6):  # well-formed samples after the hostile ones
        rig.send(_good(t0 + 0.01 * i))
        rig.pump()


@FUZZ
@given(msgs=st.lists(hostile_any(SENSORS), min_size=1, max_size=6))
@example(msgs=[mavlink.MAVLink_highres_imu_message(2 ** 64 - 1, 0, 0, -9.8, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0)])
@example(msgs=[mavlink.MAVLink_raw_imu_message(2 ** 64 - 1, 0, 0, -1000, 0, 0, 0, 0, 0, 0, 0, 0)])
@example(msgs=[mavlink.MAVLink_system_time_message(0, 2 ** 32 - 1)])
def test_hostile_sensor_messages_never_stop_the_loop(rigs, vehicle, msgs):
    """Regression examples: a time_usec near 2^64 hung the loop (prediction across 1e13 s) and
    then broke its output packing; a SYSTEM_TIME at the end of time_boot_ms's range."""
    rig = _armed_rig(rigs)
    steps = rig.loop.stats.steps
    _fly(rig, msgs, from_ground=False)
    _check_command(rig.loop, vehicle)
    assert rig.loop.stats.steps > steps or rig.loop.clock.now() > 0.13  # it stepped, or time ran ahead


@FUZZ
@given(msgs=st.lists(hostile_any(GROUND), min_size=1, max_size=6), ground=st.booleans())
def test_hostile_ground_messages_never_stop_the_loop(rigs, vehicle, msgs, ground):
    """Setpoints with any frame, type_mask, NaN or 3.4e38, commands with any id and parameters, for
    this vehicle or another, from the ground's system or the autopilot's."""
    rig = _armed_rig(rigs)
    steps = rig.loop.stats.steps
    _fly(rig, msgs, from_ground=ground)
    _check_command(rig.loop, vehicle)
    assert rig.loop.stats.steps > steps


@FUZZ
@given(data=st.data(), name=st.sampled_from(sorted(READ_FLOATS)))
def test_a_non_finite_reading_is_counted_and_never_fused(rigs, data, name):
    msg = data.draw(hostile(name))
    field = data.draw(st.sampled_from(READ_FLOATS[name]))
    setattr(msg, field, data.draw(st.sampled_from([math.nan, math.inf, -math.inf])))
    rig = _armed_rig(rigs)
    loop = rig.loop
    before = loop.stats.rejected_inputs + loop.stats.ignored_imu
    rejected_by_estimator = loop.estimator.health.rejected_total
    rig.send([msg])
    rig.pump()
    counted = loop.stats.rejected_inputs + loop.stats.ignored_imu - before
    assert counted == 1, (name, field, msg)
    rig.send(_good(0.09))
    rig.pump()
    assert np.all(np.isfinite(loop.estimator.estimate.nu))
    assert loop.estimator.health.rejected_total == rejected_by_estimator  # refused before the filter
    assert name not in IMU_RANK or loop._last_imu_stamp <= 0.09 + 1e-9


@settings(max_examples=5, deadline=timedelta(seconds=30), suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 2 ** 32 - 1))
def test_garbage_between_frames_is_counted_and_the_loop_flies_on(rigs, vehicle, seed):
    """Random datagrams between well-formed frames: counted in the link's stats and in the loop's
    telemetry counter (link_bad = bad + unknown packets), and the loop keeps stepping."""
    rig = _armed_rig(rigs)
    rng = np.random.default_rng(seed)
    steps = rig.loop.stats.steps
    sock = rig.autopilot._io.sock
    sent = 0
    for i in range(8, 20):
        junk = rng.integers(0, 256, int(rng.integers(1, 1500)), dtype=np.uint8).tobytes()
        sock.sendto(junk, rig.link.local_address)
        sent += len(junk)
        rig.send(_good(0.01 * i))
        rig.pump()
    _check_command(rig.loop, vehicle)
    s = rig.link.stats()
    assert rig.loop.stats.steps >= steps + 8
    assert s["garbage_bytes"] >= 0.9 * sent  # a random packet with a good CRC is ~1 in 65536 per marker


# -- hostile peers (issue 15): a second sender on udpin, a foreign system sending sensor data ------------

def _counts(loop) -> tuple:
    st = loop.stats
    return (st.rejected_inputs, st.ignored_imu, st.stamps_held, st.security.summary())


@FUZZ
@given(datagrams=st.lists(st.one_of(st.binary(min_size=1, max_size=600),
                                    st.tuples(hostile_any(SENSORS + GROUND), st.integers(0, 255))),
                          min_size=1, max_size=6))
def test_a_second_sender_on_udpin_is_never_read_nor_answered(rigs, vehicle, datagrams):
    """Another socket sends junk or any MAVLink (as any system) to the robot's udpin link while
    the autopilot flies it: every datagram is dropped unread and counted, nothing the robot
    sends reaches the intruder, and nothing the loop counts or flies changes."""
    import socket

    rig = _armed_rig(rigs)
    before = _counts(rig.loop)
    steps = rig.loop.stats.steps
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as intruder:
        intruder.bind(("127.0.0.1", 0))
        intruder.setblocking(False)
        for d in datagrams:
            if isinstance(d, tuple):
                msg, sysid = d
                d = bytes(msg.pack(mavlink.MAVLink(None, sysid, 1)))
            intruder.sendto(d, rig.link.local_address)
        _fly(rig, [], from_ground=False)
        try:
            answered = intruder.recv(65535)
        except BlockingIOError:
            answered = None
    assert answered is None, "the robot answered the intruder"
    assert rig.link.foreign_datagrams == len(datagrams)
    assert _counts(rig.loop) == before
    assert rig.loop.stats.steps >= steps + 5 and rig.loop.armed and not rig.loop.failsafe_active
    _check_command(rig.loop, vehicle)


@FUZZ
@given(msgs=st.lists(hostile_any(SENSORS), min_size=1, max_size=6), sysid=st.integers(2, 254),
       on_ground_link=st.booleans())
def test_a_foreign_system_sending_sensor_data_changes_nothing(rigs, vehicle, msgs, sysid, on_ground_link):
    """Any sensor or actuator-feedback message, with any values and stamps, from a system that is
    not the autopilot (through the autopilot's own socket), or from anyone on the ground link:
    refused and counted one by one; the clock, the IMU ordering and the failsafe are untouched."""
    rig = _armed_rig(rigs)
    loop = rig.loop
    t_before, imu_before = loop.clock.now(), loop._last_imu_stamp
    refused = loop.stats.security.sensors_refused
    mav = mavlink.MAVLink(None, sysid, 1)
    data = b"".join(bytes(m.pack(mav)) for m in msgs)
    (rig.station if on_ground_link else rig.autopilot).write_raw(data)
    rig.pump()
    assert loop.stats.security.sensors_refused == refused + len(msgs)
    assert (loop.clock.now(), loop._last_imu_stamp) == (t_before, imu_before)
    ignored = loop.stats.ignored_imu
    _fly(rig, [], from_ground=False)
    assert loop.stats.ignored_imu == ignored and not loop.failsafe_active and loop.armed
    _check_command(loop, vehicle)


KEY = bytes(range(32))


@FUZZ
@given(msgs=st.lists(hostile_any(SENSORS + GROUND), min_size=1, max_size=6), sysid=st.sampled_from([1, 255, 42]),
       on_ground_link=st.booleans())
def test_with_a_key_no_unsigned_message_changes_anything(rigs, vehicle, msgs, sysid, on_ground_link):
    """With signing on, any sensor, feedback, setpoint or command message, unsigned, from the
    autopilot's or the ground's ids or another's, on either link: each is counted as unsigned and
    none changes the time, the IMU ordering, the setpoint, the mode or the arming."""
    rig = _armed_rig(rigs, KEY)
    loop = rig.loop
    state = lambda: (loop.clock.now(), loop._last_imu_stamp, loop.setpoint, loop.mode, loop.armed)  # noqa: E731
    before, unsigned = state(), loop.stats.security.unsigned
    mav = mavlink.MAVLink(None, sysid, 1)
    (rig.station if on_ground_link else rig.autopilot).write_raw(b"".join(bytes(m.pack(mav)) for m in msgs))
    rig.pump()
    assert loop.stats.security.unsigned == unsigned + len(msgs)
    assert state() == before
    _fly(rig, [], from_ground=False)
    assert not loop.failsafe_active and loop.armed
    _check_command(loop, vehicle)
