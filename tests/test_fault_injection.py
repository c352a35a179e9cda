"""Fault injection in the HIL (issue #7 part 1): the joint-angle codec, the link, actuator and
sensor faults, their marks in the recording, the `jetloop hil` flags, and the closed loop."""

from __future__ import annotations

import math
import time

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


# --- the plan and the pure fault functions ----------------------------------------------------------

from hil.faults import (  # noqa: E402
    DepthJump,
    FaultPlan,
    FaultPlanError,
    FaultyLink,
    JetFault,
    StuckJoint,
    actuator_command,
    imu_fault,
    injection_events,
    link_fate,
    pressure_offset_pa,
    read_injections,
)
from onboard.vehicle import load_vehicle  # noqa: E402

V = load_vehicle()
K = V.n_units


def test_the_older_faults_name_is_the_plan():
    from hil.endpoint import Faults

    f = Faults(imu_dropouts_s=((1.0, 2.0),), garbage_times_s=(1.5,), garbage_bytes=10)
    assert isinstance(f, FaultPlan) and not f.link_faults and not f.empty
    assert FaultPlan().empty


@pytest.mark.parametrize("kwargs, match", [
    (dict(loss=0.31), r"FaultPlan.loss must be a fraction 0..0.3"),
    (dict(duplicate=-0.1), r"FaultPlan.duplicate must be a fraction"),
    (dict(delay_s=math.inf), r"FaultPlan.delay_s must be a finite time"),
    (dict(loss=0.1, loss_window_s=(5.0, 4.0)), r"loss_window_s must satisfy 0 <= t0 < t1"),
    (dict(imu_nan_s=((1.0,),)), r"imu_nan_s\[0\] must be a window"),
    (dict(jets=(JetFault(1, 1.0, 0.0),)), r"jets\[0\].*0 <= efficiency < 1"),
    (dict(stuck_joints=(StuckJoint(1, "roll", 0.0),)), r"stuck_joints\[0\].*'azimuth' or 'elevation'"),
    (dict(depth_jumps=(DepthJump(1.0, math.nan),)), r"depth_jumps\[0\].*finite offset"),
])
def test_a_bad_plan_is_refused_with_the_field_named(kwargs, match):
    with pytest.raises(FaultPlanError, match=match):
        FaultPlan(**kwargs)


def test_a_unit_the_vehicle_lacks_is_refused():
    with pytest.raises(FaultPlanError, match=r"jets\[0\].unit must be 1..4"):
        FaultPlan(jets=(JetFault(5, 0.0, 1.0),)).check_units(K)
    with pytest.raises(FaultPlanError, match=r"stuck_joints\[0\].unit must be 1..4"):
        FaultPlan(stuck_joints=(StuckJoint(0, "azimuth", 1.0),)).check_units(K)


def test_actuator_command_dead_weak_and_stuck_hand_computed():
    u = np.array([40.0, 50.0, 60.0, 70.0, 0.1, 0.2, 0.3, 0.4, -0.1, -0.2, -0.3, -0.4])
    plan = FaultPlan(jets=(JetFault(2, 0.0, 5.0), JetFault(4, 0.5, 6.0)),
                     stuck_joints=(StuckJoint(3, "elevation", 5.0),))
    assert np.array_equal(actuator_command(plan, u, 4.99, {}), u)  # nothing before t0
    got = actuator_command(plan, u, 5.0, {(3, "elevation"): 0.25})
    want = u.copy()
    want[1] = 0.0  # jet 2 dead
    want[2 * K + 2] = 0.25  # unit 3's elevation held where it was at t0
    assert np.array_equal(got, want)
    got = actuator_command(plan, u, 6.0, {(3, "elevation"): 0.25})
    want[3] = 0.5 * 70.0  # jet 4 weak: half the commanded speed
    assert np.array_equal(got, want)


def test_sensor_faults_in_their_windows():
    plan = FaultPlan(imu_freeze_s=((1.0, 2.0),), imu_nan_s=((1.5, 3.0),),
                     depth_jumps=(DepthJump(4.0, 0.3, 6.0), DepthJump(5.0, -0.1)))
    assert [imu_fault(plan, t) for t in (0.99, 1.0, 1.49, 1.5, 2.99, 3.0)] == [
        None, "freeze", "freeze", "nan", "nan", None]
    rho, g = V.environment.rho, V.environment.g
    assert pressure_offset_pa(plan, 3.99, rho, g) == 0.0
    assert pressure_offset_pa(plan, 4.0, rho, g) == pytest.approx(rho * g * 0.3, rel=1e-12)
    assert pressure_offset_pa(plan, 5.5, rho, g) == pytest.approx(rho * g * 0.2, rel=1e-12)
    assert pressure_offset_pa(plan, 6.0, rho, g) == pytest.approx(rho * g * -0.1, rel=1e-12)


def test_injection_events_say_when_each_fault_begins_and_ends():
    plan = FaultPlan(loss=0.2, loss_window_s=(2.0, 4.0), jets=(JetFault(2, 0.0, 5.0),),
                     imu_freeze_s=((3.0, 3.5),), depth_jumps=(DepthJump(6.0, 0.3),))
    assert injection_events(plan) == [
        (2.0, "INJECT link loss 0.20"), (3.0, "INJECT imu frozen"), (3.5, "INJECT END imu frozen"),
        (4.0, "INJECT END link loss"), (5.0, "INJECT jet 2 dead"), (6.0, "INJECT depth jump +0.300m")]
    assert all(len(text) <= 50 for _, text in injection_events(plan))  # STATUSTEXT.text is 50 chars


