"""ArduPilot SITL JSON interface: a client that sends servo frames exactly as
libraries/SITL/examples/JSON/readme.md and SIM_JSON.cpp define them and reads the replies the way
SIM_JSON.cpp does (newline framing, strstr + sscanf("[%f, %f, %f]"))."""

from __future__ import annotations

import json
import re
import socket
import struct
import threading

import numpy as np
import pytest

from hil.json_sitl import (
    MAGIC_16,
    MAGIC_32,
    JsonSitlBackend,
    PacketError,
    command_from_pwm,
    pack_servo_packet,
    parse_servo_packet,
)
from onboard.vehicle import load_vehicle

V = load_vehicle()

# SIM_JSON.h keytable: (section, key, kind, required)
KEYTABLE = [
    ("", "timestamp", "double", True),
    ("imu", "gyro", "vec3", True),
    ("imu", "accel_body", "vec3", True),
    ("", "position", "vec3", True),
    ("", "attitude", "vec3", False),
    ("", "quaternion", "vec4", False),
    ("", "velocity", "vec3", True),
]
NUM = r"([-+0-9.eE]+)"


def sitl_frame(frame_rate: int, frame_count: int, pwm, magic: int = MAGIC_16) -> bytes:
    """The servo packet as SIM_JSON.cpp's struct servo_packet lays it out (little-endian, no padding)."""
    n = 16 if magic == MAGIC_16 else 32
    pwm = list(pwm) + [0] * (n - len(pwm))
    return struct.pack("<HHI%dH" % n, magic, frame_rate, frame_count, *pwm)


def sitl_parse(reply: bytes) -> dict:
    """Parse one reply like SIM_JSON::recv_fdm + parse_sensors: the text between the last two newlines,
    each key found with strstr after its section, its value right after `"key":`."""
    text = reply.decode()
    assert text.startswith("\n") and text.endswith("\n"), "SIM_JSON needs a newline before and after"
    line = text.strip("\n")
    assert "\n" not in line
    out = {}
    for section, key, kind, required in KEYTABLE:
        p = line.find(section) if section else 1  # strstr(json, "") then +1 skips '{'
        if p < 0:
            assert not required, f"missing section {section}"
            continue
        p += len(section) + 1 if section else 0
        q = line.find(key, p)
        if q < 0:
            assert not required, f"missing key {section}/{key}"
            continue
        val = line[q + len(key) + 2:]
        if kind == "double":
            out[key] = float(re.match(NUM, val).group(1))
        else:
            n = 3 if kind == "vec3" else 4
            m = re.match(r"\[" + r",\s*".join([NUM] * n) + r"\]", val)  # sscanf "[%f, %f, %f]"
            assert m, f"sscanf would fail on {section}/{key}: {val[:40]!r}"
            out[key] = tuple(float(g) for g in m.groups())
    assert "attitude" in out or "quaternion" in out
    return out


def test_packet_layout_matches_sim_json_struct():
    data = sitl_frame(400, 7, [1500] * 16)
    assert len(data) == 2 + 2 + 4 + 16 * 2
    assert len(sitl_frame(400, 7, [1500] * 32, MAGIC_32)) == 2 + 2 + 4 + 32 * 2
    pkt = parse_servo_packet(data)
    assert (pkt.magic, pkt.frame_rate_hz, pkt.frame_count, pkt.pwm_us[0]) == (18458, 400, 7, 1500)
    assert pack_servo_packet(400, 7, [1500] * 16) == data


@pytest.mark.parametrize("data,msg", [
    (b"\x1aH", "shorter than its 8-byte header"),
    (struct.pack("<HHI16H", 1234, 400, 0, *[0] * 16), "expected 18458"),
    (struct.pack("<HHI15H", MAGIC_16, 400, 0, *[0] * 15), "expected 40"),
])
def test_bad_packets_are_named(data, msg):
    with pytest.raises(PacketError, match=msg):
        parse_servo_packet(data)
    b = JsonSitlBackend(V)
    assert b.handle(data) is None and b.bad_packets == 1


def test_pwm_channels_follow_the_vehicle_pwm_table():
    pwm = [0] * 16
    pwm[0] = 1900  # channel 1: jet of unit 1 full
    pwm[4] = 1100  # channel 5: azimuth of unit 1 at -angle_limit
    pwm[8] = 1700  # channel 9: elevation of unit 1 at +0.5 angle_limit
    c = command_from_pwm(V, pwm)
    lim = V.servo.angle_limit
    assert c[0] == pytest.approx(V.thruster.n_max)
    assert c[1:4] == pytest.approx([0, 0, 0])  # 0 us: jets off
    assert c[4] == pytest.approx(-lim)
    assert c[5:8] == pytest.approx([0, 0, 0])  # 0 us: joints centred
    assert c[8] == pytest.approx(0.5 * lim)


