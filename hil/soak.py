"""`jetloop soak`: hours of simulated time in lock-step, random missions and random faults, measured.

The three parties of `jetloop demo` (hil.demo.run_closed_loop: plant endpoint, onboard loop and
telemetry recorder over loopback UDP, the onboard loop and the recorder in their own processes)
fly back-to-back random missions (`random_mission`) while random faults the vehicle is meant to
survive are injected (`random_faults`). The run is deterministic for a seed (lock-step).
Three properties are measured, the way an autopilot's own soak tests measure themselves:

- deadlines: every onboard control step (estimate + control + compensate + allocate) against
  the 10 ms period of 100 Hz, in wall time and in CPU time (onboard.loop.LoopStats counts every
  overrun over the whole run; p99.9 and maxima over its step history);
- memory: the resident set (/proc/PID/statm) of the plant (this process), the onboard loop and
  the recorder sampled every simulated minute; growth = slope of a least-squares line through the
  samples after warm-up, in kB per simulated hour (the endpoint keeps no history: history=False);
- packets: every packet the endpoint sent and received is in its recording (mission.tlog),
  counted by type; MAVLink sequence numbers are continuous per source in each recording (a gap
  is a packet lost between sender and recorder); the telemetry recorder got every packet the
  onboard loop sent it (telemetry.tlog against the onboard's ground-link count).

Faults (only what the vehicle must survive and recover from): short IMU dropouts (below the
failsafe's 0.3 s IMU timeout: the estimator coasts), long IMU dropouts (they trip the failsafe;
the ground recovers explicitly, as an operator would: disarm, re-arm, send the setpoint again,
all as COMMAND_LONG / SET_POSITION_TARGET_LOCAL_NED messages in vehicle time) and bursts of
garbage bytes on the sensor link.
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
from hil.endpoint import EndpointError, Faults
from onboard.loop import arm_command, body_velocity_target, depth_yaw_target
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
GARBAGE_BYTES = Faults().garbage_bytes  # per burst (hil.endpoint.Faults has one size for the run)
RECOVER_DISARM_S = 0.3  # after the IMU returns, the ground disarms ...
RECOVER_ARM_S = 0.6  # ... re-arms and sends the setpoint again


@dataclass(frozen=True)
class Injection:
    """One fault at t_s (vehicle time) in mission `mission` (index), with its parameter."""

    kind: str  # "imu_dropout_short", "imu_dropout_long", "garbage"
    t_s: float
    length_s: float = 0.0  # dropouts
    n_bytes: int = 0  # garbage
    mission: int = -1


@dataclass(frozen=True)
class Schedule:
    """Back-to-back missions over the soak and the faults injected into them."""

    starts_s: tuple  # vehicle time each mission starts
    missions: tuple
    injections: tuple
    duration_s: float

    def setpoints(self) -> list:
        """(vehicle time, ground message): each mission's own (shifted), a disarm at its end, and the
        explicit failsafe recovery after each long IMU dropout."""
        out = []
        for t0, m in zip(self.starts_s, self.missions):
            out += [(t0 + t, msg) for t, msg in m.setpoints()]
            out.append((t0 + m.duration_s - END_S, arm_command(False)))
        for inj in self.injections:
            if inj.kind == "imu_dropout_long":
                t1 = inj.t_s + inj.length_s
                d = self.missions[inj.mission].demand_at(t1 - self.starts_s[inj.mission])
                out.append((t1 + RECOVER_DISARM_S, arm_command(False)))
                out.append((t1 + RECOVER_ARM_S, arm_command(True)))
                out.append((t1 + RECOVER_ARM_S, depth_yaw_target(d["depth_m"], d["yaw_rad"])))
                if d["surge_m_s"] is not None:
                    out.append((t1 + RECOVER_ARM_S, body_velocity_target(d["surge_m_s"], 0.0)))
        return sorted(out, key=lambda p: p[0])  # stable: at one instant, arm goes before its setpoint

    def faults(self) -> Faults:
        drops = tuple((i.t_s, round(i.t_s + i.length_s, 6)) for i in self.injections if i.kind.startswith("imu_dropout"))
        garbage = tuple(i.t_s for i in self.injections if i.kind == "garbage")
        return Faults(imu_dropouts_s=drops, garbage_times_s=garbage, garbage_bytes=GARBAGE_BYTES)

    def mission_at(self, t_s: float) -> int:
        """Index of the mission flying at t_s (-1 before the first / after the last)."""
        i = int(np.searchsorted(self.starts_s, t_s, side="right")) - 1
        if i < 0 or t_s >= self.starts_s[i] + self.missions[i].duration_s:
            return -1
        return i

    def counts(self) -> dict:
        return dict(sorted(Counter(i.kind for i in self.injections).items()))


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
        kind = rng.choice(("imu_dropout_short", "imu_dropout_long", "garbage"))
        if kind == "imu_dropout_short":
            out.append(Injection(kind, t_abs, length_s=round(float(rng.uniform(*SHORT_DROPOUT_S)), 3), mission=index))
        elif kind == "imu_dropout_long":
            out.append(Injection(kind, t_abs, length_s=round(float(rng.uniform(*LONG_DROPOUT_S)), 3), mission=index))
        else:
            out.append(Injection(kind, t_abs, n_bytes=GARBAGE_BYTES, mission=index))
    return out


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
    return Schedule(tuple(starts), tuple(missions), tuple(injections), float(duration_s))


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


def sequence_gaps(seq) -> int:
    """Packets missing from a MAVLink sequence (8-bit, wrapping): sum of (diff - 1) mod 256."""
    s = np.asarray(seq, np.int64)
    if s.size < 2:
        return 0
    return int(np.sum((np.diff(s) - 1) % 256))


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
            "counts": counts, "gaps": sequence_gaps(seq[sent]),
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


# ------------------------------------------------------------------------------------------------
# The run


class Monitor:
    """Called after every lock-step period: RSS every simulated minute, progress, vehicle depth."""

    def __init__(self, schedule: Schedule, vehicle: Vehicle, say=None, sample_s: float = MINUTE_S):
        self.schedule = schedule
        self.surface_m = vehicle.environment.surface_depth
        self.floor_m = vehicle.environment.floor_depth
        self.say = say
        self.sample_s = sample_s
        self.pids = {"plant": os.getpid()}
        self.samples: list = []  # (t_s, {party: rss_kb}): one a simulated minute, bounded by the duration
        self.endpoint = None
        self.wall0 = None
        self.depth_max_m = -math.inf
        self.end_depths_m: list = []  # vehicle depth when each mission disarms
        self._next_end = 0
        self._ends = [t0 + m.duration_s - END_S for t0, m in zip(schedule.starts_s, schedule.missions)]
        self._every = None

    def on_start(self, pids: dict) -> None:
        self.pids.update(pids)

    def sample(self, t_s: float) -> dict:
        rss = {who: rss_kb(pid) for who, pid in self.pids.items()}
        self.samples.append((t_s, rss))
        return rss

    def __call__(self, ep) -> None:
        if self.endpoint is None:
            self.endpoint = ep
            self.wall0 = time.perf_counter()
            self._every = int(round(self.sample_s / ep.period_s))
            self.sample(ep.time_s)
        t = ep.time_s + ep.period_s  # the plant has been advanced to the end of this period
        if ep.k % 10 == 0:
            depth = float(ep.plant.state[2]) - self.surface_m
            self.depth_max_m = max(self.depth_max_m, depth)
        while self._next_end < len(self._ends) and t >= self._ends[self._next_end]:
            self.end_depths_m.append(float(ep.plant.state[2]) - self.surface_m)
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


def run_soak(vehicle: Vehicle, duration_s: float, seed: int, out_dir: Path, say=None,
             warmup_s: float | None = None, faults: bool = True, sample_s: float = MINUTE_S) -> dict:
    """Fly the schedule of `seed` for `duration_s` in lock-step; measure; return the summary dict."""
    schedule = make_schedule(vehicle, duration_s, seed, faults=faults)
    if not schedule.missions:
        raise ValueError(f"duration {duration_s:g} s holds no whole random mission; use at least 120 s")
    out_dir = Path(out_dir)
    monitor = Monitor(schedule, vehicle, say=say, sample_s=sample_s)
    fly_s = schedule.starts_s[-1] + schedule.missions[-1].duration_s  # the last whole mission's end
    result = run_closed_loop(
        vehicle, schedule.setpoints(), fly_s, seed=seed, config=DEMO_CONFIG, out_dir=out_dir,
        faults=schedule.faults(), history=False, on_period=monitor, on_start=monitor.on_start,
        progress=(lambda s: say(s) if say and not s.lstrip().startswith("t =") else None),
    )
    if "error" in result.onboard:
        raise EndpointError(f"the onboard loop failed: {result.onboard['error']}")
    if "error" in result.recorder:
        raise EndpointError(f"the recorder failed: {result.recorder['error']}")
    warm = warmup_s if warmup_s is not None else min(300.0, fly_s / 4)
    return summarise(schedule, monitor, result, fly_s, warm, seed)


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
        "overruns": ob.get("overrun_log", []),  # the newest 100: (vehicle time s, wall ms, CPU ms)
    }
    # memory
    parties = list(monitor.samples[0][1])
    ts = [t for t, _ in monitor.samples]
    memory = {}
    for who in parties:
        r = [s[who] for _, s in monitor.samples]
        memory[who] = {"rss_start_kb": r[0], "rss_after_warmup_kb": next((x for t, x in zip(ts, r) if t >= warmup_s), r[-1]),
                       "rss_end_kb": r[-1], "rss_max_kb": max(r), "growth_kb_per_h": growth_kb_per_h(ts, r, warmup_s)}
    # packets: the plant endpoint's recording
    plant_rec = scan_tlog(result.tlog)
    me = plant_rec.get((1, 1), {"counts": Counter(), "gaps": 0, "first_seq": -1})
    gcs = plant_rec.get((255, 190), {"counts": Counter(), "gaps": 0, "first_seq": -1})
    onb = plant_rec.get((1, 191), {"counts": Counter(), "gaps": 0, "first_seq": -1})
    sent = Counter(ep.stats.sent)
    recorded_sent = me["counts"] + gcs["counts"]
    recorded_sent.pop(MOCAP, None)
    received = Counter(ep.stats.received) - HANDSHAKE
    sent_missing = {k: sent[k] - recorded_sent.get(k, 0) for k in sent | recorded_sent if sent[k] != recorded_sent.get(k, 0)}
    recv_missing = {k: received[k] - onb["counts"].get(k, 0) for k in received | onb["counts"]
                    if received[k] != onb["counts"].get(k, 0)}
    # the telemetry recorder's recording against what the onboard loop sent it
    tel_rec = scan_tlog(result.telemetry_tlog)
    tel = tel_rec.get((1, 191), {"counts": Counter(), "gaps": 0, "first_seq": -1})
    tel_sent = int(ob["ground_link"]["packets_out"])
    tel_recorded = int(sum(tel["counts"].values()))
    rec_counted = int(sum(result.recorder.get("messages", {}).values()))
    packets = {
        "endpoint_sent": int(sum(sent.values())),
        "endpoint_sent_recorded": int(sum(recorded_sent.values())),
        "endpoint_received": int(sum(received.values())),
        "endpoint_received_recorded": int(sum(onb["counts"].values())),
        "sent_not_recorded_by_type": sent_missing,
        "received_not_recorded_by_type": recv_missing,
        "sequence_gaps_plant_recording": {"1/1 endpoint": me["gaps"], "255/190 ground setpoints": gcs["gaps"],
                                          "1/191 onboard": onb["gaps"]},
        "onboard_first_recorded_seq": onb["first_seq"],  # 1: only the handshake HEARTBEAT (seq 0) precedes it
        "telemetry_sent": tel_sent,
        "telemetry_recorded": tel_recorded,
        "telemetry_recorder_counted": rec_counted,
        "telemetry_sequence_gaps": tel["gaps"],
        "telemetry_first_seq": tel["first_seq"],
        "mocap_recorded": int(me["counts"].get(MOCAP, 0)),
        "endpoint_resends": ep.stats.resends,
        "onboard_link": ob.get("link", {}),
        "by_type_sent": dict(sorted(sent.items())),
        "by_type_received": dict(sorted(received.items())),
        "by_type_telemetry": dict(sorted(tel["counts"].items())),
    }
    lost = (packets["endpoint_sent"] - packets["endpoint_sent_recorded"]) + (
        packets["endpoint_received"] - packets["endpoint_received_recorded"]) + sum(
        packets["sequence_gaps_plant_recording"].values()) + (tel_sent - tel_recorded) + tel["gaps"]
    packets["lost"] = int(lost)
    long_drops = sum(1 for i in schedule.injections if i.kind == "imu_dropout_long")
    ends = np.asarray(monitor.end_depths_m)
    return {
        "seed": seed,
        "duration_s": fly_s,
        "wall_s": result.wall_s,
        "missions": len(schedule.missions),
        "faults": schedule.counts(),
        "faults_total": len(schedule.injections),
        "failsafe_entries": ob["failsafe_entries"],
        "failsafe_expected": long_drops,
        "arm_refusals": ob["arm_refusals"],
        "step_errors": ob["step_errors"],
        "limit_violations": ob["limit_violations"],
        "allocation_fallbacks": ob["allocation_fallbacks"],
        "rejected_inputs": ob["rejected_inputs"],
        "depth_max_m": monitor.depth_max_m,
        "floor_clearance_min_m": monitor.floor_m - monitor.surface_m - monitor.depth_max_m,
        "missions_surfaced": int(np.sum(ends < 0.15)),
        "surface_depth_max_m": float(ends.max()) if ends.size else float("nan"),
        "deadlines": deadlines,
        "memory": {"warmup_s": warmup_s, "samples": len(monitor.samples), **memory},
        "memory_samples": [{"t_s": t, **r} for t, r in monitor.samples],
        "packets": packets,
    }


def table(s: dict) -> str:
    d, m, p = s["deadlines"], s["memory"], s["packets"]
    faults = ", ".join(f"{k} {v}" for k, v in s["faults"].items()) or "none"
    rows = [
        ("run", "simulated / wall time", f"{s['duration_s']:.0f} s / {s['wall_s']:.0f} s"),
        ("", "missions (flown / surfaced)", f"{s['missions']} / {s['missions_surfaced']}"),
        ("", "faults injected", f"{s['faults_total']}: {faults}"),
        ("", "failsafe trips (expected) / recovered", f"{s['failsafe_entries']} ({s['failsafe_expected']})"),
        ("", "step errors / limit violations", f"{s['step_errors']} / {s['limit_violations']}"),
        ("deadlines", f"steps over {d['period_ms']:.0f} ms, CPU time", f"{d['missed_cpu']} of {d['steps']}"),
        ("", "  CPU max / p99.9 / median", f"{d['cpu_max_ms']:.2f} / {d['cpu_p999_ms']:.2f} / {d['cpu_median_ms']:.2f} ms"),
        ("", f"steps over {d['period_ms']:.0f} ms, wall time", f"{d['missed_wall']} of {d['steps']}"),
        ("", "  wall max / p99.9 / median", f"{d['wall_max_ms']:.2f} / {d['wall_p999_ms']:.2f} / {d['wall_median_ms']:.2f} ms"),
    ]
    for who in ("plant", "onboard", "recorder"):
        if who in m:
            x = m[who]
            rows.append(("memory" if who == "plant" else "", f"{who}: RSS start -> end",
                         f"{x['rss_start_kb'] / 1024:.1f} -> {x['rss_end_kb'] / 1024:.1f} MB, "
                         f"growth {x['growth_kb_per_h']:+.0f} kB/h after {m['warmup_s']:.0f} s"))
    rows += [
        ("packets", "endpoint sent / in recording", f"{p['endpoint_sent']} / {p['endpoint_sent_recorded']}"),
        ("", "endpoint received / in recording", f"{p['endpoint_received']} / {p['endpoint_received_recorded']}"),
        ("", "sequence gaps in mission.tlog", f"{sum(p['sequence_gaps_plant_recording'].values())}"),
        ("", "telemetry sent / recorded (gaps)", f"{p['telemetry_sent']} / {p['telemetry_recorded']} ({p['telemetry_sequence_gaps']})"),
        ("", "lost", f"{p['lost']}"),
    ]
    w0 = max(len(r[0]) for r in rows)
    w1 = max(len(r[1]) for r in rows)
    return "\n".join(f"  {a:<{w0}}  {b:<{w1}}  {c}" for a, b, c in rows)


def verdict(s: dict, max_growth_kb_per_h: float) -> list:
    """The soak's properties that do not hold (empty: passed)."""
    bad = []
    if s["deadlines"]["missed_cpu"]:
        bad.append(f"{s['deadlines']['missed_cpu']} control steps over the period in CPU time")
    for who in ("plant", "onboard", "recorder"):
        g = s["memory"].get(who, {}).get("growth_kb_per_h", float("nan"))
        if not g <= max_growth_kb_per_h:
            bad.append(f"{who} memory grows {g:+.0f} kB/h (limit {max_growth_kb_per_h:.0f})")
    if s["packets"]["lost"]:
        bad.append(f"{s['packets']['lost']} packets lost from the recordings")
    if s["failsafe_entries"] != s["failsafe_expected"]:
        bad.append(f"{s['failsafe_entries']} failsafe trips, {s['failsafe_expected']} expected")
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
    parser.add_argument("--max-growth", type=float, default=1024.0, metavar="KB_PER_H",
                        help="memory growth per process that still passes, kB per simulated hour (default 1024)")


