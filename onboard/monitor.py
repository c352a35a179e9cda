"""Fault detection onboard: link, jets, joints, IMU and depth, from what the loop observes (pure).

No IO and no clock: `FaultMonitor` is a state object the loop feeds with observations stamped in
the loop's own time (vehicle time in lock-step, `VehicleClock`; wall time otherwise) and asks
once per control tick what is wrong. Flags are the shared vocabulary of issue #7 (`Fault`); each
raise or clear is an event (t_s, flag, text), text "FAULT <FLAG> <detail>" / "CLEARED <FLAG> ...".
In the texts units are numbered 1..k, as in the vehicle file's [[unit]] list, the ESC telemetry and
hil.faults; in arrays (`UnitHealth`, `efficiency`) they sit at index 0..k-1, as in the command.

What is detected, and from what:
- LINK_LOSS / LINK_DUPLICATE / LINK_REORDER: MAVLink sequence numbers per (system, component)
  (the first `max_sources` of them; packets of any others are only counted, `untracked_packets`)
  over the last `link_window_packets` packets of that source. A forward jump of d > 1 counts d - 1
  lost; a sequence number seen in the last 128 packets of the source is a duplicate; one that
  goes back by at most `reorder_max_back` is a late (reordered) packet and fills one counted gap;
  a forward jump counts only the numbers in between not seen (a frame marker that overtook the
  data, `ordered=False`, is no loss).
  loss = gaps / (gaps + packets); duplicate, reorder = their count / packets. Raised above
  `loss_threshold` (5 %) / `duplicate_threshold` / `reorder_threshold` once `min_packets` were seen
  (and `min_events` duplicates / late packets: the HIL endpoint re-sends a late frame marker as is).
- LINK_DELAY: sample age = the newest time the loop had seen when a sensor sample arrived minus
  the sample's own time stamp. In lock-step (`absolute_age`) that is the age itself (0 on a clean
  link: a frame's samples carry the frame's time); in real time the two clocks differ by an
  unknown offset, so the age is taken above the smallest one seen. Its running mean (delay) and
  mean absolute deviation (jitter), each an exponential average over `age_samples` samples, are
  raised above `delay_threshold_s` / `jitter_threshold_s`.
- JET_DEAD / JET_WEAK: the propeller speed the motor should have, the spec-4 `motor_lag` model
  n' = (n_cmd - n) / tau_m driven by the commands the loop sent (exact for piecewise-constant
  commands: n(t) = c + (n0 - c) exp(-(t - t0) / tau_m)), against ESC rpm / 60. The efficiency
  e = sum(n_meas n_hat) / sum(n_hat^2) is the least-squares gain of n_meas = e n_hat over an
  exponentially forgotten window of `jet_window_s`, over samples with n_hat >= `jet_min_speed`
  of n_max only (a jet at rest tells nothing). e < `jet_dead_efficiency` is dead, e <
  `jet_weak_efficiency` weak, either held for `jet_persist_s`. A dead jet is latched (the
  allocator stops commanding it, so nothing more can be learnt); a weak one clears when e
  recovers.
- JOINT_STUCK: the joint angle the servo should have, the spec-4 `servo_lag` model (first-order
  lag with a rate limit, `compensation.servo_motion`, exact per step) driven by the commanded
  angles, against the measured angles of ACTUATOR_OUTPUT_STATUS, each compared with the model at
  its own time stamp; feedback older than the newest judged (reordered) is not judged. Stuck:
  |measured - model| > `joint_tolerance_rad` while the joint stays within the tolerance of where
  that began, for `joint_persist_s` of sample time over >= `joint_min_samples` samples, at the
  measured angle. (The model cannot know when the commands reached the servo: over a delayed,
  lossy or reordering link a healthy joint lags its model but still moves, which restarts the
  evidence.) It clears when the joint is seen away from that angle by more than the tolerance
  (for the same time). The allocator holds a stuck joint still, so a false alarm would never show
  itself: `joint_probe_s` after the raise the joint is released in `health` (the fault stays
  raised); if it follows its commands it clears, if the evidence builds up again it is held
  again and the next probe waits twice as long (up to `joint_probe_max_s`).
- IMU_FROZEN: `imu_frozen_samples` consecutive IMU samples with the very same six values (real
  noise never repeats); `imu()` then answers False: the sample must not reach the estimator nor
  count as fresh for the failsafe. Clears at the first sample that differs.
- IMU_NAN: an IMU message that did not decode (NaN / inf); clears `imu_nan_clear_s` after the last.
- IMU_LOST: no IMU message at all (good, frozen or NaN) for `imu_timeout_s`, once one was seen:
  the failsafe's timeout. Clears at the next IMU message.
- DEPTH_JUMP: the estimator's depth rejections (innovation gate) - `depth_rejections` of them
  within `depth_window_s` - or a depth re-anchor (`health.depth_resets`); clears
  `depth_clear_s` after the last one.
"""