def test_first_reply_is_the_hand_computed_buoyant_vehicle():
    """Jets off, level at 0.5 m: accel_body z = -(B - W) / (m + X_wdot * wall) - g after one frame."""
    b = JsonSitlBackend(V, depth_m=0.5)
    pwm = [1100] * 4 + [1500] * 8 + [0] * 4
    r = sitl_parse(b.handle(sitl_frame(400, 1, pwm)))
    e, body, hydro = V.environment, V.body, V.hydro
    net_up = e.rho * e.g * body.volume - body.mass * e.g  # 1.4715 N
    wall = 1 + V.effects.wall_proximity.k_wall * (body.radius / (e.floor_depth - 0.5)) ** 3
    az = -net_up / (body.mass + hydro.added_mass[2] * wall)
    assert r["timestamp"] == pytest.approx(1 / 400)
    assert r["accel_body"][2] == pytest.approx(az - e.g, abs=2e-3)
    assert r["accel_body"][0] == pytest.approx(0, abs=1e-9)
    assert r["gyro"] == pytest.approx((0, 0, 0), abs=1e-9)
    assert r["position"][2] == pytest.approx(0.5 + 0.5 * az * (1 / 400) ** 2, abs=1e-6)
    assert r["velocity"][2] == pytest.approx(az / 400, rel=0.02)
    assert r["quaternion"] == pytest.approx((1, 0, 0, 0))


def test_lock_step_by_frame_count():
    b = JsonSitlBackend(V, depth_m=0.5)
    pwm = [1500] * 12
    times = [sitl_parse(b.handle(sitl_frame(400, k, pwm)))["timestamp"] for k in range(10, 110)]
    assert times == pytest.approx([k / 400 for k in range(1, 101)], abs=1e-12)
    # the same frame again (SITL re-sends after a silence): same reply, no step
    again = b.handle(sitl_frame(400, 109, pwm))
    assert again == b.last_reply and b.duplicates == 1
    assert sitl_parse(again)["timestamp"] == pytest.approx(100 / 400)
    # a gap: counted as lost, still one step
    r = sitl_parse(b.handle(sitl_frame(400, 113, pwm)))
    assert b.lost_frames == 3 and r["timestamp"] == pytest.approx(101 / 400)
    # frame count back to 0: SITL restarted; the vehicle starts over
    first = sitl_parse(b.handle(sitl_frame(400, 0, pwm)))
    assert b.resets == 1 and first["timestamp"] == pytest.approx(1 / 400)
    fresh = sitl_parse(JsonSitlBackend(V, depth_m=0.5).handle(sitl_frame(400, 0, pwm)))
    assert first == fresh


def test_both_magics_fly_the_same_vehicle():
    pwm = [1700, 1300, 1800, 1200, 1500, 1600, 1400, 1500, 1300, 1500, 1500, 1700]
    a, b = JsonSitlBackend(V, depth_m=0.5), JsonSitlBackend(V, depth_m=0.5)
    for k in range(200):
        ra = a.handle(sitl_frame(1000, k, pwm, MAGIC_16))
        rb = b.handle(sitl_frame(1000, k, pwm + [1234] * 20, MAGIC_32))
    assert ra == rb  # channels 17..32 are not in asr4's [pwm] table
    r = sitl_parse(ra)
    assert r["timestamp"] == pytest.approx(0.2)
    assert np.linalg.norm(r["velocity"]) > 1e-3  # the asymmetric jets moved it


def test_over_udp_replies_to_the_sender():
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    port = sock.getsockname()[1]
    backend = JsonSitlBackend(V, depth_m=0.5)
    server = threading.Thread(target=backend.serve, kwargs=dict(sock=sock, max_frames=50, idle_timeout_s=5.0))
    server.start()
    client = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    client.bind(("127.0.0.1", 0))
    client.settimeout(5.0)
    stamps = []
    try:
        client.sendto(b"not a frame", ("127.0.0.1", port))  # ignored, counted
        for k in range(50):
            client.sendto(sitl_frame(400, k, [1500] * 16), ("127.0.0.1", port))
            reply, addr = client.recvfrom(65000)
            assert addr == ("127.0.0.1", port)
            stamps.append(sitl_parse(reply)["timestamp"])
    finally:
        server.join(10)
        client.close()
        sock.close()
    assert stamps == pytest.approx([k / 400 for k in range(1, 51)])
    assert backend.bad_packets == 1


