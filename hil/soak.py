"""`jetloop soak`: hours of simulated time in lock-step, random missions and random faults, measured.

The three parties of `jetloop demo` (hil.demo.run_closed_loop: plant endpoint, onboard loop and
telemetry recorder over loopback UDP, the onboard loop and the recorder in their own processes)
fly back-to-back random missions (`random_mission`) while random faults the vehicle is meant to
survive are injected (`random_faults`). The run is deterministic for a seed (lock-step).
Three properties are measured, the way an autopilot's own soak tests measure themselves:

- deadlines: every onboard control step (estimate + control + compensate + allocate) against
  the 10 ms period of 100 Hz, in wall time and in CPU time (onboard.loop.LoopStats counts every
  overrun over the whole run and logs the newest 100 with where their time went; p99.9 and
  maxima over its step history). On a virtual machine a thread's CPU clock also counts stalls
  of its vCPU (bench/bench_cpu_clock.py), so the time stolen from the onboard's vCPU is read
  every lock-step period and an overrun whose excess it makes up is counted as the machine's;
  the verdict fails on the rest (`StealClock`, `stolen_around`, `stolen_explains`);
- memory: the resident set (/proc/PID/statm) of the plant (this process), the onboard loop and
  the recorder sampled every simulated minute; growth = slope of a least-squares line through the
  samples after warm-up, in kB per simulated hour (the endpoint keeps no history: history=False);
- packets: every packet the endpoint sent and received is in its recording (mission.tlog),
  counted by type; MAVLink sequence numbers are continuous per source in each recording (a gap
  is a packet lost between sender and recorder); the telemetry recorder got every packet the
  onboard loop sent it (telemetry.tlog against the onboard's ground-link count).

Faults (hil.faults.FaultPlan; only what the vehicle must survive and recover from), drawn per
mission while it is submerged: short IMU dropouts or NaN IMU windows (below the failsafe's 0.3 s
IMU timeout: the estimator coasts), long ones (they trip the failsafe; the ground recovers
explicitly, as an operator would: disarm, re-arm, send the setpoint again, all as COMMAND_LONG /
SET_POSITION_TARGET_LOCAL_NED messages in vehicle time), a frozen IMU, a depth sensor jump, and
bursts of garbage bytes on the sensor link; and over the run one window each of link packet
loss (up to 30 %), delay with jitter, duplicates and reordering (`random_link_faults`).
A dead or weak jet and a stuck joint last for the rest of a run, so they are not drawn.
"""

from __future__ import annotations

import json
import math
import os
import sys
import time
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hil.demo import DEMO_CONFIG, Leg, Mission, run_closed_loop
from hil.endpoint import EndpointError
from hil.faults import DepthJump, FaultPlan
from onboard.loop import Overrun, arm_command, body_velocity_target, depth_yaw_target
from onboard.vehicle import Vehicle, load_vehicle

MINUTE_S = 60.0
MOCAP = "ATT_POS_MOCAP"  # written into the plant's recording by the recorder itself, never sent
HANDSHAKE = Counter({"HEARTBEAT": 1})  # what the endpoint takes before recording starts (HilEndpoint.start)


# ------------------------------------------------------------------------------------------------
# Missions (pure)


@dataclass(frozen=True)
class Envelope:
    """What a random mission may ask of the vehicle (pool geometry and speed)."""

    depth_min_m: float
    depth_max_m: float  # deepest setpoint: the hull stays clear of the floor by `floor_margin_m`
    surge_max_m_s: float = 0.3
    leg_min_s: float = 6.0
    leg_max_s: float = 15.0
    legs_min: int = 2
    legs_max: int = 5

    @classmethod
    def from_vehicle(cls, vehicle: Vehicle, floor_margin_m: float = 0.15, depth_min_m: float = 0.25) -> "Envelope":
        env = vehicle.environment
        pool_m = env.floor_depth - env.surface_depth
        deepest = pool_m - vehicle.body.radius - floor_margin_m  # hull bottom floor_margin_m above the floor
        if deepest <= depth_min_m:
            raise ValueError(f"vehicle {vehicle.name}: the pool ({pool_m:.2f} m) is too shallow for a "
                             f"{vehicle.body.radius:.2f} m hull below {depth_min_m:.2f} m")
        return cls(depth_min_m=depth_min_m, depth_max_m=round(deepest, 3))


ARM_S = 1.0  # a mission arms 1 s after it starts
DIVE_S = 8.0  # the first leg: dive to depth, heading and zero speed
SURFACE_S = 10.0  # the last leg: stop and surface
END_S = 1.0  # after the surface leg the mission disarms; the next mission starts then
END_MEAN_S = 2.0  # surfaced: the mean centre depth over the last 2 s of the surface leg is under the
# hull's radius (its top is out of the water). The vehicle floats with its centre about 0.12 m down
# and, still asked for depth 0, bobs by +-0.04 m there: one sample could catch it at 0.17 m.


def random_mission(rng: np.random.Generator, env: Envelope) -> Mission:
    """Dive to a random depth and heading, then 2-5 random legs (new depth, new heading, forward
    at a random speed, or hold), then stop and surface. Times are the mission's own (0 at its start);
    each leg lasts leg_min_s..leg_max_s, enough to settle (hil.demo.Leg.settle_s)."""
    depth = lambda: round(float(rng.uniform(env.depth_min_m, env.depth_max_m)), 3)  # noqa: E731
    yaw = lambda: round(float(rng.uniform(-math.pi, math.pi)), 4)  # noqa: E731
    legs = [Leg(ARM_S, "dive", depth_m=depth(), yaw_rad=yaw(), surge_m_s=0.0, settle_s=6.0)]
    t = ARM_S + DIVE_S
    for _ in range(int(rng.integers(env.legs_min, env.legs_max + 1))):
        kind = rng.choice(("depth", "yaw", "forward", "hold"))
        if kind == "depth":
            leg = Leg(t, "depth", depth_m=depth(), surge_m_s=0.0, settle_s=5.0)
        elif kind == "yaw":
            leg = Leg(t, "yaw", yaw_rad=yaw(), surge_m_s=0.0, settle_s=4.0)
        elif kind == "forward":
            leg = Leg(t, "forward", surge_m_s=round(float(rng.uniform(0.05, env.surge_max_m_s)), 3), settle_s=3.0)
        else:
            leg = Leg(t, "hold", surge_m_s=0.0, settle_s=2.0)
        legs.append(leg)
        t += round(float(rng.uniform(env.leg_min_s, env.leg_max_s)), 2)
    legs.append(Leg(t, "surface", depth_m=0.0, surge_m_s=0.0, settle_s=SURFACE_S))
    return Mission(legs=tuple(legs), duration_s=round(t + SURFACE_S + END_S, 2), arm_s=ARM_S)


def mission_problems(mission: Mission, env: Envelope) -> list:
    """What makes `mission` unfit for a soak (empty when it is valid): legs in time order inside
    the mission, each long enough to settle, depths and speeds in the envelope, surfacing and
    stopping at the end."""
    out = []
    legs = mission.legs
    if not legs:
        return ["no legs"]
    if legs[0].t0_s < mission.arm_s:
        out.append(f"first leg at {legs[0].t0_s} s, before arming at {mission.arm_s} s")
    for a, b in zip(legs, legs[1:]):
        if b.t0_s - a.t0_s < max(env.leg_min_s, a.settle_s):
            out.append(f"leg {a.name!r} at {a.t0_s} s lasts {b.t0_s - a.t0_s:.2f} s, under "
                       f"{max(env.leg_min_s, a.settle_s)} s")
    for leg in legs:
        if leg.depth_m is not None and not (leg.depth_m == 0.0 or env.depth_min_m <= leg.depth_m <= env.depth_max_m):
            out.append(f"leg {leg.name!r}: depth {leg.depth_m} m outside {env.depth_min_m}..{env.depth_max_m} m")
        if leg.surge_m_s is not None and not 0.0 <= leg.surge_m_s <= env.surge_max_m_s:
            out.append(f"leg {leg.name!r}: surge {leg.surge_m_s} m/s outside 0..{env.surge_max_m_s} m/s")
        if leg.yaw_rad is not None and not -math.pi <= leg.yaw_rad <= math.pi:
            out.append(f"leg {leg.name!r}: yaw {leg.yaw_rad} rad outside -pi..pi")
    last = legs[-1]
    if last.depth_m != 0.0 or last.surge_m_s != 0.0:
        out.append(f"the last leg {last.name!r} does not stop and surface")
    if mission.duration_s < last.t0_s + last.settle_s:
        out.append(f"the mission ends at {mission.duration_s} s, before its last leg settles")
    return out