def test_link_fate_from_the_draws():
    plan = FaultPlan(loss=0.2, delay_s=0.02, jitter_s=0.01, duplicate=0.1, reorder=0.05,
                     reorder_window_s=(1.0, 2.0))
    assert link_fate(plan, 0.5, (0.19, 0.0, 0.0, 0.0)).lost  # u0 < loss
    f = link_fate(plan, 0.5, (0.2, 0.05, 0.0, 0.5))  # kept; u1 < 0.1: duplicated; outside the reorder window
    assert (f.lost, f.copies, f.reorder) == (False, 2, False)
    assert f.delay_s == pytest.approx(0.02 + 0.5 * 0.01)
    f = link_fate(plan, 1.5, (0.9, 0.1, 0.04, 0.0))
    assert (f.copies, f.reorder, f.delay_s) == (1, True, 0.02)


# --- the faulty link, over real loopback UDP ---------------------------------------------------------

from onboard.link import Link  # noqa: E402
import pymavlink.dialects.v20.ardupilotmega as mavlink2  # noqa: E402


class Clock:
    def __init__(self):
        self.t = 0.0

    def __call__(self):
        return self.t


@pytest.fixture
def pair():
    """(plant side: udpin, controller side: udpout to it), the plant side has heard its peer."""
    a = Link("udpin:127.0.0.1:0")
    b = Link(f"udpout:127.0.0.1:{a.local_address[1]}", source_system=1, source_component=191)
    b.send(codec.heartbeat())
    assert a.recv(2.0) is not None and a.has_peer
    yield a, b
    a.close()
    b.close()


def numbered(i: int):
    return mavlink2.MAVLink_named_value_int_message(0, b"i", i)


def drain(link, first_timeout=0.5, then=0.05):
    out = []
    m = link.recv(first_timeout)
    while m is not None:
        out.append(m)
        m = link.recv(then)
    return out


