"""Ground station model and live view: loss from sequence numbers, link drop and return, jets from
PWM, warnings, stream rates; over real loopback UDP: garbage floods and truncated packets."""

from __future__ import annotations

import io
import math
import time

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from ground.commands import StreamRates, message_interval, parse_command, CommandError
from ground.ground_cli import GroundSession, run_view
from ground.station import Limits, SourceLink, Station
from ground.view import render_text
from onboard.link import Link
from onboard.vehicle import load_vehicle
from conftest import free_udp_port


def _packets(msgs, system=1, component=1):
    """Pack msgs with one sender (consecutive sequence numbers) and parse them back."""
    tx = mavlink.MAVLink(None, system, component)
    rx = mavlink.MAVLink(None)
    out = []
    for m in msgs:
        out.append(rx.parse_char(m.pack(tx)))
        tx.seq = (tx.seq + 1) % 256  # pack() leaves the sequence to the sender (as onboard.link does)
    return out


def _named(name, value, ms=0):
    return mavlink.MAVLink_named_value_float_message(ms, name.encode(), value)


def _hb(armed=False, mode=4):
    return mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_SUBMARINE, mavlink.MAV_AUTOPILOT_GENERIC,
                                            128 if armed else 0, mode, mavlink.MAV_STATE_ACTIVE, 3)


def test_sequence_loss_counts_wraparound_gaps():
    s = SourceLink()
    # 250..255, 0, 1 consecutive (no loss across the wrap), then 5: 2, 3, 4 lost
    gaps = [s.observe(q) for q in (250, 251, 252, 253, 254, 255, 0, 1, 5)]
    assert gaps == [0] * 8 + [3]
    assert (s.received, s.lost) == (9, 3)
    assert s.loss_fraction == pytest.approx(3 / 12)


def test_station_counts_packets_a_sender_dropped_per_source():
    st = Station()
    pk = _packets([_named("depth", 0.1 * i) for i in range(20)])
    dropped = {3, 4, 11}
    for i, m in enumerate(pk):
        if i not in dropped:
            st.update(m, 1.0 + 0.01 * i)
    other = _packets([_named("x", 1.0) for _ in range(5)], system=2)
    for m in other:
        st.update(m, 2.0)
    snap = st.snapshot(2.0)
    assert st.sources[(1, 1)].lost == len(dropped) == 3
    assert st.sources[(1, 1)].received == len(pk) - len(dropped) == 17
    assert st.sources[(2, 1)].lost == 0
    assert snap.lost == 3
    assert snap.loss_fraction == pytest.approx(3 / (17 + 5 + 3))
    assert any("2 packet(s) lost" in e for _, e in st.events)  # 3 and 4
    assert snap.depth_m == pytest.approx(1.9)  # last delivered value (i = 19)


def test_link_drop_and_return_are_noticed_and_logged():
    st = Station(limits=Limits(link_timeout_s=2.0))
    pk = _packets([_hb()] * 3)
    st.update(pk[0], 10.0)
    st.tick(11.9)
    assert st.link_up
    st.tick(12.1)  # 2.1 s of silence > 2.0 s
    assert not st.link_up and st.link_lost_count == 1
    assert "LINK LOST" in st.snapshot(12.1).warnings
    st.update(pk[1], 15.0)
    assert st.link_up
    texts = [e for _, e in st.events]
    assert any(t.startswith("LINK LOST: nothing for 2.1 s") for t in texts)
    assert "link back after 5.0 s" in texts  # 15.0 - 10.0


def test_heartbeat_attitude_and_named_values_fill_the_snapshot():
    st = Station()
    msgs = [_hb(armed=True, mode=2), mavlink.MAVLink_attitude_message(1000, 0.1, -0.2, 3.0, 0.01, 0.02, 0.03),
            _named("depth", 1.25), _named("depth_sp", 1.5), _named("u_est", 0.3), _named("step_ms", 1.5),
            _named("failsafe", 0.0),
            mavlink.MAVLink_debug_float_array_message(0, b"wrench", 1, [3.0, 4.0, 0, 0, 0, 0] + [0.0] * 52)]
    for m in _packets(msgs):
        st.update(m, 5.0)
    s = st.snapshot(5.0)
    assert s.vehicle == (1, 1) and s.armed is True and s.mode == "depth_hold" and s.failsafe is False
    assert s.attitude_rad == pytest.approx((0.1, -0.2, 3.0))
    assert (s.depth_m, s.depth_setpoint_m, s.velocity_m_s[0]) == pytest.approx((1.25, 1.5, 0.3))
    assert s.residual_norm == pytest.approx(5.0)  # |(3, 4, 0, 0, 0, 0) - 0| = 5
    assert s.warnings == ()  # depth error 0.25 < 0.5, level, fast loop


