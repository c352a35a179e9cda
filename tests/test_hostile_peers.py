"""Hostile peers against the onboard loop (issue 15 items 1 and 3), over real UDP sockets on 127.0.0.1.

The rig is the robot as `jetloop onboard --link udpout:PLANT --ground udpin:G` runs it, in
lock-step: a plant (udpin, system 1 component 1) sends sensor frames, a ground station (udpout to
G, system 255) commands, and attackers send from their own sockets. Sensor data must come from the
autopilot on the main link only; with a key, every inbound message must be signed; a stamp far in
the future never poisons the time or the IMU ordering; garbage on the ground link is counted like
garbage on the main link.
"""

from __future__ import annotations

import hashlib
import math
import socket

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from onboard import mavlink_codec as codec
from onboard.link import Link
from onboard.loop import LoopConfig, OnboardLoop, StampGuard, VehicleClock, arm_command, depth_yaw_target
from onboard.sensors import ImuSample, PressureSample
from onboard.signing import enable_signing
from onboard.vehicle import load_vehicle

V = load_vehicle()
KEY = hashlib.sha256(b"jetloop hostile peers").digest()
FUTURE_US = 10 ** 12  # the adversarial run's stamp: 11.6 days ahead


def imu(t: float):
    wobble = 1e-3 * math.sin(100.0 * t)  # a real IMU is never exactly repeated (the monitor calls that frozen)
    return codec.encode_imu(ImuSample(t, (wobble, 0.0, -9.80665), (0.0, wobble, 0.0)))


def frame(t: float) -> list:
    """What the plant sends for instant t: IMU, depth, then the SYSTEM_TIME frame marker."""
    e = V.environment
    return [imu(t), codec.encode_pressure(PressureSample(t, e.p_atm + e.rho * e.g * 0.3, 20.0)),
            mavlink.MAVLink_system_time_message(0, codec.time_boot_ms(t))]


def hostile_imu(time_usec: int = FUTURE_US):
    return mavlink.MAVLink_highres_imu_message(time_usec, 0, 0, -9.8, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 63, 0)


def wire(msg, src: int, comp: int = 1, key: bytes | None = None) -> bytes:
    mav = mavlink.MAVLink(None, src, comp)
    if key is not None:
        enable_signing(mav, key)
    return bytes(msg.pack(mav))


class Robot:
    """The onboard loop with a main link to a plant and a udpin ground link a ground station talks to."""

    def __init__(self, key: bytes | None = None, **config):
        self.plant = Link("udpin:127.0.0.1:0", source_system=1, source_component=1)
        self.main = Link(f"udpout:127.0.0.1:{self.plant.local_address[1]}", 1, 191, signing_key=key)
        self.ground = Link("udpin:127.0.0.1:0", 1, 191, signing_key=key)
        self.station = Link(f"udpout:127.0.0.1:{self.ground.local_address[1]}", 255, 190)
        if key is not None:
            enable_signing(self.plant.mav, key)
            enable_signing(self.station.mav, key)
        self.loop = OnboardLoop(V, self.main, VehicleClock(block_s=0.01), LoopConfig(signing_key=key, **config),
                                ground=self.ground)
        self.loop.start()
        assert self.plant.recv(2.0) is not None  # the robot's hello: the plant's udpin peer
        self.station.send(codec.heartbeat())  # the station's hello: the ground link's peer
        self.t = 0.0

    def pump(self, polls: int = 80) -> None:
        """poll() until two polls in a row read nothing (a poll that steps reads nothing itself)."""
        quiet = 0
        for _ in range(polls):
            before = self.main.bytes_in + self.ground.bytes_in + self.loop.link_foreign()
            self.loop.poll()
            idle = (self.main.bytes_in + self.ground.bytes_in + self.loop.link_foreign() == before
                    and not self.loop._tick_due() and not self.main._ready and not self.ground._ready)
            quiet = quiet + 1 if idle else 0
            if quiet >= 2:
                return

    def fly(self, n: int = 5) -> None:
        """n frames of the plant, 10 ms apart, each answered."""
        for _ in range(n):
            self.t = round(self.t + 0.01, 6)
            with self.plant.batch():
                for m in frame(self.t):
                    self.plant.send(m)
            self.pump()

    def command(self, msg) -> None:
        self.station.send(msg)
        self.pump()

    def texts(self) -> dict:
        """NAMED_VALUE_FLOAT telemetry the station received so far (newest value of each)."""
        out = {}
        m = self.station.recv(0.2)
        while m is not None:
            if m.get_type() == "NAMED_VALUE_FLOAT":
                out[m.name] = m.value
            m = self.station.recv(0.05)
        return out

    def close(self) -> None:
        for lk in (self.plant, self.main, self.ground, self.station):
            lk.close()