def _run_jetloop_hil_json_sitl(extra_args, pwm, frames: int, rate_hz: int = 400):
    """`jetloop hil --json-sitl ... --duration frames/rate_hz` as its own process, fed `frames` SITL
    frames of `pwm`; returns (replies parsed as SIM_JSON does, returncode, stdout, stderr)."""
    import subprocess
    import sys
    import time

    probe = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    probe.bind(("127.0.0.1", 0))
    port = probe.getsockname()[1]
    probe.close()
    proc = subprocess.Popen(
        [sys.executable, "-m", "ground.cli", "hil", "--json-sitl", "--link", f"udpin:127.0.0.1:{port}",
         "--duration", repr(frames / rate_hz), *extra_args],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    client = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    client.settimeout(0.5)
    replies = []
    try:
        deadline = time.monotonic() + 60
        k = 0
        while len(replies) < frames and time.monotonic() < deadline:
            client.sendto(sitl_frame(rate_hz, k, pwm), ("127.0.0.1", port))
            try:
                r = sitl_parse(client.recvfrom(65000)[0])
            except socket.timeout:
                continue  # not listening yet: SITL re-sends the same frame, so do we
            if replies and r["timestamp"] == replies[-1]["timestamp"]:
                continue  # the answer to a re-sent frame: the same state again
            replies.append(r)
            k += 1
        out, err = proc.communicate(timeout=60)
    finally:
        client.close()
        if proc.poll() is None:
            proc.kill()
    return replies, proc.returncode, out, err


def test_jetloop_hil_json_sitl_command():
    """`jetloop hil --json-sitl` as its own process answers SITL frames until its duration."""
    replies, rc, out, err = _run_jetloop_hil_json_sitl(["--depth", "0.5"], [1500] * 16, 20)
    assert [r["timestamp"] for r in replies] == pytest.approx([k / 400 for k in range(1, 21)])
    assert rc == 0, err
    assert "20 frames" in out
    assert "-f vectored_6dof" not in out  # asr4 is not ArduSub's heavy frame


def test_jetloop_hil_json_sitl_names_the_heavy_frame_for_the_bluerov():
    """The start-up line a user copies: for the eight-thruster BlueROV2 Heavy it carries
    `-f vectored_6dof` (without it ArduSub's default frame leaves thrusters 7 and 8 idle)."""
    replies, rc, out, err = _run_jetloop_hil_json_sitl(["--vehicle", "bluerov2_heavy"], [1500] * 16, 5)
    assert rc == 0, err
    assert "-l 33.810313,-118.393867,0,185 -f vectored_6dof" in out.splitlines()[0], out


def test_jetloop_hil_jet_neutral_makes_1500_us_no_thrust():
    """`--jet-neutral 1500` reaches the plant: ArduSub's two-way outputs (1500 us neutral, 1100 us
    full reverse) on asr4's one-way jets give no thrust; without the option the same frames run jet 1
    at half speed (1500 us is the middle of jet_range) and push the vehicle along its direction."""
    pwm = [1500, 1100, 1100, 1100] + [1500] * 12  # jet 1 at neutral, jets 2-4 "reversed", joints centred
    speeds = {}
    for name, extra in (("neutral", ["--jet-neutral", "1500"]), ("without", [])):
        replies, rc, out, err = _run_jetloop_hil_json_sitl(["--vehicle", "asr4", "--depth", "0.5", *extra], pwm, 200)
        assert rc == 0, err
        assert len(replies) == 200
        speeds[name] = float(np.hypot(*replies[-1]["velocity"][:2]))  # horizontal, m/s, after 0.5 s
    assert speeds["neutral"] < 1e-9, speeds          # no jet pushes: nothing moves it sideways
    assert speeds["without"] > 0.02, speeds          # half-speed jet 1: a push you cannot miss


# --- issue 17: the four protocol findings, and the BlueROV2 Heavy as ArduSub flies it --------

HEAVY = load_vehicle("bluerov2_heavy")
NEUTRAL_8 = [1500] * 8


def _plant_after(v, t_s, pwm, depth_m, dt_s):
    """The same vehicle in hil.plant, advanced `t_s` at `dt_s` (the cross-form check)."""
    from hil.plant import Plant

    p = Plant(v, dt_s=dt_s, depth_m=depth_m, noise=False, command=command_from_pwm(v, pwm))
    p.advance(t_s)
    return p.state


def test_heavy_frame_at_400_then_1200_hz_is_one_flight():
    """SITL at 400 Hz, then SIM_RATE_HZ 1200: the same plant goes on (no rebuild, no reset),
    the clock is continuous, and the flight equals hil.plant's over the same 0.5 s."""
    b = JsonSitlBackend(HEAVY, depth_m=1.0)
    first = NEUTRAL_8 + [1000] * 8  # what SITL's first frame carries on 9-16
    r = sitl_parse(b.handle(sitl_frame(400, 0, first)))
    # Hand-computed: thrusters at neutral, level at 1 m: it sinks with (W - B) / (m + Z_wdot)
    e, body, hydro = HEAVY.environment, HEAVY.body, HEAVY.hydro
    net_down = body.mass * e.g - e.rho * e.g * body.volume  # 0.9810 N
    az = net_down / (body.mass + hydro.added_mass[2])  # 0.03048 m/s^2
    assert r["accel_body"][2] == pytest.approx(az - e.g, abs=1e-4)
    assert r["timestamp"] == pytest.approx(1 / 400)
    plant = b.plant
    for k in range(1, 100):
        b.handle(sitl_frame(400, k, NEUTRAL_8 + [0] * 8))
    stamps = []
    for k in range(100, 400):
        stamps.append(sitl_parse(b.handle(sitl_frame(1200, k, NEUTRAL_8 + [0] * 8)))["timestamp"])
    assert b.plant is plant and b.rate_changes == 1 and b.resets == 0
    assert stamps == pytest.approx([0.25 + j / 1200 for j in range(1, 301)], abs=1e-9)  # 9 decimals
    want = _plant_after(HEAVY, 0.5, NEUTRAL_8, 1.0, 1 / 2400)
    assert b.plant.state[:13] == pytest.approx(want[:13], abs=1e-9)
    assert b.plant.state[9] == pytest.approx(0.0116, abs=5e-4)  # w(0.5 s): sinking, damped


def test_heavy_frame_forward_pilot_input_moves_it_forward_at_1200_hz():
    """ArduSub's forward stick on the heavy frame: motors 1, 2 below neutral, 3, 4 above."""
    b = JsonSitlBackend(HEAVY, depth_m=1.0)
    pwm = [1400, 1400, 1600, 1600] + [1500] * 4 + [0] * 8
    for k in range(1200):
        r = sitl_parse(b.handle(sitl_frame(1200, k, pwm)))
    assert r["timestamp"] == pytest.approx(1.0)
    assert r["velocity"][0] > 0.1 and abs(r["velocity"][1]) < 1e-6
    assert b.plant.state[:13] == pytest.approx(_plant_after(HEAVY, 1.0, pwm, 1.0, 1 / 1200)[:13], abs=1e-9)


def test_below_100_hz_a_frame_is_still_one_over_frame_rate():
    """At 50 Hz a frame is 20 ms of physics (it was 10 ms: the clock ran at half speed)."""
    b = JsonSitlBackend(HEAVY, depth_m=1.0)
    pwm = [1500] * 4 + [1600] * 4  # vertical motors: positive output pushes down
    stamps = [sitl_parse(b.handle(sitl_frame(50, k, pwm)))["timestamp"] for k in range(10)]
    assert stamps == pytest.approx([k / 50 for k in range(1, 11)], abs=1e-12)
    assert b.substeps == 20
    assert b.plant.state[:13] == pytest.approx(_plant_after(HEAVY, 0.2, pwm, 1.0, 0.001)[:13], abs=1e-12)


def test_first_frame_1000_us_on_channels_9_to_16_is_unused_later_it_is_a_command():
    b = JsonSitlBackend(V, depth_m=0.5)
    pwm = [1100] * 4 + [1500] * 4 + [1000] * 8
    b.handle(sitl_frame(400, 0, pwm))
    k = V.n_units
    assert b.plant.command[2 * k:3 * k] == pytest.approx([0.0] * k)  # elevations centred, not -80 deg
    b.handle(sitl_frame(400, 1, pwm))
    assert b.plant.command[2 * k:3 * k] == pytest.approx([-V.servo.angle_limit] * k)


def test_a_diverged_vehicle_never_puts_nan_into_the_json():
    b = JsonSitlBackend(V, depth_m=0.5)
    b.handle(sitl_frame(400, 0, [1500] * 16))
    b.plant.state[7] = 1e200  # a surge speed whose quadratic damping overflows
    reply = b.handle(sitl_frame(400, 1, [1500] * 16))

    def refuse(name):
        raise AssertionError(f"{name} in the reply")

    frame = json.loads(reply, parse_constant=refuse)
    assert b.diverged == 1 and frame["position"][2] == pytest.approx(0.5)  # started over
    assert sitl_parse(reply)["timestamp"] == pytest.approx(2 / 400)


def test_jet_neutral_on_a_vehicle_without_jets_is_one_line(capsys):
    """--jet-neutral sets where a one-way jet stops: on the BlueROV2 (fixed two-way thrusters only)
    it means nothing, and is refused in one line rather than silently accepted."""
    from ground.cli import main

    assert main(["hil", "--json-sitl", "--vehicle", "bluerov2_heavy", "--jet-neutral", "1500", "--duration", "0.1"]) == 2
    err = capsys.readouterr().err.strip()
    assert err == ("jetloop hil: --jet-neutral: bluerov2_heavy has no water-jets (its fixed thrusters stop in their "
                   "thrust curve's dead band)"), err