# ------------------------------------------------------------------------------------------------
# Faults (pure)


SHORT_DROPOUT_S = (0.05, 0.2)  # below the failsafe's IMU timeout (0.3 s): the estimator coasts
LONG_DROPOUT_S = (0.5, 1.5)  # trips the failsafe: recovered by disarm + re-arm
FREEZE_SHORT_S = (0.03, 0.07)  # IMU values repeat with fresh stamps: under the monitor's 10 samples
FREEZE_LONG_S = (0.2, 0.5)  # frozen for 10 samples or more: onboard.monitor raises IMU_FROZEN, the failsafe trips
DEPTH_JUMP_M = (0.05, 0.15)  # the depth sensor steps by +- this ...
DEPTH_JUMP_S = (1.0, 3.0)  # ... for this long
GARBAGE_BYTES = FaultPlan().garbage_bytes  # per burst (FaultPlan has one size for the run)
KINDS = ("imu_dropout_short", "imu_dropout_long", "imu_nan_short", "imu_nan_long", "imu_freeze_short",
         "imu_freeze_long", "depth_jump", "garbage")
# no usable IMU for > 0.3 s, or a frozen one: the failsafe must trip (and the ground recover it)
TRIPS = ("imu_dropout_long", "imu_nan_long", "imu_freeze_long")
LENGTHS_S = {"imu_dropout_short": SHORT_DROPOUT_S, "imu_nan_short": SHORT_DROPOUT_S,
             "imu_dropout_long": LONG_DROPOUT_S, "imu_nan_long": LONG_DROPOUT_S,
             "imu_freeze_short": FREEZE_SHORT_S, "imu_freeze_long": FREEZE_LONG_S}
RECOVER_DISARM_S = 0.3  # after the IMU returns, the ground disarms ...
RECOVER_ARM_S = 0.6  # ... re-arms and sends the setpoint again


@dataclass(frozen=True)
class Injection:
    """One fault at t_s (vehicle time) in mission `mission` (index), with its parameter."""

    kind: str  # one of KINDS
    t_s: float
    length_s: float = 0.0  # windows (dropout, NaN, freeze, depth jump)
    n_bytes: int = 0  # garbage
    offset_m: float = 0.0  # depth jump
    mission: int = -1


@dataclass(frozen=True)
class Schedule:
    """Back-to-back missions over the soak and the faults injected into them."""

    starts_s: tuple  # vehicle time each mission starts
    missions: tuple
    injections: tuple
    duration_s: float
    link: dict = field(default_factory=dict)  # FaultPlan link fields (loss, loss_window_s, ...)

    def setpoints(self) -> list:
        """(vehicle time, ground message): each mission's own (shifted), a disarm at its end, and the
        explicit failsafe recovery after each long IMU dropout."""
        out = []
        for t0, m in zip(self.starts_s, self.missions):
            out += [(t0 + t, msg) for t, msg in m.setpoints()]
            out.append((t0 + m.duration_s - END_S, arm_command(False)))
        for inj in self.injections:
            if inj.kind in TRIPS:
                t1 = inj.t_s + inj.length_s
                d = self.missions[inj.mission].demand_at(t1 - self.starts_s[inj.mission])
                out.append((t1 + RECOVER_DISARM_S, arm_command(False)))
                out.append((t1 + RECOVER_ARM_S, arm_command(True)))
                out.append((t1 + RECOVER_ARM_S, depth_yaw_target(d["depth_m"], d["yaw_rad"])))
                if d["surge_m_s"] is not None:
                    out.append((t1 + RECOVER_ARM_S, body_velocity_target(d["surge_m_s"], 0.0)))
        return sorted(out, key=lambda p: p[0])  # stable: at one instant, arm goes before its setpoint

    def faults(self) -> FaultPlan:
        win = lambda *kinds: tuple((i.t_s, round(i.t_s + i.length_s, 6)) for i in self.injections  # noqa: E731
                                   if i.kind in kinds)
        jumps = tuple(DepthJump(i.t_s, i.offset_m, round(i.t_s + i.length_s, 6))
                      for i in self.injections if i.kind == "depth_jump")
        garbage = tuple(i.t_s for i in self.injections if i.kind == "garbage")
        return FaultPlan(imu_dropouts_s=win("imu_dropout_short", "imu_dropout_long"),
                         imu_nan_s=win("imu_nan_short", "imu_nan_long"), imu_freeze_s=win("imu_freeze_short", "imu_freeze_long"),
                         depth_jumps=jumps, garbage_times_s=garbage, garbage_bytes=GARBAGE_BYTES, **self.link)

    def mission_at(self, t_s: float) -> int:
        """Index of the mission flying at t_s (-1 before the first / after the last)."""
        i = int(np.searchsorted(self.starts_s, t_s, side="right")) - 1
        if i < 0 or t_s >= self.starts_s[i] + self.missions[i].duration_s:
            return -1
        return i

    def armed_expected(self, t_s: float, margin_s: float = 0.5) -> bool:
        """Whether the vehicle should be armed and driving at t_s: inside a mission, margin_s past its
        arming and before its surface leg, and not in a failsafe trip or its recovery (+ margin)."""
        m = self.mission_at(t_s)
        if m < 0:
            return False
        t0, mission = self.starts_s[m], self.missions[m]
        if not t0 + mission.arm_s + margin_s <= t_s < t0 + mission.legs[-1].t0_s:
            return False
        return not any(i.t_s <= t_s < i.t_s + i.length_s + RECOVER_ARM_S + margin_s
                       for i in self.injections if i.kind in TRIPS)

    def next_armed_s(self, t_s: float, within_s: float = 120.0, step_s: float = 0.05) -> float | None:
        """The first instant from t_s (on a step_s grid) at which `armed_expected`; None within within_s."""
        for k in range(int(within_s / step_s) + 1):
            if self.armed_expected(t_s + k * step_s):
                return t_s + k * step_s
        return None

    def counts(self) -> dict:
        c = Counter(i.kind for i in self.injections)
        for name in ("loss", "delay_s", "duplicate", "reorder"):
            if self.link.get(name):
                c[f"link_{name.removesuffix('_s')}"] += 1
        return dict(sorted(c.items()))