@pytest.fixture
def robot():
    r = Robot()
    yield r
    r.close()


@pytest.fixture
def signed_robot():
    r = Robot(KEY)
    yield r
    r.close()


def _armed(r: Robot) -> Robot:
    r.fly(3)
    r.command(arm_command(True))
    r.command(depth_yaw_target(0.3, 0.0))
    r.fly(5)
    assert r.loop.armed and not r.loop.failsafe_active
    return r


def _healthy_after(r: Robot, steps_before: int) -> None:
    """The robot flies on: real IMU samples fused, no failsafe, and it can still be re-armed."""
    ignored = r.loop.stats.ignored_imu
    r.fly(40)  # 0.4 s: longer than the 0.3 s IMU timeout
    assert r.loop.stats.ignored_imu == ignored, "real IMU samples dropped as out of order"
    assert not r.loop.failsafe_active, r.loop.fs_state
    assert r.loop.stats.steps >= steps_before + 40
    assert r.loop.clock.now() == pytest.approx(r.t)
    r.command(arm_command(False))
    r.command(arm_command(True))
    assert r.loop.armed


# -- item 1: sensor data from the wrong party -----------------------------------------------------------

def test_the_adversarial_runs_packet_on_the_signed_ground_port_changes_nothing(signed_robot):
    """The issue's case: one unsigned HIGHRES_IMU from system 99, time_usec 1e12, to the ground port
    of an armed, signing robot. Refused at every layer it reaches; the robot flies on."""
    r = _armed(signed_robot)
    steps = r.loop.stats.steps
    attacker = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        attacker.sendto(wire(hostile_imu(), 99), r.ground.local_address)
        r.pump()
    finally:
        attacker.close()
    assert r.ground.foreign_datagrams == 1  # the ground link's peer is the station: never read
    _healthy_after(r, steps)


def test_sensor_data_on_the_ground_link_is_refused_and_counted(robot):
    """Even from the ground link's own peer (a misbehaving station), sensor data is not read."""
    r = _armed(robot)
    steps = r.loop.stats.steps
    r.station.write_raw(wire(hostile_imu(), 99))
    r.station.write_raw(wire(hostile_imu(), 1))  # claiming to be the autopilot does not help
    r.station.write_raw(wire(mavlink.MAVLink_system_time_message(0, 10 ** 9), 1))
    r.pump()
    _healthy_after(r, steps)
    assert r.loop.stats.security.sensors_refused == 3
    assert r.loop.stats.summary()["sensors_refused"] == 3
    assert r.texts()["sens_ref"] == 3


def test_sensor_data_from_another_system_on_the_main_link_is_refused(robot):
    """A second system behind the plant's address (a router, a companion) is not the autopilot:
    the autopilot is the first sender of sensor data on the main link (here 1:1)."""
    r = _armed(robot)
    steps = r.loop.stats.steps
    r.plant.write_raw(wire(hostile_imu(), 99))
    r.plant.write_raw(wire(hostile_imu(), 1, comp=42))  # another component of the autopilot's system
    r.plant.write_raw(wire(hostile_imu(), 255, comp=190))  # a ground system never supplies sensor data
    r.pump()
    _healthy_after(r, steps)
    assert r.loop.gate.autopilot == (1, 1)
    assert r.loop.stats.security.sensors_refused == 3


def test_a_configured_autopilot_is_the_only_source_of_sensor_data():
    r = Robot(autopilot=(1, 0))  # system 1, any component
    try:
        r.plant.write_raw(wire(hostile_imu(10_000), 7))  # first on the link, but not the one configured
        r.pump()
        assert r.loop.clock.now() == float("-inf") and r.loop.stats.security.sensors_refused == 1
        _armed(r)
    finally:
        r.close()
    with pytest.raises(ValueError, match="autopilot: expected"):
        Robot(autopilot=(255, 1))


