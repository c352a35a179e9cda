"""The plant behind ArduPilot's SITL JSON physics interface, so an ArduSub SITL build can fly it.

Protocol (ArduPilot `libraries/SITL/examples/JSON/readme.md` and `libraries/SITL/SIM_JSON.cpp`):
- SITL sends UDP to the physics backend (default port 9002) one binary servo packet per frame,
  little-endian and unpadded: uint16 magic, uint16 frame_rate, uint32 frame_count, uint16 pwm[N],
  with magic 18458 for N = 16 or magic 29569 for N = 32 (SERVO_32_ENABLE).
- The backend answers to the sender's address with one JSON object per frame, preceded and
  terminated by "\\n": timestamp (s, absolute physics time), imu.gyro (rad/s, body),
  imu.accel_body (m/s^2, body, specific force), position (m, NED), velocity (m/s, NED), and
  attitude (roll, pitch, yaw) and/or quaternion (q1..q4 = w, x, y, z; SITL prefers it).
  SIM_JSON.cpp reads it with strstr + sscanf("[%f, %f, %f]"): a key's `[` must follow its `:`
  directly, so the reply is written without spaces after colons.
- Lock-step by frame count: a new frame_count advances the plant by 1/frame_rate; the same
  frame_count again (SITL re-sends after 1 s of silence) gets the same reply without stepping;
  a smaller frame_count means SITL restarted, so the plant restarts from its initial state.
PWM channels map to jets and joints through the vehicle's `[pwm]` table (onboard.pwm); a channel
at 0 us (no output configured) reads as jets off and joints centred.
"""

from __future__ import annotations

import json
import math
import socket
import struct
from dataclasses import dataclass

import numpy as np

from onboard import model
from onboard.pwm import pwm_to_command
from onboard.sensors import imu_sample
from onboard.vehicle import Vehicle

MAGIC_16 = 18458
MAGIC_32 = 29569
HEADER = struct.Struct("<HHI")
PACKET_16 = struct.Struct("<HHI16H")
PACKET_32 = struct.Struct("<HHI32H")
MAX_STEP_S = 0.01  # a frame_rate below 100 Hz is simulated in 10 ms pieces (readme: max time step)
PLANT_STEP_S = 0.001  # plant integration step: 1/frame_rate is split into steps of at most this


@dataclass(frozen=True)
class ServoPacket:
    magic: int
    frame_rate_hz: int
    frame_count: int
    pwm_us: tuple  # channels 1..N


class PacketError(ValueError):
    pass


def parse_servo_packet(data: bytes) -> ServoPacket:
    """Decode one SITL servo packet; PacketError names what was wrong."""
    if len(data) < HEADER.size:
        raise PacketError(f"servo packet of {len(data)} bytes is shorter than its 8-byte header")
    magic = HEADER.unpack_from(data)[0]
    layout = {MAGIC_16: PACKET_16, MAGIC_32: PACKET_32}.get(magic)
    if layout is None:
        raise PacketError(f"servo packet magic {magic}, expected {MAGIC_16} (16 channels) or {MAGIC_32} (32)")
    if len(data) != layout.size:
        raise PacketError(f"servo packet with magic {magic} has {len(data)} bytes, expected {layout.size}")
    fields = layout.unpack(data)
    return ServoPacket(fields[0], fields[1], fields[2], tuple(fields[3:]))


def pack_servo_packet(frame_rate_hz: int, frame_count: int, pwm_us) -> bytes:
    """What SITL sends (the inverse of parse_servo_packet), for tests and tools."""
    pwm = [int(p) for p in pwm_us]
    if len(pwm) == 16:
        return PACKET_16.pack(MAGIC_16, frame_rate_hz, frame_count, *pwm)
    if len(pwm) == 32:
        return PACKET_32.pack(MAGIC_32, frame_rate_hz, frame_count, *pwm)
    raise PacketError(f"SITL sends 16 or 32 PWM channels, got {len(pwm)}")


def command_from_pwm(v: Vehicle, pwm_us) -> np.ndarray:
    """Commands from SITL PWM via the vehicle's [pwm] maps; 0 us (channel unused) = off / centred."""
    pwm = np.array(pwm_us, dtype=float)
    for ch in v.pwm.jet_channels:
        if ch <= len(pwm) and pwm[ch - 1] == 0:
            pwm[ch - 1] = v.pwm.jet_range[0]
    for ch in v.pwm.azimuth_channels + v.pwm.elevation_channels:
        if ch <= len(pwm) and pwm[ch - 1] == 0:
            pwm[ch - 1] = 0.5 * (v.pwm.servo_range[0] + v.pwm.servo_range[1])
    if len(pwm) < 16:
        pwm = np.concatenate([pwm, np.zeros(16 - len(pwm))])
    return pwm_to_command(v, pwm)