def random_faults(rng: np.random.Generator, start_s: float, mission: Mission, index: int,
                  per_mission: tuple = (1, 3), gap_s: float = 4.0) -> list:
    """1-3 faults at random instants while the mission is armed and below the surface (from the
    dive's settling to the surface leg), at least gap_s apart, a long dropout's recovery done
    before the next fault and before the surface leg."""
    lo = mission.arm_s + mission.legs[0].settle_s
    hi = mission.legs[-1].t0_s - LONG_DROPOUT_S[1] - RECOVER_ARM_S - 1.0
    out: list = []
    if hi <= lo:
        return out
    n = int(rng.integers(per_mission[0], per_mission[1] + 1))
    times = np.sort(rng.uniform(lo, hi, n))
    last = -math.inf
    for t in times:
        if t - last < gap_s:
            continue
        last = t
        t_abs = round(start_s + float(t), 2)
        kind = str(rng.choice(KINDS))
        if kind in LENGTHS_S:
            out.append(Injection(kind, t_abs, length_s=round(float(rng.uniform(*LENGTHS_S[kind])), 3), mission=index))
        elif kind == "depth_jump":
            off = float(rng.uniform(*DEPTH_JUMP_M)) * float(rng.choice((-1.0, 1.0)))
            out.append(Injection(kind, t_abs, length_s=round(float(rng.uniform(*DEPTH_JUMP_S)), 3),
                                 offset_m=round(off, 3), mission=index))
        else:
            out.append(Injection(kind, t_abs, n_bytes=GARBAGE_BYTES, mission=index))
    return out


def random_link_faults(rng: np.random.Generator, duration_s: float) -> dict:
    """One window each of packet loss (10-30 %), delay (10-50 ms + up to 20 ms jitter), duplicates
    and reordering (5-20 %), each a sixth of the run (at most 5 min) at a random place in it."""
    length = min(300.0, duration_s / 6)

    def window():
        t0 = round(float(rng.uniform(0.05 * duration_s, 0.95 * duration_s - length)), 2)
        return (t0, round(t0 + length, 2))

    return {"loss": round(float(rng.uniform(0.1, 0.3)), 3), "loss_window_s": window(),
            "delay_s": round(float(rng.uniform(0.01, 0.05)), 3), "jitter_s": round(float(rng.uniform(0.0, 0.02)), 3),
            "delay_window_s": window(),
            "duplicate": round(float(rng.uniform(0.05, 0.2)), 3), "duplicate_window_s": window(),
            "reorder": round(float(rng.uniform(0.05, 0.2)), 3), "reorder_window_s": window()}


def make_schedule(vehicle: Vehicle, duration_s: float, seed: int, faults: bool = True) -> Schedule:
    """Random missions back to back until `duration_s`, random faults inside them (seeded)."""
    rng = np.random.default_rng(seed)
    env = Envelope.from_vehicle(vehicle)
    starts, missions, injections = [], [], []
    t = 0.0
    while True:
        m = random_mission(rng, env)
        if t + m.duration_s > duration_s:
            break
        if faults:
            injections += random_faults(rng, t, m, len(missions))
        starts.append(t)
        missions.append(m)
        t = round(t + m.duration_s, 2)
    link = random_link_faults(rng, float(duration_s)) if faults else {}
    return Schedule(tuple(starts), tuple(missions), tuple(injections), float(duration_s), link)


# ------------------------------------------------------------------------------------------------
# Measurements (pure)


def growth_kb_per_h(t_s, rss_kb, warmup_s: float) -> float:
    """Slope of the least-squares line through the samples at t >= warmup_s, in kB per hour."""
    t = np.asarray(t_s, float)
    r = np.asarray(rss_kb, float)
    keep = t >= warmup_s
    if keep.sum() < 3:
        return float("nan")
    slope_kb_s = np.polyfit(t[keep], r[keep], 1)[0]
    return float(slope_kb_s * 3600.0)


def sequence_gaps(seq) -> dict:
    """What a MAVLink sequence (8-bit, wrapping) says about the packets of one sender, in the order
    they were recorded: each step is unwrapped as a signed difference in -128..127 (reordering and
    duplicates move it back), so `missing` = numbers in the span never seen, `duplicates` =
    repeats, `reordered` = steps back. A run of 128 or more lost packets in a row would be misread."""
    s = np.asarray(seq, np.int64)
    if s.size < 2:
        return {"missing": 0, "duplicates": 0, "reordered": 0}
    d = (np.diff(s) + 128) % 256 - 128
    u = np.concatenate([[0], np.cumsum(d)])
    n_unique = np.unique(u).size
    return {"missing": int(u.max() - u.min() + 1 - n_unique), "duplicates": int(s.size - n_unique),
            "reordered": int(np.sum(d < 0))}


def armed_timeline(path: Path, source=(1, 191)):
    """(vehicle time s, armed) of every HIL_ACTUATOR_CONTROLS from the onboard loop in a plant
    recording: its mode carries MAV_MODE_FLAG_SAFETY_ARMED while the loop drives the jets."""
    from ground.recording import decode_message, scan_packets

    buf, off, plen, mid, src, ts = scan_packets(Path(path).read_bytes())
    a, sel = decode_message(buf, off, plen, mid, "HIL_ACTUATOR_CONTROLS")
    if a is None:
        return np.zeros(0), np.zeros(0, bool)
    mine = src[sel] == source[0] * 256 + source[1]
    return np.asarray(a["time_usec"][mine], float) / 1e6, (np.asarray(a["mode"][mine]) & 128) != 0


def armed_at(timeline, t_s: float) -> bool:
    """Whether the newest command at or before t_s said armed."""
    t, armed = timeline
    i = int(np.searchsorted(t, t_s + 1e-9, side="right")) - 1
    return bool(i >= 0 and armed[i])


def scan_tlog(path: Path) -> dict:
    """Every good packet of a .tlog by (system, component) source: message counts and sequence
    numbers (through ground.recording's compiled scanner, which checks each packet's CRC)."""
    from ground.recording import _dialect, scan_packets

    buf, off, plen, mid, src, ts = scan_packets(Path(path).read_bytes())
    v2 = buf[np.maximum(off - 10, 0)] == 0xFD
    seq = np.where(v2, buf[np.maximum(off - 6, 0)], buf[np.maximum(off - 4, 0)]).astype(np.int64)
    d = _dialect()
    names = {i: cls.msgname for i, cls in d.mavlink_map.items()}
    out = {}
    for s in np.unique(src):
        sel = src == s
        counts = Counter()
        for m, c in zip(*np.unique(mid[sel], return_counts=True)):
            counts[names.get(int(m), f"ID_{int(m)}")] = int(c)
        sent = sel & (mid != getattr(d, f"MAVLINK_MSG_ID_{MOCAP}"))  # the recorder's own mocap has its own numbers
        out[(int(s) >> 8, int(s) & 0xFF)] = {
            "counts": counts, **sequence_gaps(seq[sent]),
            "first_seq": int(seq[sent][0]) if sent.any() else -1,
        }
    return out


def rss_kb(pid: int | str = "self") -> int:
    """Resident set size of a process in kB (/proc/PID/statm, second field, in pages)."""
    try:
        with open(f"/proc/{pid}/statm") as f:
            pages = int(f.read().split()[1])
    except (OSError, ValueError, IndexError):
        return -1
    return pages * os.sysconf("SC_PAGE_SIZE") // 1024


def rss_by_kind_kb(pid: int | str = "self") -> dict:
    """Resident kB of a process by kind of mapping (/proc/PID/smaps): "heap" (malloc's main arena,
    the brk heap), "anon" (anonymous mappings: Python's object arenas, large numpy buffers, other
    malloc arenas), "stack", "file" (code and data of modules and libraries); {} if gone. Where
    memory growth lands says what grows: Python objects or numpy buffers (anon) or malloc's heap."""
    out = {"heap": 0, "anon": 0, "stack": 0, "file": 0}
    kind = "anon"
    try:
        with open(f"/proc/{pid}/smaps") as f:
            for line in f:
                head = line.split(None, 6)
                if head and head[0].endswith(":"):
                    if head[0] == "Rss:":
                        out[kind] += int(head[1])
                    continue
                name = head[5].strip() if len(head) > 5 else ""  # a mapping line: address perms offset dev inode [name]
                kind = ("heap" if name == "[heap]" else "stack" if name.startswith("[stack") else
                        "file" if name.startswith("/") else "anon")
    except (OSError, ValueError, IndexError):
        return {}
    return out