def run(args) -> int:
    from onboard.vehicle import VehicleFileError

    if not (math.isfinite(args.duration) and args.duration > 0):
        print(f"jetloop soak: --duration must be a positive number of seconds, got {args.duration}", file=sys.stderr)
        return 2
    try:
        vehicle = load_vehicle(args.vehicle)
    except VehicleFileError as exc:
        print(f"jetloop soak: {exc}", file=sys.stderr)
        return 2
    out = Path(args.out)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        print(f"jetloop soak: cannot create output directory {out}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    say = lambda s: print(s, file=sys.stderr, flush=True)  # noqa: E731
    say(f"jetloop soak: {args.duration:.0f} s simulated, seed {args.seed}, vehicle {vehicle.name}, "
        f"faults {'off' if args.no_faults else 'on'}, output {out}/")
    try:
        summary = run_soak(vehicle, args.duration, args.seed, out, say=say, faults=not args.no_faults)
    except (EndpointError, ValueError) as exc:
        print(f"jetloop soak: {exc}", file=sys.stderr)
        return 1
    summary["command"] = (f"jetloop soak --duration {args.duration:g} --seed {args.seed} --out {args.out}"
                          + (" --no-faults" if args.no_faults else ""))
    bad = verdict(summary, args.max_growth)
    summary["failed"] = bad
    (out / "summary.json").write_text(json.dumps(summary, indent=2, default=_jsonable) + "\n")
    print(table(summary))
    print(f"\nwrote {out / 'summary.json'}, {out / 'mission.tlog'}, {out / 'telemetry.tlog'}")
    if bad:
        print("FAILED: " + "; ".join(bad))
        return 1
    print("PASSED: zero missed deadlines (CPU), bounded memory, zero packets lost")
    return 0


def _jsonable(x):
    if isinstance(x, (np.integer,)):
        return int(x)
    if isinstance(x, (np.floating,)):
        return float(x)
    return str(x)
