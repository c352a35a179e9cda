"""The onboard loop: MAVLink sensors in, estimate -> control -> compensate -> allocate, commands out.

The loop takes its clock and its link as arguments (DESIGN.md), so the same code runs against a
socket, a serial line, a log replay or the HIL in lock-step:
- `WallClock`: control ticks follow the monotonic clock (a real autopilot, `jetloop hil --realtime`).
- `VehicleClock`: time is the newest vehicle time seen in the sensor stream (HIGHRES_IMU.time_usec,
  SCALED_PRESSURE2/ATTITUDE/SYSTEM_TIME.time_boot_ms), so a control tick happens when the stream
  says that instant has come: lock-step HIL and log replay, deterministic.

Inputs: HIGHRES_IMU (or SCALED_IMU / SCALED_IMU2 / RAW_IMU, the best one present is used),
SCALED_PRESSURE2 (depth), ATTITUDE; ground setpoints SET_POSITION_TARGET_LOCAL_NED (depth z and
yaw in MAV_FRAME_LOCAL_NED; body velocity in a body frame, or NED velocity rotated by the
estimated yaw), MANUAL_CONTROL (joystick: surge, sway, heave and yaw-rate demands), COMMAND_LONG
(MAV_CMD_COMPONENT_ARM_DISARM; MAV_CMD_DO_SET_MODE, custom mode in param2), answered with
COMMAND_ACK. Anything that cannot be decoded (NaN, wrong type) is counted and ignored.
Every message first passes `CommandGate.admit(msg, link)` (onboard.signing): sensor data counts
only from the autopilot on the main link, with a key every message must be signed; and a sensor
stamp far from the stream's time is held by `StampGuard` until the stream confirms it (issue 15).

Outputs every control tick: HIL_ACTUATOR_CONTROLS (jets 0..1, azimuths then elevations -1..1;
`output="hil"`) and SERVO_OUTPUT_RAW (the PWM of the vehicle's [pwm] table; with `output="pwm"`
that is the actuator command itself, for a serial PWM board). Telemetry for the ground (on the
ground link when there is one, else on the main link): HEARTBEAT (MAV_TYPE_SUBMARINE) and
SYS_STATUS at 1 Hz, ATTITUDE, NAMED_VALUE_FLOAT (depth, setpoints, allocation status,
estimator rejections, loop timing) and a DEBUG_FLOAT_ARRAY "wrench" (demanded and achieved
body wrench) at `telemetry_rate_hz`; STATUSTEXT when the failsafe trips or clears.

Faults (issue #7, onboard.monitor): every received packet's sequence number, every sensor
sample's age and values, ESC_TELEMETRY rpm and ACTUATOR_OUTPUT_STATUS joint angles feed a
`FaultMonitor`, ticked with each command sent. NAMED_VALUE_FLOAT "faults" (the `Fault` bitmask)
goes out with the other named values, STATUSTEXT "FAULT ..." / "CLEARED ..." on each change,
SYS_STATUS health bits (motor outputs, gyro/accel, pressure) and drop_rate_comm follow the flags.
A frozen IMU's samples reach neither the estimator nor the failsafe's freshness (which trips);
a dead or weak jet and a stuck joint are handed to the allocator (`set_health`).
"""

from __future__ import annotations

import gc
import math
import resource
import time
from collections import deque
from dataclasses import dataclass, field, replace
from itertools import islice

# CPU time (this thread's) spent in the cyclic garbage collector, so that an overrun can be put
# down to a collection or not (a full pass over the ~170 000 objects numba, OSQP and pymavlink
# leave behind measures 57-168 ms). One callback per process, whatever the number of loops.
_gc_cpu_s = [0.0, 0.0]  # [total, start of the collection under way]


def _gc_timer(phase, info) -> None:
    if phase == "start":
        _gc_cpu_s[1] = time.thread_time()
    else:
        _gc_cpu_s[0] += time.thread_time() - _gc_cpu_s[1]


gc.callbacks.append(_gc_timer)

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from . import mavlink_codec as codec
from .control import ManualAxes, Setpoint
from .mavlink_codec import CodecError
from .pwm import command_to_normalised, command_to_pwm
from .sensors import depth_from_pressure
from .history import PairRing, Ring
from .vehicle import Vehicle
from .signing import GCS_SYSTEMS, SecurityCounts

IMU_RANK = {"HIGHRES_IMU": 0, "SCALED_IMU": 1, "SCALED_IMU2": 2, "SCALED_IMU3": 3, "RAW_IMU": 4}
BODY_FRAMES = (mavlink.MAV_FRAME_BODY_NED, mavlink.MAV_FRAME_BODY_OFFSET_NED, mavlink.MAV_FRAME_BODY_FRD)
# SET_POSITION_TARGET_LOCAL_NED.type_mask bits (POSITION_TARGET_TYPEMASK)
IGNORE_X, IGNORE_Y, IGNORE_Z = 1, 2, 4
IGNORE_VX, IGNORE_VY, IGNORE_VZ = 8, 16, 32
IGNORE_YAW, IGNORE_YAW_RATE = 1024, 2048
# Modes (HEARTBEAT.custom_mode, MAV_CMD_DO_SET_MODE param2): ArduSub's numbers where it has them
MODES = {"stabilize": 0, "depth_hold": 2, "guided": 4, "manual": 19}
MODE_NAMES = {v: k for k, v in MODES.items()}
HISTORY = 360_000  # control steps of statistics kept (one hour at 100 Hz)
TELEMETRY_STREAMS = ("ATTITUDE", "NAMED_VALUE_FLOAT", "DEBUG_FLOAT_ARRAY")  # at telemetry_rate_hz unless asked


# ------------------------------------------------------------------------------------------------
# Clocks


class WallClock:
    """Real time: seconds since construction on the monotonic clock."""

    lockstep = False

    def __init__(self):
        self._t0 = time.monotonic()

    def now(self) -> float:
        return time.monotonic() - self._t0

    def wait_s(self, t_next: float) -> float:
        return max(0.0, t_next - self.now())

    def observe(self, t_vehicle: float) -> None:
        pass

    def rebase(self, t_vehicle: float) -> None:
        pass


class VehicleClock:
    """Lock-step / replay: the newest vehicle time the sensor stream has reached."""

    lockstep = True

    def __init__(self, block_s: float = 0.5):
        self._t = -math.inf
        self.block_s = block_s

    def now(self) -> float:
        return self._t

    def wait_s(self, t_next: float) -> float:
        return self.block_s  # only a message can move time on

    def observe(self, t_vehicle: float) -> None:
        if t_vehicle > self._t:
            self._t = t_vehicle

    def rebase(self, t_vehicle: float) -> None:
        """The sensor stream's time base moved (StampGuard re-anchored): time is where it now is."""
        self._t = t_vehicle