def proc_counters(pid: int | str = "self") -> dict:
    """What the kernel says a process went through (cumulative): minor and major page faults,
    CPU time (s, user + system), involuntary context switches of its main thread (/proc/PID/stat
    and status; the onboard loop runs there); and the
    machine's stolen time (s, /proc/stat: a hypervisor running other guests on our vCPUs). Read
    once a simulated minute so an overrun can be set beside what its minute held; {} if gone."""
    fields = _stat_fields(pid)
    if not fields:
        return {}
    try:
        with open(f"/proc/{pid}/status") as f:
            nivcsw = next(int(line.split()[1]) for line in f if line.startswith("nonvoluntary_ctxt_switches"))
        with open("/proc/stat") as f:
            steal = int(f.readline().split()[8])
    except (OSError, ValueError, IndexError, StopIteration):
        return {}
    tick = os.sysconf("SC_CLK_TCK")
    # fields[0] is the state (field 3 of proc(5)): minflt is field 10, majflt 12, utime 14, stime 15
    return {"minflt": int(fields[7]), "majflt": int(fields[9]), "cpu_s": (int(fields[11]) + int(fields[12])) / tick,
            "nivcsw": nivcsw, "steal_s": steal / tick}


def minute_context(times_s, samples: list, who: str = "onboard") -> dict:
    """For the simulated minutes holding `times_s` (e.g. CPU overruns) against every minute: the
    party's minor page faults, involuntary context switches and the machine's stolen time per
    minute (medians). `samples`: [(t_s, {party: proc_counters})] as the Monitor takes them."""
    t = np.array([s[0] for s in samples if s[1].get(who)], float)
    keys = ("minflt", "nivcsw", "steal_s")
    c = np.array([[s[1][who][k] for k in keys] for s in samples if s[1].get(who)], float).reshape(-1, len(keys))
    if len(t) < 2:
        return {}
    per_min = np.diff(c, axis=0)  # row i: the minute (t[i], t[i+1]]
    hit = sorted({int(i) for i in np.searchsorted(t, np.asarray(times_s, float), side="left") - 1
                  if 0 <= i < len(per_min)})
    out = {"minutes": len(per_min), "minutes_hit": len(hit)}
    for j, k in enumerate(keys):
        out[f"{k}_median"] = float(np.median(per_min[:, j]))
        out[f"{k}_median_hit"] = float(np.median(per_min[hit, j])) if hit else float("nan")
    return out


class StealClock:
    """The hypervisor's stolen time of each vCPU (/proc/stat, in clock ticks of 10 ms), read once
    a lock-step period. On this kind of machine (a VM; nested here) the stolen time is not all
    taken out of a thread's CPU clock: 1.1 ms of constant work was measured at up to 106 ms of
    thread CPU time, 58 of its 59 repetitions over 5x the median with steal on their vCPU
    around them (bench/bench_cpu_clock.py). A control step
    over the period in CPU time is therefore set beside the steal of its vCPU at that moment."""

    def __init__(self):
        self._fd = os.open("/proc/stat", os.O_RDONLY)

    def read(self) -> list:
        """Stolen ticks per vCPU so far ([] if /proc/stat cannot be read)."""
        try:
            text = os.pread(self._fd, 1 << 16, 0).decode()
        except OSError:
            return []
        return [int(line.split()[8]) for line in text.splitlines()[1:] if line.startswith("cpu")]

    def close(self) -> None:
        os.close(self._fd)


def last_cpu(pid: int | str) -> int:
    """The CPU a process last ran on (/proc/PID/stat field 39), -1 if gone."""
    fields = _stat_fields(pid)
    return int(fields[36]) if len(fields) > 36 else -1


def _stat_fields(pid: int | str) -> list:
    """/proc/PID/stat from its field 3 on (after the command name, which may hold spaces); [] if gone.
    fields[0] is the state (field 3 of proc(5)), so field N of proc(5) is fields[N - 3]."""
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()
    except (OSError, IndexError):
        return []


def stolen_explains(excess_ms: float, ticks: int, tick_ms: float = 10.0) -> bool:
    """Whether `ticks` of steal around a step account for its `excess_ms` of CPU time over the
    median step: some steal (ticks >= 1) and the excess within what it may have been. /proc/stat
    counts steal in whole ticks of a running total, so a window's true steal is under ticks + 1."""
    return ticks >= 1 and excess_ms <= (ticks + 1) * tick_ms


def stolen_around(times_s, period_s: float, stolen, before: int = 1, after: int = 2) -> list:
    """For each step time (an overrun's vehicle time), the ticks stolen from the step's vCPU over
    the lock-step periods k - before .. k + after, k its period (the step runs inside period k;
    steal is booked at the vCPU's next scheduler tick, up to 4 ms later). `stolen[k]`: ticks stolen
    from the onboard's vCPU during period k, as `Monitor` records them."""
    out = []
    for t in times_s:
        k = int(round(t / period_s))
        w = np.asarray(stolen[max(k - before, 0):max(k + after + 1, 0)])
        w = w[w >= 0]  # -1: not read
        out.append(int(w.sum()) if w.size else -1)  # -1: none of the window was read
    return out


def retime(vehicle: Vehicle, tlog: Path, times_s, say=None) -> dict:
    """Re-execute the onboard's control steps from the plant's recording and re-time the steps
    at `times_s` (the overruns' vehicle times): {t: (CPU ms of the replayed step, whether it
    commanded exactly what the live step did)}.

    Lock-step makes the onboard loop a deterministic function of its inputs, and the plant's
    recording holds every input it was sent (a `tlog:` link on the vehicle clock replays them,
    tests/test_closed_loop.py checks it reproduces every command), so the replayed step at t is
    the live step at t, computed again. A step whose live CPU time was over the period but whose
    replay, commanding the same, took a millisecond did not overrun by its own work: its CPU
    clock counted something else (bench/bench_cpu_clock.py). Steps not found map to (nan, False),
    and so do steps older than the replayed loop's step history (onboard.loop.HISTORY: an hour)."""
    from onboard.link import Link
    from onboard.loop import OnboardLoop, VehicleClock
    from onboard.pwm import command_to_normalised

    want = {int(round(t * 1e6)) for t in times_s}
    live: dict = {}
    replay = Link(f"tlog:{tlog}")
    loop = OnboardLoop(vehicle, replay, VehicleClock(), DEMO_CONFIG)
    handle = loop.handle

    def keep_live(m):  # what the live loop commanded at the wanted instants, as the plant got it
        if m.get_type() == "HIL_ACTUATOR_CONTROLS" and m.time_usec in want and m.get_srcComponent() == 191:
            live.setdefault(m.time_usec, np.array(m.controls[:12], dtype=np.float32))
        handle(m)

    loop.handle = keep_live
    wall0 = time.perf_counter()
    if say:
        say(f"re-timing {len(want)} overrun steps: replaying {tlog} through a fresh onboard loop")
    loop.run(idle_exit_s=5.0)  # wall time with nothing read: a replay ends at its last packet, but a
    # loaded machine (load average 8-10 on 2 cores) stalled the replay 0.5 s mid-run and cut it short
    replay.close()
    if say:
        say(f"replayed {loop.stats.steps} steps in {time.perf_counter() - wall0:.0f} s")
    cpu = np.asarray(loop.stats.step_cpu_s) * 1e3
    out = {}
    for i, (t, command) in enumerate(loop.stats.commands):
        us = int(round(t * 1e6))
        if us in want:
            mine = np.array(command_to_normalised(vehicle, command), dtype=np.float32)
            out[us] = (float(cpu[i]), us in live and bool(np.array_equal(mine, live[us])))
    return {t: out.get(int(round(t * 1e6)), (math.nan, False)) for t in times_s}