def test_jets_from_pwm_through_the_vehicle_maps():
    from onboard.model import thrust_newton

    v = load_vehicle()
    st = Station(v)
    pwm = [1500, 1100, 1900, 1300] + [1900, 1500, 1100, 1500] + [1500, 1700, 1500, 1500] + [0] * 4
    (m,) = _packets([mavlink.MAVLink_servo_output_raw_message(0, 0, *pwm)])
    st.update(m, 1.0)
    j = st.snapshot(1.0).jets
    n_max, lim = v.thruster.n_max, v.servo.angle_limit
    # jets: (pwm - 1100) / 800 * n_max; joints: ((pwm - 1100) / 800 * 2 - 1) * limit
    assert j.speed_rev_s == pytest.approx((0.5 * n_max, 0.0, n_max, 0.25 * n_max))
    assert j.azimuth_rad == pytest.approx((lim, 0.0, -lim, 0.0))
    assert j.elevation_rad == pytest.approx((0.0, 0.5 * lim, 0.0, 0.0))
    assert j.thrust_n == pytest.approx([thrust_newton(v, n) for n in j.speed_rev_s])
    w = st.snapshot(1.0).warnings
    assert "jet 1 joint at its limit" in w and "jet 3 joint at its limit" in w and "jet 2 joint at its limit" not in w


def test_out_of_bounds_values_raise_warnings_once_in_the_log():
    st = Station()
    for m in _packets([_hb(), mavlink.MAVLink_attitude_message(0, math.radians(40), 0, 0, 0, 0, 0),
                       _named("depth", 1.0), _named("depth_sp", 0.2), _named("failsafe", 1.0),
                       _named("step_ms", 25.0)]):
        st.update(m, 1.0)
    w = st.snapshot(1.0).warnings
    assert "FAILSAFE active" in w
    assert "tilt 40 deg > 30" in w
    assert "depth error +0.80 m" in w
    assert "control step 25.0 ms > 10" in w
    st.snapshot(1.1)
    assert sum("WARNING tilt" in e for _, e in st.events) == 1


def test_command_ack_gives_the_round_trip():
    st = Station()
    st.command_sent(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 10.0)
    (ack,) = _packets([mavlink.MAVLink_command_ack_message(mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 0, 0, 255, 190)])
    st.update(ack, 10.042)
    assert st.rtt_s == pytest.approx(0.042)
    assert any("command 400: accepted" in e for _, e in st.events)


def test_stream_rates_follow_set_message_interval():
    rates = StreamRates({"ATTITUDE": 10.0, "NAMED_VALUE_FLOAT": 10.0})
    (cmd,) = _packets([message_interval("ATTITUDE", 4.0)], system=255)
    assert rates.handle(cmd) == mavlink.MAV_RESULT_ACCEPTED
    (stop,) = _packets([message_interval("NAMED_VALUE_FLOAT", 0.0)], system=255)  # 0 Hz -> interval -1
    assert stop.param2 == -1.0 and rates.handle(stop) == mavlink.MAV_RESULT_ACCEPTED
    ticks = [k * 0.01 for k in range(200)]  # 2 s of a 100 Hz loop
    assert sum(rates.due("ATTITUDE", t) for t in ticks) == 8  # 4 Hz x 2 s
    assert sum(rates.due("NAMED_VALUE_FLOAT", t) for t in ticks) == 0
    (default,) = _packets([mavlink.MAVLink_command_long_message(1, 1, 511, 0, 32, 0, 0, 0, 0, 0, 0)])
    assert rates.handle(default) == mavlink.MAV_RESULT_ACCEPTED  # interval 0: the default again
    assert rates.rate_hz["LOCAL_POSITION_NED"] == 0.0  # id 32 has no default here
    (bad,) = _packets([mavlink.MAVLink_command_long_message(1, 1, 511, 0, 9999, 1e5, 0, 0, 0, 0, 0)])
    assert rates.handle(bad) == mavlink.MAV_RESULT_DENIED


