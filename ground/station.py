"""The ground station's telemetry model: MAVLink messages in, a picture of the vehicle out (pure).

No IO here: the caller passes each received message with the wall time it arrived (`now_s`,
any monotonic clock) and calls `tick(now_s)` between messages so a silent link is noticed.
`snapshot(now_s)` gives a frozen `Snapshot` for a view; `events` is the log of what happened
(link lost / back, garbage and bad packets, STATUSTEXT, command acks, warnings raised).

What is read (onboard/loop.py's telemetry, plus an ArduSub vehicle's standard messages):
- HEARTBEAT: vehicle type, armed flag (MAV_MODE_FLAG_SAFETY_ARMED), custom mode, system status.
- ATTITUDE: roll, pitch, yaw and rates.
- NAMED_VALUE_FLOAT: depth, depth_sp, yaw_sp, u_sp, u_est, alloc_err, alloc_fb, qp_us, step_ms,
  step_p99, failsafe, armed, est_rej, in_rej, link_bad, faults (the onboard loop's names).
- DEBUG_FLOAT_ARRAY "wrench": demanded wrench (6) then achieved wrench (6); the allocation
  residual is their difference.
- SERVO_OUTPUT_RAW: per-jet speed, azimuth and elevation through the vehicle's [pwm] maps
  (onboard.pwm.pwm_to_command), thrust from the speed by seed 000 eq. 15 at zero inflow
  (onboard.model.jet_thrust).
- SCALED_PRESSURE2 (ArduSub's depth sensor) -> depth when no "depth" value comes;
  LOCAL_POSITION_NED / VFR_HUD -> velocity when no "u_est" comes.
- SYS_STATUS: sensor health bits, load, onboard link errors.
- COMMAND_ACK: result and the round trip since the command went out (`command_sent`).

Link quality per (system, component): packet loss from the MAVLink sequence number (seq runs
0..255; a jump from s to s' means (s' - s - 1) mod 256 packets lost, as mavutil counts it),
plus the link's own counters of garbage bytes and bad packets (`link_counters`). Latency: the
round trip of the last acknowledged command, and the one-way delay jitter of the telemetry
(arrival time minus vehicle time, above the smallest seen: clocks need not agree for it).
"""

from __future__ import annotations

import math
from collections import deque
from dataclasses import dataclass

import numpy as np

SEQ_MODULO = 256
MAV_MODE_FLAG_SAFETY_ARMED = 128
MAV_AUTOPILOT_INVALID = 8
MAV_TYPE_GCS = 6
MAV_TYPE_SUBMARINE = 12
MAV_CMD_ACK_NAMES = {0: "accepted", 1: "temporarily rejected", 2: "denied", 3: "unsupported", 4: "failed",
                     5: "in progress", 6: "cancelled"}
MODE_NAMES = {0: "stabilize", 2: "depth_hold", 4: "guided", 19: "manual"}  # onboard.loop.MODES
HEALTH_BITS = {1: "gyro", 2: "accel", 8: "pressure", 0x200000: "ahrs", 0x8000: "motors"}
ATMOSPHERE_PA = 101325.0
RHO_G = 1025.0 * 9.80665  # sea water, for SCALED_PRESSURE2 depth when the vehicle sends no depth


def printable(text: str) -> str:
    """Text from the wire as shown to a person: a character that is not printable (an escape
    sequence, a bell, C1 controls) is written as its escape (\\x1b), so a peer's STATUSTEXT
    cannot clear the operator's screen, move the cursor or retitle the terminal (issue 15
    re-run: `jetloop ground --plain` printed them raw)."""
    return "".join(c if c.isprintable() else repr(c)[1:-1] for c in text)


@dataclass(frozen=True)
class Limits:
    """Bounds beyond which the view warns (operator's limits, not the vehicle's)."""

    tilt_rad: float = math.radians(30.0)  # |roll| or |pitch|
    depth_error_m: float = 0.5
    allocation_residual: float = 1.0  # weighted error of the allocation QP
    step_ms: float = 10.0  # a control step longer than the 100 Hz period
    loss_fraction: float = 0.05
    link_timeout_s: float = 2.0  # no packet for this long: link lost
    joint_fraction: float = 0.95  # a joint beyond this fraction of its angle limit is saturated
    delay_jitter_s: float = 0.5