# ------------------------------------------------------------------------------------------------
# The run


def warm_up(vehicle: Vehicle, seed: int = 0) -> None:
    """Fly 6 s in this process (threads) through every path the soak uses: arming, depth, yaw and
    surge, each sensor fault and its failsafe recovery, each link fault. Compiled (numba) code is
    then loaded before the soak forks its parties, so no control step pays for a first call; a
    robot does the same before it arms."""
    sp = [(0.3, arm_command(True)), (0.3, depth_yaw_target(0.4, 1.0)), (2.0, body_velocity_target(0.2, 0.0)),
          (3.6, arm_command(False)), (3.9, arm_command(True)), (3.9, depth_yaw_target(0.4, 1.0))]
    plan = FaultPlan(imu_freeze_s=((3.0, 3.2),), imu_nan_s=((4.5, 4.6),), imu_dropouts_s=((4.8, 4.9),),
                     depth_jumps=(DepthJump(5.0, 0.1, 5.5),), garbage_times_s=(5.2,),
                     loss=0.2, loss_window_s=(2.0, 6.0), delay_s=0.02, jitter_s=0.01, delay_window_s=(2.0, 6.0),
                     duplicate=0.1, duplicate_window_s=(2.0, 6.0), reorder=0.1, reorder_window_s=(2.0, 6.0))
    from onboard.link import Link
    from onboard.loop import OnboardLoop, VehicleClock

    with Link("udpin:127.0.0.1:0") as link:  # construction and an unarmed step: no lock-step timeout here
        OnboardLoop(vehicle, link, VehicleClock(), DEMO_CONFIG).step(0.0)
    for attempt in range(3):  # a first compile of the armed paths may outlast the lock-step's 30 s
        try:
            run_closed_loop(vehicle, sp, 6.0, seed=seed, config=DEMO_CONFIG, faults=plan, history=False,
                            processes=False)
            return
        except EndpointError:
            if attempt == 2:
                raise


class Monitor:
    """Called after every lock-step period: RSS every simulated minute, progress, vehicle depth."""

    def __init__(self, schedule: Schedule, vehicle: Vehicle, say=None, sample_s: float = MINUTE_S,
                 wall_limit_s: float | None = None):
        self.schedule = schedule
        self.wall_limit_s = wall_limit_s
        self.t_s = 0.0  # vehicle time flown
        self.surface_m = vehicle.environment.surface_depth
        self.radius_m = vehicle.body.radius
        self.floor_m = vehicle.environment.floor_depth
        self.say = say
        self.sample_s = sample_s
        self.pids = {"plant": os.getpid()}
        self.samples: list = []  # (t_s, {party: rss_kb}): one a simulated minute, bounded by the duration
        self.counters: list = []  # (t_s, {party: proc_counters}), the same minutes
        self.kinds: list = []  # (t_s, {party: rss_by_kind_kb}), the same minutes
        self.steal = StealClock()
        self._steal0 = None
        self.period_s = math.nan  # the lock-step period (the endpoint's)
        self.stolen = np.zeros(0, np.int16)  # ticks stolen from the onboard's vCPU in each lock-step
        # period, -1 where not read; allocated and written whole at the first period (no growth)
        self.endpoint = None
        self.wall0 = None
        self.depth_max_m = -math.inf
        self.end_depths_m: list = []  # mean vehicle depth over the END_MEAN_S before each mission disarms
        self._next_end = 0
        self._end_sum = self._end_n = 0
        self._ends = [t0 + m.duration_s - END_S for t0, m in zip(schedule.starts_s, schedule.missions)]
        self._every = None

    def stop(self) -> bool:
        """True once the wall-time limit is reached (checked at a simulated minute, after its sample)."""
        if self.wall_limit_s is None or self.endpoint is None or self.wall0 is None:
            return False
        ep = self.endpoint
        return (ep.k % self._every == 0 and time.perf_counter() - self.wall0 > self.wall_limit_s)

    def on_start(self, pids: dict) -> None:
        self.pids.update(pids)

    def sample(self, t_s: float) -> dict:
        rss = {who: rss_kb(pid) for who, pid in self.pids.items()}
        self.samples.append((t_s, rss))
        self.counters.append((t_s, {who: proc_counters(pid) for who, pid in self.pids.items()}))
        self.kinds.append((t_s, {who: rss_by_kind_kb(pid) for who, pid in self.pids.items()}))
        return rss

    def _record_steal(self, k: int) -> None:
        """Ticks stolen from the onboard's vCPU since the previous period (the step of period k ran there)."""
        now = self.steal.read()
        cpu = last_cpu(self.pids["onboard"]) if "onboard" in self.pids else -1
        if self._steal0 is not None and 0 <= cpu < len(now) and len(now) == len(self._steal0) and k < len(self.stolen):
            self.stolen[k] = min(now[cpu] - self._steal0[cpu], 32767)
        self._steal0 = now

    def __call__(self, ep) -> None:
        if self.endpoint is None:
            self.endpoint = ep
            self.wall0 = time.perf_counter()
            self._every = int(round(self.sample_s / ep.period_s))
            self.period_s = ep.period_s
            self.stolen = np.full(int(round(self.schedule.duration_s / ep.period_s)) + 2, -1, np.int16)
            self.sample(ep.time_s)
        t = ep.time_s + ep.period_s  # the plant has been advanced to the end of this period
        self.t_s = t
        self._record_steal(ep.k)
        if ep.k % 10 == 0:
            depth = float(ep.plant.state[2]) - self.surface_m
            self.depth_max_m = max(self.depth_max_m, depth)
        if self._next_end < len(self._ends) and t >= self._ends[self._next_end] - END_MEAN_S:
            self._end_sum += float(ep.plant.state[2]) - self.surface_m
            self._end_n += 1
        while self._next_end < len(self._ends) and t >= self._ends[self._next_end]:
            self.end_depths_m.append(self._end_sum / max(self._end_n, 1))
            self._end_sum = self._end_n = 0
            self._next_end += 1
        if (ep.k + 1) % self._every == 0:
            rss = self.sample(t)
            if self.say:
                wall = time.perf_counter() - self.wall0
                done = sum(1 for e in self._ends if e <= t)
                faults = sum(1 for i in self.schedule.injections if i.t_s <= t)
                self.say(f"soak t = {t / 60:5.1f} min  wall {wall:6.0f} s  missions {done:3d}  faults {faults:3d}  "
                         "RSS kB " + " ".join(f"{k} {v}" for k, v in rss.items())
                         + f"  resends {ep.stats.resends}")


@dataclass
class SoakResult:
    summary: dict
    memory: list = field(default_factory=list)


MAX_SOAK_S = 7 * 86400.0  # a week simulated (an hour takes about half an hour here): beyond it, a typo


class NoMission(ValueError):
    """The duration holds no whole random mission."""