def send_frames(faulty, clock, n, per_frame=50, period=0.01, msg=numbered):
    for f in range(0, n, per_frame):
        clock.t = (f // per_frame) * period
        with faulty.batch():
            for i in range(f, min(f + per_frame, n)):
                faulty.send(msg(i))


def binomial_bound(p, n):
    return 4.0 * math.sqrt(p * (1 - p) / n)  # 4 sigma: a fixed seed either passes or fails for good


def test_outgoing_loss_fraction_and_what_the_tap_saw(pair):
    a, b = pair
    clock, tapped = Clock(), []
    n, p = 3000, 0.2
    faulty = FaultyLink(a, FaultPlan(loss=p), clock, seed=11, tap=lambda pkt, name: tapped.append(pkt))
    send_frames(faulty, clock, n)
    got = drain(b)
    lost = faulty.out.lost
    assert len(got) == n - lost == len(tapped)
    assert abs(lost / n - p) < binomial_bound(p, n)
    assert [bytes(m.get_msgbuf()) for m in got] == tapped  # the recording holds what crossed
    assert [m.value for m in got] == sorted(set(m.value for m in got))  # in order, no repeats


def test_the_same_seed_loses_the_same_packets(pair):
    a, b = pair
    runs = []
    for _ in range(2):
        clock = Clock()
        faulty = FaultyLink(a, FaultPlan(loss=0.3), clock, seed=5)
        send_frames(faulty, clock, 400)
        runs.append([m.value for m in drain(b)])
    other = FaultyLink(a, FaultPlan(loss=0.3), Clock(), seed=6)
    send_frames(other, Clock(), 400)
    assert runs[0] == runs[1]
    assert [m.value for m in drain(b)] != runs[0]


def test_the_frame_marker_is_never_lost_in_lock_step(pair):
    a, b = pair
    clock = Clock()
    faulty = FaultyLink(a, FaultPlan(loss=0.3, delay_s=0.05, reorder=0.5), clock, seed=1)
    send_frames(faulty, clock, 500, per_frame=10,
                msg=lambda i: mavlink2.MAVLink_system_time_message(0, i))
    assert [m.time_boot_ms for m in drain(b)] == list(range(500))
    assert faulty.out.passed == 0  # no draw was even made for them


def test_delay_holds_a_packet_until_its_frame(pair):
    a, b = pair
    clock = Clock()
    faulty = FaultyLink(a, FaultPlan(delay_s=0.02, delay_window_s=(0.0, 0.05)), clock, seed=0)
    with faulty.batch():
        faulty.send(numbered(1))  # at t = 0: due at 0.02
    for t in (0.01, 0.02):
        clock.t = t
        with faulty.batch():
            pass
        got = drain(b, 0.2)
        assert [m.value for m in got] == ([] if t < 0.02 else [1])
    clock.t = 0.05  # the window has ended: no delay
    with faulty.batch():
        faulty.send(numbered(2))
    assert [m.value for m in drain(b)] == [2]


def test_jitter_spreads_the_delay_uniformly(pair):
    a, b = pair
    clock = Clock()
    faulty = FaultyLink(a, FaultPlan(delay_s=0.02, jitter_s=0.03), clock, seed=3)
    arrival = {}
    for k in range(200):  # one packet per 10 ms frame; read what each frame delivers
        clock.t = k * 0.01
        with faulty.batch():
            if k < 100:
                faulty.send(numbered(k))
        for m in drain(b, 0.005, then=0.0):  # loopback: a datagram is there once sent
            arrival[m.value] = round(clock.t - m.value * 0.01, 6)
    assert sorted(arrival) == list(range(100))
    delays = np.array(list(arrival.values()))
    # frames are 10 ms: a delay of 0.02 + U(0, 0.03) s goes out with the frame at or after it
    assert delays.min() >= 0.02 and delays.max() <= 0.05 + 1e-9
    assert set(np.round(delays, 2)) == {0.03, 0.04, 0.05}  # 0.02 only for u = 0 exactly


def test_duplicates_arrive_twice_as_the_same_packet(pair):
    a, b = pair
    clock = Clock()
    n, p = 2000, 0.1
    faulty = FaultyLink(a, FaultPlan(duplicate=p), clock, seed=2)
    send_frames(faulty, clock, n)
    got = drain(b)
    dups = faulty.out.duplicated
    assert len(got) == n + dups and abs(dups / n - p) < binomial_bound(p, n)
    twice = [x for x, y in zip(got, got[1:]) if x.get_msgbuf() == y.get_msgbuf()]
    assert len(twice) == dups  # byte for byte the same packet, sequence number included


def test_reordered_packets_arrive_after_the_next_one(pair):
    a, b = pair
    clock = Clock()
    n, p = 2000, 0.1
    faulty = FaultyLink(a, FaultPlan(reorder=p, reorder_window_s=(0.0, 10.0)), clock, seed=4)
    send_frames(faulty, clock, n)
    clock.t = 10.0  # past the window: one more packet lets a held one out
    with faulty.batch():
        faulty.send(numbered(n))
    values = [m.value for m in drain(b)]
    assert sorted(values) == list(range(n + 1))  # nothing lost
    swaps = sum(1 for x, y in zip(values, values[1:]) if y < x)
    assert swaps == faulty.out.reordered
    # a packet is held only when none is held already, so slightly fewer than p of them
    assert abs(swaps / n - p * (1 - p)) < binomial_bound(p, n)


def test_incoming_loss_counts_every_arrival(pair):
    a, b = pair
    clock = Clock()
    n, p = 1000, 0.3
    faulty = FaultyLink(a, FaultPlan(loss=p), clock, seed=8)
    got = []
    for f in range(0, n, 50):  # a frame's worth at a time: the socket buffer never overflows
        with b.batch():
            for i in range(f, f + 50):
                b.send(numbered(i))
        deadline = time.monotonic() + 2.0
        while faulty.arrivals < f + 50 and time.monotonic() < deadline:
            m = faulty.recv(0.1)
            if m is not None:
                got.append(m.value)
    assert faulty.arrivals == n and faulty.into.passed == n
    assert len(got) == n - faulty.into.lost
    assert abs(faulty.into.lost / n - p) < binomial_bound(p, n)
    assert faulty.stats()["injected"]["in"]["lost"] == faulty.into.lost


def test_incoming_delay_delivers_at_the_due_vehicle_time(pair):
    a, b = pair
    clock = Clock()
    faulty = FaultyLink(a, FaultPlan(delay_s=0.03), clock, seed=0)
    b.send(numbered(7))
    assert faulty.recv(1.0) is None and faulty.arrivals == 1  # arrived, held
    clock.t = 0.02
    assert faulty.recv(0.05) is None
    clock.t = 0.03
    assert faulty.recv(0.0).value == 7



def test_a_packet_held_for_reordering_follows_a_delayed_one(pair):
    """Found by the hour soak: a packet held back to be overtaken waited for the next packet that
    was NOT delayed, so at the start of a delay window it stayed held for the whole window and
    was never delivered (one unexplained sequence gap). It must follow the packet that overtakes
    it, into the delay too, in both directions."""
    a, b = pair
    clock = Clock()
    plan = FaultPlan(reorder=1.0, reorder_window_s=(0.0, 0.01), delay_s=0.02, delay_window_s=(0.01, 1.0))
    out = FaultyLink(a, plan, clock, seed=0)
    with out.batch():
        out.send(numbered(1))  # t = 0: reordered, held behind the next packet
    clock.t = 0.01
    with out.batch():
        out.send(numbered(2))  # delayed to 0.03, and 1 with it, after it
    assert drain(b, 0.1) == [] and out.stats()["injected"]["held_out"] == 2
    clock.t = 0.03
    with out.batch():
        pass
    assert [m.value for m in drain(b)] == [2, 1]
    assert out.stats()["injected"]["held_out"] == 0

    back = FaultyLink(b, plan, clock := Clock(), seed=0)
    a.send(numbered(1))
    assert back.recv(1.0) is None and back.stats()["injected"]["held_in"] == 1  # held behind
    clock.t = 0.01
    a.send(numbered(2))
    assert back.recv(1.0) is None and back.stats()["injected"]["held_in"] == 2  # both delayed
    clock.t = 0.03
    assert [back.recv(0.0).value, back.recv(0.0).value] == [2, 1]
    assert back.stats()["injected"]["held_in"] == 0

# --- the endpoint with a scripted controller (real sockets, lock-step, no onboard loop) ---------------

import threading  # noqa: E402

from hil.endpoint import HilEndpoint  # noqa: E402
from hil.plant import Plant  # noqa: E402
from hil.tlog import TlogWriter  # noqa: E402
from onboard.pwm import command_to_normalised, command_to_pwm  # noqa: E402

TAU_M = V.thruster.motor_time_constant


def _controller(port, stop, command_at, seen):
    """Answers every new frame marker with HIL_ACTUATOR_CONTROLS of command_at(t); keeps all it got."""
    link = Link(f"udpout:127.0.0.1:{port}", source_system=1, source_component=191)
    link.send(codec.heartbeat(armed=True))
    last = -1
    while not stop.is_set():
        m = link.recv(0.05)
        if m is None:
            continue
        seen.append(m)
        if m.get_type() == "SYSTEM_TIME" and m.time_boot_ms > last:
            last = m.time_boot_ms
            controls = list(command_to_normalised(V, command_at(last / 1e3))) + [0.0] * (16 - 3 * K)
            link.send(mavlink2.MAVLink_hil_actuator_controls_message(last * 1000, controls, 0, 0))
    link.close()


def scripted_flight(plan, duration_s, command_at, tlog_path=None, seed=9):
    """Fly the plant (0.5 m deep) against the scripted controller; returns (endpoint, what the
    controller received, [(t, plant state)] after every period)."""
    link = Link("udpin:127.0.0.1:0", source_system=1, source_component=1)
    stop, seen, states = threading.Event(), [], []
    ctl = threading.Thread(target=_controller, args=(link.local_address[1], stop, command_at, seen))
    ctl.start()
    tlog = TlogWriter(tlog_path) if tlog_path is not None else None
    try:
        ep = HilEndpoint(V, link, Plant(V, seed=seed, depth_m=0.5), faults=plan, tlog=tlog, seed=seed,
                         reply_timeout_s=0.05, give_up_s=5.0,
                         on_period=lambda e: states.append((e.time_s, e.plant.state.copy())))
        ep.run(duration_s)
    finally:
        stop.set()
        ctl.join()
        if tlog is not None:
            tlog.close()
        link.close()
    return ep, seen, states


def state_at(states, t):
    return next(x for ts, x in states if abs(ts - t) < 1e-9)


LAY = Plant(V).layout
N_CMD = 60.0


def test_dead_and_weak_jets_show_in_the_propellers_and_the_esc_rpm_not_in_the_servo_output():
    plan = FaultPlan(jets=(JetFault(2, 0.0, 0.3), JetFault(4, 0.5, 0.3)))
    cmd = np.array([N_CMD] * K + [0.0] * 2 * K)
    ep, seen, states = scripted_flight(plan, 1.0, lambda t: cmd)
    # spec 4 motor lag n' = (e n_cmd - n) / tau_m from n(0) = 0; the command of frame t acts from t
    # to t + 0.01, and the state recorded after frame t is at t (the plant advances at the next step)
    def n_hat(t, e):
        n03 = N_CMD * (1 - math.exp(-0.3 / TAU_M))
        return e * N_CMD + (n03 - e * N_CMD) * math.exp(-(t - 0.3) / TAU_M)

    n = state_at(states, 0.9)[LAY.n]
    assert n[0] == pytest.approx(N_CMD * (1 - math.exp(-0.9 / TAU_M)), rel=1e-4)
    assert n[1] == pytest.approx(n_hat(0.9, 0.0), abs=1e-3)  # dead: 0.03 rev/s left of 58.6
    assert n[3] == pytest.approx(n_hat(0.9, 0.5), rel=1e-4)
    esc = [m for m in seen if m.get_type() == "ESC_TELEMETRY_1_TO_4"]
    servo = [m for m in seen if m.get_type() == "SERVO_OUTPUT_RAW"]
    rpm = list(esc[-1].rpm)  # the last frame, t = 0.99
    assert rpm[1] == round(60 * n_hat(0.99, 0.0)) <= 1  # rpm, rounded to the uint16 field
    assert rpm[0] == round(60 * N_CMD * (1 - math.exp(-0.99 / TAU_M)))
    assert rpm[3] == round(60 * n_hat(0.99, 0.5))
    pwm = command_to_pwm(V, cmd)
    assert [servo[-1].servo1_raw, servo[-1].servo2_raw, servo[-1].servo4_raw] == [pwm[0], pwm[1], pwm[3]]


def test_a_stuck_joint_stays_at_its_angle_at_onset_and_the_feedback_says_so():
    plan = FaultPlan(stuck_joints=(StuckJoint(1, "azimuth", 0.3),))

    def command_at(t):
        az = 0.2 if t < 0.5 else -0.3
        return np.array([0.0] * K + [az] * K + [0.0] * K)

    ep, seen, states = scripted_flight(plan, 1.0, command_at)
    a_onset = state_at(states, 0.3)[LAY.alpha][0]
    assert a_onset == pytest.approx(0.2, abs=1e-3)  # 10 servo time constants after the step
    x = state_at(states, 0.99)
    assert x[LAY.alpha][0] == pytest.approx(a_onset, abs=1e-12)  # stuck
    assert x[LAY.alpha][1] == pytest.approx(-0.3, abs=1e-3)  # the others follow the command
    fb = [m for m in seen if m.get_type() == "ACTUATOR_OUTPUT_STATUS"]
    assert len(fb) == round(1.0 * V.sensors.attitude_rate)  # at the attitude rate
    t, alpha, beta = codec.decode_joint_angles(fb[-1], K)
    assert alpha[0] == pytest.approx(a_onset, abs=1e-6) and alpha[1] == pytest.approx(-0.3, abs=1e-3)
    assert t == pytest.approx(1.0 - 1.0 / V.sensors.attitude_rate)


def test_imu_freeze_and_nan_windows_in_the_sent_messages():
    plan = FaultPlan(imu_freeze_s=((0.2, 0.4),), imu_nan_s=((0.6, 0.7),))
    ep, seen, _ = scripted_flight(plan, 0.9, lambda t: np.zeros(3 * K))
    imu = [m for m in seen if m.get_type() == "HIGHRES_IMU"]
    t = np.array([m.time_usec / 1e6 for m in imu])
    v = np.array([[m.xacc, m.yacc, m.zacc, m.xgyro, m.ygyro, m.zgyro] for m in imu])
    assert np.all(np.diff(t) > 0)  # fresh time stamps throughout
    frozen = (t >= 0.2 - 1e-9) & (t < 0.4 - 1e-9)
    before = np.nonzero(t < 0.2 - 1e-9)[0][-1]
    assert frozen.sum() == round(0.2 * V.sensors.imu_rate)
    assert np.all(v[frozen] == v[before])  # the very values of the last sample before the freeze
    nan = (t >= 0.6 - 1e-9) & (t < 0.7 - 1e-9)
    assert nan.sum() == round(0.1 * V.sensors.imu_rate) and np.all(np.isnan(v[nan]))
    rest = ~frozen & ~nan
    assert np.all(np.isfinite(v[rest])) and len(np.unique(v[rest][:, 3])) == rest.sum()  # noise never repeats


def test_depth_jump_is_a_pressure_step_of_rho_g_offset():
    plan = FaultPlan(depth_jumps=(DepthJump(0.3, 0.3, 0.6),))
    zero = np.zeros(3 * K)
    _, seen, _ = scripted_flight(plan, 0.9, lambda t: zero)
    _, clean, _ = scripted_flight(FaultPlan(), 0.9, lambda t: zero)

    def pressure(msgs):
        return {m.time_boot_ms: m.press_abs for m in msgs if m.get_type() == "SCALED_PRESSURE2"}

    p, p0 = pressure(seen), pressure(clean)
    assert p.keys() == p0.keys()
    step_hpa = V.environment.rho * V.environment.g * 0.3 / 100.0  # p = p_atm + rho g d, in hPa
    f32 = float(np.spacing(np.float32(1100.0)))  # press_abs is float32: one step near 1000 hPa
    for ms in p:
        want = step_hpa if 300 <= ms < 600 else 0.0
        assert abs((p[ms] - p0[ms]) - want) <= 2 * f32, ms


def _tlog_packets(path):
    """(src (system, component), message type, packet bytes) of every packet in a .tlog, via pymavlink."""
    from pymavlink import mavutil

    conn = mavutil.mavlink_connection(str(path), dialect="ardupilotmega")
    out = []
    while (m := conn.recv_match()) is not None:
        if m.get_type() != "BAD_DATA":
            out.append(((m.get_srcSystem(), m.get_srcComponent()), m.get_type(), bytes(m.get_msgbuf()),
                         getattr(m, "_timestamp", None), m))
    conn.close()
    return out


def test_lock_step_with_link_faults_costs_no_wall_time_and_records_what_crossed(tmp_path):
    plan = FaultPlan(loss=0.3, loss_window_s=(0.2, 0.8), duplicate=0.1, reorder=0.1, delay_s=0.01,
                     jitter_s=0.02, delay_window_s=(0.5, 1.0), jets=(JetFault(2, 0.0, 0.5),),
                     imu_freeze_s=((0.3, 0.4),))
    path = tmp_path / "hil.tlog"
    t0 = time.monotonic()
    ep, seen, _ = scripted_flight(plan, 1.0, lambda t: np.zeros(3 * K), tlog_path=path)
    wall = time.monotonic() - t0
    assert ep.stats.periods == 100 and ep.stats.resends == 0  # no reply timeout, however much was lost
    assert wall < 5.0
    inj = ep.link.stats()["injected"]
    assert inj["out"]["lost"] > 0 and inj["in"]["lost"] > 0 and inj["out"]["duplicated"] > 0
    assert inj["out"]["delayed"] > 0 and inj["out"]["reordered"] > 0

    packets = _tlog_packets(path)
    # the outgoing side of the recording is exactly what reached the controller, in order (mocap
    # truth and the injector's marks are never sent)
    sent = [p[2] for p in packets if p[0] == (1, 1) and p[1] != "ATT_POS_MOCAP"]
    assert sent == [bytes(m.get_msgbuf()) for m in seen]
    # the incoming side: the commands delivered, never the lost ones
    cmds = [p for p in packets if p[1] == "HIL_ACTUATOR_CONTROLS"]
    assert len(cmds) == ep.stats.received["HIL_ACTUATOR_CONTROLS"] < 100 + inj["in"]["duplicated"]
    assert sum(p[1] == "SYSTEM_TIME" for p in packets) == 100  # the frame marker is never lost

    marks = [(round(p[3] - 1_767_225_600, 6), p[4].text) for p in packets if p[0] == (1, 250)]
    want = [(0.0, "INJECT link duplicate 0.10"), (0.0, "INJECT link reorder 0.10"),
            (0.2, "INJECT link loss 0.30"), (0.3, "INJECT imu frozen"), (0.4, "INJECT END imu frozen"),
            (0.5, "INJECT link delay 0.010s jitter 0.020s"), (0.5, "INJECT jet 2 dead"),
            (0.8, "INJECT END link loss")]  # the delay's end (1.0 s) is after the last frame (0.99 s)
    assert marks == want  # as pymavlink reads them (log time = epoch + vehicle time)
    assert [(round(t, 6), text) for t, text in read_injections(path)] == want  # as ground.recording scans them
    assert [p[1] for p in packets if p[0] == (1, 250)] == ["STATUSTEXT"] * len(want)

    from ground.recording import read_recording

    rec = read_recording(path)  # the marks do not disturb the diagnosis' reader
    assert rec.vehicle_id == (1, 1) and rec.skipped.skipped_bytes == 0 and rec.skipped.bad_crc_packets == 0
    assert "STATUSTEXT" not in rec.messages  # they are not the vehicle's

    again = tmp_path / "again.tlog"
    scripted_flight(plan, 1.0, lambda t: np.zeros(3 * K), tlog_path=again)
    assert again.read_bytes() == path.read_bytes()  # deterministic in lock-step, faults and all


# --- `jetloop hil` fault flags -------------------------------------------------------------------------

from ground.cli import main as jetloop  # noqa: E402


@pytest.mark.parametrize("flags, message", [
    (["--loss", "0.4"], "--loss '0.4': expected FRACTION[@T0[:T1]], FRACTION 0..0.3"),
    (["--loss", "0.1@5:2"], "--loss '0.1@5:2': expected FRACTION[@T0[:T1]], FRACTION 0..0.3 with 0 <= T0 < T1"),
    (["--duplicate", "lots"], "--duplicate 'lots': expected FRACTION[@T0[:T1]], FRACTION 0..1"),
    (["--delay", "nan"], "--delay 'nan': expected SECONDS[@T0[:T1]], SECONDS >= 0 (a finite number)"),
    (["--jitter", "-0.01"], "--jitter '-0.01': expected SECONDS >= 0"),
    (["--dead-jet", "5@1"], "--dead-jet '5@1': expected UNIT@T0, UNIT a jet number 1..4"),
    (["--dead-jet", "2"], "--dead-jet '2': expected UNIT@T0 (the onset time @T0 is missing)"),
    (["--dead-jet", "2@1:3"], "--dead-jet '2@1:3': expected UNIT@T0 (this fault has no end time)"),
    (["--weak-jet", "2@1"], "--weak-jet '2@1': expected UNIT:EFFICIENCY@T0, EFFICIENCY in (0, 1)"),
    (["--weak-jet", "2:0@1"], "(use --dead-jet for 0)"),
    (["--stuck-joint", "1:roll@2"], "--stuck-joint '1:roll@2': expected UNIT:azimuth@T0 or UNIT:elevation@T0"),
    (["--imu-freeze", "4"], "--imu-freeze '4': expected T0:T1 with 0 <= T0 < T1"),
    (["--imu-nan", "4:3"], "--imu-nan '4:3': expected T0:T1 with 0 <= T0 < T1"),
    (["--depth-jump", "0.3"], "--depth-jump '0.3': expected OFFSET_M@T0[:T1] (the onset time @T0 is missing)"),
    (["--json-sitl", "--loss", "0.1"], "fault injection and --key work on the MAVLink endpoint, not with --json-sitl"),
])
def test_malformed_fault_flags_exit_2_naming_the_flag(flags, message, capsys):
    assert jetloop(["hil", *flags, "--wait", "0.1", "--duration", "0.1"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("jetloop hil: ") and message in err and "Traceback" not in err


def test_every_fault_flag_reaches_the_plan():
    import argparse

    from hil.faults import add_fault_arguments, plan_from_args

    p = argparse.ArgumentParser()
    add_fault_arguments(p)
    args = p.parse_args(
        "--loss 0.2@1:9 --delay 0.02 --jitter 0.01 --duplicate 0.05 --reorder 0.05@2 --dead-jet 2@5.0 "
        "--weak-jet 3:0.5@5.5 --stuck-joint 1:azimuth@6 --imu-freeze 3:4 --imu-nan 7:7.5 "
        "--depth-jump 0.3@6 --depth-jump=-0.1@8:9".split())  # = before a leading minus
    assert plan_from_args(args, K) == FaultPlan(
        loss=0.2, loss_window_s=(1.0, 9.0), delay_s=0.02, jitter_s=0.01, duplicate=0.05,
        reorder=0.05, reorder_window_s=(2.0, math.inf),
        jets=(JetFault(2, 0.0, 5.0), JetFault(3, 0.5, 5.5)), stuck_joints=(StuckJoint(1, "azimuth", 6.0),),
        imu_freeze_s=((3.0, 4.0),), imu_nan_s=((7.0, 7.5),),
        depth_jumps=(DepthJump(6.0, 0.3), DepthJump(8.0, -0.1, 9.0)))
    assert plan_from_args(p.parse_args([]), K).empty


def test_the_flag_values_are_the_onboard_monitors():
    from hil.faults import FLAG
    from onboard.monitor import Fault

    assert FLAG == {f.name: f.value for f in Fault}


# --- the closed loop: plant + onboard loop + recorder, lock-step over loopback UDP ---------------------
#
# For each fault: the onboard side detects it (its summary's faults_seen has the flag, and the
# fault is raised at or after the injection), reports it in telemetry (the ground recording holds
# NAMED_VALUE_FLOAT "faults" with the bit and STATUSTEXT "FAULT <FLAG> ..."), and the plant's
# recording marks when it was injected.

from hil.demo import Leg, Mission, run_closed_loop  # noqa: E402
from hil.faults import FLAG  # noqa: E402

SURFACE_M = V.environment.surface_depth
HOLD_DEPTH_M = 0.4


@pytest.fixture(scope="module")
def warm():
    """Compile the onboard loop in this process, every path of it (the fault monitor's models run
    once ESC and joint feedback arrive, the allocator once armed): a 1.5 s flight with the parties
    as threads. Then every forked onboard loop starts at once, even on loaded cores."""
    mission = hold(1.5)
    run_closed_loop(V, mission.setpoints(), mission.duration_s, processes=False,
                    faults=FaultPlan(jets=(JetFault(1, 0.5, 1.0),), imu_nan_s=((1.2, 1.3),)))


def hold(duration_s, yaw_at_s=None):
    """Arm and dive to 0.4 m at 0.5 s, hold depth and heading (a 45 deg yaw step at yaw_at_s)."""
    legs = [Leg(0.5, "dive", depth_m=HOLD_DEPTH_M, yaw_rad=0.0, surge_m_s=0.0)]
    if yaw_at_s is not None:
        legs.append(Leg(yaw_at_s, "yaw", yaw_rad=math.radians(45.0)))
    return Mission(tuple(legs), duration_s, arm_s=0.5)


def fly(plan, mission, tmp_path, seed=1):
    r = run_closed_loop(V, mission.setpoints(), mission.duration_s, seed=seed, faults=plan, out_dir=tmp_path)
    assert "error" not in r.onboard, r.onboard.get("error")
    assert r.endpoint["periods"] == round(mission.duration_s * V.sensors.imu_rate)
    return r


def telemetry_faults(path):
    """(OR of the NAMED_VALUE_FLOAT "faults" values, [STATUSTEXT texts]) of the onboard telemetry."""
    from pymavlink import mavutil

    conn = mavutil.mavlink_connection(str(path), dialect="ardupilotmega")
    mask, texts = 0, []
    while (m := conn.recv_match(type=["NAMED_VALUE_FLOAT", "STATUSTEXT"])) is not None:
        if m.get_type() == "NAMED_VALUE_FLOAT" and m.name == "faults":
            mask |= int(m.value)
        elif m.get_type() == "STATUSTEXT":
            texts.append(m.text)
    conn.close()
    return mask, texts


def assert_detected(r, plan, flags):
    """Every injected fault named in `flags` was detected, reported and marked."""
    seen = r.onboard.get("faults_seen", 0)
    found = {d["flag"]: d for d in r.extra["detections"]}
    mask, texts = telemetry_faults(r.telemetry_tlog)
    marks = [text for _, text in read_injections(r.tlog)]
    assert marks == [text for _, text in injection_events(plan)
                     if _ < r.endpoint["periods"] / V.sensors.imu_rate]  # the plant's recording says when
    for name in flags:
        assert seen & FLAG[name], f"{name} not in the onboard summary's faults_seen ({seen})"
        assert found[name]["detected_s"] is not None, f"{name} raised only before its injection"
        assert mask & FLAG[name], f"{name} not in the NAMED_VALUE_FLOAT 'faults' telemetry"
        assert any(t.startswith(f"FAULT {name}") for t in texts), f"no STATUSTEXT 'FAULT {name}' ({texts})"


def truth_window(r, t0, t1):
    sel = [s for s in r.truth if t0 <= s.time_s < t1]
    depth = np.array([s.pos_ned_m[2] - SURFACE_M for s in sel])
    rp = np.degrees(np.abs(np.array([s.euler_rad[:2] for s in sel])))
    return depth, rp


@pytest.mark.slow
def test_closed_loop_thirty_percent_loss_is_detected_and_the_loop_still_flies(warm, tmp_path):
    plan = FaultPlan(loss=0.3, loss_window_s=(2.0, math.inf))
    r = fly(plan, hold(8.0), tmp_path)
    assert_detected(r, plan, ["LINK_LOSS"])
    # lock-step paid no reply timeout for the losses: were markers or commands lost like the rest,
    # ~0.3 x 600 frames would wait one; a loaded machine may still make the controller late a few times
    assert r.endpoint["resends"] <= 3
    lost = r.endpoint["link"]["injected"]["in"]["lost_by_type"]["HIL_ACTUATOR_CONTROLS"]
    assert r.endpoint["commands_applied"] == r.endpoint["periods"] - lost  # every other one was applied
    assert abs(lost / 600 - 0.3) < binomial_bound(0.3, 600)  # 6 s of 100 Hz commands in the window
    assert r.onboard["failsafe_entries"] == 0
    depth, rp = truth_window(r, 3.0, 8.0)
    assert np.max(np.abs(depth - HOLD_DEPTH_M)) < 0.05 and np.max(rp) < 2.0  # held depth and level


@pytest.mark.slow
def test_closed_loop_delay_duplicates_and_reordering_are_detected(warm, tmp_path):
    # the monitor raises LINK_DELAY above 50 ms mean sample age (MonitorConfig.delay_threshold_s)
    w = (2.0, math.inf)
    plan = FaultPlan(delay_s=0.08, jitter_s=0.02, delay_window_s=w, duplicate=0.05, duplicate_window_s=w,
                     reorder=0.05, reorder_window_s=w)
    r = fly(plan, hold(6.0), tmp_path)
    assert_detected(r, plan, ["LINK_DELAY", "LINK_DUPLICATE", "LINK_REORDER"])
    assert r.endpoint["resends"] <= 3 and r.onboard["failsafe_entries"] == 0
    depth, rp = truth_window(r, 3.0, 6.0)
    assert np.max(np.abs(depth - HOLD_DEPTH_M)) < 0.05 and np.max(rp) < 5.0


@pytest.mark.slow
def test_closed_loop_one_jet_dead_reconfigures_and_holds_depth_and_attitude(warm, tmp_path):
    """Bounds: from 1.5 s after the jet dies (detection ~0.6 s, then the QP without it): depth
    error < 5 cm, |roll|, |pitch| < 5 deg; during the transient < 10 deg."""
    plan = FaultPlan(jets=(JetFault(2, 0.0, 3.0),))
    r = fly(plan, hold(9.0), tmp_path)
    assert_detected(r, plan, ["JET_DEAD"])
    assert r.onboard["failsafe_entries"] == 0
    _, rp = truth_window(r, 3.0, 4.5)
    assert np.max(rp) < 10.0
    depth, rp = truth_window(r, 4.5, 9.0)
    assert np.max(np.abs(depth - HOLD_DEPTH_M)) < 0.05
    assert np.max(rp) < 5.0
    # the plant's jet 2 really is dead: no thrust from it whatever the allocator asks
    late = np.array([c[:K] for t, c in r.commands if t >= 4.5])
    assert late.size and np.all(late[:, 1] <= 1e-6)  # and the allocator stopped asking


@pytest.mark.slow
def test_closed_loop_weak_jet_and_stuck_joint_are_detected(warm, tmp_path):
    # a 45 deg yaw step after the onset makes the azimuths move away from where unit 1's is stuck
    plan = FaultPlan(jets=(JetFault(3, 0.5, 3.0),), stuck_joints=(StuckJoint(1, "azimuth", 3.0),))
    r = fly(plan, hold(8.0, yaw_at_s=4.0), tmp_path)
    assert_detected(r, plan, ["JET_WEAK", "JOINT_STUCK"])
    depth, rp = truth_window(r, 4.0, 8.0)
    assert np.max(np.abs(depth - HOLD_DEPTH_M)) < 0.05 and np.max(rp) < 5.0


@pytest.mark.slow
def test_closed_loop_imu_freeze_nan_silence_and_depth_jump_are_detected(warm, tmp_path):
    plan = FaultPlan(imu_freeze_s=((3.0, 3.2),), imu_nan_s=((4.0, 4.2),), depth_jumps=(DepthJump(5.0, 0.3),),
                     imu_dropouts_s=((6.0, 6.5),))
    r = fly(plan, hold(7.0), tmp_path)
    assert_detected(r, plan, ["IMU_FROZEN", "IMU_NAN", "DEPTH_JUMP", "IMU_LOST"])


def test_links_on_port_0_never_share_a_port():
    """Two closed loops at once (two test workers) each open udpin:127.0.0.1:0 links. With
    SO_REUSEADDR, Linux may hand a port 0 bind a port another such socket holds (a few in 500),
    and the two loops then steal each other's packets: every closed-loop test here hung at t = 0."""
    links = [Link("udpin:127.0.0.1:0") for _ in range(500)]
    try:
        ports = [link.local_address[1] for link in links]
        assert len(set(ports)) == len(ports)
    finally:
        for link in links:
            link.close()


def test_real_time_mode_runs_through_link_faults_markers_included():
    """Real time follows the wall clock and applies whatever arrived: nothing is exempt there, the
    frame marker is lost like any packet, and the endpoint never waits for an answer."""
    link = Link("udpin:127.0.0.1:0", source_system=1, source_component=1)
    stop, seen = threading.Event(), []
    ctl = threading.Thread(target=_controller, args=(link.local_address[1], stop, lambda t: np.zeros(3 * K), seen))
    ctl.start()
    try:
        ep = HilEndpoint(V, link, Plant(V, seed=3, depth_m=0.5), lockstep=False, seed=3,
                         faults=FaultPlan(loss=0.3, delay_s=0.02))
        ep.run(0.5)
    finally:
        stop.set()
        ctl.join()
        link.close()
    inj = ep.link.stats()["injected"]
    assert ep.stats.periods == 50 and ep.link.exempt == frozenset()
    assert inj["out"]["lost_by_type"].get("SYSTEM_TIME", 0) > 0  # markers too
    markers = sum(m.get_type() == "SYSTEM_TIME" for m in seen)
    assert 0 < markers <= 50 - inj["out"]["lost_by_type"]["SYSTEM_TIME"]  # a lost one never arrives
    assert 0 < ep.stats.commands_applied < 50  # some answers lost, the rest applied when they came