@dataclass
class SourceLink:
    """Sequence bookkeeping for one (system, component)."""

    received: int = 0
    lost: int = 0
    last_seq: int | None = None

    def observe(self, seq: int) -> int:
        """Count one packet with sequence number `seq`; returns how many were lost before it."""
        gap = 0
        if self.last_seq is not None:
            gap = (seq - self.last_seq - 1) % SEQ_MODULO
        self.last_seq = seq
        self.received += 1
        self.lost += gap
        return gap

    @property
    def loss_fraction(self) -> float:
        total = self.received + self.lost
        return self.lost / total if total else 0.0


@dataclass(frozen=True)
class Jets:
    thrust_n: tuple
    speed_rev_s: tuple
    azimuth_rad: tuple
    elevation_rad: tuple


@dataclass(frozen=True)
class Snapshot:
    """What the view shows, at one instant (nan where nothing has come yet)."""

    vehicle: tuple | None  # (system, component)
    vehicle_type: int | None
    armed: bool | None
    mode: str
    system_status: int | None
    attitude_rad: tuple  # roll, pitch, yaw
    rates_rad_s: tuple
    depth_m: float
    depth_setpoint_m: float
    yaw_setpoint_rad: float
    velocity_m_s: tuple  # surge, sway, heave (estimated; nan where not sent)
    surge_setpoint_m_s: float
    jets: Jets | None
    wrench_demand: tuple
    wrench_achieved: tuple
    residual_norm: float  # |demand - achieved| (N, N m mixed: a magnitude to watch)
    allocation_error: float  # the allocator's weighted error
    allocation_fallbacks: float
    qp_us: float
    step_ms: float
    step_p99_ms: float
    failsafe: bool | None
    estimator_rejections: float
    link_up: bool
    link_lost_count: int
    since_last_s: float
    packets: int
    lost: int
    loss_fraction: float
    garbage_bytes: int
    bad_packets: int
    rate_hz: float
    rtt_s: float
    delay_jitter_s: float
    warnings: tuple
    events: tuple  # the last few (time_s, text)
    faults: int | None = None  # onboard.monitor.Fault bitmask (NAMED_VALUE_FLOAT "faults"); None: not sent


_NAMED = {"depth", "depth_sp", "yaw_sp", "u_sp", "u_est", "alloc_err", "alloc_fb", "qp_us", "step_ms",
          "step_p99", "failsafe", "armed", "est_rej", "in_rej", "link_bad", "faults"}