def run_soak(vehicle: Vehicle, duration_s: float, seed: int, out_dir: Path, say=None,
             warmup_s: float | None = None, faults: bool = True, sample_s: float = MINUTE_S,
             wall_limit_s: float | None = None, re_time: bool = True) -> dict:
    """Fly the schedule of `seed` for `duration_s` in lock-step; measure; return the summary dict.
    `re_time`: afterwards re-execute the logged CPU overruns from the recording (`retime`)."""
    schedule = make_schedule(vehicle, duration_s, seed, faults=faults)
    if not schedule.missions:
        raise NoMission(f"duration {duration_s:g} s holds no whole random mission; use at least 120 s")
    out_dir = Path(out_dir)
    if say:
        say("warming up: 6 s flown in this process through every path, so no control step compiles")
    warm_up(vehicle, seed)
    monitor = Monitor(schedule, vehicle, say=say, sample_s=sample_s, wall_limit_s=wall_limit_s)
    fly_s = schedule.starts_s[-1] + schedule.missions[-1].duration_s  # the last whole mission's end
    try:
        result = run_closed_loop(
            vehicle, schedule.setpoints(), fly_s, seed=seed, config=DEMO_CONFIG, out_dir=out_dir,
            faults=schedule.faults(), history=False, on_period=monitor, on_start=monitor.on_start,
            progress=(lambda s: say(s) if say and not s.lstrip().startswith("t =") else None), halt=monitor.stop,
        )
    finally:
        monitor.steal.close()
    if "error" in result.onboard:
        raise EndpointError(f"the onboard loop failed: {result.onboard['error']}")
    if "error" in result.recorder:
        raise EndpointError(f"the recorder failed: {result.recorder['error']}")
    flown_s = min(fly_s, round(monitor.t_s, 6))
    warm = warmup_s if warmup_s is not None else min(300.0, flown_s / 4)
    summary = summarise(schedule, monitor, result, flown_s, warm, seed)
    summary["stopped_early"] = flown_s < fly_s - 1e-6  # by the wall-time limit
    summary["planned_s"] = fly_s
    d = summary["deadlines"]
    if re_time:
        times = [o["t_s"] for o in d["overruns"]]
        attribute_retimed(d, retime(vehicle, result.tlog, times, say=say) if times else {})
    return summary


def summarise(schedule: Schedule, monitor: Monitor, result, fly_s: float, warmup_s: float, seed: int) -> dict:
    ob = result.onboard
    ep = monitor.endpoint
    period_s = ep.period_s
    # deadlines
    deadlines = {
        "period_ms": period_s * 1e3,
        "steps": ob["steps"],
        "missed_wall": ob["overruns_wall"],
        "missed_cpu": ob["overruns_cpu"],
        "wall_max_ms": ob["step_max_ms"], "wall_p999_ms": ob["step_p999_ms"], "wall_p99_ms": ob["step_p99_ms"],
        "wall_median_ms": ob["step_median_ms"],
        "cpu_max_ms": ob["step_cpu_max_ms"], "cpu_p999_ms": ob["step_cpu_p999_ms"], "cpu_p99_ms": ob["step_cpu_p99_ms"],
        "cpu_median_ms": ob["step_cpu_median_ms"],
        "history_steps": ob["history_steps"],
        "overruns": ob.get("overrun_log", []),  # the newest 100, onboard.loop.Overrun.as_dict()
    }
    # the minutes of those overruns against all minutes: page faults, preemption, stolen time
    deadlines["overrun_minutes"] = minute_context([o["t_s"] for o in deadlines["overruns"]], monitor.counters)
    # ...and beside the hypervisor: an overrun is the machine's when enough time was stolen from
    # its vCPU around it to make up its excess over the median step (`stolen_explains`)
    tick_ms = 1000.0 / os.sysconf("SC_CLK_TCK")
    stolen = stolen_around([o["t_s"] for o in deadlines["overruns"]], monitor.period_s, monitor.stolen)
    machine = 0
    for o, ticks in zip(deadlines["overruns"], stolen):
        o["stolen_ms"] = ticks * tick_ms if ticks >= 0 else None
        o["machine"] = stolen_explains(o["cpu_ms"] - deadlines["cpu_median_ms"], ticks, tick_ms)
        machine += o["machine"]
    deadlines["missed_cpu_stolen"] = machine
    # the rest are the onboard's own, and so are overruns older than the log's newest 100
    # (unchecked); when the overruns are re-executed (run_soak, attribute_retimed) that judges instead
    deadlines["missed_cpu_own"] = ob["overruns_cpu"] - machine
    deadlines["periods_with_steal"] = int(np.sum(monitor.stolen > 0))
    deadlines["periods_recorded"] = int(np.sum(monitor.stolen >= 0))
    # memory
    parties = list(monitor.samples[0][1])
    ts = [t for t, _ in monitor.samples]
    memory = {}
    for who in parties:
        r = [s[who] for _, s in monitor.samples]
        memory[who] = {"rss_start_kb": r[0], "rss_after_warmup_kb": next((x for t, x in zip(ts, r) if t >= warmup_s), r[-1]),
                       "rss_end_kb": r[-1], "rss_max_kb": max(r), "growth_kb_per_h": growth_kb_per_h(ts, r, warmup_s)}
        kinds = [(t, k[who]) for t, k in monitor.kinds if k.get(who)]
        if kinds:  # where it grew: the growth of each kind of mapping, like the total's
            memory[who]["growth_by_kind_kb_per_h"] = {
                kind: growth_kb_per_h([t for t, _ in kinds], [k[kind] for _, k in kinds], warmup_s) for kind in kinds[0][1]}
    # packets: the plant endpoint's recording (what crossed its link: with link faults, a packet
    # the injector lost is counted in its stats, never recorded; a duplicate is recorded twice)
    plant_rec = scan_tlog(result.tlog)
    none = {"counts": Counter(), "missing": 0, "duplicates": 0, "reordered": 0, "first_seq": -1}
    me, gcs, onb = (plant_rec.get(src, none) for src in ((1, 1), (255, 190), (1, 191)))
    inj = ep.link.stats().get("injected") if hasattr(ep.link, "inner") else None
    out_lost = in_lost = out_dup = held_out = held_in = 0
    if inj is not None:
        out_lost, in_lost, out_dup = inj["out"]["lost"], inj["in"]["lost"], inj["out"]["duplicated"]
        held_out, held_in = inj["held_out"], inj["held_in"]  # still held back when the run stopped
    sent = Counter(ep.stats.sent)
    recorded_sent = me["counts"] + gcs["counts"]
    recorded_sent.pop(MOCAP, None)
    received = Counter(ep.stats.received) - HANDSHAKE
    by_type = lambda a, b: {k: a[k] - b.get(k, 0) for k in sorted(a | b) if a[k] != b.get(k, 0)}  # noqa: E731
    # the telemetry recorder's recording against what the onboard loop sent it
    tel_rec = scan_tlog(result.telemetry_tlog)
    tel = tel_rec.get((1, 1), tel_rec.get((1, 191), none))  # the loop is component 1 to the ground (issue 16)
    tel_sent = int(ob["ground_link"]["packets_out"])
    tel_recorded = int(sum(tel["counts"].values()))
    n_sent, n_sent_rec = int(sum(sent.values())), int(sum(recorded_sent.values()))
    n_recv, n_recv_rec = int(sum(received.values())), int(sum(onb["counts"].values()))
    unexplained = {
        "sent, not in the recording": n_sent - out_lost + out_dup - held_out - n_sent_rec,
        "received, not in the recording": n_recv - n_recv_rec,
        "endpoint sequence gaps": max(0, me["missing"] - out_lost - held_out),
        "ground setpoint sequence gaps": gcs["missing"],
        "onboard sequence gaps": max(0, onb["missing"] - in_lost - held_in),
        "telemetry sent, not recorded": tel_sent - tel_recorded,
        "telemetry sequence gaps": tel["missing"],
    }
    packets = {
        "endpoint_sent": n_sent,
        "endpoint_sent_recorded": n_sent_rec,
        "endpoint_received": n_recv,
        "endpoint_received_recorded": n_recv_rec,
        "injected": {"lost_out": out_lost, "lost_in": in_lost, "duplicated_out": out_dup,
                     "held_out_at_end": held_out, "held_in_at_end": held_in, "detail": inj},
        "sent_minus_recorded_by_type": by_type(sent, recorded_sent),
        "received_minus_recorded_by_type": by_type(received, onb["counts"]),
        "sequence_plant_recording": {f"{k}": {x: v[x] for x in ("missing", "duplicates", "reordered", "first_seq")}
                                     for k, v in (("1/1 endpoint", me), ("255/190 ground", gcs), ("1/191 onboard", onb))},
        "telemetry_sent": tel_sent,
        "telemetry_recorded": tel_recorded,
        "telemetry_recorder_counted": int(sum(result.recorder.get("messages", {}).values())),
        "telemetry_sequence": {x: tel[x] for x in ("missing", "duplicates", "reordered", "first_seq")},
        "mocap_recorded": int(me["counts"].get(MOCAP, 0)),
        "endpoint_resends": ep.stats.resends,
        "onboard_link": ob.get("link", {}),
        "by_type_sent": dict(sorted(sent.items())),
        "by_type_received": dict(sorted(received.items())),
        "by_type_telemetry": dict(sorted(tel["counts"].items())),
        "unexplained": unexplained,
    }
    packets["lost"] = int(sum(abs(v) for v in unexplained.values()))
    flown = [i for i in schedule.injections if i.t_s < fly_s]  # a run stopped early flew only these
    long_drops = sum(1 for i in flown if i.kind in TRIPS and i.t_s + i.length_s < fly_s)  # tripped before the end
    ends = np.asarray(monitor.end_depths_m)
    # survived and recovered: the loop drives the jets again (armed) once the fault is over
    timeline = armed_timeline(result.tlog)
    after_s = RECOVER_ARM_S + 1.0
    back = [armed_at(timeline, i.t_s + i.length_s + after_s) for i in flown if i.t_s + i.length_s + after_s < fly_s]
    for k in ("loss", "delay", "duplicate", "reorder"):  # after a link fault: armed when next expected
        w = schedule.link.get(f"{k}_window_s")
        if schedule.link.get(k if k != "delay" else "delay_s"):
            t = schedule.next_armed_s(w[1] + after_s)
            if t is not None and t < fly_s:
                back.append(armed_at(timeline, t))
    counts = Counter(i.kind for i in flown)
    counts.update({k: v for k, v in schedule.counts().items() if k.startswith("link_")
                   and schedule.link[k.removeprefix("link_") + "_window_s"][0] < fly_s})
    return {
        "seed": seed,
        "duration_s": fly_s,
        "wall_s": result.wall_s,
        "missions": len(monitor.end_depths_m),  # completed (all of them unless stopped early)
        "faults": dict(sorted(counts.items())),
        "faults_total": int(sum(counts.values())),
        "fault_plan": {"injections": [i.__dict__ for i in flown], "link": schedule.link},
        "failsafe_entries": ob["failsafe_entries"],
        "failsafe_expected": long_drops,
        "faults_checked_recovered": len(back),  # armed 1.6 s after each fault; after a link window, when next expected
        "faults_recovered": int(sum(back)),
        "arm_refusals": ob["arm_refusals"],
        "step_errors": ob["step_errors"],
        "limit_violations": ob["limit_violations"],
        "allocation_fallbacks": ob["allocation_fallbacks"],
        "rejected_inputs": ob["rejected_inputs"],
        "depth_max_m": monitor.depth_max_m,
        "floor_clearance_min_m": monitor.floor_m - monitor.surface_m - monitor.depth_max_m,
        "missions_surfaced": int(np.sum(ends < monitor.radius_m)),
        "surface_depth_max_m": float(ends.max()) if ends.size else float("nan"),
        "deadlines": deadlines,
        "memory": {"warmup_s": warmup_s, "samples": len(monitor.samples), **memory},
        "memory_samples": [{"t_s": t, **r} for t, r in monitor.samples],
        "proc_samples": [{"t_s": t, **c} for t, c in monitor.counters],  # cumulative, a simulated minute apart
        "packets": packets,
    }