def test_operator_commands_parse_to_standard_messages():
    (m,) = parse_command("depth 1.5 yaw 90")
    assert m.get_type() == "SET_POSITION_TARGET_LOCAL_NED" and m.z == 1.5 and m.yaw == pytest.approx(math.pi / 2)
    assert m.coordinate_frame == mavlink.MAV_FRAME_LOCAL_NED
    (m,) = parse_command("arm")
    assert (m.command, m.param1) == (mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0)
    (m,) = parse_command("mode depth_hold")
    assert (m.command, m.param2) == (mavlink.MAV_CMD_DO_SET_MODE, 2.0)
    (m,) = parse_command("manual 2000 -100 500 0")
    assert (m.x, m.y, m.z, m.r) == (1000, -100, 500, 0)  # x clipped to +-1000
    (m,) = parse_command("rate ATTITUDE 5")
    assert (m.command, m.param1, m.param2) == (511, 30.0, 200_000.0)  # id 30, 1e6 / 5 us
    for bad in ("fly", "depth deep", "mode warp", "rate NOT_A_MESSAGE 1", ""):
        with pytest.raises(CommandError):
            parse_command(bad)


def test_view_keeps_running_through_garbage_truncation_and_link_loss():
    port = free_udp_port()
    session = GroundSession(f"udpin:127.0.0.1:{port}", load_vehicle(), limits=Limits(link_timeout_s=0.3))
    tx = Link(f"udpout:127.0.0.1:{port}")
    try:
        tx.send(_hb())
        session.poll(0.2)
        assert session.station.link_up and session.station.vehicle_id == (1, 1)
        # a flood of garbage bytes (no 0xFD / 0xFE start marker in it), then a good packet
        rng = np.random.default_rng(4)
        junk = rng.integers(0, 0xFC, 20_000, dtype=np.uint8).tobytes()
        for k in range(0, len(junk), 1000):
            tx.write_raw(junk[k:k + 1000])
        tx.send(_named("depth", 0.5))
        # a truncated packet followed by a good one in the same datagram
        torn = bytes(mavlink.MAVLink_attitude_message(9, 1, 1, 1, 1, 1, 1).pack(mavlink.MAVLink(None, 1, 1)))[:15]  # of 40
        good = bytes(_named("depth_sp", 1.25).pack(tx.mav))
        tx.mav.seq = (tx.mav.seq + 1) % 256
        tx.write_raw(torn + good)
        deadline = time.monotonic() + 2.0
        while session.station.values.get("depth_sp") is None and time.monotonic() < deadline:
            session.poll(0.05)
        st = session.station
        assert st.values["depth"] == 0.5 and st.values["depth_sp"] == 1.25  # exact in float32
        assert st.garbage_bytes >= 20_000
        assert st.bad_packets >= 1
        # silence: the link is declared lost, and back when packets come again
        t0 = time.monotonic()
        while st.link_up and time.monotonic() - t0 < 2.0:
            session.poll(0.05)
        assert not st.link_up
        text_lost = render_text(session.snapshot())
        tx.send(_hb())
        session.poll(0.3)
        assert st.link_up
        out = io.StringIO()
        run_view(session, once=True, out=out)
        text = out.getvalue()
    finally:
        tx.close()
        session.close()
    assert "LINK LOST" in text_lost and "link LOST" in text_lost
    events = "\n".join(e for _, e in st.events)
    assert "garbage byte(s) on the link" in events
    assert "bad packet(s)" in events
    assert "LINK LOST" in events and "link back after" in events
    # the 1 s view window outlasts the 0.3 s timeout: it reports the second drop and carries on
    assert "link LOST  (2 drop(s))" in text and "depth 0.50 m  setpoint 1.25 m" in text