def test_with_a_key_sensor_data_must_be_signed_too(signed_robot):
    """Unsigned or wrongly signed sensor data from the autopilot's own address and ids is refused."""
    r = _armed(signed_robot)
    steps = r.loop.stats.steps
    sec = r.loop.stats.security
    before = (sec.unsigned, sec.bad_signature)
    r.plant.write_raw(wire(hostile_imu(), 1))  # unsigned, the autopilot's ids
    r.plant.write_raw(wire(hostile_imu(), 1, key=hashlib.sha256(b"wrong").digest()))
    r.pump()
    assert (sec.unsigned, sec.bad_signature) == (before[0] + 1, before[1] + 1)
    _healthy_after(r, steps)


# -- item 1: a stamp far in the future --------------------------------------------------------------

def test_one_sample_stamped_far_ahead_never_poisons_the_ordering(robot):
    """From the autopilot itself (a corrupt stamp): held, counted, and the stream flies on. Before,
    every later real sample was out of order and the IMU failsafe tripped for good."""
    r = _armed(robot)
    steps = r.loop.stats.steps
    r.plant.send(hostile_imu())
    r.plant.send(mavlink.MAVLink_system_time_message(0, 2 ** 32 - 1))
    r.pump()
    _healthy_after(r, steps)
    assert r.loop.stats.stamps_held == 2
    assert r.loop.stats.summary()["stamps_held"] == 2


def test_a_real_jump_of_the_stream_is_followed_after_three_samples(robot):
    """A recording with a gap, or a stream that really moved on: three samples agreeing on the new
    time re-anchor it; a clock that ran ahead (a poisoned first sample) comes back."""
    r = _armed(robot)
    r.t = 100.0  # the plant's stream jumps 100 s ahead and stays there
    r.fly(10)
    assert r.loop.stats.time_rebases == 1 and r.loop.stats.stamps_held == 2
    assert r.loop.clock.now() == pytest.approx(r.t)
    assert not r.loop.failsafe_active


def test_a_poisoned_first_sample_is_recovered_from():
    """The worst case: the first sensor sample ever seen is stamped 11 days ahead. The real stream
    re-anchors the clock three samples later and the loop steps and arms as usual."""
    r = Robot()
    try:
        r.plant.send(hostile_imu())
        r.pump()
        assert r.loop.clock.now() == pytest.approx(FUTURE_US / 1e6)
        r.fly(5)
        assert r.loop.clock.now() == pytest.approx(r.t)
        _armed(r)
        assert r.loop.stats.time_rebases == 1
    finally:
        r.close()


def test_stamp_guard_hand_computed():
    g = StampGuard(max_skew_s=1.0, confirm=3)
    assert [g.admit(t) for t in (0.0, 0.5, 1.4, 0.5)] == ["ok"] * 4  # within 1 s of the newest (1.4)
    assert g.admit(1e6) == "held" and g.admit(2.0) == "ok"  # a lone outlier; the stream goes on
    assert [g.admit(t) for t in (50.0, 50.5, 51.0)] == ["held", "held", "rebased"]
    assert g.newest == 51.0 and (g.held, g.rebases) == (3, 1)
    assert [g.admit(t) for t in (5.0, 60.0, 5.1)] == ["held", "held", "held"]  # not consecutive: no rebase
    assert g.admit(5.2) == "held" and g.admit(5.3) == "rebased" and g.newest == 5.3


# -- item 3: garbage on every link is counted -----------------------------------------------------------

def test_garbage_on_the_ground_link_is_counted_and_reported(robot):
    """link_bad, SYS_STATUS errors_comm and the exit summary covered the main link only."""
    r = _armed(robot)
    for junk in (b"\xfd\x09\x00\x00\x00\xff\xbe\x00\x00\x00" + bytes(11), b"\xfe\x05" + bytes(10)):
        r.station.write_raw(junk)  # framed packets whose CRC fails, from the ground link's peer
    r.fly(110)  # past the next 1 Hz SYS_STATUS
    bad = r.ground.bad_packets + r.ground.unknown_packets
    assert bad >= 2 and r.main.bad_packets + r.main.unknown_packets == 0
    tm, sys_status = {}, []
    m = r.station.recv(0.2)
    while m is not None:
        if m.get_type() == "NAMED_VALUE_FLOAT":
            tm[m.name] = m.value
        elif m.get_type() == "SYS_STATUS":
            sys_status.append(m.errors_comm)
        m = r.station.recv(0.05)
    assert tm["link_bad"] == bad and sys_status[-1] == bad