class StampGuard:
    """Sensor time stamps against the newest one accepted: a stamp more than `max_skew_s` away from
    it (ahead or behind) is held back, not believed, until `confirm` such stamps in a row agree
    with each other within `max_skew_s`; then the stream really moved (an autopilot reboot, a gap
    in a replayed log) and the guard re-anchors on it. So one stamp far in the future, corrupt or
    hostile, never moves the clock or the IMU ordering on (issue 15: a lone HIGHRES_IMU stamped
    1e12 us made every later real sample "out of order" and tripped the failsafe for good), and
    a real jump costs `confirm` samples. `admit(t, now=None)` -> "ok", "held" or "rebased".

    The rule against stamps a little ahead (issue 15, second pass):
    - the skew must be below the IMU failsafe's timeout (LoopConfig checks it): a stamp accepted
      ahead drops the real samples before it as out of order, and that may not last a timeout;
    - in real time (`now`: the loop's own clock) the stream may not run ahead of that clock: its
      offset (stamp - now) is tracked, following drift at most `rate_tolerance` (1 %, a crystal
      drifts 1e-4) of the time passed, and a stamp more than `max_skew_s` ahead of the tracked
      offset is held; held stamps confirm a new time base only when they agree on one offset
      (not merely with each other), so a walk of stamps each a little ahead of the last gets
      one step in and no further (each step below the skew; a walk slow enough to agree with
      itself over `confirm` samples re-anchors, and every re-anchor is counted, time_rebases);
    - in lock-step (`now` None) the stream is the clock, so only the skew bounds a step.
    """

    def __init__(self, max_skew_s: float = 1.0, confirm: int = 3, rate_tolerance: float = 0.01):
        self.max_skew_s = float(max_skew_s)
        self.confirm = int(confirm)
        self.rate_tolerance = float(rate_tolerance)
        self.newest = -math.inf
        self._candidate = None  # (first, newest, count, offset of the first) of stamps that disagree with `newest`
        self._offset = None  # (stamp - now, now) in real time: the stream's offset from the loop's clock, and when
        self.held = 0  # stamps held back (never believed)
        self.rebases = 0

    def _ahead(self, t: float, now: float | None) -> bool:
        if now is None or self._offset is None:
            return False
        off, at = self._offset
        return (t - now) - off > self.max_skew_s + self.rate_tolerance * max(0.0, now - at)

    def _track(self, t: float, now: float | None, reset: bool = False) -> None:
        if now is None:
            return
        if self._offset is None or reset:
            self._offset = (t - now, now)
            return
        off, at = self._offset
        step = self.rate_tolerance * max(0.0, now - at)  # the offset follows drift, never a jump
        self._offset = (min(max(t - now, off - step), off + step), now)

    def admit(self, t: float, now: float | None = None) -> str:
        if self.newest == -math.inf or (abs(t - self.newest) <= self.max_skew_s and not self._ahead(t, now)):
            self._candidate = None  # the stream goes on where it was: a held stamp was a lone one
            self.newest = max(self.newest, t)
            self._track(t, now)
            return "ok"
        c = self._candidate
        off = None if now is None else t - now
        if c is None:
            agrees = False
        elif now is None or c[3] is None:
            agrees = abs(t - c[1]) <= self.max_skew_s
        else:
            agrees = abs(off - c[3]) <= self.max_skew_s  # one time base: one offset from the loop's clock
        c = (c[0], max(c[1], t), c[2] + 1, c[3]) if agrees else (t, t, 1, off)
        if c[2] >= self.confirm:
            self._candidate = None
            self.newest = c[1]
            self._track(t, now, reset=True)
            self.rebases += 1
            return "rebased"
        self._candidate = c
        self.held += 1
        return "held"


# ------------------------------------------------------------------------------------------------
# Setpoints: ground messages <-> the demand the loop flies


def depth_yaw_target(depth_m: float | None = None, yaw_rad: float | None = None, time_boot_ms: int = 0):
    """SET_POSITION_TARGET_LOCAL_NED carrying depth (NED z below the surface) and/or yaw."""
    mask = IGNORE_X | IGNORE_Y | IGNORE_VX | IGNORE_VY | IGNORE_VZ | 0b111000000 | IGNORE_YAW_RATE
    if depth_m is None:
        mask |= IGNORE_Z
    if yaw_rad is None:
        mask |= IGNORE_YAW
    return mavlink.MAVLink_set_position_target_local_ned_message(
        time_boot_ms, 1, 1, mavlink.MAV_FRAME_LOCAL_NED, mask,
        0.0, 0.0, float(depth_m or 0.0), 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, float(yaw_rad or 0.0), 0.0,
    )


def body_velocity_target(u_m_s: float, v_m_s: float = 0.0, time_boot_ms: int = 0):
    """SET_POSITION_TARGET_LOCAL_NED carrying a body-frame (FRD) horizontal velocity only."""
    mask = IGNORE_X | IGNORE_Y | IGNORE_Z | IGNORE_VZ | 0b111000000 | IGNORE_YAW | IGNORE_YAW_RATE
    return mavlink.MAVLink_set_position_target_local_ned_message(
        time_boot_ms, 1, 1, mavlink.MAV_FRAME_BODY_FRD, mask,
        0.0, 0.0, 0.0, float(u_m_s), float(v_m_s), 0.0, 0.0, 0.0, 0.0, 0.0, 0.0,
    )


def arm_command(arm: bool = True):
    return mavlink.MAVLink_command_long_message(
        1, 1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1.0 if arm else 0.0, 0, 0, 0, 0, 0, 0
    )


def mode_command(mode: str):
    return mavlink.MAVLink_command_long_message(
        1, 1, mavlink.MAV_CMD_DO_SET_MODE, 0, float(mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED),
        float(MODES[mode]), 0, 0, 0, 0, 0,
    )


def apply_position_target(sp: Setpoint, msg, yaw_estimate_rad: float) -> Setpoint:
    """A SET_POSITION_TARGET_LOCAL_NED on top of the current setpoint (only the fields not ignored).

    z is the depth (NED z below the surface) unless the frame is a body frame; yaw in NED;
    vx, vy body velocities in a body frame, NED velocities (rotated by the estimated yaw) otherwise;
    vz (with z ignored) a heave velocity. A position target ends joystick control.
    """
    mask = int(msg.type_mask)
    if msg.coordinate_frame not in (mavlink.MAV_FRAME_LOCAL_NED,) + BODY_FRAMES:  # never read another as NED
        raise CodecError(f"setpoint refused: frame {msg.coordinate_frame} unsupported")
    body = msg.coordinate_frame in BODY_FRAMES
    used = {"z": not mask & IGNORE_Z, "vx": not mask & IGNORE_VX, "vy": not mask & IGNORE_VY,
            "vz": not mask & IGNORE_VZ, "yaw": not mask & IGNORE_YAW}
    for name, read in used.items():  # an ignored field may be anything (senders often put NaN there)
        if read and not math.isfinite(float(getattr(msg, name))):
            raise CodecError(f"setpoint refused: {name} {float(getattr(msg, name))} not finite")
    depth, yaw = sp.depth_m, sp.yaw_rad
    u, v, w = sp.velocity_body_m_s
    if not mask & IGNORE_Z and not body:
        depth, w = float(msg.z), None
    if not mask & IGNORE_YAW:
        yaw = float(msg.yaw)
    if not (mask & IGNORE_VX and mask & IGNORE_VY):
        vx = 0.0 if mask & IGNORE_VX else float(msg.vx)
        vy = 0.0 if mask & IGNORE_VY else float(msg.vy)
        if not body:  # NED velocity: into the body by the estimated yaw
            c, s_ = math.cos(yaw_estimate_rad), math.sin(yaw_estimate_rad)
            vx, vy = c * vx + s_ * vy, -s_ * vx + c * vy
        u, v = vx, vy
    if not mask & IGNORE_VZ and mask & IGNORE_Z:
        depth, w = None, float(msg.vz)
    return Setpoint(depth_m=depth, yaw_rad=yaw, velocity_body_m_s=(u, v, w), manual=None)


def manual_axes(msg) -> ManualAxes:
    """MANUAL_CONTROL (+-1000; z 0..1000 with 500 neutral, up above 500, as ArduSub) -> stick axes."""
    for name in ("x", "y", "z", "r"):
        if not math.isfinite(float(getattr(msg, name))):
            raise CodecError(f"setpoint refused: manual {name} {float(getattr(msg, name))} not finite")
    return ManualAxes(surge=msg.x / 1000.0, sway=msg.y / 1000.0, heave_down=(500.0 - msg.z) / 500.0,
                      yaw_right=msg.r / 1000.0)


# ------------------------------------------------------------------------------------------------
# Configuration and statistics