def table(s: dict) -> str:
    d, m, p = s["deadlines"], s["memory"], s["packets"]
    faults = ", ".join(f"{k} {v}" for k, v in s["faults"].items()) or "none"
    rows = [
        ("run", "simulated / wall time", f"{s['duration_s']:.0f} s / {s['wall_s']:.0f} s"
                + (f" (stopped by the wall-time limit; {s['planned_s']:.0f} s planned)" if s.get("stopped_early") else "")),
        ("", "missions (flown / surfaced)", f"{s['missions']} / {s['missions_surfaced']}"),
        ("", "faults injected", f"{s['faults_total']}: {faults}"),
        ("", "failsafe trips (expected)", f"{s['failsafe_entries']} ({s['failsafe_expected']})"),
        ("", "armed again after the fault (1.6 s; link: when due)", f"{s['faults_recovered']} of {s['faults_checked_recovered']}"),
        ("", "step errors / limit violations", f"{s['step_errors']} / {s['limit_violations']}"),
        ("deadlines", f"steps over {d['period_ms']:.0f} ms, CPU time", f"{d['missed_cpu']} of {d['steps']}"),
        ("", "  of them made up by time stolen from the vCPU around them",
         f"{d.get('missed_cpu_stolen', 0)} (steal in {d.get('periods_with_steal', 0)} of {d.get('periods_recorded', 0)} periods)"),
        ("", "  of them re-executed from the recording in the period, same command",
         f"{d['missed_cpu_replayed_in_period']}" if "missed_cpu_replayed_in_period" in d else "not re-executed"),
        ("", "  the onboard's own", f"{d.get('missed_cpu_own', d['missed_cpu'])}"),
        ("", "  CPU max / p99.9 / median", f"{d['cpu_max_ms']:.2f} / {d['cpu_p999_ms']:.2f} / {d['cpu_median_ms']:.2f} ms"),
        ("", f"steps over {d['period_ms']:.0f} ms, wall time", f"{d['missed_wall']} of {d['steps']}"),
        ("", "  wall max / p99.9 / median", f"{d['wall_max_ms']:.2f} / {d['wall_p999_ms']:.2f} / {d['wall_median_ms']:.2f} ms"),
    ]
    om = d.get("overrun_minutes") or {}
    if om.get("minutes_hit"):
        rows.append(("", f"  the {om['minutes_hit']} minutes with one of the newest 100 CPU overruns (all minutes), medians",
                     f"onboard page faults {om['minflt_median_hit']:.0f} ({om['minflt_median']:.0f}), "
                     f"preempted {om['nivcsw_median_hit']:.0f} ({om['nivcsw_median']:.0f}), "
                     f"machine steal {om['steal_s_median_hit']:.2f} s ({om['steal_s_median']:.2f} s)"))
    for o in d["overruns"][-5:]:
        o = dict(o)
        stolen, machine = o.pop("stolen_ms", None), o.pop("machine", False)
        replay, same = o.pop("replay_cpu_ms", None), o.pop("replay_same_command", False)
        rows.append(("", "  overrun", Overrun.from_dict(o).where()
                     + (f", {stolen:.0f} ms stolen around it" if stolen is not None else "")
                     + (" (made up)" if machine else "")
                     + (f"; re-executed {replay:.2f} ms" + (", same command" if same else ", other command")
                        if replay is not None else "")))
    for who in ("plant", "onboard", "recorder"):
        if who in m:
            x = m[who]
            rows.append(("memory" if who == "plant" else "", f"{who}: RSS start -> end",
                         f"{x['rss_start_kb'] / 1024:.1f} -> {x['rss_end_kb'] / 1024:.1f} MB, "
                         f"growth {x['growth_kb_per_h']:+.0f} kB/h after {m['warmup_s']:.0f} s"))
            if x.get("growth_by_kind_kb_per_h"):
                rows.append(("", "  growth by mapping", ", ".join(f"{k} {v:+.0f}" for k, v in x["growth_by_kind_kb_per_h"].items()) + " kB/h"))
    rows += [
        ("packets", "endpoint sent / in recording", f"{p['endpoint_sent']} / {p['endpoint_sent_recorded']}"),
        ("", "endpoint received / in recording", f"{p['endpoint_received']} / {p['endpoint_received_recorded']}"),
        ("", "  lost / duplicated by the link injector", f"{p['injected']['lost_out'] + p['injected']['lost_in']} / "
                                                              f"{p['injected']['duplicated_out']} out"),
        ("", "sequence gaps not injected, mission.tlog", f"{sum(v for k, v in p['unexplained'].items() if 'gaps' in k and 'telemetry' not in k)}"),
        ("", "telemetry sent / recorded (seq gaps)", f"{p['telemetry_sent']} / {p['telemetry_recorded']} ({p['telemetry_sequence']['missing']})"),
        ("", "lost (not explained by injection)", f"{p['lost']}"),
    ]
    w0 = max(len(r[0]) for r in rows)
    w1 = max(len(r[1]) for r in rows)
    return "\n".join(f"  {a:<{w0}}  {b:<{w1}}  {c}" for a, b, c in rows)


