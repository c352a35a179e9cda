"""The plant's MAVLink endpoint: plays the autopilot's sensor side for an onboard controller.

Each control period the endpoint advances the plant, sends what an ArduSub autopilot would
(HEARTBEAT at 1 Hz; SCALED_PRESSURE2, ATTITUDE, HIGHRES_IMU at their sensor rates; every period
SERVO_OUTPUT_RAW of the command in force and ESC telemetry of the propellers) and then
SYSTEM_TIME, whose time_boot_ms marks "everything up to this instant has been sent". So the
recording holds, from the vehicle (system 1, component 1), every stream spec/recording.md needs. It applies the actuator commands it receives: HIL_ACTUATOR_CONTROLS
(normalised: jets 0..1, joints -1..1, onboard.pwm) or, with `actuators="pwm"`, the PWM of
SERVO_OUTPUT_RAW through the vehicle's [pwm] maps.

Modes:
- lock-step: after the marker of instant t_k the plant waits for the command stamped t_k
  (HIL_ACTUATOR_CONTROLS.time_usec, or SERVO_OUTPUT_RAW.time_usec) before it advances to
  t_k+1. Nothing depends on the wall clock, so the same seed gives the same recording byte for
  byte, as fast as the CPU allows.
- real time: the plant follows the wall clock and applies whatever command has arrived.

Ground setpoints of a scripted mission are injected in vehicle time, as a ground station's
messages routed through the autopilot (system 255), so a mission is deterministic in lock-step.
The recording (.tlog, hil.tlog) holds everything sent and received, stamped with vehicle time,
plus the pool's motion-capture truth (ATT_POS_MOCAP) at the attitude rate, never sent.

Joint angle feedback: ACTUATOR_OUTPUT_STATUS at the attitude rate with the plant's actual joint
angles (smart servos report their position; onboard.mavlink_codec.encode_joint_angles).

Faults (hil.faults.FaultPlan, `faults=`): link faults wrap the link in a hil.faults.FaultyLink
(then the recording holds what crossed it); a dead, weak or stuck actuator changes the command
the plant executes (SERVO_OUTPUT_RAW still reports what the controller commanded; the ESC rpm and
the joint feedback show what the actuators do); IMU freeze/NaN and depth jumps change the sensor
messages. Each fault's start (and end) is marked in the recording by a never-sent STATUSTEXT
"INJECT ..." from the fault injector, system 1 component 250.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field, replace

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from onboard import mavlink_codec as codec
from onboard.pwm import command_to_pwm, normalised_to_command, pwm_to_command
from onboard.vehicle import Vehicle

from .faults import (
    INJECTOR_COMPONENT,
    INJECTOR_SYSTEM,
    LOCKSTEP_EXEMPT,
    FaultPlan,
    FaultyLink,
    actuator_command,
    imu_fault,
    injection_events,
    joint_index,
    pressure_offset_pa,
)
from .tlog import FIXED_EPOCH_US

GCS_SYSTEM = 255
GCS_COMPONENT = 190
SERVO_TIME_WRAP = 1 << 32


class EndpointError(RuntimeError):
    """The controller on the other side stopped answering (lock-step) or never appeared."""


Faults = FaultPlan  # the older name: Faults(imu_dropouts_s=..., garbage_times_s=..., garbage_bytes=...)


@dataclass
class EndpointStats:
    periods: int = 0
    commands_applied: int = 0
    commands_late: int = 0  # real time: periods that ended with no new command
    resends: int = 0  # lock-step: markers sent again after a reply timeout
    stale_replies: int = 0  # commands stamped for an earlier period
    bad_commands: int = 0  # non-finite or malformed commands, ignored
    sent: dict = field(default_factory=dict)
    received: dict = field(default_factory=dict)


class HilEndpoint:
    """Plant + link: `start()`, then `step()` per control period, or `run(duration_s)`."""

    def __init__(
        self,
        vehicle: Vehicle,
        link,
        plant,
        control_period_s: float = 0.01,
        lockstep: bool = True,
        actuators: str = "hil",
        setpoints=(),
        faults: FaultPlan = FaultPlan(),
        tlog=None,
        reply_timeout_s: float = 0.5,
        give_up_s: float = 10.0,
        seed: int = 0,
        on_period=None,
        history: bool = True,
        abort=None,
        signing_key: bytes | None = None,
    ):
        """`abort()`: None while the controller may still answer, else why it never will (e.g. its
        process died); checked while waiting for it, so a dead controller fails at once.
        `signing_key`: sign everything sent (sensors and the injected ground setpoints), as an
        autopilot with MAVLink 2 signing does; a robot with that key refuses anything unsigned."""
        if actuators not in ("hil", "pwm"):
            raise ValueError(f"actuators must be 'hil' or 'pwm', got {actuators!r}")
        self.vehicle = vehicle
        self.link = link
        self.plant = plant
        self.period_s = float(control_period_s)
        self.lockstep = lockstep
        self.actuators = actuators
        self.setpoints = sorted(setpoints, key=lambda p: p[0])  # [(t_s, pymavlink message)]
        self._next_setpoint = 0
        faults.check_units(vehicle.n_units)
        self.faults = faults
        self.tlog = tlog
        self.reply_timeout_s = reply_timeout_s
        self.give_up_s = give_up_s
        self.on_period = on_period
        self.abort = abort
        self.k = 0
        self.stats = EndpointStats()
        self._marker_packet = b""  # the last frame marker, re-sent as is when a reply is late
        self.history = history  # keep truth and commands (off for long runs: they grow)
        self.truth: list = []  # TruthSample at the IMU instants
        self.commands: list = []  # (t_s, command vector applied from t_s)
        self._gcs = mavlink.MAVLink(None, srcSystem=GCS_SYSTEM, srcComponent=GCS_COMPONENT)
        self._rng = np.random.default_rng(seed + 7919)
        self._garbage_due = sorted(faults.garbage_times_s)
        self._next_heartbeat_s = 0.0
        self._mocap_period_s = 1.0 / vehicle.sensors.attitude_rate
        self._next_mocap_s = 0.0
        self._answered_us = -1
        self._applied_at_s = 0.0  # vehicle time the command in force was applied
        self._wall0 = None
        self._commanded = np.array(plant.command, dtype=float)  # the controller's (before actuator faults)
        self._stuck_rad: dict = {}  # (unit, joint) -> angle at the fault's onset
        self._frozen_imu = None  # the last good IMU sample before a freeze
        self._last_imu = None
        self._next_joints_s = 0.0
        self._arrived_us = -1  # lock-step: newest command stamp that reached the fault injector
        self._injector = codec.make_mavlink(INJECTOR_SYSTEM, INJECTOR_COMPONENT)
        self._signing = []  # the packers that sign (their timestamps follow the clock each frame)
        if signing_key is not None:
            from onboard.signing import enable_signing

            self._signing = [getattr(link, "inner", link).mav, self._gcs]
            for i, mav in enumerate(self._signing):
                enable_signing(mav, signing_key, link_id=i)
        self._marks = injection_events(faults)
        self._actuator_faults = bool(faults.jets or faults.stuck_joints)
        self._rho_g = (vehicle.environment.rho, vehicle.environment.g)
        self._tapped = faults.link_faults
        if faults.link_faults:
            self.link = FaultyLink(link, faults, clock=lambda: self.time_s, seed=seed,
                                   exempt=LOCKSTEP_EXEMPT if lockstep else (),
                                   tap=self._tap, on_arrival=self._note_arrival)

    # -- time ----------------------------------------------------------------------------------
    @property
    def time_s(self) -> float:
        return self.k * self.period_s

    def _stamp_us(self, t_s: float) -> int:
        return FIXED_EPOCH_US + int(round(t_s * 1e6))

    # -- recording -----------------------------------------------------------------------------
    def _record(self, packet: bytes, t_s: float, msg_type: str) -> None:
        if self.tlog is not None:
            self.tlog.write_packet(packet, self._stamp_us(t_s), msg_type)

    def _send(self, msg, t_s: float) -> bytes:
        packet = self.link.send(msg)
        name = msg.get_type()
        self.stats.sent[name] = self.stats.sent.get(name, 0) + 1
        if not self._tapped:  # a FaultyLink records what goes onto the wire itself (_tap)
            self._record(packet, t_s, name)
        return packet

    def _tap(self, packet: bytes, name: str) -> None:
        self._record(packet, self.time_s, name)

    def _mark(self, text: str, t_s: float) -> None:
        """A never-sent STATUSTEXT from the fault injector into the recording."""
        if self.tlog is not None:
            msg = mavlink.MAVLink_statustext_message(mavlink.MAV_SEVERITY_NOTICE, text.encode()[:50], 0, 0)
            self.tlog.write_packet(codec.encode(self._injector, msg), self._stamp_us(t_s), "STATUSTEXT")

    def _send_as_gcs(self, msg, t_s: float) -> None:
        packet = bytes(msg.pack(self._gcs))
        self._gcs.seq = (self._gcs.seq + 1) % 256
        self.link.write_raw(packet)
        name = msg.get_type()
        self.stats.sent[name] = self.stats.sent.get(name, 0) + 1
        self._record(packet, t_s, name)

    # -- start ---------------------------------------------------------------------------------
    def start(self, wait_s: float = 10.0) -> None:
        """Wait until the controller speaks (a udpin link learns its address from it)."""
        deadline = time.monotonic() + wait_s
        raw = getattr(self.link, "inner", self.link)  # the handshake is not subject to link faults
        while not raw.has_peer:
            self._check_abort()
            if time.monotonic() > deadline:
                raise EndpointError(f"no controller spoke on {self.link.connection} within {wait_s:.0f} s")
            m = raw.recv(0.1)
            if m is not None:
                self._handle(m, self.time_s, record=False)  # the handshake is not the flight
        self._wall0 = time.monotonic()

    def _check_abort(self) -> None:
        why = self.abort() if self.abort is not None else None
        if why:
            raise EndpointError(why)

    # -- one control period ----------------------------------------------------------------------
    def step(self) -> None:
        """Send everything up to t_k, take the command for t_k, advance the plant to t_k+1."""
        t = self.time_s
        samples = self.plant.advance(t + 1e-9)
        if self.history:
            self.truth.extend(samples.truth)
        with self.link.batch():  # one datagram per frame
            self._emit(t, samples)
        if self.lockstep:
            self._await_command(t)
        else:
            self._drain_until(self._wall0 + t + self.period_s, t)
        if self._actuator_faults:  # a fault begins at its t0 whether or not a command came
            self._command_plant(t)
        self.stats.periods += 1
        if self.on_period is not None:
            self.on_period(self)
        self.k += 1

    def run(self, duration_s: float, stop=None) -> None:
        """Periods until `duration_s` of vehicle time (or until `stop()` is true)."""
        if self._wall0 is None:
            self.start()
        n = int(round(duration_s / self.period_s))
        while self.k < n and not (stop is not None and stop()):
            self.step()

    def _emit(self, t: float, samples) -> None:
        if self._signing:  # pymavlink adds 10 us per packet: keep the signing time on the clock
            from onboard.signing import refresh_timestamp

            for mav in self._signing:
                refresh_timestamp(mav)
        while self._marks and self._marks[0][0] <= t + 1e-9:
            self._mark(self._marks.pop(0)[1], t)
        if t + 1e-9 >= self._next_heartbeat_s:
            self._send(codec.heartbeat(armed=True), t)
            self._next_heartbeat_s += 1.0
        while self._next_setpoint < len(self.setpoints) and self.setpoints[self._next_setpoint][0] <= t + 1e-9:
            self._send_as_gcs(self.setpoints[self._next_setpoint][1], t)
            self._next_setpoint += 1
        # recorded at the frame's time t (a burst received at once; each message carries its own
        # sample time), so the .tlog's clock never goes back whatever the rates
        f = self.faults
        for s in samples.pressure:
            if f.depth_jumps:
                s = replace(s, press_abs_pa=s.press_abs_pa + pressure_offset_pa(f, s.time_s, *self._rho_g))
            self._send(codec.encode_pressure(s), t)
        for s in samples.attitude:
            self._send(codec.encode_attitude(s), t)
        for s in samples.imu:
            if any(t0 <= s.time_s < t1 for t0, t1 in f.imu_dropouts_s):
                continue
            self._send(self._imu_message(s), t)
        if t + 1e-9 >= self._next_joints_s:  # the servos' measured angles, at the attitude rate
            self._next_joints_s += self._mocap_period_s
            x, lay = self.plant.state, self.plant.layout
            self._send(codec.encode_joint_angles(t, x[lay.alpha], x[lay.beta]), t)
        # what the autopilot outputs: SERVO_OUTPUT_RAW of the command in force, stamped with the
        # time it took effect (the previous frame's answer), and the propellers' rpm now
        act = self.plant.actuators(command_to_pwm(self.vehicle, self._commanded))
        if self.stats.commands_applied:  # nothing to report before the first command
            self._send(codec.encode_actuators(replace(act, time_s=self._applied_at_s))[0], t)
        for msg in codec.encode_actuators(act)[1:]:
            self._send(msg, t)
        if self.tlog is not None and t + 1e-9 >= self._next_mocap_s:
            self._next_mocap_s += self._mocap_period_s
            x = self.plant.state
            mocap = mavlink.MAVLink_att_pos_mocap_message(
                codec.time_usec(t), [float(c) for c in x[3:7]], float(x[0]), float(x[1]), float(x[2]), [float("nan")] + [0.0] * 20
            )
            self.tlog.write(mocap, self._stamp_us(t))
        while self._garbage_due and self._garbage_due[0] <= t + 1e-9:
            self._garbage_due.pop(0)
            self.link.write_raw(self._rng.integers(0, 256, self.faults.garbage_bytes, dtype=np.uint8).tobytes())
        self._marker_packet = self._send(mavlink.MAVLink_system_time_message(0, codec.time_boot_ms(t)), t)

    def _imu_message(self, s):
        """HIGHRES_IMU of sample s, frozen (the last good values, fresh stamp) or NaN when a fault says."""
        fault = imu_fault(self.faults, s.time_s) if (self.faults.imu_freeze_s or self.faults.imu_nan_s) else None
        if fault == "nan":
            nan = float("nan")
            return mavlink.MAVLink_highres_imu_message(
                codec.time_usec(s.time_s), nan, nan, nan, nan, nan, nan,
                0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, codec.HIGHRES_IMU_ACCEL_GYRO, 0)
        if fault == "freeze":
            if self._frozen_imu is None:
                self._frozen_imu = self._last_imu if self._last_imu is not None else s
            return codec.encode_imu(replace(self._frozen_imu, time_s=s.time_s))
        self._frozen_imu = None
        self._last_imu = s
        return codec.encode_imu(s)

    # -- commands --------------------------------------------------------------------------------
    def _note_arrival(self, m) -> None:
        """A message reached the fault injector: a command counts as the controller's answer."""
        name = m.get_type()
        if name == "HIL_ACTUATOR_CONTROLS" and self.actuators == "hil":
            self._arrived_us = max(self._arrived_us, int(m.time_usec))
        elif name == "SERVO_OUTPUT_RAW" and self.actuators == "pwm":
            self._arrived_us = max(self._arrived_us, self._unwrap(int(m.time_usec), self.time_s))

    def _await_command(self, t: float) -> None:
        want_us = codec.time_usec(t)
        waited = 0.0
        while max(self._answered_us, self._arrived_us) < want_us:
            before = getattr(self.link, "arrivals", 0)
            m = self.link.recv(self.reply_timeout_s)
            if m is None:
                if getattr(self.link, "arrivals", 0) != before:
                    continue  # it came, and the fault injector lost it or holds it back
                waited += self.reply_timeout_s
                self._check_abort()
                if waited >= self.give_up_s:
                    raise EndpointError(
                        f"lock-step: no actuator command for t = {t:.3f} s within {self.give_up_s:.0f} s "
                        f"on {self.link.connection}"
                    )
                # The marker may have been lost: send the same packet again (same sequence
                # number) and do not record it, so a slow controller (e.g. compiling on its first
                # start) leaves the recording byte for byte what a fast one would.
                self.stats.resends += 1
                self.link.write_raw(self._marker_packet)
                continue
            self._handle(m, t)

    def _drain_until(self, wall_deadline: float, t: float) -> None:
        before = self.stats.commands_applied
        while True:
            left = wall_deadline - time.monotonic()
            m = self.link.recv(max(left, 0.0))
            if m is not None:
                self._handle(m, t)
            if left <= 0:
                break
        if self.stats.commands_applied == before:
            self.stats.commands_late += 1

    def _handle(self, m, t: float, record: bool = True) -> None:
        name = m.get_type()
        self.stats.received[name] = self.stats.received.get(name, 0) + 1
        if record:
            self._record(bytes(m.get_msgbuf()), t, name)
        if name == "HIL_ACTUATOR_CONTROLS" and self.actuators == "hil":
            stamp = int(m.time_usec)
            controls = np.asarray(m.controls[: 3 * self.vehicle.n_units], dtype=float)
            if not np.all(np.isfinite(controls)):
                self.stats.bad_commands += 1
                return
            self._apply(normalised_to_command(self.vehicle, controls), stamp, t)
        elif name == "SERVO_OUTPUT_RAW" and self.actuators == "pwm":
            pwm = [getattr(m, f"servo{i}_raw", 0) or 0 for i in range(1, 17)]
            self._apply(pwm_to_command(self.vehicle, pwm), self._unwrap(int(m.time_usec), t), t)

    def _unwrap(self, stamp32: int, t: float) -> int:
        now = codec.time_usec(t)
        base = now - (now % SERVO_TIME_WRAP)
        stamp = base + stamp32
        return stamp - SERVO_TIME_WRAP if stamp > now + SERVO_TIME_WRAP // 2 else stamp

    def _apply(self, command, stamp_us: int, t: float) -> None:
        if self.lockstep and stamp_us < self._answered_us:
            self.stats.stale_replies += 1
            return
        self._commanded = np.asarray(command, dtype=float).copy()
        self._command_plant(t)
        self._applied_at_s = t
        if self.history:
            self.commands.append((t, np.asarray(command, dtype=float).copy()))
        self._answered_us = max(self._answered_us, stamp_us)
        self.stats.commands_applied += 1

    def _command_plant(self, t: float) -> None:
        """The controller's command through the actuator faults in force at t, into the plant."""
        if not self._actuator_faults:
            self.plant.set_command(self._commanded)
            return
        k = self.vehicle.n_units
        x, lay = self.plant.state, self.plant.layout
        for s in self.faults.stuck_joints:
            if t + 1e-9 >= s.t0_s and (s.unit, s.joint) not in self._stuck_rad:
                angles = np.concatenate([x[lay.alpha], x[lay.beta]])
                self._stuck_rad[(s.unit, s.joint)] = float(angles[joint_index(k, s.unit, s.joint)])
        self.plant.set_command(actuator_command(self.faults, self._commanded, t, self._stuck_rad))