from __future__ import annotations

import enum
import math
from collections import deque
from dataclasses import dataclass

import numpy as np

from .compensation import _servo_motion  # the compiled kernel of compensation.servo_motion (spec 4)


class Fault(enum.IntFlag):
    """Onboard fault flags (issue #7 vocabulary; the values are fixed: telemetry carries them)."""

    LINK_LOSS = 1
    LINK_DELAY = 2
    LINK_DUPLICATE = 4
    LINK_REORDER = 8
    JET_DEAD = 16
    JET_WEAK = 32
    JOINT_STUCK = 64
    IMU_FROZEN = 128
    IMU_NAN = 256
    DEPTH_JUMP = 512
    IMU_LOST = 1024


NONE = Fault(0)
MODEL_SETTLE_S = 0.5  # > 5 motor time constants: a model started mid-flight has forgotten its start
EVENT_HISTORY = 10_000  # events kept (a flapping fault in a long soak must not grow memory)


def fault_names(mask: int) -> str:
    """'JET_DEAD|LINK_LOSS' for a bitmask ('' for 0), in value order."""
    return "|".join(f.name for f in Fault if int(mask) & f.value)


# ------------------------------------------------------------------------------------------------
# Configuration


@dataclass(frozen=True)
class MonitorConfig:
    """Thresholds and the actuator models' constants (`from_vehicle` fills the latter)."""

    n_units: int = 4
    n_max_rev_s: float = 83.3
    motor_time_constant_s: float = 0.08  # 0: motor_lag off (n = n_cmd)
    servo_time_constant_s: float = 0.03  # 0: servo_lag off (angle = command)
    servo_rate_limit_rad_s: float = 5.0
    angle_limit_rad: float = 1.3963
    imu_timeout_s: float = 0.3
    absolute_age: bool = True  # lock-step: the loop's clock is vehicle time, ages are absolute
    # link
    link_window_packets: int = 500
    min_packets: int = 50
    loss_threshold: float = 0.05
    duplicate_threshold: float = 0.01
    reorder_threshold: float = 0.01
    reorder_max_back: int = 64
    min_events: int = 10  # duplicates / late packets in the window before their ratio counts
    age_samples: int = 50
    delay_threshold_s: float = 0.05
    jitter_threshold_s: float = 0.02
    link_persist_s: float = 0.2
    link_clear_s: float = 2.0
    link_check_period_s: float = 0.05  # link ratios are evaluated at this period, not every tick
    # jets
    jet_window_s: float = 0.15
    jet_min_speed: float = 0.1  # fraction of n_max
    jet_min_samples: float = 5.0  # equivalent samples in the window before judging
    jet_dead_efficiency: float = 0.3
    jet_weak_efficiency: float = 0.8
    jet_persist_s: float = 0.3
    jet_republish: float = 0.05  # a weak jet's published efficiency follows its estimate by this step
    # joints
    joint_tolerance_rad: float = 0.02  # lock-step: the model meets the plant's joints to ~4e-6 rad
    joint_persist_s: float = 0.2
    joint_stale_s: float = 0.5  # older joint feedback is no evidence
    joint_min_samples: int = 5  # in-order feedback samples that must agree before a joint is judged
    joint_probe_s: float = 5.0  # a stuck joint is released to the allocator this long after it was held
    joint_probe_max_s: float = 60.0  # (doubling after each probe that finds it stuck, up to this)
    joint_probe_window_s: float = 1.0  # a probe that shows nothing either way holds the joint again
    max_sources: int = 16  # (system, component) streams tracked; packets of any more are only counted
    # IMU
    imu_frozen_samples: int = 10
    imu_nan_clear_s: float = 1.0
    # depth
    depth_rejections: int = 3
    depth_window_s: float = 0.5
    depth_clear_s: float = 2.0

    def __post_init__(self):
        if not (isinstance(self.n_units, int) and self.n_units >= 1):
            raise ValueError(f"MonitorConfig.n_units: expected an integer >= 1, got {self.n_units!r}")
        for name in ("motor_time_constant_s", "servo_time_constant_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"MonitorConfig.{name}: expected a time >= 0 s, got {v!r}")
        for name in ("n_max_rev_s", "servo_rate_limit_rad_s", "angle_limit_rad", "imu_timeout_s",
                     "loss_threshold", "duplicate_threshold", "reorder_threshold", "delay_threshold_s",
                     "jitter_threshold_s", "jet_window_s", "jet_min_speed", "joint_tolerance_rad",
                     "link_check_period_s", "depth_window_s", "joint_probe_s", "joint_probe_max_s",
                     "joint_probe_window_s"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"MonitorConfig.{name}: expected a finite number > 0, got {v!r}")
        if not 0 < self.jet_dead_efficiency < self.jet_weak_efficiency <= 1:
            raise ValueError("MonitorConfig: expected 0 < jet_dead_efficiency < jet_weak_efficiency <= 1, got "
                             f"{self.jet_dead_efficiency!r}, {self.jet_weak_efficiency!r}")
        for name in ("link_window_packets", "min_packets", "age_samples", "imu_frozen_samples", "depth_rejections",
                     "min_events", "joint_min_samples", "max_sources"):
            v = getattr(self, name)
            if not (isinstance(v, int) and v >= 1):
                raise ValueError(f"MonitorConfig.{name}: expected an integer >= 1, got {v!r}")
        if not (isinstance(self.reorder_max_back, int) and 1 <= self.reorder_max_back < 128):
            raise ValueError(f"MonitorConfig.reorder_max_back: expected an integer 1..127, got {self.reorder_max_back!r}")

    @classmethod
    def from_vehicle(cls, v, **overrides) -> "MonitorConfig":
        """Actuator models from the vehicle file (a lag that is off has time constant 0)."""
        kw = dict(
            n_units=v.n_units, n_max_rev_s=v.thruster.n_max,
            motor_time_constant_s=v.thruster.motor_time_constant if v.effects.on("motor_lag") else 0.0,
            servo_time_constant_s=v.servo.time_constant if v.effects.on("servo_lag") else 0.0,
            servo_rate_limit_rad_s=v.servo.rate_limit, angle_limit_rad=v.servo.angle_limit,
        )
        kw.update(overrides)
        return cls(**kw)


@dataclass(frozen=True)
class UnitHealth:
    """What the allocator must know: thrust efficiency per unit (1 healthy, 0 dead; the motor
    reaches e * commanded speed) and stuck joints (angle in rad, NaN where the joint is free)."""

    efficiency: tuple
    stuck_alpha_rad: tuple
    stuck_beta_rad: tuple

    @classmethod
    def healthy(cls, n_units: int) -> "UnitHealth":
        return cls((1.0,) * n_units, (math.nan,) * n_units, (math.nan,) * n_units)

    @property
    def nominal(self) -> bool:
        return all(e == 1.0 for e in self.efficiency) and not any(
            math.isfinite(a) for a in self.stuck_alpha_rad + self.stuck_beta_rad)


# ------------------------------------------------------------------------------------------------
# Pieces


class _Debounce:
    """A condition held `persist_s` raises; its absence held `clear_s` clears."""

    __slots__ = ("on", "since")

    def __init__(self):
        self.on = False
        self.since = None  # time the condition first disagreed with `on`

    def update(self, cond: bool, t: float, persist_s: float, clear_s: float) -> bool:
        """True when `on` changed at this call."""
        if cond == self.on:
            self.since = None
            return False
        if self.since is None:
            self.since = t
        if t - self.since >= (persist_s if cond else clear_s) - 1e-9:
            self.on = cond
            self.since = None
            return True
        return False


class _Source:
    """Sequence-number bookkeeping of one (system, component) over a sliding window of packets."""

    __slots__ = ("last", "seen", "count", "window", "gaps", "dups", "reorders", "received")

    def __init__(self, window: int):
        self.last = -1
        self.seen = [-(1 << 30)] * 256  # packet index at which each sequence number was last seen
        self.count = 0
        self.window = deque(maxlen=window)  # per packet: 0 normal, 1 dup, 2 late, 3 late unordered, 4 * gap
        self.gaps = 0
        self.dups = 0
        self.reorders = 0
        self.received = 0  # packets in the window that were not duplicates

    def push(self, code: int) -> None:
        w = self.window
        if len(w) == w.maxlen:
            self._count(w[0], -1)
        w.append(code)
        self._count(code, 1)

    def _count(self, code: int, sign: int) -> None:
        if code == 1:
            self.dups += sign
        else:
            self.received += sign
            if code == 2 or code == 3:  # a late packet: it filled one gap counted before
                self.reorders += sign if code == 2 else 0
                self.gaps -= sign
            else:
                self.gaps += sign * (code >> 2)


# ------------------------------------------------------------------------------------------------
# The monitor


class FaultMonitor:
    """Observations in, fault flags out. Feed it from the loop; call `tick` every control period."""

    def __init__(self, config: MonitorConfig = MonitorConfig()):
        c = self.config = config
        k = self.k = c.n_units
        self.faults = NONE  # flags active now
        self.faults_seen = NONE  # every flag ever raised
        self.events: deque = deque(maxlen=EVENT_HISTORY)  # (t_s, Fault, text), raises and clears
        self._new: list = []  # events not yet taken by `pop_events`
        self._active: dict = {}  # instance key -> Fault, for every raised instance
        # link
        self._sources: dict = {}  # at most config.max_sources
        self.untracked_packets = 0  # packets of sources beyond them
        self._deb_link = {f: _Debounce() for f in (Fault.LINK_LOSS, Fault.LINK_DUPLICATE, Fault.LINK_REORDER,
                                                    Fault.LINK_DELAY)}
        self._next_link_check = -math.inf
        self.link_ratios = {"loss": 0.0, "duplicate": 0.0, "reorder": 0.0}  # worst source, last check
        self._age_min = math.inf
        self.delay_s = 0.0  # running mean of the sample age
        self.jitter_s = 0.0  # running mean |age - delay|
        self._age_alpha = 1.0 / c.age_samples
        self._ages = 0
        # actuator models: state at _t_model and the command in force since then
        self._t_model = None
        self._n_model = np.zeros(k)
        self._n_cmd = np.zeros(k)
        self._j_model = np.zeros(2 * k)  # alpha 0..k-1, beta k..2k-1
        self._j_cmd = np.zeros(2 * k)
        # the models at the last ticks (t, n, n_cmd, joints, joint_cmd): feedback that arrives late
        # (a delayed link) is compared with the model at its own time, not with the model now
        self._past: deque = deque(maxlen=64)
        # The models run only once actuator feedback has been seen (none: nothing to compare, no
        # cost); they start at the command in force and judge nothing for MODEL_SETTLE_S.
        self._models_on = False
        self._cmd = np.zeros(3 * k)
        self._judge_from = math.inf
        # jets
        self._sxy = [0.0] * k
        self._sxx = [0.0] * k
        self._sw = [0.0] * k
        self._t_rpm = [None] * k
        self.efficiency = [1.0] * k  # estimate (1 until there is evidence)
        self._jet_state = ["ok"] * k  # published: ok / weak / dead
        self._jet_candidate = ["ok"] * k
        self._jet_since = [0.0] * k
        self._rpm_new = False
        # joints
        self._j_meas = np.full(2 * k, math.nan)
        self._j_resid = np.zeros(2 * k)
        self._t_joint = -math.inf
        self._joint_new = False
        # evidence of a free joint being stuck: since when (sample time) its residual has been over
        # the tolerance while it stayed within the tolerance of `_anchor`, over how many samples
        self._j_since = np.full(2 * k, math.nan)
        self._j_count = np.zeros(2 * k, dtype=np.int64)
        self._anchor = np.full(2 * k, math.nan)
        self._moved_since = np.full(2 * k, math.nan)  # a raised joint seen away from its stuck angle
        self._stuck = [math.nan] * (2 * k)  # raised: the angle it is stuck at
        self._held = [False] * (2 * k)  # raised and published to the allocator (False while probed)
        self._probe_at = [math.inf] * (2 * k)
        self._probe_every = [c.joint_probe_s] * (2 * k)
        self._probe_end = [math.inf] * (2 * k)
        self._stuck_count = 0
        # IMU
        self._imu_last = None
        self._imu_repeats = 0
        self._t_imu = None  # newest IMU message of any kind
        self._t_nan = -math.inf
        # depth
        self._depth_rej = 0
        self._depth_resets = 0
        self._depth_times: deque = deque(maxlen=64)
        self._t_depth_evidence = -math.inf
        # published unit health for the allocator, and its version (bumped on every change)
        self.health = UnitHealth.healthy(k)
        self.health_version = 0

    # -- flags ---------------------------------------------------------------------------------
    def _raise(self, key, flag: Fault, t: float, detail: str = "") -> None:
        if key in self._active:
            return
        self._active[key] = flag
        self.faults |= flag
        self.faults_seen |= flag
        self._event(t, flag, f"FAULT {flag.name}{' ' + detail if detail else ''}")

    def _clear(self, key, t: float, detail: str = "") -> None:
        flag = self._active.pop(key, None)
        if flag is None:
            return
        if not any(f is flag for f in self._active.values()):
            self.faults &= ~flag
        self._event(t, flag, f"CLEARED {flag.name}{' ' + detail if detail else ''}")

    def _event(self, t: float, flag: Fault, text: str) -> None:
        ev = (float(t), flag, text[:50])
        self.events.append(ev)
        self._new.append(ev)

    def pop_events(self) -> list:
        """Events (t_s, flag, text) since the last call, oldest first."""
        out, self._new = self._new, []
        return out

    # -- link ----------------------------------------------------------------------------------
    def packet(self, system: int, component: int, seq: int, ordered: bool = True) -> None:
        """A MAVLink packet from (system, component) with sequence number seq (0..255).

        `ordered=False`: a packet that may legitimately overtake, trail or repeat the others
        (lock-step's frame marker: hil.faults never delays it, and the HIL endpoint re-sends it as
        is while it waits for a late controller): it fills its place in the sequence but neither
        moves the order on nor counts as reordered or duplicated."""
        key = (system, component)
        s = self._sources.get(key)
        if s is None:
            if len(self._sources) >= self.config.max_sources:
                self.untracked_packets += 1  # a sender cycling its ids must not grow memory
                return
            s = self._sources[key] = _Source(self.config.link_window_packets)
        idx = s.count
        s.count = idx + 1
        seq &= 0xFF
        if idx - s.seen[seq] < 128:
            if ordered:
                s.push(1)  # seen among this source's last 128 packets: a duplicate
            return
        s.seen[seq] = idx
        if s.last < 0:
            s.last = seq
            s.push(0)
            return
        last = s.last
        d = (seq - last) & 0xFF
        if d < 128:
            if not ordered:
                s.push(0)  # ahead: the next ordered packet will find its number seen
                return
            missing = 0  # numbers in between not seen among the last 128 packets (for now)
            if d > 1:
                seen = s.seen
                for q in range(last + 1, last + d):
                    if idx - seen[q & 0xFF] >= 128:
                        missing += 1
            s.last = seq
            s.push(4 * missing)
        elif 256 - d <= self.config.reorder_max_back:
            s.push(2 if ordered else 3)  # late: it fills a gap counted before
        else:
            if ordered:
                s.last = seq  # far back: the sender restarted; resynchronise
            s.push(0)

    def sample_age(self, t_now_s: float, t_sample_s: float) -> None:
        """A sensor sample stamped t_sample_s arrived when the loop's clock said t_now_s."""
        raw = t_now_s - t_sample_s
        if not math.isfinite(raw):
            return  # nothing seen yet
        if self.config.absolute_age:
            age = raw if raw > 0.0 else 0.0
        else:
            if raw < self._age_min:
                self._age_min = raw
            age = raw - self._age_min
        a = self._age_alpha if self._ages >= self.config.age_samples else 1.0 / (self._ages + 1)
        self._ages += 1
        self.delay_s += a * (age - self.delay_s)
        self.jitter_s += a * (abs(age - self.delay_s) - self.jitter_s)

    def _check_link(self, t: float) -> None:
        c = self.config
        loss = dup = reo = 0.0
        for s in self._sources.values():
            n = s.received + s.dups
            if n < c.min_packets:
                continue
            gaps = max(s.gaps, 0)  # < 0 only while a late packet's gap has left the window
            loss = max(loss, gaps / (gaps + s.received)) if s.received else loss
            if s.dups >= c.min_events:
                dup = max(dup, s.dups / n)
            if s.reorders >= c.min_events:
                reo = max(reo, s.reorders / n)
        self.link_ratios = {"loss": loss, "duplicate": dup, "reorder": reo}
        conds = {
            Fault.LINK_LOSS: (loss > c.loss_threshold, f"{100 * loss:.0f}%"),
            Fault.LINK_DUPLICATE: (dup > c.duplicate_threshold, f"{100 * dup:.0f}%"),
            Fault.LINK_REORDER: (reo > c.reorder_threshold, f"{100 * reo:.0f}%"),
            Fault.LINK_DELAY: (self.delay_s > c.delay_threshold_s or self.jitter_s > c.jitter_threshold_s,
                               f"{1e3 * self.delay_s:.0f}+-{1e3 * self.jitter_s:.0f} ms"),
        }
        for flag, (cond, detail) in conds.items():
            if self._deb_link[flag].update(cond, t, c.link_persist_s, c.link_clear_s):
                if cond:
                    self._raise(flag, flag, t, detail)
                else:
                    self._clear(flag, t)

    @property
    def drop_rate(self) -> float:
        """Worst source's loss ratio at the last check (0..1)."""
        return self.link_ratios["loss"]

    # -- IMU -----------------------------------------------------------------------------------
    def imu(self, t_s: float, accel, gyro) -> bool:
        """A decoded IMU sample at t_s (its time stamp). False: frozen, keep it out of everything."""
        self._imu_arrived(t_s)
        values = (tuple(accel), tuple(gyro))
        if values == self._imu_last:
            self._imu_repeats += 1
            if self._imu_repeats + 1 >= self.config.imu_frozen_samples:
                self._raise("imu_frozen", Fault.IMU_FROZEN, t_s, f"{self._imu_repeats + 1} identical samples")
                return False
            return True
        self._imu_last = values
        self._imu_repeats = 0
        self._clear("imu_frozen", t_s)  # (only if it was raised)
        return True

    def imu_invalid(self, t_s: float) -> None:
        """An IMU message that did not decode (NaN / inf), arriving at loop time t_s."""
        if not math.isfinite(t_s):
            t_s = self._t_imu if self._t_imu is not None else 0.0
        self._imu_arrived(t_s)
        self._t_nan = t_s
        self._raise("imu_nan", Fault.IMU_NAN, t_s)

    def _imu_arrived(self, t_s: float) -> None:
        if self._t_imu is None or t_s > self._t_imu:
            self._t_imu = t_s
        if "imu_lost" in self._active:
            self._clear("imu_lost", t_s)

    @property
    def imu_frozen(self) -> bool:
        return "imu_frozen" in self._active

    # -- actuators -----------------------------------------------------------------------------
    def _advance_models(self, t: float) -> None:
        """Move the motor and servo models to t under the command in force (spec 4 lags)."""
        dt = t - self._t_model
        if dt <= 0.0:
            return
        c = self.config
        if c.motor_time_constant_s > 0:
            self._n_model = self._n_cmd + (self._n_model - self._n_cmd) * math.exp(-dt / c.motor_time_constant_s)
        else:
            self._n_model = self._n_cmd.copy()
        self._j_model = self._joints_at(dt)
        self._t_model = t

    def _joints_at(self, dt: float, j0=None, cmd=None) -> np.ndarray:
        """Joint angles dt after a state j0 under command cmd (default: the model's now)."""
        c = self.config
        lim = c.angle_limit_rad
        j0 = self._j_model if j0 is None else j0
        cmd = self._j_cmd if cmd is None else cmd
        if c.servo_time_constant_s <= 0 or dt <= 0:
            return np.clip(cmd, -lim, lim) if dt > 0 else j0
        return _servo_motion(j0, cmd, float(dt), c.servo_time_constant_s, c.servo_rate_limit_rad_s, lim)[0]

    def _start_models(self) -> None:
        """First actuator feedback: the models start at the command in force (settled)."""
        self._models_on = True
        c, k = self.config, self.k
        self._n_cmd = np.minimum(np.maximum(self._cmd[:k], 0.0), c.n_max_rev_s)
        self._j_cmd = np.ascontiguousarray(self._cmd[k:3 * k])
        self._n_model = self._n_cmd.copy()
        self._j_model = np.clip(self._j_cmd, -c.angle_limit_rad, c.angle_limit_rad)
        self._judge_from = self._t_model + MODEL_SETTLE_S

    def _snapshot(self, t: float):
        """The model state in force at time t: (t0, n0, n_cmd, j0, j_cmd), or None if too old."""
        if t >= self._t_model:
            return self._t_model, self._n_model, self._n_cmd, self._j_model, self._j_cmd
        for snap in reversed(self._past):
            if snap[0] <= t:
                return snap
        return None

    def rpm(self, t_s: float, first_unit: int, rpm) -> None:
        """ESC telemetry received at loop time t_s: rpm of units first_unit, first_unit + 1, ..."""
        c = self.config
        if self._t_model is None or not math.isfinite(t_s):
            return
        if not self._models_on:
            self._start_models()
            return
        # ESC telemetry carries no time: it is taken as measured the link's mean delay ago
        t_meas = t_s - self.delay_s
        snap = self._snapshot(t_meas)
        if snap is None:
            return
        t0, n0, n_cmd = snap[0], snap[1], snap[2]
        dt = max(t_meas - t0, 0.0)
        decay = math.exp(-dt / c.motor_time_constant_s) if c.motor_time_constant_s > 0 else 0.0
        floor = c.jet_min_speed * c.n_max_rev_s
        for j, r in enumerate(rpm):
            i = first_unit + j
            if not 0 <= i < self.k:
                continue
            n_hat = float(n_cmd[i] + (n0[i] - n_cmd[i]) * decay)
            if n_hat < floor:
                continue
            last = self._t_rpm[i]
            lam = math.exp(-(t_s - last) / c.jet_window_s) if last is not None and t_s > last else 1.0
            n_meas = abs(float(r)) / 60.0
            self._sxy[i] = lam * self._sxy[i] + n_meas * n_hat
            self._sxx[i] = lam * self._sxx[i] + n_hat * n_hat
            self._sw[i] = lam * self._sw[i] + 1.0
            self._t_rpm[i] = t_s
            self.efficiency[i] = self._sxy[i] / self._sxx[i]
            self._rpm_new = True

    def joints(self, t_s: float, alpha_rad, beta_rad) -> None:
        """Measured joint angles (ACTUATOR_OUTPUT_STATUS) stamped t_s.

        Only feedback newer than the newest judged counts (a reordered or repeated sample is no
        evidence); it is compared with the model at its own time stamp. A free joint gathers
        evidence of being stuck while its residual is over the tolerance AND it stays within the
        tolerance of where the evidence began: a joint that lags its model because the commands
        reach it late (link delay, loss, reordering) still moves, which restarts the evidence."""
        if self._t_model is None or not math.isfinite(t_s):
            return  # before the first command: no reference to compare with
        if not self._models_on:
            self._start_models()
            return
        c = self.config
        if t_s <= self._t_joint and t_s > self._t_joint - c.joint_stale_s:
            return  # older than the newest judged (far older: the sender's clock restarted)
        snap = self._snapshot(t_s)
        meas = np.array(tuple(alpha_rad) + tuple(beta_rad), dtype=float)
        if snap is None or meas.shape != self._j_model.shape or not np.all(np.isfinite(meas)):
            return  # older than the models kept, or not k + k finite angles
        tol = c.joint_tolerance_rad
        gap = t_s - self._t_joint > c.joint_stale_s  # evidence does not bridge a feedback gap
        resid = np.abs(meas - self._joints_at(t_s - snap[0], snap[3], snap[4]))
        cand = resid > tol
        going = np.isfinite(self._j_since) & ~(np.abs(meas - self._anchor) > tol)  # (NaN anchor: not going)
        if gap:
            going[:] = False
        cont = cand & going
        start = cand & ~going
        self._j_count = np.where(cont, self._j_count + 1, np.where(start, 1, 0))
        self._j_since = np.where(cont, self._j_since, np.where(start, t_s, math.nan))
        self._anchor = np.where(cont, self._anchor, meas)
        stuck = np.array(self._stuck)
        away = np.abs(meas - stuck) > tol  # a raised joint seen away from its angle (False where free)
        self._moved_since = np.where(away & ~gap, np.where(np.isfinite(self._moved_since), self._moved_since, t_s),
                                     math.nan)
        self._j_meas = meas
        self._j_resid = resid
        self._t_joint = t_s
        self._joint_new = True

    def _check_jets(self, t: float) -> bool:
        c = self.config
        changed = False
        for i in range(self.k):
            if self._jet_state[i] == "dead" or self._sw[i] < c.jet_min_samples:
                continue
            e = self.efficiency[i]
            cand = "dead" if e < c.jet_dead_efficiency else "weak" if e < c.jet_weak_efficiency else "ok"
            if cand != self._jet_candidate[i]:
                self._jet_candidate[i] = cand
                self._jet_since[i] = t
            state = self._jet_state[i]
            if cand != state and t - self._jet_since[i] >= c.jet_persist_s - 1e-9:
                if state != "ok":
                    self._clear(("jet", i), t, f"unit {i + 1}")
                self._jet_state[i] = cand
                if cand != "ok":
                    flag = Fault.JET_DEAD if cand == "dead" else Fault.JET_WEAK
                    self._raise(("jet", i), flag, t, f"unit {i + 1} e={e:.2f}")
                changed = True
            elif state == "weak" and abs(e - self.health.efficiency[i]) > c.jet_republish:
                changed = True  # a weak jet's efficiency estimate moved: republish it
        return changed

    def _check_joints(self, t: float) -> bool:
        """Raise, clear, release for a probe or hold again; True when the published health changed.

        A free joint is raised once its evidence (see `joints`) has lasted `joint_persist_s` of
        sample time over `joint_min_samples` samples: it is then held for the allocator at the
        measured angle. A raised joint seen away from that angle for `joint_persist_s` is cleared.
        Since the allocator holds a stuck joint still, a false alarm would never show itself: a held
        joint is released to the allocator (`health` free, the fault still raised) `joint_probe_s`
        after it was held; if it follows the commands it clears, if the evidence of being stuck
        builds up again it is held again and the next probe waits twice as long."""
        c = self.config
        if not self._stuck_count and not np.isfinite(self._j_since).any():
            return False  # none stuck, none on its way to be
        tj = self._t_joint
        fresh = t - tj <= c.joint_stale_s
        persist = c.joint_persist_s - 1e-9
        changed = False
        for j in range(2 * self.k):
            since = self._j_since[j]
            evidence = fresh and tj - since >= persist and self._j_count[j] >= c.joint_min_samples
            what = f"unit {j % self.k + 1} {'azimuth' if j < self.k else 'elevation'}"
            if not math.isfinite(self._stuck[j]):
                if evidence:
                    self._stuck[j] = float(self._j_meas[j])
                    self._held[j] = True
                    self._probe_every[j] = c.joint_probe_s
                    self._probe_at[j] = t + c.joint_probe_s
                    self._stuck_count += 1
                    self._raise(("joint", j), Fault.JOINT_STUCK, t, f"{what} at {self._stuck[j]:.2f} rad")
                    changed = True
                continue
            moved = self._moved_since[j]
            if fresh and tj - moved >= persist:  # (NaN: not moved)
                self._stuck[j] = math.nan
                self._held[j] = False
                self._moved_since[j] = math.nan
                self._stuck_count -= 1
                self._clear(("joint", j), t, what)
                changed = True
            elif self._held[j]:
                if t >= self._probe_at[j]:  # release it: does it follow its commands?
                    self._held[j] = False
                    self._probe_end[j] = t + c.joint_probe_window_s
                    self._j_since[j] = math.nan
                    self._j_count[j] = 0
                    changed = True
            elif evidence or t >= self._probe_end[j]:  # stuck after all (or no sign either way)
                self._held[j] = True
                if evidence:
                    self._probe_every[j] = min(2.0 * self._probe_every[j], c.joint_probe_max_s)
                self._probe_at[j] = t + self._probe_every[j]
                self._j_since[j] = math.nan
                self._j_count[j] = 0
                changed = True
        return changed

    def _publish_health(self) -> None:
        k = self.k
        eff = tuple(0.0 if s == "dead" else round(self.efficiency[i], 3) if s == "weak" else 1.0
                    for i, s in enumerate(self._jet_state))
        held = [a if h else math.nan for a, h in zip(self._stuck, self._held)]
        h = UnitHealth(eff, tuple(held[:k]), tuple(held[k:]))
        if h != self.health:
            self.health = h
            self.health_version += 1

    # -- the tick ------------------------------------------------------------------------------
    def tick(self, t_s: float, command=None, health=None) -> Fault:
        """One control period at t_s: check every condition, then take `command` (the command
        sent now, in force from t_s) into the actuator models. `health`: the estimator's
        EstimatorHealth (depth rejections, and `depth_resets` where it has them). Returns the
        flags active now."""
        c = self.config
        t = float(t_s)
        if self._models_on:
            if command is not None:  # the segment [t_model, t) under the command in force ends here
                self._past.append((self._t_model, self._n_model, self._n_cmd, self._j_model, self._j_cmd))
            self._advance_models(t)
        if self._rpm_new:
            self._rpm_new = False
            if t >= self._judge_from and self._check_jets(t):
                self._publish_health()
        if self._joint_new or self._stuck_count:  # new feedback (ATTITUDE rate), or a probe due
            self._joint_new = False
            if t >= self._judge_from and self._check_joints(t):
                self._publish_health()
        if self._t_imu is not None and t - self._t_imu > c.imu_timeout_s + 1e-9:
            self._raise("imu_lost", Fault.IMU_LOST, t, f"none for {t - self._t_imu:.2f} s")
        if "imu_nan" in self._active and t - self._t_nan > c.imu_nan_clear_s:
            self._clear("imu_nan", t)
        if health is not None:
            self._check_depth(t, health)
        if t >= self._next_link_check:
            self._next_link_check = t + c.link_check_period_s
            self._check_link(t)
        if command is not None:
            cmd = self._cmd = np.array(command, dtype=float)  # a copy: the caller's may change
            if self._models_on:
                k = self.k
                self._n_cmd = np.minimum(np.maximum(cmd[:k], 0.0), c.n_max_rev_s)
                self._j_cmd = cmd[k:3 * k]
            self._t_model = t
        return self.faults

    def _check_depth(self, t: float, health) -> None:
        c = self.config
        rej = int(health.rejected_gated[2])
        resets = int(getattr(health, "depth_resets", 0))
        evidence = False
        if rej > self._depth_rej:
            for _ in range(min(rej - self._depth_rej, self._depth_times.maxlen)):
                self._depth_times.append(t)
            while self._depth_times and self._depth_times[0] < t - c.depth_window_s:
                self._depth_times.popleft()
            evidence = len(self._depth_times) >= c.depth_rejections
            self._depth_rej = rej
        if resets > self._depth_resets:
            self._depth_resets = resets
            evidence = True
        if evidence:
            self._t_depth_evidence = t
            self._raise("depth", Fault.DEPTH_JUMP, t, f"{rej} rejected, {resets} re-anchored")
        elif "depth" in self._active and t - self._t_depth_evidence > c.depth_clear_s:
            self._clear("depth", t)


__all__ = ["Fault", "FaultMonitor", "MonitorConfig", "UnitHealth", "fault_names"]