@dataclass(frozen=True)
class LoopConfig:
    control_rate_hz: float = 100.0
    output: str = "hil"  # "hil": HIL_ACTUATOR_CONTROLS + SERVO_OUTPUT_RAW; "pwm": SERVO_OUTPUT_RAW only
    allocator: str = "qp"  # "qp" (OSQP) or "baseline" (pseudo-inverse with clipping)
    compensation: bool = True  # seed-004 azimuth-transient compensation
    imu_timeout_s: float = 0.3
    telemetry_rate_hz: float = 10.0
    qp_time_budget_s: float | None = None  # None: 1 ms in real time, unlimited in lock-step
    mode_at_start: str = "guided"
    compensation_iterations: int = 2
    yaw_preview: bool = True  # with compensation: cancel the azimuths' yaw reaction ahead (YawPreview)
    allocation_change_weight: float | None = None  # None: the allocator's default (AllocationConfig)
    estimator_backend: str = "filterpy"  # or "compiled": the same EKF equations in numba (onboard.estimator)
    signing_key: bytes | None = None  # MAVLink 2 signing on: unsigned commands refused (ground.commands)
    fault_monitor: bool = True  # onboard.monitor: detect, report and reconfigure around faults
    ground_systems: tuple = GCS_SYSTEMS  # source systems whose commands/setpoints count (others: foreign)
    autopilot: tuple | None = None  # (system, component 0=any) whose sensor data counts; None: the first component 1 sending sensor data on the main link
    max_stamp_skew_s: float = 0.2  # a sensor stamp further than this from the newest is held (StampGuard); < imu_timeout_s
    identity: str = "auto"  # to the ground: "vehicle" (component 1), "companion" (191), "auto" (onboard.microservices.Identity)
    parameter_file: str | None = None  # where MAVLink parameter sets persist and are read at start (onboard.params)

    def __post_init__(self):
        if not (math.isfinite(self.control_rate_hz) and self.control_rate_hz > 0):
            raise ValueError(f"control_rate_hz: expected a rate > 0 Hz, got {self.control_rate_hz!r}")
        if self.output not in ("hil", "pwm"):
            raise ValueError(f"output: expected 'hil' or 'pwm', got {self.output!r}")
        if self.allocator not in ("qp", "baseline"):
            raise ValueError(f"allocator: expected 'qp' or 'baseline', got {self.allocator!r}")
        if self.estimator_backend not in ("filterpy", "compiled"):
            raise ValueError(f"estimator_backend: expected 'filterpy' or 'compiled', got {self.estimator_backend!r}")
        if self.mode_at_start not in MODES:
            raise ValueError(f"mode_at_start: expected one of {sorted(MODES)}, got {self.mode_at_start!r}")
        if not (math.isfinite(self.max_stamp_skew_s) and self.max_stamp_skew_s > 0):
            raise ValueError(f"max_stamp_skew_s: expected a time > 0 s, got {self.max_stamp_skew_s!r}")
        if not self.max_stamp_skew_s < self.imu_timeout_s:  # a stamp accepted ahead must not starve the failsafe
            raise ValueError(f"max_stamp_skew_s {self.max_stamp_skew_s:g} s: expected below imu_timeout_s "
                             f"{self.imu_timeout_s:g} s (real samples behind a stamp accepted ahead are dropped)")


PHASES = ("estimate", "control", "allocate", "checks", "monitor")  # of a control step, in order (Overrun)


@dataclass(frozen=True)
class Overrun:
    """One control step over the period in CPU time, with what is needed to say where it went: the
    wall time of each phase (a NaN phase did not run: disarmed, or the step failed before it), the
    thread's user and system CPU, page faults and context switches over the step
    (getrusage(RUSAGE_THREAD)), the CPU in the garbage collector, and the samples the estimator fused."""

    t_s: float
    wall_ms: float
    cpu_ms: float
    gc_ms: float
    user_ms: float
    sys_ms: float
    minflt: int
    majflt: int
    nvcsw: int  # voluntary context switches (the thread waited)
    nivcsw: int  # involuntary (preempted)
    estimate_ms: float  # fusing the queued samples (and predicting between them)
    control_ms: float  # failsafe and controller
    allocate_ms: float  # compensate and allocate (QP)
    checks_ms: float  # limit checks and statistics
    monitor_ms: float  # fault monitor
    samples: int  # samples queued for the estimator

    @classmethod
    def of(cls, t, wall_s, cpu_s, gc_s, t0, marks, r0, r1, samples) -> "Overrun":
        ends = [t0, *marks]
        ph = [(b - a) * 1e3 for a, b in zip(ends, ends[1:])]  # NaN where a phase did not run
        return cls(t, wall_s * 1e3, cpu_s * 1e3, gc_s * 1e3, (r1.ru_utime - r0.ru_utime) * 1e3,
                   (r1.ru_stime - r0.ru_stime) * 1e3, r1.ru_minflt - r0.ru_minflt, r1.ru_majflt - r0.ru_majflt,
                   r1.ru_nvcsw - r0.ru_nvcsw, r1.ru_nivcsw - r0.ru_nivcsw, *ph, samples)

    def as_dict(self) -> dict:
        return {k: (None if v != v else round(v, 4)) if isinstance(v, float) else v for k, v in self.__dict__.items()}

    @classmethod
    def from_dict(cls, d: dict) -> "Overrun":
        return cls(**{k: math.nan if v is None else v for k, v in d.items()})

    def where(self) -> str:
        """The record in a line: CPU split, the longest phase, faults and switches."""
        ran = {p: getattr(self, p + "_ms") for p in PHASES}
        phases = {p: v for p, v in ran.items() if v == v}  # NaN: the phase did not run
        top = max(phases, key=phases.get) if phases else "none"
        return (f"t {self.t_s:.2f} s: CPU {self.cpu_ms:.1f} ms (user {self.user_ms:.1f}, system {self.sys_ms:.1f}, "
                f"GC {self.gc_ms:.1f}), longest phase {top} {phases.get(top, math.nan):.1f} ms, "
                f"{self.minflt} page faults, {self.nivcsw} preemptions, {self.samples} samples")


@dataclass
class LoopStats:
    steps: int = 0
    # Histories keep the newest `HISTORY` entries in arrays allocated up front (onboard.history.Ring),
    # so a robot running for hours does not grow: a deque of floats grew for its first hour (hil.soak)
    step_time_s: Ring = field(default_factory=lambda: Ring(HISTORY))  # wall time of estimate+control+compensate+allocate
    step_cpu_s: Ring = field(default_factory=lambda: Ring(HISTORY))  # the same step's CPU time (this thread)
    solve_time_s: Ring = field(default_factory=lambda: Ring(HISTORY))
    weighted_error: Ring = field(default_factory=lambda: Ring(HISTORY))
    fallbacks: int = 0
    limit_violations: int = 0
    failsafe_entries: int = 0
    arm_refusals: int = 0
    rejected_inputs: int = 0  # messages that did not decode (NaN / inf / malformed)
    step_errors: int = 0  # steps where a collaborator raised: the jets got the safe command
    ignored_imu: int = 0  # IMU messages of a lower-ranked source or out of order
    commands: PairRing = field(default_factory=lambda: PairRing(HISTORY))  # (t, command) sent
    # Over the whole run (not only the history): steps whose compute time exceeded the control period
    overruns_wall: int = 0
    overruns_cpu: int = 0
    overrun_log: deque = field(default_factory=lambda: deque(maxlen=100))  # the newest `Overrun`s (over in CPU time)
    security: SecurityCounts = field(default_factory=SecurityCounts)  # signing, foreign, envelope (onboard.signing)

    faults_seen: int = 0  # OR of every onboard.monitor.Fault flag ever raised
    fault_events: deque = field(default_factory=lambda: deque(maxlen=10_000))  # (t_s, Fault, text)
    frozen_imu: int = 0  # IMU samples kept out of the estimator because the IMU is frozen
    stamps_held: int = 0  # sensor samples whose stamp sat too far from the stream's time (StampGuard)
    time_rebases: int = 0  # times the sensor stream's time base moved for good and the loop followed

    def summary(self) -> dict:
        st = np.asarray(self.step_time_s) * 1e3
        cpu = np.asarray(self.step_cpu_s) * 1e3
        qp = np.asarray(self.solve_time_s) * 1e6
        return {
            "steps": self.steps,
            "step_median_ms": float(np.median(st)) if st.size else float("nan"),
            "step_p99_ms": float(np.percentile(st, 99)) if st.size else float("nan"),
            "step_max_ms": float(st.max()) if st.size else float("nan"),
            "step_cpu_median_ms": float(np.median(cpu)) if cpu.size else float("nan"),
            "step_cpu_p99_ms": float(np.percentile(cpu, 99)) if cpu.size else float("nan"),
            "step_p999_ms": float(np.percentile(st, 99.9)) if st.size else float("nan"),
            "step_cpu_p999_ms": float(np.percentile(cpu, 99.9)) if cpu.size else float("nan"),
            "step_cpu_max_ms": float(cpu.max()) if cpu.size else float("nan"),
            "history_steps": int(st.size),  # the steps the percentiles and maxima cover (newest HISTORY)
            "overruns_wall": self.overruns_wall,
            "overruns_cpu": self.overruns_cpu,
            "overrun_log": [e.as_dict() for e in self.overrun_log],
            "solve_median_us": float(np.median(qp)) if qp.size else float("nan"),
            "solve_p99_us": float(np.percentile(qp, 99)) if qp.size else float("nan"),
            "allocation_fallbacks": self.fallbacks,
            "weighted_error_mean": float(np.mean(self.weighted_error)) if self.weighted_error else float("nan"),
            "limit_violations": self.limit_violations,
            "failsafe_entries": self.failsafe_entries,
            "arm_refusals": self.arm_refusals,
            "rejected_inputs": self.rejected_inputs,
            "step_errors": self.step_errors,
            "faults_seen": int(self.faults_seen),
            "fault_events": [(t, int(f), text) for t, f, text in self.fault_events],
            "stamps_held": self.stamps_held,
            "time_rebases": self.time_rebases,
            **self.security.summary(),
        }