def sensor_json(time_s: float, x, xdot, params, v: Vehicle) -> str:
    """The JSON frame SITL reads, from the plant state x and its derivative (noise-free: SITL adds
    its own sensor noise). Returns the line including the leading and trailing newline."""
    imu = imu_sample(time_s, x, xdot, params, v, np.zeros(3), np.zeros(3))
    R = model.rotation(x[3:7])
    vel_ned = R @ np.asarray(x[7:10])
    roll, pitch, yaw = model.quat_to_euler(x[3:7])
    frame = {
        "timestamp": round(float(time_s), 9),
        "imu": {"gyro": _vec(imu.gyro_frd_rad_s), "accel_body": _vec(imu.accel_frd_m_s2)},
        "position": _vec(x[0:3]),
        "velocity": _vec(vel_ned),
        "attitude": _vec((roll, pitch, yaw)),
        "quaternion": _vec(x[3:7]),
    }
    return "\n" + json.dumps(frame, separators=(",", ":")) + "\n"


def _vec(values) -> list:
    return [float(f"{float(c):.9g}") for c in values]


class JsonSitlBackend:
    """The physics side of the SITL JSON protocol: `handle(packet bytes) -> reply bytes or None`.

    Pure of sockets so a test or a replay can drive it; `serve` puts it on a UDP port.
    """

    def __init__(self, vehicle: Vehicle, seed: int = 0, depth_m: float = 0.0, plant_factory=None):
        from hil.plant import Plant

        self.vehicle = vehicle
        self._make = plant_factory or (lambda dt: Plant(vehicle, dt_s=dt, seed=seed, depth_m=depth_m, noise=False))
        self.plant = None
        self.frame_rate_hz = 0
        self.last_frame = None
        self.last_reply = b""
        self.frames = 0
        self.duplicates = 0
        self.lost_frames = 0
        self.resets = 0
        self.bad_packets = 0

    def _restart(self, frame_rate_hz: int, state=None) -> None:
        step = min(1.0 / frame_rate_hz, MAX_STEP_S)
        self.substeps = max(1, math.ceil(step / PLANT_STEP_S - 1e-9))
        self.step_s = step
        self.plant = self._make(step / self.substeps)
        if state is not None:
            self.plant.state = state
        self.frame_rate_hz = frame_rate_hz
        self.time_base_s = self.time_s if state is not None else 0.0
        self.frames_at_rate = 0

    @property
    def time_s(self) -> float:
        """Physics time of the last reply: frames so far times their step."""
        if self.plant is None:
            return 0.0
        return self.time_base_s + self.frames_at_rate * self.step_s

    def handle(self, data: bytes) -> bytes | None:
        """One servo packet in, the JSON frame to answer (None for a packet that is not SITL's)."""
        try:
            pkt = parse_servo_packet(data)
        except PacketError:
            self.bad_packets += 1
            return None
        if pkt.frame_rate_hz <= 0:
            self.bad_packets += 1
            return None
        if self.plant is None or (self.last_frame is not None and pkt.frame_count < self.last_frame):
            if self.plant is not None:
                self.resets += 1  # frame count went back: SITL restarted, so does the vehicle
            self._restart(pkt.frame_rate_hz)
            self.last_frame = None
        elif pkt.frame_rate_hz != self.frame_rate_hz:
            self._restart(pkt.frame_rate_hz, state=self.plant.state)  # SIM_RATE_HZ changed
        if self.last_frame is not None and pkt.frame_count == self.last_frame:
            self.duplicates += 1
            return self.last_reply
        if self.last_frame is not None and pkt.frame_count > self.last_frame + 1:
            self.lost_frames += pkt.frame_count - self.last_frame - 1
        self.last_frame = pkt.frame_count
        p = self.plant
        p.set_command(command_from_pwm(self.vehicle, pkt.pwm_us))
        p.advance((p.step_index + self.substeps) * p.dt_s)
        self.frames_at_rate += 1
        self.frames += 1
        x = p.state
        xdot = np.zeros_like(x)
        model.derivative(x, p.command, p.params, xdot)
        self.last_reply = sensor_json(self.time_s, x, xdot, p.params, self.vehicle).encode()
        return self.last_reply

    def serve(self, host: str = "127.0.0.1", port: int = 9002, max_frames: int | None = None,
              idle_timeout_s: float | None = None, on_frame=None, sock=None, duration_s: float | None = None) -> None:
        """Answer SITL frames on UDP until `max_frames`, `duration_s` of physics time, or
        `idle_timeout_s` without a packet."""
        own = sock is None
        if own:
            sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.bind((host, port))
        sock.settimeout(idle_timeout_s)
        buf = bytearray(65535)  # one receive buffer, not a 64 kB allocation per frame (onboard.link._Udp)
        view = memoryview(buf)
        try:
            while (max_frames is None or self.frames < max_frames) and (
                    duration_s is None or self.time_s < duration_s - 1e-9):
                try:
                    n, addr = sock.recvfrom_into(buf)
                    data = bytes(view[:n])
                except socket.timeout:
                    return
                except OSError:
                    continue
                reply = self.handle(data)
                if reply is not None:
                    try:
                        sock.sendto(reply, addr)  # readme: reply to the address it came from
                    except OSError:
                        pass
                    if on_frame is not None:
                        on_frame(self)
        finally:
            if own:
                sock.close()