class Station:
    """Telemetry model updated from messages; see the module doc. `vehicle` (onboard.vehicle)
    gives the PWM maps and thrust curve for the per-jet panel; without it jets are not shown."""

    def __init__(self, vehicle=None, limits: Limits = Limits(), own_system: int = 255, event_history: int = 200):
        self.limits = limits
        self.own_system = own_system
        self.vehicle = vehicle
        self._params = None
        if vehicle is not None:
            from onboard.model import pack_params

            self._params = pack_params(vehicle)
        self.sources: dict = {}
        self.events: deque = deque(maxlen=event_history)
        self.values: dict = {}
        self.vehicle_id = None
        self.vehicle_type = None
        self.armed = None
        self.mode = "?"
        self.system_status = None
        self.health_missing: tuple = ()
        self.attitude = (math.nan,) * 3
        self.rates = (math.nan,) * 3
        self.pressure_depth_m = math.nan
        self.velocity_ned = (math.nan,) * 3
        self.groundspeed = math.nan
        self.command_u = None
        self._pwm = None
        self.wrench_demand = (math.nan,) * 6
        self.wrench_achieved = (math.nan,) * 6
        self.packets = 0
        self.last_rx_s = None
        self.link_up = False
        self.link_lost_count = 0
        self.garbage_bytes = 0
        self.bad_packets = 0
        self.rtt_s = math.nan
        self._pending: dict = {}  # command id -> wall time sent
        self._offsets: deque = deque()  # (arrival, offset) with increasing offsets: sliding minimum
        self.delay_jitter_s = math.nan
        self._arrivals: deque = deque(maxlen=512)
        self._active: set = set()  # warnings currently raised (to log each once)
        self._dispatch = {
            "HEARTBEAT": self._heartbeat, "ATTITUDE": self._attitude,
            "NAMED_VALUE_FLOAT": self._named, "DEBUG_FLOAT_ARRAY": self._debug_array,
            "SERVO_OUTPUT_RAW": self._servo, "SCALED_PRESSURE2": self._pressure,
            "LOCAL_POSITION_NED": self._local_position, "VFR_HUD": self._vfr_hud,
            "SYS_STATUS": self._sys_status, "COMMAND_ACK": self._command_ack, "STATUSTEXT": self._statustext,
        }

    # -- input ---------------------------------------------------------------------------------
    def update(self, msg, now_s: float) -> None:
        """One good message received at wall time `now_s`."""
        src = (msg.get_srcSystem(), msg.get_srcComponent())
        link = self.sources.get(src)
        if link is None:
            link = self.sources[src] = SourceLink()
        gap = link.observe(msg.get_seq())
        if gap:
            self._event(now_s, f"{gap} packet(s) lost from {src[0]}/{src[1]} (sequence gap)")
        self.packets += 1
        self._arrivals.append(now_s)
        if not self.link_up:
            self.link_up = True
            self._event(now_s, "link up" if self.last_rx_s is None else
                        f"link back after {now_s - self.last_rx_s:.1f} s")
        self.last_rx_s = now_s
        handler = self._dispatch.get(msg.get_type())
        if handler is not None and src[0] != self.own_system:
            try:
                handler(msg, now_s)
            except (TypeError, ValueError, AttributeError, OverflowError, IndexError):
                self._event(now_s, f"{msg.get_type()} from {src[0]}/{src[1]} could not be read")

    def link_counters(self, garbage_bytes: int, bad_packets: int, now_s: float) -> None:
        """The link's running totals (onboard.link.Link.garbage_bytes / bad_packets + unknown)."""
        if garbage_bytes > self.garbage_bytes:
            self._event(now_s, f"{garbage_bytes - self.garbage_bytes} garbage byte(s) on the link")
        if bad_packets > self.bad_packets:
            self._event(now_s, f"{bad_packets - self.bad_packets} bad packet(s) (CRC/length/truncated)")
        self.garbage_bytes, self.bad_packets = garbage_bytes, bad_packets

    def command_sent(self, command_id: int, now_s: float) -> None:
        """A COMMAND_LONG went out: its COMMAND_ACK gives the round trip."""
        self._pending[int(command_id)] = now_s

    def tick(self, now_s: float) -> None:
        """Notice a silent link (no packet for `limits.link_timeout_s`)."""
        if self.link_up and self.last_rx_s is not None and now_s - self.last_rx_s > self.limits.link_timeout_s:
            self.link_up = False
            self.link_lost_count += 1
            self._event(now_s, f"LINK LOST: nothing for {now_s - self.last_rx_s:.1f} s")

    # -- handlers ------------------------------------------------------------------------------
    def _heartbeat(self, m, now_s):
        if m.autopilot == MAV_AUTOPILOT_INVALID or m.type == MAV_TYPE_GCS:
            return  # another ground station
        if self.vehicle_id is None:
            self.vehicle_id = (m.get_srcSystem(), m.get_srcComponent())
            self._event(now_s, f"vehicle {self.vehicle_id[0]}/{self.vehicle_id[1]} type {m.type}")
        armed = bool(m.base_mode & MAV_MODE_FLAG_SAFETY_ARMED)
        if self.armed is not None and armed != self.armed:
            self._event(now_s, "ARMED" if armed else "disarmed")
        self.armed = armed
        self.vehicle_type = int(m.type)
        self.mode = MODE_NAMES.get(int(m.custom_mode), str(int(m.custom_mode)))
        self.system_status = int(m.system_status)

    def _attitude(self, m, now_s):
        self.attitude = (float(m.roll), float(m.pitch), float(m.yaw))
        self.rates = (float(m.rollspeed), float(m.pitchspeed), float(m.yawspeed))
        self._delay(now_s, m.time_boot_ms / 1e3)

    def _named(self, m, now_s):
        name = m.name.decode("ascii", "replace") if isinstance(m.name, bytes) else str(m.name)
        name = name.rstrip("\x00")
        if name in _NAMED:
            self.values[name] = float(m.value)

    def _debug_array(self, m, now_s):
        name = m.name.decode("ascii", "replace") if isinstance(m.name, bytes) else str(m.name)
        if name.rstrip("\x00") == "wrench":
            d = [float(x) for x in m.data[:12]]
            self.wrench_demand, self.wrench_achieved = tuple(d[:6]), tuple(d[6:12])

    def _servo(self, m, now_s):
        if self.vehicle is None or m.port != 0:
            return
        self._pwm = m  # mapped to jets only when a snapshot asks (keeps ingest cheap)
        self.command_u = None

    def _pressure(self, m, now_s):
        # hydrostatic depth below the surface, p = p_atm + rho g z (ArduSub's default water)
        self.pressure_depth_m = (float(m.press_abs) * 100.0 - ATMOSPHERE_PA) / RHO_G

    def _local_position(self, m, now_s):
        self.velocity_ned = (float(m.vx), float(m.vy), float(m.vz))

    def _vfr_hud(self, m, now_s):
        self.groundspeed = float(m.groundspeed)

    def _sys_status(self, m, now_s):
        present = int(m.onboard_control_sensors_present)
        missing = present & ~int(m.onboard_control_sensors_health)
        self.health_missing = tuple(n for bit, n in HEALTH_BITS.items() if missing & bit)

    def _command_ack(self, m, now_s):
        sent = self._pending.pop(int(m.command), None)
        if sent is not None:
            self.rtt_s = now_s - sent
        self._event(now_s, f"command {int(m.command)}: {MAV_CMD_ACK_NAMES.get(int(m.result), m.result)}")

    def _statustext(self, m, now_s):
        text = m.text.decode("ascii", "replace") if isinstance(m.text, bytes) else str(m.text)
        self._event(now_s, f"vehicle says: {printable(text.rstrip(chr(0)))}")

    def _delay(self, now_s: float, vehicle_t: float, window_s: float = 10.0) -> None:
        """Arrival minus vehicle time, above its minimum over the last `window_s` (a window, so
        the slow drift between the two clocks does not pile up as false delay)."""
        offset = now_s - vehicle_t
        w = self._offsets
        while w and (w[-1][1] >= offset or now_s - w[0][0] > window_s):  # monotonic min-queue
            if w[-1][1] >= offset:
                w.pop()
            else:
                w.popleft()
        w.append((now_s, offset))
        self.delay_jitter_s = offset - w[0][1]

    def _event(self, now_s: float, text: str) -> None:
        self.events.append((now_s, text))

    # -- output --------------------------------------------------------------------------------
    def _jets(self) -> Jets | None:
        if self.vehicle is None or self._pwm is None:
            return None
        from onboard.model import jet_thrust
        from onboard.pwm import pwm_to_command

        if self.command_u is None:
            m = self._pwm
            self.command_u = pwm_to_command(self.vehicle, [getattr(m, f"servo{c}_raw", 0) or 0 for c in range(1, 17)])

        k = self.vehicle.n_units
        u = self.command_u
        thrust = tuple(float(jet_thrust(float(n), 0.0, self._params)) for n in u[:k])
        return Jets(thrust, tuple(map(float, u[:k])), tuple(map(float, u[k:2 * k])), tuple(map(float, u[2 * k:3 * k])))

    def warnings(self, now_s: float) -> tuple:
        """Out-of-bounds conditions now, worst first; each newly raised one is logged once."""
        L, v, w = self.limits, self.values, []  # (key, text): a key is logged once while raised
        if not self.link_up:
            w.append(("link", "LINK LOST" if self.last_rx_s is not None else "no link yet"))
        if v.get("failsafe", 0.0) >= 0.5:
            w.append(("failsafe", "FAILSAFE active"))
        if self.health_missing:
            w.append(("health", "unhealthy: " + ", ".join(self.health_missing)))
        roll, pitch, _ = self.attitude
        if max(abs(roll), abs(pitch)) > L.tilt_rad:
            w.append(("tilt", f"tilt {math.degrees(max(abs(roll), abs(pitch))):.0f} deg > "
                              f"{math.degrees(L.tilt_rad):.0f}"))
        d, dsp = self._depth(), v.get("depth_sp", math.nan)
        if abs(d - dsp) > L.depth_error_m:
            w.append(("depth", f"depth error {d - dsp:+.2f} m"))
        if v.get("alloc_err", 0.0) > L.allocation_residual:
            w.append(("alloc", f"allocation residual {v['alloc_err']:.2f}"))
        if v.get("step_ms", 0.0) > L.step_ms:
            w.append(("step", f"control step {v['step_ms']:.1f} ms > {L.step_ms:.0f}"))
        loss = self._loss()
        if loss > L.loss_fraction:
            w.append(("loss", f"packet loss {100 * loss:.1f} %"))
        if self.delay_jitter_s > L.delay_jitter_s:
            w.append(("late", f"telemetry {self.delay_jitter_s:.2f} s late"))
        jets = self._jets()
        if jets is not None:
            lim = L.joint_fraction * self.vehicle.servo.angle_limit
            for i, (a, b) in enumerate(zip(jets.azimuth_rad, jets.elevation_rad)):
                if abs(a) > lim or abs(b) > lim:
                    w.append((f"joint{i}", f"jet {i + 1} joint at its limit"))
        for key, text in w:
            if key not in self._active:
                self._event(now_s, "WARNING " + text)
        self._active = {key for key, _ in w}
        return tuple(text for _, text in w)

    def _depth(self) -> float:
        return self.values.get("depth", self.pressure_depth_m)

    def _loss(self) -> float:
        lost = sum(s.lost for s in self.sources.values())
        got = sum(s.received for s in self.sources.values())
        return lost / (lost + got) if lost + got else 0.0

    def rate_hz(self, now_s: float, window_s: float = 2.0) -> float:
        n = sum(1 for t in self._arrivals if now_s - t <= window_s)
        return n / window_s

    def snapshot(self, now_s: float, n_events: int = 8) -> Snapshot:
        v, nan = self.values, math.nan
        vel = (v.get("u_est", self.groundspeed), nan, nan)
        if not math.isnan(self.velocity_ned[0]):
            vel = (v.get("u_est", self.velocity_ned[0]), self.velocity_ned[1], self.velocity_ned[2])
        dem, ach = np.asarray(self.wrench_demand), np.asarray(self.wrench_achieved)
        warnings = self.warnings(now_s)
        return Snapshot(
            vehicle=self.vehicle_id, vehicle_type=self.vehicle_type, armed=self.armed, mode=self.mode,
            system_status=self.system_status, attitude_rad=self.attitude, rates_rad_s=self.rates,
            depth_m=self._depth(), depth_setpoint_m=v.get("depth_sp", nan), yaw_setpoint_rad=v.get("yaw_sp", nan),
            velocity_m_s=vel, surge_setpoint_m_s=v.get("u_sp", nan), jets=self._jets(),
            wrench_demand=self.wrench_demand, wrench_achieved=self.wrench_achieved,
            residual_norm=float(np.linalg.norm(dem - ach)), allocation_error=v.get("alloc_err", nan),
            allocation_fallbacks=v.get("alloc_fb", nan), qp_us=v.get("qp_us", nan), step_ms=v.get("step_ms", nan),
            step_p99_ms=v.get("step_p99", nan),
            failsafe=None if "failsafe" not in v else v["failsafe"] >= 0.5,
            estimator_rejections=v.get("est_rej", nan), link_up=self.link_up, link_lost_count=self.link_lost_count,
            since_last_s=nan if self.last_rx_s is None else now_s - self.last_rx_s,
            packets=self.packets, lost=sum(s.lost for s in self.sources.values()), loss_fraction=self._loss(),
            garbage_bytes=self.garbage_bytes, bad_packets=self.bad_packets, rate_hz=self.rate_hz(now_s),
            rtt_s=self.rtt_s, delay_jitter_s=self.delay_jitter_s, warnings=warnings,
            events=tuple(list(self.events)[-n_events:]),
            faults=int(v["faults"]) if math.isfinite(v.get("faults", nan)) else None,  # a NaN mask: not known
        )