def test_the_exit_summary_names_every_link(robot):
    from onboard.cli import summary_lines

    r = _armed(robot)
    r.station.write_raw(b"\xfd\x09\x00\x00\x00\xff\xbe\x00\x00\x00" + bytes(11))
    r.fly(2)
    lines = summary_lines("stopped", r.loop, {"link": r.main, "ground": r.ground})
    link_line = next(x for x in lines if x.startswith("jetloop onboard: link "))
    ground_line = next(x for x in lines if x.startswith("jetloop onboard: ground "))
    assert "bad_packets 0" in link_line and "bad_packets 1" in ground_line
    assert "link errors 1 (link 0, ground 1)" in lines[0]


# -- item 11: `onboard --link tlog:` on a file that holds no MAVLink -------------------------------------

@pytest.mark.parametrize("content", [b"", bytes(range(256)) * 40, b"\x00" * 7 + b"\xfd" + bytes(300)],
                         ids=["empty", "every byte value", "a false start marker"])
def test_onboard_refuses_a_tlog_that_holds_no_mavlink(tmp_path, capsys, content):
    """It ran to its idle timeout and exited 0; now one clear line and exit code 2, at once."""
    from ground.cli import main

    path = tmp_path / "not.tlog"
    path.write_bytes(content)
    assert main(["onboard", "--link", f"tlog:{path}", "--lockstep"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"jetloop onboard: link tlog:{path}: ")
    assert ("the recording is empty" if not content else "no MAVLink packet in its first") in err[0]
    assert "Traceback" not in err[0]


def test_onboard_refuses_a_device_or_a_pipe_as_its_tlog(tmp_path):
    """`jetloop onboard --link tlog:/dev/zero` read the device until the kernel's OOM killer
    stopped it at 23 GB (issue 15, adversarial re-run), and a FIFO blocked it for good. Run as a
    child with its address space capped at 3 GB, so that a regression is a MemoryError here and
    not the machine's memory."""
    import os
    import resource
    import subprocess
    import sys

    fifo = tmp_path / "pipe.tlog"
    os.mkfifo(fifo)

    def cap():
        resource.setrlimit(resource.RLIMIT_AS, (3 << 30, 3 << 30))

    for source, why in (("/dev/zero", "not a regular file"), (str(fifo), "not a regular file"),
                        (str(tmp_path), "Is a directory")):
        p = subprocess.run([sys.executable, "-m", "ground.cli", "onboard", "--link", f"tlog:{source}", "--lockstep"],
                           capture_output=True, text=True, timeout=120, preexec_fn=cap)
        err = p.stderr.strip().splitlines()
        assert p.returncode == 2 and len(err) == 1, (source, p.returncode, p.stderr[-800:])
        assert err[0].startswith(f"jetloop onboard: link tlog:{source}: cannot read recording: ") and why in err[0], err


# -- jetloop onboard itself ----------------------------------------------------------------------------

@pytest.mark.parametrize("args, words", [
    (["--autopilot", "255"], "--autopilot '255': system 255 is a ground system"),
    (["--autopilot", "1:300"], "--autopilot '1:300': expected SYS[:COMP]"),
    (["--ground-peer", "127.0.0.1:9"], "--ground-peer needs --ground udpin:HOST:PORT"),
    (["--peer", "127.0.0.1:0"], "peer '127.0.0.1:0': expected HOST:PORT"),
])
def test_onboard_peer_and_autopilot_options_are_checked_in_one_line(capsys, args, words):
    from ground.cli import main

    assert main(["onboard", "--link", "udpin:127.0.0.1:0", *args]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and words in err[0], err


@pytest.mark.slow
def test_the_adversarial_run_against_the_jetloop_onboard_process(tmp_path):
    """The issue's attack on the real process: `jetloop onboard --link udpout:PLANT --ground
    udpin:G --key K`, a signing plant streaming IMU at 100 Hz, a signing station that arms it,
    and one unsigned HIGHRES_IMU from system 99 stamped 1e12 us sent to G. The robot stays armed,
    without failsafe, and its exit lines count the intruder on the ground link."""
    import signal
    import subprocess
    import sys
    import threading
    import time

    from conftest import free_udp_port

    keyfile = tmp_path / "robot.key"
    keyfile.write_text(KEY.hex())
    g = free_udp_port()
    plant = Link("udpin:127.0.0.1:0", 1, 1)
    enable_signing(plant.mav, KEY)
    proc = subprocess.Popen([sys.executable, "-m", "ground.cli", "onboard", "--link",
                             f"udpout:127.0.0.1:{plant.local_address[1]}", "--ground", f"udpin:127.0.0.1:{g}",
                             "--key", keyfile, "--realtime"], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    station = Link(f"udpout:127.0.0.1:{g}", 255, 190)
    enable_signing(station.mav, KEY)
    stop = threading.Event()

    def stream():  # the autopilot's IMU at 100 Hz, on its own time since boot
        t0 = time.monotonic()
        while not stop.is_set():
            plant.send(imu(time.monotonic() - t0))
            plant.recv(0.0)
            time.sleep(0.01)

    streamer = threading.Thread(target=stream, daemon=True)
    streamer.start()
    seen = {}

    def telemetry(seconds):
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            m = station.recv(0.1)
            if m is not None and m.get_type() == "NAMED_VALUE_FLOAT":
                seen[m.name] = m.value

    attacker = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    try:
        deadline = time.monotonic() + 300  # the first start compiles the model
        while time.monotonic() < deadline and seen.get("armed") != 1.0:
            station.send(arm_command(True))
            telemetry(0.5)
        assert seen.get("armed") == 1.0, seen
        attacker.sendto(wire(hostile_imu(), 99), ("127.0.0.1", g))
        seen.clear()
        telemetry(1.5)  # five IMU timeouts' worth
        assert (seen.get("armed"), seen.get("failsafe"), seen.get("link_foe")) == (1.0, 0.0, 1.0), seen
    finally:
        stop.set()
        streamer.join(5)
        attacker.close()
        proc.send_signal(signal.SIGTERM)
        try:
            out = proc.communicate(timeout=60)[0]
        except subprocess.TimeoutExpired:
            proc.kill()
            out = proc.communicate()[0]
        plant.close()
        station.close()
    line = next(x for x in out.splitlines() if x.startswith(f"jetloop onboard: ground udpin:127.0.0.1:{g}:"))
    assert "foreign_datagrams 1" in line, line
    assert "failsafes 0" in next(x for x in out.splitlines() if "steps, step median" in x)


# -- the second pass (issue 15): stamps inside the old 1 s skew, and walks of them -----------------------

def test_a_stamp_half_a_second_ahead_is_held_and_never_trips_the_imu_failsafe(robot):
    """0.3-1 s ahead was inside the 1 s skew the guard allowed and beyond the 0.3 s IMU timeout:
    in lock-step the clock jumped there, every real sample before it was out of order, and the
    failsafe tripped. The skew is now below the timeout (0.2 s of 0.3 s), so such a stamp is held."""
    r = _armed(robot)
    steps = r.loop.stats.steps
    r.plant.send(imu(r.t + 0.6))
    r.pump()
    _healthy_after(r, steps)
    assert r.loop.stats.stamps_held == 1 and r.loop.stats.time_rebases == 0


def test_the_stamp_skew_must_be_below_the_imu_timeout():
    with pytest.raises(ValueError, match=r"max_stamp_skew_s 0.3 s: expected below imu_timeout_s 0.3 s"):
        LoopConfig(max_stamp_skew_s=0.3)
    assert LoopConfig().max_stamp_skew_s < LoopConfig().imu_timeout_s


def test_stamp_guard_in_real_time_holds_a_stream_that_runs_ahead_of_the_loops_clock():
    """Hand-computed: the stream may not run ahead of the loop's own clock (plus the skew, plus
    1 % drift): a walk of stamps each 0.15 s ahead of the last, within the skew of the newest,
    gets one step in and no further, and never re-anchors, since its samples do not agree on one
    offset from the loop's clock."""
    g = StampGuard(max_skew_s=0.2, confirm=3)
    assert [g.admit(t, now=t - 5.0) for t in (10.0, 10.01, 10.02)] == ["ok"] * 3  # offset 10 - 5 = 5 s
    # at 5.03 s: 10.17 is 0.14 s ahead of the offset (ok); 10.32 is 0.29 s (held); the held ones
    # agree with each other within the skew but not on one offset (5.29, 5.44 | 5.59, 5.74 | ...)
    walk = [g.admit(10.02 + 0.15 * k, now=5.03) for k in range(1, 8)]
    assert walk[0] == "ok" and walk[1:] == ["held"] * 6 and g.rebases == 0
    assert g.newest == pytest.approx(10.17)
    assert [g.admit(t, now=t - 5.0) for t in (10.05, 10.06)] == ["ok", "ok"]  # the real stream goes on
    # a real jump (an autopilot reboot) is three samples agreeing on a new offset: followed
    assert [g.admit(t, now=t + 95.0) for t in (0.01, 0.02, 0.03)] == ["held", "held", "rebased"]
    assert g.admit(0.5, now=95.04) == "held"  # ahead of the new offset (-95 s) by 0.46 s
    assert g.admit(0.05, now=95.05) == "ok"


def test_in_real_time_a_walk_of_stamps_neither_moves_the_ordering_nor_trips_the_failsafe():
    """The adversarial run's walk, against the real-time loop over UDP: the autopilot's stream at
    100 Hz on its own boot time, then six samples from its address each 0.15 s ahead of the one
    before (every one within the old 1 s skew of the newest). Before, the IMU ordering walked
    0.9 s ahead, every real sample after was dropped as out of order and the failsafe tripped."""
    import time

    from onboard.loop import WallClock

    r = Robot.__new__(Robot)
    r.plant = Link("udpin:127.0.0.1:0", source_system=1, source_component=1)
    r.main = Link(f"udpout:127.0.0.1:{r.plant.local_address[1]}", 1, 191)
    r.ground = Link("udpin:127.0.0.1:0", 1, 191)
    r.station = Link(f"udpout:127.0.0.1:{r.ground.local_address[1]}", 255, 190)
    r.loop = OnboardLoop(V, r.main, WallClock(), LoopConfig(), ground=r.ground)
    try:
        r.loop.start()
        assert r.plant.recv(2.0) is not None
        r.station.send(codec.heartbeat())
        t0 = time.monotonic() - 7.0  # the autopilot booted 7 s before

        def fly(seconds, walk=()):
            end = time.monotonic() + seconds
            next_frame = time.monotonic()
            walk = list(walk)
            while time.monotonic() < end:
                if time.monotonic() >= next_frame:
                    t = time.monotonic() - t0
                    with r.plant.batch():
                        for m in frame(t):
                            r.plant.send(m)
                        for k in range(len(walk)):
                            r.plant.send(imu(t + walk.pop(0)))
                    next_frame += 0.01
                r.loop.poll()

        fly(1.0)
        r.station.send(arm_command(True))
        fly(0.5)
        assert r.loop.armed and not r.loop.failsafe_active
        before = r.loop.stats.ignored_imu
        fly(1.0, walk=[0.15 * k for k in range(1, 7)])
        assert not r.loop.failsafe_active and r.loop.stats.failsafe_entries == 0, r.loop.fs_state
        assert r.loop.stats.time_rebases == 0
        assert r.loop._last_imu_stamp <= time.monotonic() - t0 + 0.01
        assert r.loop.stats.ignored_imu - before <= 25  # the real samples behind the one step the walk got in
    finally:
        r.close()


@pytest.mark.parametrize("stray", [
    mavlink.MAVLink_system_time_message(0, 5_000_000),  # a companion's clock message: no sensor data
    hostile_imu(5_000_000),  # sensor data, but from a companion's component
], ids=["SYSTEM_TIME", "IMU from 191"])
def test_a_stray_message_from_a_companion_does_not_become_the_autopilot(stray):
    """The first sensor message on the main link elected its sender for good: a companion's
    SYSTEM_TIME (1:191) ahead of the autopilot's first sample made the companion the autopilot and
    every real sample was refused. Only sensor data (IMU, pressure, attitude) from an autopilot's
    component (MAV_COMP_ID_AUTOPILOT1) elects; what comes before from anyone else is refused."""
    r = Robot()
    try:
        r.plant.write_raw(wire(stray, 1, comp=191))
        r.pump()
        assert r.loop.gate.autopilot is None and r.loop.stats.security.sensors_refused == 1
        assert r.loop.clock.now() == float("-inf")
        _armed(r)
        assert r.loop.gate.autopilot == (1, 1)
        r.plant.write_raw(wire(stray, 1, comp=191))  # and after the election, refused as before
        r.pump()
        assert r.loop.stats.security.sensors_refused == 2
    finally:
        r.close()
