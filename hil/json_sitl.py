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
- Lock-step by frame count: a new frame_count advances the plant by 1/frame_rate, at every
  rate (1 Hz included: integrated in RK4 steps of at most 1 ms); the same frame_count again (SITL
  re-sends after 1 s of silence) gets the same reply without stepping; a smaller frame_count
  means SITL restarted, so the plant restarts from its initial state. A new frame_rate (SITL
  walks SIM_RATE_HZ 1 Hz per frame towards its target) changes the step only: the vehicle, its
  state and the physics clock go on.
PWM channels map to jets, joints and fixed thrusters through the vehicle's `[pwm]` table
(onboard.pwm). A channel at 0 us (no output configured) reads as jets off, thrusters off and
joints centred; so does 1000 us on channels 9-16 in the first frame after a (re)start, which
is what SITL sends there before its outputs are set up.
- The reply is always finite JSON: a state that is not finite (a diverged vehicle) restarts the
  vehicle from its initial state and is counted (`diverged`); no NaN or Infinity is written.
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
PLANT_STEP_S = 0.001  # plant integration step: 1/frame_rate is split into steps of at most this
UNSET_US = 1000  # SITL's first frame carries this on channels 9-16 before their outputs are set


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


def command_from_pwm(v: Vehicle, pwm_us, first_frame: bool = False) -> np.ndarray:
    """Commands from SITL PWM via the vehicle's [pwm] maps; 0 us (channel unused) = off / centred,
    and in the first frame 1000 us on channels 9-16 too (SITL's value before setup)."""
    pwm = np.array(pwm_us, dtype=float)
    if first_frame:
        rest = pwm[8:16]
        rest[rest == UNSET_US] = 0.0
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
        "timestamp": round(float(time_s), 9) if math.isfinite(time_s) else 0.0,
        "imu": {"gyro": _vec(imu.gyro_frd_rad_s), "accel_body": _vec(imu.accel_frd_m_s2)},
        "position": _vec(x[0:3]),
        "velocity": _vec(vel_ned),
        "attitude": _vec((roll, pitch, yaw)),
        "quaternion": _vec(x[3:7]),
    }
    return "\n" + json.dumps(frame, separators=(",", ":"), allow_nan=False) + "\n"


def _vec(values) -> list:
    """Numbers as SITL's sscanf reads them; a non-finite value (which `handle` never lets through)
    is written as 0, never as NaN or Infinity, which are not JSON."""
    return [float(f"{float(c):.9g}") if math.isfinite(float(c)) else 0.0 for c in values]


class JsonSitlBackend:
    """The physics side of the SITL JSON protocol: `handle(packet bytes) -> reply bytes or None`.

    Pure of sockets so a test or a replay can drive it; `serve` puts it on a UDP port.
    """

    def __init__(self, vehicle: Vehicle, seed: int = 0, depth_m: float = 0.0, plant_factory=None):
        from hil.plant import Plant

        self.vehicle = vehicle
        self._make = plant_factory or (lambda dt: Plant(vehicle, dt_s=dt, seed=seed, depth_m=depth_m, noise=False))
        self.plant = None  # built once per (re)start; its state is the vehicle's
        self.frame_rate_hz = 0
        self.last_frame = None
        self.last_reply = b""
        self.frames = 0
        self.duplicates = 0
        self.lost_frames = 0
        self.resets = 0
        self.rate_changes = 0
        self.diverged = 0
        self.bad_packets = 0

    def _restart(self) -> None:
        """The vehicle from its initial state, the physics clock at 0."""
        self.plant = self._make(PLANT_STEP_S)
        self.time_base_s = 0.0
        self.frames_at_rate = 0
        self.frame_rate_hz = 0
        self.step_s = 0.0

    def _set_rate(self, frame_rate_hz: int) -> None:
        """A frame is 1/frame_rate of physics, in RK4 steps of at most PLANT_STEP_S. Only the step
        changes: the vehicle goes on from its state, the clock from where it is."""
        if self.frame_rate_hz:
            self.rate_changes += 1
        self.time_base_s = self.time_s
        self.frames_at_rate = 0
        self.frame_rate_hz = frame_rate_hz
        self.step_s = 1.0 / frame_rate_hz
        self.substeps = max(1, math.ceil(self.step_s / PLANT_STEP_S - 1e-9))

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
            self._restart()
            self.last_frame = None
        if pkt.frame_rate_hz != self.frame_rate_hz:
            self._set_rate(pkt.frame_rate_hz)  # SIM_RATE_HZ changed: the step only
        if self.last_frame is not None and pkt.frame_count == self.last_frame:
            self.duplicates += 1
            return self.last_reply
        if self.last_frame is not None and pkt.frame_count > self.last_frame + 1:
            self.lost_frames += pkt.frame_count - self.last_frame - 1
        first = self.last_frame is None
        self.last_frame = pkt.frame_count
        p = self.plant
        p.set_command(command_from_pwm(self.vehicle, pkt.pwm_us, first_frame=first))
        x = model.rk4_steps(p.state, p.command, p.params, self.step_s / self.substeps, self.substeps)
        if not np.all(np.isfinite(x)):  # diverged: start the vehicle over rather than send NaN
            self.diverged += 1
            x = self._make(PLANT_STEP_S).state
        p.state = x
        self.frames_at_rate += 1
        self.frames += 1
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