def test_a_peers_status_text_cannot_drive_the_operators_terminal():
    """Issue 15 re-run: a STATUSTEXT holding escape sequences (clear the screen, retitle the
    terminal, a bell) reached `jetloop ground --plain`'s output raw. They are shown escaped."""
    st = Station()
    for m in _packets([_hb(), mavlink.MAVLink_statustext_message(4, b"\x1b[2J\x1b]0;pwn\x07evil\x7f")]):
        st.update(m, 1.0)
    frame = render_text(st.snapshot(1.0))
    assert "vehicle says: \\x1b[2J\\x1b]0;pwn\\x07evil\\x7f" in frame
    assert not any(not c.isprintable() for line in frame.splitlines() for c in line)


def test_ground_cli_once_prints_a_frame_and_rejects_bad_arguments(tmp_path, capsys):
    from ground.cli import main

    port = free_udp_port()
    assert main(["ground", "--link", f"udpin:127.0.0.1:{port}", "--once", "--record", str(tmp_path)]) == 0
    out = capsys.readouterr()
    assert "[link]" in out.out and "link waiting" in out.out and "no link yet" in out.out
    assert "recorded 1 packets (0 in, 1 out)" in out.err  # the ground's own heartbeat
    assert main(["ground", "--link", "bogus", "--once"]) == 2
    assert "expected udpin:HOST:PORT" in capsys.readouterr().err
    assert main(["ground", "--rates", "ATTITUDE=fast", "--once"]) == 2
    assert "expected MESSAGE=HZ" in capsys.readouterr().err
    assert main(["ground", "--cmd", "dive", "--once"]) == 2
    assert "expected arm | disarm" in capsys.readouterr().err


# -- the serial path: two pseudo-terminal pairs joined by a 57600-baud "radio" --------------------

class _Radio:
    """Joins two pty masters like a pair of 57600-baud telemetry radios: at most 5760 bytes/s each
    way (8N1: 10 bits a byte), a 4 KiB buffer each way; bytes that do not fit are dropped (counted)."""

    BYTES_PER_S = 57600 / 10
    BUFFER = 4096

    def __init__(self, a_fd, b_fd):
        import threading

        self.fds = (a_fd, b_fd)
        self.buf = [bytearray(), bytearray()]  # a->b, b->a
        self.dropped = [0, 0]
        self.carried = [0, 0]
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self):
        import os
        import select

        last = time.monotonic()
        while not self._stop.is_set():
            ready, _, _ = select.select(list(self.fds), [], [], 0.005)
            for i, fd in enumerate(self.fds):
                if fd in ready:
                    try:
                        data = os.read(fd, 4096)
                    except OSError:
                        continue
                    room = self.BUFFER - len(self.buf[i])
                    self.buf[i] += data[:room]
                    self.dropped[i] += max(0, len(data) - room)
            now = time.monotonic()
            allowance = int(self.BYTES_PER_S * (now - last))
            if allowance > 0:
                last = now
                for i in (0, 1):
                    chunk = bytes(self.buf[i][:allowance])
                    if chunk:
                        os.write(self.fds[1 - i], chunk)
                        del self.buf[i][:len(chunk)]
                        self.carried[i] += len(chunk)

    def idle(self):
        return not self.buf[0] and not self.buf[1]

    def close(self):
        self._stop.set()
        self._thread.join(2.0)


def _serial_run(tmp_path, rates, seconds):
    """The onboard loop's telemetry over a pty + 57600-baud radio to a ground session on the other
    pty; returns (session, radio, counts of messages recorded, loop)."""
    import os

    from ground.recording import read_recording
    from onboard.loop import LoopConfig, OnboardLoop, WallClock

    vm, vs = os.openpty()
    gm, gs = os.openpty()
    radio = _Radio(vm, gm)
    session = GroundSession(f"{os.ttyname(gs)}:57600", load_vehicle(), record_dir=tmp_path, rates=rates)
    main = Link("udpout:127.0.0.1:9")  # the autopilot side is not under test: discard port
    ground_link = Link(f"{os.ttyname(vs)}:57600")
    loop = OnboardLoop(load_vehicle(), main, WallClock(), LoopConfig(), ground=ground_link)
    try:
        loop.start()
        t0 = time.monotonic()
        while rates and time.monotonic() - t0 < 3.0:  # the vehicle waits for the ground's requests
            session.poll(0.01)
            g = ground_link.recv(0.01)
            while g is not None:
                loop.handle(g)
                g = ground_link.recv(0.0)
            if sum(1 for n in rates if loop.rates.rate_hz.get(n) == rates[n]) == len(rates):
                break
        t0 = time.monotonic()
        for k in range(int(seconds * 100)):  # 100 Hz control ticks
            g = ground_link.recv(0.0)
            while g is not None:
                loop.handle(g)
                g = ground_link.recv(0.0)
            loop.step(0.01 * k)
            session.poll(0.0)
            time.sleep(max(0.0, t0 + 0.01 * (k + 1) - time.monotonic()))
        deadline = time.monotonic() + 5.0
        while not radio.idle() and time.monotonic() < deadline:
            session.poll(0.02)
        for _ in range(10):
            session.poll(0.02)
    finally:
        radio.close()
        session.close()
        ground_link.close()
        main.close()
        os.close(vm), os.close(gm), os.close(vs), os.close(gs)
    counts = read_recording(session.recorder.files[0]).messages
    return session, radio, counts, loop