# ------------------------------------------------------------------------------------------------
# The loop


class OnboardLoop:
    """The robot's loop: `poll()` forever (or `run()`); `step(t)` is one control period.

    Collaborators, built from the vehicle: `Estimator` (onboard.estimator), `Controller`
    (onboard.control), `QpAllocator` or `PseudoInverseAllocator` (onboard.allocation),
    `TransientCompensator` + `allocate_compensated` (onboard.compensation) and the failsafe state
    machine (onboard.failsafe). Pass `estimator=` / `controller=` to inject tuned ones.
    """

    def __init__(self, vehicle: Vehicle, link, clock, config: LoopConfig = LoopConfig(), ground=None,
                 estimator=None, controller=None, warm_up: bool = True):
        from . import failsafe
        from .allocation import AllocationConfig, PseudoInverseAllocator, QpAllocator
        from .compensation import TransientCompensator, YawPreview, allocate_compensated
        from .control import Controller
        from .estimator import Estimator

        self.vehicle = vehicle
        self.link = link
        self.ground = ground
        self.clock = clock
        self.config = config
        self.period_s = 1.0 / config.control_rate_hz
        self.k = vehicle.n_units
        self.estimator = estimator if estimator is not None else Estimator(vehicle, backend=config.estimator_backend)
        self.controller = controller if controller is not None else Controller(vehicle)
        # In lock-step nothing may depend on the wall clock: the QP's time budget is lifted there.
        budget = config.qp_time_budget_s or (10.0 if clock.lockstep else 1e-3)
        overrides = {} if config.allocation_change_weight is None else {"change_weight": config.allocation_change_weight}
        alloc_cfg = AllocationConfig.from_vehicle(vehicle, time_budget_s=budget, **overrides)
        cls = QpAllocator if config.allocator == "qp" else PseudoInverseAllocator
        self.allocator = cls(vehicle, self.period_s, alloc_cfg)
        self.compensator = TransientCompensator(vehicle, self.period_s) if config.compensation else None
        self._allocate_compensated = allocate_compensated  # imported here, not on every tick
        # the yaw preview needs the controller's own reference (Controller.yaw_preview) and feed-forward
        g = getattr(self.controller, "gains", None)
        self.yaw_preview = None
        self.yaw_preview_off = ""  # why the preview asked for is off (its plan is unstable for this vehicle)
        if (config.yaw_preview and self.compensator is not None and self.compensator.active
                and getattr(g, "feedforward", False) and hasattr(self.controller, "yaw_preview")):
            try:
                self.yaw_preview = YawPreview(vehicle, self.period_s, g.yaw_bandwidth_rad_s, g.damping_ratio)
            except ValueError as exc:
                # A refinement, not a need: with transients unlike seed 004's (199 stable rows drawn
                # within 10x of them: 59 plans unstable) the loop died on this at start (issue 15,
                # adversarial re-run); it flies with the compensation alone and says so.
                self.yaw_preview_off = str(exc)
        self._fs = failsafe
        self.fs_state = failsafe.FailsafeState(imu_timeout_s=config.imu_timeout_s)
        self.setpoint = Setpoint()
        self.mode = MODES[config.mode_at_start]
        self.command = failsafe.safe_command(self.k)
        self.allocation = None
        self.prediction = None
        self.demand = np.zeros(6)
        self.stats = LoopStats()
        self.stats.commands.reserve(3 * self.k)  # allocated here, not inside the first control step
        # the ground's signing and SET_MESSAGE_INTERVAL, onboard side (ground/commands.py)
        from .signing import CommandGate
        from .stream_rates import StreamRates

        self.gate = CommandGate(config.signing_key, config.ground_systems, envelope=vehicle.envelope,
                                own_system=getattr(getattr(link, "mav", None), "srcSystem", 1),
                                counts=self.stats.security, autopilot=config.autopilot)
        self._stamps = StampGuard(config.max_stamp_skew_s)
        self.rates = StreamRates({**{n: config.telemetry_rate_hz for n in TELEMETRY_STREAMS},
                                  "SERVO_OUTPUT_RAW": config.control_rate_hz})  # the ground's copy
        self._queue: list = []  # (t, arrival order, kind, sample) awaiting the estimator
        self._marks = [math.nan] * 5  # the control step's phase ends (perf_counter s), see Overrun
        self._order = 0
        self._imu_rank = len(IMU_RANK)
        self._last_imu_stamp = -math.inf  # the newest IMU's own time stamp (s)
        self._has_pressure2 = False
        self._depth_seen = False  # a depth sample has counted (SYS_STATUS pressure health)
        self._est_started = False
        self._next_tick = None
        self._marker_t = -math.inf  # newest SYSTEM_TIME: the stream is complete up to it
        self._last_answer_us = -1
        self._next_heartbeat = -math.inf
        self._was_enabled = False
        self._started = False
        self._last_rx_wall = time.monotonic()
        self._next_error_text = -math.inf
        self.monitor = None
        self._health_version = 0
        self._stuck_joints = None  # boolean mask (2k) of joints the monitor found stuck, or None
        if config.fault_monitor:
            from .monitor import FaultMonitor, MonitorConfig

            self.monitor = FaultMonitor(MonitorConfig.from_vehicle(
                vehicle, imu_timeout_s=config.imu_timeout_s, absolute_age=clock.lockstep,
                # in real time a command reaches the servos up to a period late: at the rate limit
                # that is rate * period (0.05 rad at 5 rad/s and 100 Hz) of honest mismatch
                joint_tolerance_rad=0.02 if clock.lockstep else 0.1))
        from .microservices import MESSAGES, Microservices

        self._service_messages = MESSAGES

        self._rx_link = "main"  # the link the message being handled came from
        self.services = Microservices(self)  # identity, parameters, requests, mission (ground stations)
        if warm_up:
            self._warm_up()
        self._last_rx_wall = time.monotonic()  # idle from here: construction and warm-up take ~0.6 s

    def _warm_up(self) -> None:
        """Fly a few control steps of a scratch loop (disarmed, then armed with a depth, yaw and
        speed setpoint, actuator feedback included) on a link that reaches nobody, so every compiled
        kernel of the step is loaded before the first real tick: numba loads cached code at its
        first call, and a fresh process's first two ticks cost 70 and 50 ms of CPU (measured), i.e.
        missed deadlines at 100 Hz. A robot initialises the same way before it arms. Nothing of the
        scratch loop's state reaches this one."""
        from .link import Link
        from .sensors import ActuatorSample, ImuSample, PressureSample

        with Link("udpin:127.0.0.1:0") as nowhere:  # never spoken to: its sends go nowhere
            scratch = OnboardLoop(self.vehicle, nowhere, VehicleClock(), replace(self.config, signing_key=None, parameter_file=None),
                                  warm_up=False)
            k, dt = self.k, self.period_s
            e = self.vehicle.environment
            p0 = e.p_atm + e.rho * e.g * 0.3  # 0.3 m down
            for i in range(6):
                t = i * dt
                scratch.handle(codec.encode_imu(ImuSample(t, (0.01 * i, 0.0, -9.81), (0.001, 0.0, 0.0))))
                scratch.handle(codec.encode_pressure(PressureSample(t, p0 + 10.0 * i, 20.0)))
                if i >= 2:
                    for m in codec.encode_actuators(ActuatorSample(t, (1500,) * (3 * k), (600.0,) * k))[1:]:
                        scratch.handle(m)
                    scratch.handle(codec.encode_joint_angles(t, (0.0,) * k, (0.0,) * k))
                if i == 1:
                    scratch.fs_state = self._fs.on_arm(scratch.fs_state, t)
                    scratch.setpoint = Setpoint(depth_m=0.3, yaw_rad=0.2, velocity_body_m_s=(0.1, 0.0, None))
                scratch.step(t)

    @property
    def armed(self) -> bool:
        return self.fs_state.outputs_enabled

    @property
    def failsafe_active(self) -> bool:
        return self.fs_state.mode is self._fs.Mode.FAILSAFE

    # -- running -------------------------------------------------------------------------------
    def start(self) -> None:
        """Say hello on every link (a udpin peer learns our address from it)."""
        if not self._started:
            self._started = True
            self.link.send(self._heartbeat(companion=self.ground is not None))
            if self.ground is not None:
                self.ground.send(self._heartbeat())

    def run(self, duration_s: float | None = None, stop=None, idle_exit_s: float | None = None) -> str:
        """Poll until `stop()` is true, the clock reaches `duration_s` (clock time; the last tick
        before it), or nothing arrives for `idle_exit_s` of wall time. Returns why it stopped.
        Parameters set and not yet written (they are, at most once a second) are written then."""
        self.start()
        try:
            while True:
                if stop is not None and stop():
                    return "stopped"
                if duration_s is not None and self.clock.now() >= duration_s - 0.5 * self.period_s:
                    return "duration reached"
                if idle_exit_s is not None and time.monotonic() - self._last_rx_wall > idle_exit_s:
                    return f"nothing received for {idle_exit_s:g} s"
                self.poll()
        finally:
            self.services.save_params(force=True)

    def poll(self) -> None:
        """Step if a control tick is due, else wait (at most until the tick) for one message."""
        self.start()
        if self._next_tick is None and not self.clock.lockstep:
            self._next_tick = self.clock.now()  # real time ticks with or without sensors: HEARTBEAT at 1 Hz
        if self._tick_due():
            now = self.clock.now()
            if now - self._next_tick > 2 * self.period_s:  # far behind (a gap): skip, do not burst
                self._next_tick += math.floor((now - self._next_tick) / self.period_s) * self.period_s
            t = self._next_tick
            self._next_tick = t + self.period_s
            self.step(t)
            return
        wait = self.clock.wait_s(self._next_tick) if self._next_tick is not None else 0.1
        m = self.link.recv(wait)
        if m is not None:
            self._last_rx_wall = time.monotonic()
            self.handle(m)
        if self.ground is not None:
            g = self.ground.recv(0.0)
            while g is not None:
                self.handle(g, link="ground")
                g = self.ground.recv(0.0)

    def _tick_due(self) -> bool:
        """Wall clock: the tick time has come. Vehicle clock: the stream is complete up to the tick,
        i.e. a SYSTEM_TIME marker reached it or a newer sample arrived."""
        if self._next_tick is None:
            return False
        if self.clock.lockstep:
            return self.clock.now() > self._next_tick + 1e-7 or self._marker_t >= self._next_tick - 1e-7
        return self.clock.now() >= self._next_tick

    # -- input ---------------------------------------------------------------------------------
    def handle(self, m, link: str = "main") -> None:
        """One received message: a sensor sample into the queue, a setpoint or command applied.
        `link`: "main" (the autopilot's or plant's) or "ground", where it came from; sensor data
        counts only from the autopilot on the main link (onboard.signing.CommandGate).
        What does not decode (NaN, inf, a field out of range) is counted and dropped."""
        name = m.get_type()
        self._rx_link = link
        if self.services.for_another_component(m):  # companion: the autopilot's command, left to it
            return
        verdict = self.gate.admit(m, link)  # signing, sources, envelope, arm/mode params: counted there
        for reply in verdict.replies:  # COMMAND_ACK DENIED / STATUSTEXT "setpoint refused: ..."
            (self.ground or self.link).send(reply)
        if not verdict.accepted:
            return
        mon = self.monitor
        if mon is not None:
            sysid = m.get_srcSystem()
            if sysid:  # 0: a message object built in this process, never on a wire (no sequence)
                # lock-step's frame marker may overtake the data (hil.faults never delays it)
                mon.packet(sysid, m.get_srcComponent(), m.get_seq(),
                           not (name == "SYSTEM_TIME" and self.clock.lockstep))
        try:
            if name in IMU_RANK:
                self._on_imu(m)
            elif name in ("SCALED_PRESSURE2", "SCALED_PRESSURE"):
                if name == "SCALED_PRESSURE" and self._has_pressure2:
                    return  # ArduSub's depth sensor is SCALED_PRESSURE2; the other is the board's
                self._has_pressure2 |= name == "SCALED_PRESSURE2"
                s = codec.decode_pressure(m)
                if not self._stamp_ok(s.time_s):
                    return
                if mon is not None:
                    mon.sample_age(self.clock.now(), s.time_s)
                self._observe(s.time_s)
                self._depth_seen = True
                self._enqueue(s.time_s, "depth", depth_from_pressure(s.press_abs_pa, self.vehicle))
            elif name == "ATTITUDE":
                s = codec.decode_attitude(m)
                if not self._stamp_ok(s.time_s):
                    return
                if mon is not None:
                    mon.sample_age(self.clock.now(), s.time_s)
                self._observe(s.time_s)
                self._enqueue(s.time_s, "attitude", s)
            elif name == "SYSTEM_TIME":
                t = m.time_boot_ms / 1e3
                if not self._stamp_ok(t):
                    return
                self._observe(t)
                self._marker_t = max(self._marker_t, t)
                self._answer_marker(t)
            elif name == "SET_POSITION_TARGET_LOCAL_NED":
                self.setpoint = apply_position_target(self.setpoint, m, self._yaw_estimate())
                self.mode = MODES["guided"]
            elif name == "MANUAL_CONTROL":
                self.setpoint = Setpoint(manual=manual_axes(m))
                self.mode = MODES["manual"]
            elif name == "COMMAND_LONG":
                self._on_command(m)
            elif name in self._service_messages:
                self.services.handle(m, link)
            elif mon is None:
                pass
            elif name in codec.ESC_GROUPS:  # propeller speeds: the jets' health
                first, rpm = codec.decode_rpm(m)
                mon.rpm(self.clock.now(), first, rpm)
            elif name == "ACTUATOR_OUTPUT_STATUS":  # smart servos' angles: stuck joints
                t, alpha, beta = codec.decode_joint_angles(m, self.k)
                mon.joints(t, alpha, beta)
        except (CodecError, ValueError, TypeError, AttributeError, OverflowError) as exc:
            self.stats.rejected_inputs += 1
            if mon is not None and name in IMU_RANK:
                mon.imu_invalid(self.clock.now())  # an IMU reading NaN / inf
            if name in ("SET_POSITION_TARGET_LOCAL_NED", "MANUAL_CONTROL"):  # the ground hears why
                why = str(exc) if str(exc).startswith("setpoint refused") else f"setpoint refused: {name[:20]} malformed"
                for reply in self.gate.refusal_text(why):  # rate-limited with the envelope's refusals
                    (self.ground or self.link).send(reply)
            if name in ("COMMAND_LONG", "COMMAND_INT"):  # the command protocol: always an ack, FAILED here
                ack = mavlink.MAVLink_command_ack_message(int(m.command), mavlink.MAV_RESULT_FAILED, 0, 0,
                                                          m.get_srcSystem(), m.get_srcComponent())
                (self.ground or self.link).send(ack)

    def _stamp_ok(self, t: float) -> bool:
        """Whether a sensor sample stamped t may count (StampGuard); follows a confirmed new time base."""
        verdict = self._stamps.admit(t, None if self.clock.lockstep else self.clock.now())
        if verdict == "held":
            self.stats.stamps_held += 1
            return False
        if verdict == "rebased":
            self._rebase(t)
        return True

    def _rebase(self, t: float) -> None:
        """The sensor stream's time moved for good (confirmed by StampGuard): the IMU ordering
        restarts there; on the vehicle clock (lock-step, replay), time follows it, back too (a
        clock a poisoned first sample ran ahead), and IMU freshness is counted from it, because a
        jump of the stream's own time is not a stretch of real time without an IMU."""
        self.stats.time_rebases += 1
        self._last_imu_stamp = -math.inf
        if not self.clock.lockstep:
            return  # real time: the wall clock is the time; only the ordering was the stream's
        if t < self.clock.now():
            self.clock.rebase(t)
            self._queue.clear()  # samples of the abandoned time base
            self._est_started = False
            self._marker_t = -math.inf
            self._last_answer_us = -1
            self._next_tick = None  # set again by the next sample (_observe)
        if self.fs_state.last_imu_s is not None:
            self.fs_state = replace(self.fs_state, last_imu_s=t)

    def _observe(self, t: float) -> None:
        self.clock.observe(t)
        if self._next_tick is None:
            now = self.clock.now()
            if math.isfinite(now):
                self._next_tick = now if self.clock.lockstep else now + self.period_s

    def _on_imu(self, m) -> None:
        rank = IMU_RANK[m.get_type()]
        if rank > self._imu_rank:
            self.stats.ignored_imu += 1  # a better IMU stream is present
            return
        s = codec.decode_imu(m)
        if not self._stamp_ok(s.time_s):
            return
        mon = self.monitor
        if mon is not None:
            mon.sample_age(self.clock.now(), s.time_s)  # late ones too: their age is the point
        if rank == self._imu_rank and s.time_s <= self._last_imu_stamp:
            self.stats.ignored_imu += 1  # duplicate or out of order
            return
        self._imu_rank = rank
        self._last_imu_stamp = s.time_s
        if mon is not None:
            # IMU freshness on the loop's clock: in real time the stamps are the sensor source's
            # boot time, an offset from it (IMU_LOST raised and cleared every tick, issue 16)
            arrived = s.time_s if self.clock.lockstep else self.clock.now()
            if not mon.imu(arrived, s.accel_frd_m_s2, s.gyro_frd_rad_s):
                self._observe(s.time_s)  # time moves on, but a frozen sample is not a fresh one
                self.stats.frozen_imu += 1
                return
        self._observe(s.time_s)
        self.fs_state = self._fs.on_imu(self.fs_state, self.clock.now())
        self._enqueue(s.time_s, "imu", s)

    def _enqueue(self, t: float, kind: str, sample) -> None:
        self._queue.append((t, self._order, kind, sample))
        self._order += 1

    def _on_command(self, m) -> None:
        cmd = int(m.command)
        result = mavlink.MAV_RESULT_ACCEPTED
        now = self.clock.now() if math.isfinite(self.clock.now()) else 0.0
        if cmd == mavlink.MAV_CMD_COMPONENT_ARM_DISARM:
            fs = self._fs
            if float(m.param1) >= 0.5:
                self.fs_state = fs.on_arm(self.fs_state, now, self.estimator.diverged, self._imu_fault())
                if not self.armed:
                    result = mavlink.MAV_RESULT_TEMPORARILY_REJECTED
                    self.stats.arm_refusals += 1
                    self._statustext(mavlink.MAV_SEVERITY_WARNING, self.fs_state.reason)
            else:
                was_failsafe = self.failsafe_active
                self.fs_state = fs.on_disarm(self.fs_state, now)
                if was_failsafe:  # the explicit recovery: start estimating afresh
                    if self.estimator.diverged:
                        self.estimator.reset()
                        self._est_started = False
                    self._statustext(mavlink.MAV_SEVERITY_NOTICE, "failsafe cleared: disarmed")
        elif cmd == mavlink.MAV_CMD_DO_SET_MODE:
            mode = int(round(float(m.param2)))
            if mode in MODE_NAMES:
                self.mode = mode
                est = self.estimator.estimate
                if MODE_NAMES[mode] == "depth_hold":
                    self.setpoint = Setpoint(depth_m=est.depth_m, yaw_rad=est.euler_rad[2])
                elif MODE_NAMES[mode] in ("stabilize", "manual"):
                    self.setpoint = Setpoint(manual=ManualAxes())
            else:
                result = mavlink.MAV_RESULT_DENIED
        elif cmd == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
            result = self.rates.handle(m)
        else:
            result = self.services.command(m)  # requests for messages, capabilities; else UNSUPPORTED
        ack = mavlink.MAVLink_command_ack_message(cmd, result, 0, 0, m.get_srcSystem(), m.get_srcComponent())
        self.link.send(ack)
        if self.ground is not None:
            self.ground.send(ack)
        self.services.after_ack(self.ground if self._rx_link == "ground" and self.ground is not None else self.link)

    def _yaw_estimate(self) -> float:
        return float(self.estimator.estimate.euler_rad[2])

    # -- the control step ----------------------------------------------------------------------
    def step(self, t: float) -> None:
        """One control period at clock time t: estimate, failsafe, control, compensate, allocate, send."""
        t0 = time.perf_counter()
        c0 = time.thread_time()
        r0 = resource.getrusage(resource.RUSAGE_THREAD)
        gc0 = _gc_cpu_s[0]
        queued = len(self._queue)
        marks = self._marks
        failed = False
        try:
            est, command = self._compute(t)
        except Exception as exc:  # the robot's loop never dies: safe output, counted and reported
            failed = True
            self.stats.step_errors += 1
            est = self.estimator.estimate
            command = self._fs.safe_command(self.k)
            self.demand = np.zeros(6)
            self.allocator.previous = None
            if t >= self._next_error_text:
                self._next_error_text = t + 1.0
                self._statustext(mavlink.MAV_SEVERITY_ERROR, f"step error: {exc}")  # jets safe
        self._was_enabled = self.armed and not failed
        marks[3] = time.perf_counter()
        if self.monitor is not None:
            self._monitor_tick(t, command, est)
        self.command = command
        marks[4] = time.perf_counter()
        elapsed = marks[4] - t0
        cpu_s = time.thread_time() - c0
        self.stats.step_cpu_s.append(cpu_s)
        self.stats.step_time_s.append(elapsed)
        if elapsed > self.period_s:  # wall time: also whatever else the machine runs meanwhile
            self.stats.overruns_wall += 1
        if cpu_s > self.period_s:  # CPU time: this step's own work
            self.stats.overruns_cpu += 1
            self.stats.overrun_log.append(Overrun.of(t, elapsed, cpu_s, _gc_cpu_s[0] - gc0, t0, marks, r0,
                                                     resource.getrusage(resource.RUSAGE_THREAD), queued))
        self.stats.steps += 1
        self.stats.commands.append((t, command.copy()))
        with self.link.batch():
            if self.ground is not None:
                with self.ground.batch():
                    self._send_outputs(t, command)
                    self._telemetry(t, est, elapsed)
            else:
                self._send_outputs(t, command)
                self._telemetry(t, est, elapsed)

    def _compute(self, t: float):
        """Estimate, failsafe, control, compensate, allocate: (estimate, command) for this tick."""
        marks = self._marks  # wall clock at the end of each phase, for an overrun's record (Overrun)
        marks[0] = marks[1] = marks[2] = marks[3] = math.nan
        self._run_estimator()
        marks[0] = time.perf_counter()
        est = self.estimator.estimate
        was_failsafe = self.failsafe_active
        self.fs_state = self._fs.on_tick(self.fs_state, t, self.estimator.diverged,
                                         self.estimator.health.diverged_reason, self._imu_fault())
        if self.failsafe_active and not was_failsafe:
            self.stats.failsafe_entries += 1
            self._statustext(mavlink.MAV_SEVERITY_CRITICAL, f"FAILSAFE {self.fs_state.reason}"[:50])
        if not self.armed:
            self.demand = np.zeros(6)
            return est, self._fs.safe_command(self.k)
        if not self._was_enabled:  # joints start from the safe (neutral) command
            self.controller.reset()
            self.allocator.previous = None
            if self.compensator is not None:
                self.compensator.reset()
            if self.yaw_preview is not None:
                self.yaw_preview.reset()
        achieved = None
        if self.allocation is not None and self._was_enabled:
            achieved = np.array(self.allocation.wrench_achieved, dtype=float)
            if self.prediction is not None:
                achieved += self.prediction.wrench_n
            if self.yaw_preview is not None:
                # yaw: what the jets gave for the controller's demand, without the preview's
                # correction c and the reaction c is there to cancel (not a saturation of the jets)
                achieved[5] = self.allocation.wrench_achieved[5] - self.yaw_preview.c
        self.demand = self.controller.step(est, self.setpoint, self.period_s, achieved=achieved).as_array()
        marks[1] = time.perf_counter()
        if self.compensator is not None:
            tau = self.demand
            if self.yaw_preview is not None:  # the reaction of what the yaw reference will ask, ahead
                tau = tau.copy()
                tau[5] += self.yaw_preview.step(self.controller.yaw_preview(self.yaw_preview.horizon, self.period_s))
            res = self._allocate_compensated(self.allocator, self.compensator, tau, nu_r=est.nu,
                                             iterations=self.config.compensation_iterations)
            alloc, self.prediction = res.allocation, res.prediction
        else:
            alloc = self.allocator.allocate(self.demand, nu_r=est.nu)
        self.allocation = alloc
        marks[2] = time.perf_counter()
        command = np.asarray(alloc.command, dtype=float)
        self.stats.solve_time_s.append(alloc.solve_time_s)
        if math.isfinite(alloc.weighted_error):
            self.stats.weighted_error.append(float(alloc.weighted_error))
        self.stats.fallbacks += int(bool(alloc.fallback))
        self.stats.limit_violations += self._violations(command)
        return est, command

    def _imu_fault(self) -> str:
        return "frozen" if self.monitor is not None and self.monitor.imu_frozen else ""

    def _monitor_tick(self, t: float, command, est) -> None:
        """Fault checks of this tick: events out as STATUSTEXT, unit health into the allocator."""
        mon = self.monitor
        try:
            mon.tick(t, command, est.health)
        except Exception as exc:  # a monitor bug must not stop the robot: say so, keep flying
            if t >= self._next_error_text:
                self._next_error_text = t + 1.0
                self._statustext(mavlink.MAV_SEVERITY_ERROR, f"monitor error: {exc}")
            return
        events = mon.pop_events()
        if events:
            st = self.stats
            st.faults_seen = int(mon.faults_seen)
            for ev in events:
                st.fault_events.append(ev)
                sev = mavlink.MAV_SEVERITY_WARNING if ev[2].startswith("FAULT") else mavlink.MAV_SEVERITY_NOTICE
                self._statustext(sev, ev[2])
        if mon.health_version != self._health_version:
            self._health_version = mon.health_version
            h = mon.health
            set_health = getattr(self.allocator, "set_health", None)
            if set_health is not None:
                set_health(h.efficiency, h.stuck_alpha_rad, h.stuck_beta_rad)
            stuck = np.isfinite(np.array(h.stuck_alpha_rad + h.stuck_beta_rad, float))
            self._stuck_joints = stuck if stuck.any() else None

    def _run_estimator(self) -> None:
        """Fuse the queued samples in time order, predicting between them with the held command."""
        if not self._queue:
            return
        self._queue.sort(key=lambda e: (e[0], e[1]))
        est = self.estimator
        for t, _, kind, sample in self._queue:
            if not self._est_started:
                est.time_s = t
                self._est_started = True
            dt = t - est.time_s
            if dt > 1.0:  # predict across at most the last second of a gap: a stamp 1e13 s ahead
                est.time_s, dt = t - 1.0, 1.0  # (corrupt or hostile) took hours in 20 ms steps (fuzzing)
            while dt > 1e-7:
                h = min(dt, 0.02)
                est.predict(h, self.command)
                dt -= h
            if kind == "imu":
                est.update_imu(sample)
            elif kind == "depth":
                est.update_depth(sample)
            else:
                est.update_attitude(sample)
        self._queue.clear()

    def _violations(self, command) -> int:
        """Limits an allocated command must never break: 0 <= n <= n_max, |angle| <= limit, and
        joint travel per step <= rate_limit * dt (against the previous command sent)."""
        k, v = self.k, self.vehicle
        tol = 1e-9
        n_hi, lim = v.thruster.n_max + tol, v.servo.angle_limit + tol
        travel_max = v.servo.rate_limit * self.period_s + 1e-6
        # plain floats: a dozen numpy calls on 12 values cost ~40 us a tick, these loops ~3 us
        c, prev = command.tolist(), self.command.tolist()
        stuck = self._stuck_joints  # a stuck joint's command jumps to where it is stuck: no travel
        bad = 0
        for i in range(k):
            if c[i] < -tol or c[i] > n_hi:
                bad += 1
        for j in range(k, len(c)):
            a = c[j]
            if abs(a) > lim:
                bad += 1
            if abs(a - prev[j]) > travel_max and (stuck is None or not stuck[j - k]):
                bad += 1
        return bad

    # -- output --------------------------------------------------------------------------------
    def _send_outputs(self, t: float, command) -> None:
        us = codec.time_usec(max(t, 0.0))
        pwm = command_to_pwm(self.vehicle, command)
        if self.config.output == "hil":
            controls = np.zeros(16)
            controls[: 3 * self.k] = command_to_normalised(self.vehicle, command)
            mode = mavlink.MAV_MODE_FLAG_SAFETY_ARMED if self.armed else 0
            self.link.send(mavlink.MAVLink_hil_actuator_controls_message(us, [float(c) for c in controls], mode, 0))
        servo = mavlink.MAVLink_servo_output_raw_message(us & 0xFFFFFFFF, 0, *(int(p) for p in pwm))
        self.link.send(servo)
        if self.ground is not None and self.rates.due("SERVO_OUTPUT_RAW", t):
            self.ground.send(servo)
        self._last_answer_us = max(self._last_answer_us, us)

    def _answer_marker(self, t: float) -> None:
        """Lock-step: every frame marker gets a command stamped with it, even between control ticks."""
        if not self.clock.lockstep:
            return
        if self._next_tick is not None and t >= self._next_tick - 1e-7:
            return  # a tick is due at or before t: poll() steps and answers
        if codec.time_usec(max(t, 0.0)) > self._last_answer_us:
            with self.link.batch():
                self._send_outputs(t, self.command)

    def _heartbeat(self, companion: bool = False):
        """HEARTBEAT as MAV_TYPE_SUBMARINE for the ground. `companion`: towards an autopilot while
        a separate ground link exists, the loop is its companion computer (MAV_TYPE_ONBOARD_CONTROLLER,
        MAV_AUTOPILOT_INVALID), so a recording on that side names the autopilot as the vehicle."""
        base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (mavlink.MAV_MODE_FLAG_SAFETY_ARMED if self.armed else 0)
        status = (mavlink.MAV_STATE_CRITICAL if self.failsafe_active
                  else mavlink.MAV_STATE_ACTIVE if self.armed else mavlink.MAV_STATE_STANDBY)
        if companion:
            return mavlink.MAVLink_heartbeat_message(
                mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID, base, self.mode, status, 3)
        kind, autopilot, flags = self.services.heartbeat_fields(self.mode)  # companion of a flight stack: 191
        return mavlink.MAVLink_heartbeat_message(kind, autopilot, base | flags, self.mode, status, 3)

    def _telemetry(self, t: float, est, step_s: float) -> None:
        out = self.ground if self.ground is not None else self.link
        if t + 1e-9 >= self._next_heartbeat:
            self._next_heartbeat = t + 1.0
            out.send(self._heartbeat())
            if out is not self.link:
                self.link.send(self._heartbeat(companion=True))
            out.send(self._sys_status(step_s))
            self.services.one_hz(out, max(t, 0.0))
            ms = codec.time_boot_ms(max(t, 0.0))
            for name, value in est.health.as_dict().items():  # gating / NaN rejections per stream
                out.send(mavlink.MAVLink_named_value_float_message(ms, name[:10].encode(), float(value)))
        self.services.streams(out, max(t, 0.0))  # LOCAL_POSITION_NED when a ground station asks for it
        send = {n: self.rates.due(n, t) for n in TELEMETRY_STREAMS}  # rates: SET_MESSAGE_INTERVAL
        if not any(send.values()):
            return
        ms = codec.time_boot_ms(max(t, 0.0))
        roll, pitch, yaw = est.euler_rad
        p, q, r = est.rates_rad_s
        if send["ATTITUDE"]:
            out.send(mavlink.MAVLink_attitude_message(ms, roll, pitch, yaw, p, q, r))
        a = self.allocation
        if send["NAMED_VALUE_FLOAT"]:
            self._named_values(out, ms, est, step_s)
        if send["DEBUG_FLOAT_ARRAY"]:
            data = list(self.demand) + (list(a.wrench_achieved) if a is not None else [0.0] * 6)
            data = [float(x) if math.isfinite(x) else 0.0 for x in data] + [0.0] * (58 - len(data))
            out.send(mavlink.MAVLink_debug_float_array_message(codec.time_usec(max(t, 0.0)), b"wrench", 1, data))

    def _named_values(self, out, ms: int, est, step_s: float) -> None:
        """NAMED_VALUE_FLOAT telemetry, built only on the ticks it is due (not every control tick)."""
        a = self.allocation
        sp = self.setpoint
        st = self.stats
        recent = np.fromiter(islice(reversed(st.step_time_s), 100), float) * 1e3
        nan = math.nan
        values = {
            "depth": est.depth_m,
            "depth_sp": sp.depth_m if sp.depth_m is not None else nan,
            "yaw_sp": sp.yaw_rad if sp.yaw_rad is not None else nan,
            "u_sp": sp.velocity_body_m_s[0] if sp.velocity_body_m_s[0] is not None else nan,
            "u_est": est.velocity_body_m_s[0],
            "alloc_err": a.weighted_error if a is not None else 0.0,
            "alloc_fb": float(st.fallbacks),
            "qp_us": a.solve_time_s * 1e6 if a is not None else 0.0,
            "step_ms": step_s * 1e3,
            "step_p99": float(np.percentile(recent, 99)) if recent.size else 0.0,
            "failsafe": 1.0 if self.failsafe_active else 0.0,
            "armed": 1.0 if self.armed else 0.0,
            "est_rej": float(est.health.rejected_total),
            "in_rej": float(st.rejected_inputs),
            "link_bad": float(self.link_errors()),  # every link's, the ground's included
        }
        foreign = self.link_foreign()
        if foreign:  # datagrams from senders other than a link's peer, dropped unread
            values["link_foe"] = float(foreign)
        if self.stats.stamps_held:
            values["stamp_held"] = float(self.stats.stamps_held)
        if self.monitor is not None:
            values["faults"] = float(int(self.monitor.faults))  # onboard.monitor.Fault bitmask
        values.update(self.stats.security.telemetry())  # sig_unsig, sig_bad, sig_replay, foreign, ... once non-zero
        for name, value in values.items():
            out.send(mavlink.MAVLink_named_value_float_message(ms, name.encode(), float(value)))

    def links(self) -> dict:
        """The loop's links by role: {"link": main, "ground": ground link (when there is one)}."""
        return {"link": self.link} if self.ground is None else {"link": self.link, "ground": self.ground}

    def link_errors(self) -> int:
        """Bad and unknown packets over every link (telemetry link_bad, SYS_STATUS errors_comm)."""
        return sum(getattr(lk, "bad_packets", 0) + getattr(lk, "unknown_packets", 0) for lk in self.links().values())

    def link_foreign(self) -> int:
        """Datagrams from anyone but a link's peer, over every link (dropped unread)."""
        return sum(getattr(lk, "foreign_datagrams", 0) for lk in self.links().values())

    def _sys_status(self, step_s: float):
        S = mavlink
        present = (S.MAV_SYS_STATUS_SENSOR_3D_GYRO | S.MAV_SYS_STATUS_SENSOR_3D_ACCEL
                   | S.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE | S.MAV_SYS_STATUS_AHRS
                   | S.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS)
        # health: a sensor not heard from yet is not healthy; the geofence bit (no fence, so never
        # breached) is set, as ArduPilot does, else MAVProxy reads its absence as a fence breach
        health = present | S.MAV_SYS_STATUS_GEOFENCE
        if self.fs_state.last_imu_s is None:
            health &= ~(S.MAV_SYS_STATUS_SENSOR_3D_GYRO | S.MAV_SYS_STATUS_SENSOR_3D_ACCEL)
        if not self._depth_seen:
            health &= ~S.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE
        if not self._est_started:
            health &= ~S.MAV_SYS_STATUS_AHRS
        if self.failsafe_active:
            health &= ~(S.MAV_SYS_STATUS_SENSOR_3D_GYRO | S.MAV_SYS_STATUS_SENSOR_3D_ACCEL)
        if self.estimator.diverged:
            health &= ~S.MAV_SYS_STATUS_AHRS
        drop = 0
        mon = self.monitor
        if mon is not None:
            f = int(mon.faults)
            F = type(mon.faults)
            if f & (F.JET_DEAD | F.JET_WEAK | F.JOINT_STUCK):
                health &= ~S.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS
            if f & (F.IMU_FROZEN | F.IMU_NAN | F.IMU_LOST):
                health &= ~(S.MAV_SYS_STATUS_SENSOR_3D_GYRO | S.MAV_SYS_STATUS_SENSOR_3D_ACCEL)
            if f & F.DEPTH_JUMP:
                health &= ~S.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE
            drop = min(int(round(mon.drop_rate * 10_000)), 10_000)  # c%
        load = int(min(step_s / self.period_s, 1.0) * 1000)
        errors = min(self.link_errors(), 0xFFFF)
        return S.MAVLink_sys_status_message(present, present, health, load, 0, -1, -1, drop, errors,
                                            min(self.stats.rejected_inputs, 0xFFFF), 0, 0, 0)

    def _statustext(self, severity: int, text: str) -> None:
        msg = mavlink.MAVLink_statustext_message(severity, text[:50].encode())
        (self.ground or self.link).send(msg)