def attribute_retimed(deadlines: dict, retimed: dict) -> None:
    """Put the re-timed steps (`retime`) into a summary's deadlines: each logged overrun gets its
    replayed CPU time and whether the replay commanded the same; an overrun is the onboard's own
    unless its replay, commanding the same, fit the period. Overruns beyond the log (the newest
    100) were not re-timed and count as the onboard's own."""
    period = deadlines["period_ms"]
    cleared = 0
    for o in deadlines["overruns"]:
        cpu_ms, same = retimed.get(o["t_s"], (math.nan, False))
        o["replay_cpu_ms"], o["replay_same_command"] = (None if cpu_ms != cpu_ms else round(cpu_ms, 4)), same
        cleared += bool(same and cpu_ms <= period)
    deadlines["missed_cpu_replayed_in_period"] = cleared
    deadlines["missed_cpu_own"] = deadlines["missed_cpu"] - cleared


def verdict(s: dict, max_growth_kb_per_h: float) -> list:
    """The soak's properties that do not hold (empty: passed)."""
    bad = []
    d = s["deadlines"]
    own = d.get("missed_cpu_own", d["missed_cpu"])
    if own:
        bad.append(f"{own} control steps over the period in CPU time that re-executed from the recording "
                   "did not fit it either (or were not re-executed)")
    for who in ("plant", "onboard", "recorder"):
        g = s["memory"].get(who, {}).get("growth_kb_per_h", float("nan"))
        if not g <= max_growth_kb_per_h:
            bad.append(f"{who} memory grows {g:+.0f} kB/h (limit {max_growth_kb_per_h:.0f})")
    if s["packets"]["lost"]:
        bad.append(f"{s['packets']['lost']} packets lost from the recordings")
    if s["failsafe_entries"] != s["failsafe_expected"]:
        bad.append(f"{s['failsafe_entries']} failsafe trips, {s['failsafe_expected']} expected")
    if s["faults_recovered"] != s["faults_checked_recovered"]:
        bad.append(f"{s['faults_checked_recovered'] - s['faults_recovered']} faults not recovered from")
    if s["missions_surfaced"] != s["missions"]:
        bad.append(f"{s['missions'] - s['missions_surfaced']} missions did not end at the surface")
    return bad


# ------------------------------------------------------------------------------------------------
# CLI


def configure(parser) -> None:
    parser.add_argument("--duration", type=float, default=3600.0, metavar="S",
                        help="simulated seconds (default 3600); the last whole random mission ends at or before it")
    parser.add_argument("--seed", type=int, default=0, help="seed of the missions, faults and plant noise (default 0)")
    parser.add_argument("--out", default="jetloop-soak", metavar="DIR",
                        help="directory for mission.tlog, telemetry.tlog and summary.json (default ./jetloop-soak/)")
    parser.add_argument("--vehicle", default=None, help="vehicle TOML (default: the reference vehicle asr4)")
    parser.add_argument("--no-faults", action="store_true", help="random missions only, no fault injected")
    parser.add_argument("--wall-limit", type=float, default=None, metavar="S",
                        help="stop (and report what was flown) after this many seconds of wall time")
    parser.add_argument("--max-growth", type=float, default=1024.0, metavar="KB_PER_H",
                        help="memory growth per process that still passes, kB per simulated hour (default 1024)")
    parser.add_argument("--no-retime", action="store_true",
                        help="do not re-execute the CPU overruns from the recording afterwards (saves ~10 min an hour)")
    parser.add_argument("--retime", metavar="DIR", default=None,
                        help="only re-execute the CPU overruns of the soak in DIR (its summary.json and "
                             "mission.tlog; give the --vehicle it flew) and judge it again; fly nothing")


def run(args) -> int:
    from onboard.vehicle import VehicleFileError, require_jets

    if not (math.isfinite(args.duration) and 0 < args.duration <= MAX_SOAK_S):
        print(f"jetloop soak: --duration must be a number of seconds in (0, {MAX_SOAK_S:.0f}] (a week), "
              f"got {args.duration:g}", file=sys.stderr)
        return 2
    try:
        vehicle = load_vehicle(args.vehicle)
        require_jets(vehicle, "soak")
    except VehicleFileError as exc:
        print(f"jetloop soak: {exc}", file=sys.stderr)
        return 2
    say = lambda s: print(s, file=sys.stderr, flush=True)  # noqa: E731
    if args.retime is not None:
        return _retime_dir(Path(args.retime), vehicle, args.max_growth, say)
    from ground.cli import make_output_dir

    out = make_output_dir(args.out, "jetloop soak")
    if out is None:
        return 2
    say(f"jetloop soak: {args.duration:.0f} s simulated, seed {args.seed}, vehicle {vehicle.name}, "
        f"faults {'off' if args.no_faults else 'on'}, output {out}/")
    try:
        summary = run_soak(vehicle, args.duration, args.seed, out, say=say, faults=not args.no_faults,
                           wall_limit_s=args.wall_limit, re_time=not args.no_retime)
    except NoMission as exc:  # the duration is too short for the schedule: a usage error
        print(f"jetloop soak: {exc}", file=sys.stderr)
        return 2
    except (EndpointError, ValueError) as exc:
        print(f"jetloop soak: {exc}", file=sys.stderr)
        return 1
    summary["command"] = (f"jetloop soak --duration {args.duration:g} --seed {args.seed} --out {args.out}"
                          + (" --no-faults" if args.no_faults else ""))
    return _report(summary, out, args.max_growth)


def _report(summary: dict, out: Path, max_growth: float) -> int:
    bad = verdict(summary, max_growth)
    summary["failed"] = bad
    (out / "summary.json").write_text(json.dumps(summary, indent=2, default=_jsonable) + "\n")
    print(table(summary))
    print(f"\nwrote {out / 'summary.json'}, {out / 'mission.tlog'}, {out / 'telemetry.tlog'}")
    if bad:
        print("FAILED: " + "; ".join(bad))
        return 1
    print("PASSED: no control step of the onboard's own over the period (CPU), bounded memory, zero packets lost")
    return 0


def _retime_dir(out: Path, vehicle: Vehicle, max_growth: float, say) -> int:
    """`jetloop soak --retime DIR`: re-execute a finished soak's overruns, judge it again."""
    try:
        summary = json.loads((out / "summary.json").read_text())
        d = summary["deadlines"]
        times = [float(o["t_s"]) for o in d["overruns"]]
        if not (out / "mission.tlog").is_file():
            raise OSError(f"{out / 'mission.tlog'}: no such file")
    except (OSError, ValueError, KeyError, TypeError) as exc:
        print(f"jetloop soak --retime: {out} is not a finished soak: {exc}", file=sys.stderr)
        return 2
    attribute_retimed(d, retime(vehicle, out / "mission.tlog", times, say=say) if times else {})
    return _report(summary, out, max_growth)


def _jsonable(x):
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, (np.floating,)):
        return float(x)
    return str(x)