def test_serial_57600_with_requested_rates_loses_nothing(tmp_path):
    rates = {"ATTITUDE": 5.0, "NAMED_VALUE_FLOAT": 1.0, "DEBUG_FLOAT_ARRAY": 1.0, "SERVO_OUTPUT_RAW": 5.0}
    session, radio, counts, loop = _serial_run(tmp_path / "asked", rates, seconds=3.0)
    assert {n: loop.rates.rate_hz[n] for n in rates} == rates  # the vehicle took every request
    st = session.station
    assert radio.dropped == [0, 0]
    assert st.sources[(1, 1)].lost == 0 and st.bad_packets == 0 and st.garbage_bytes == 0
    # 3 s at the asked rates (the first due at t = 0): 5 Hz -> 15, 1 Hz -> 3
    for name in ("ATTITUDE", "SERVO_OUTPUT_RAW", "DEBUG_FLOAT_ARRAY"):
        assert counts[name] == round(3.0 * rates[name]), name
    assert counts["ATTITUDE"] == 15 and counts["SERVO_OUTPUT_RAW"] == 15
    assert counts["DEBUG_FLOAT_ARRAY"] == 3
    assert radio.carried[0] / 3.0 < _Radio.BYTES_PER_S  # the radio was never saturated
    acks = [e for _, e in st.events if e.startswith("command 511: accepted")]
    assert len(acks) == 4


def test_serial_57600_at_default_rates_floods_the_radio(tmp_path):
    """The same link without asking for rates: 100 Hz SERVO_OUTPUT_RAW and 10 Hz telemetry
    (~10 kB/s) overrun a 5.76 kB/s radio, and the ground sees the loss (the check can fail)."""
    session, radio, counts, loop = _serial_run(tmp_path / "default", {}, seconds=2.0)
    assert radio.dropped[0] > 0
    st = session.station
    assert st.sources[(1, 1)].lost > 0 or st.bad_packets > 0


def test_delay_jitter_is_measured_against_a_sliding_minimum():
    st = Station()
    # (arrival wall s, vehicle ms): offsets 100.0, 100.0, 100.3 -> 0.3 s late
    for now, ms in ((100.0, 0), (100.1, 100), (100.5, 200)):
        (m,) = _packets([mavlink.MAVLink_attitude_message(ms, 0, 0, 0, 0, 0, 0)])
        st.update(m, now)
    assert st.delay_jitter_s == pytest.approx(0.3)
    # the clocks drift 0.5 s apart, steadily: after the 10 s window it is no longer "late"
    for k in range(1, 30):
        (m,) = _packets([mavlink.MAVLink_attitude_message(200 + 1000 * k, 0, 0, 0, 0, 0, 0)])
        st.update(m, 100.5 + k * 1.0 + 0.5)  # offset 100.8 from here on
    assert st.delay_jitter_s == pytest.approx(0.0, abs=1e-9)


def test_station_mode_names_are_the_onboard_loops():
    """ground.station keeps its own copy (importing onboard.loop costs seconds of numba); it must agree."""
    from ground.station import MODE_NAMES
    from onboard.loop import MODE_NAMES as ONBOARD_MODE_NAMES

    assert MODE_NAMES == ONBOARD_MODE_NAMES
