"""Fault injection for the HIL: what goes wrong on purpose, when, and the link that makes it happen.

`FaultPlan` (frozen) says which faults begin when, in vehicle time (s since the plant booted):
- link, both directions between the endpoint and the controller: packet loss, delay + jitter,
  duplicates, reordering, each a fraction (or a time) with its own window [t0, t1);
- actuators: a jet dead (efficiency 0) or weak (efficiency e: the motor reaches only e times the
  commanded speed, so its ESC rpm shows it) from t0; a joint (azimuth or elevation of a unit)
  stuck from t0 at the angle it had then;
- sensors: the IMU frozen (the same HIGHRES_IMU values repeated with fresh time stamps) or NaN in a
  window; the depth sensor jumping (a step offset in pressure, rho g offset, from t0 until t1);
- the older `Faults` of hil.endpoint: IMU silence windows and garbage bytes on the link.
Units are numbered 1..k as in the vehicle file's [[unit]] list and the ESC telemetry.

The pure part (`actuator_command`, `imu_fault`, `pressure_offset_pa`, `injection_events`,
`link_fate`) says what a fault does to a command, a sample or a packet; `FaultyLink` applies the
link faults around an `onboard.link.Link` with seeded generators (one per direction), so the same
seed gives the same run in lock-step. Time there is the endpoint's vehicle time: a delayed packet
is held in a queue and goes out with the first frame at or after its due time.

Lock-step survives every link fault without waiting on the wall clock:
- the frame marker SYSTEM_TIME (and what the endpoint writes raw: its re-sent markers, injected
  ground messages, garbage) is never dropped, delayed or reordered. It is the simulation's clock
  tick, not the vehicle's data; the controller still ticks and answers on time, with whatever
  sensor data has reached it;
- the controller's answer counts as "answered" when it reaches the injector (`arrivals`,
  `on_arrival`), whatever the injector then does with it (drops it, holds it back): the plant
  goes on with the command in force, as a real autopilot does when a command is lost.
What the recording holds is what crossed the faulty link: outgoing packets when (and as often
as) they go onto the wire (`tap`), incoming ones when they are delivered; a dropped packet is
counted in `stats()["injected"]`, never recorded.
"""

from __future__ import annotations

import heapq
import math
from collections import deque
from contextlib import contextmanager
from dataclasses import dataclass, field, fields

import numpy as np

ALWAYS = (0.0, math.inf)
JOINTS = ("azimuth", "elevation")
INJECTOR_SYSTEM = 1
INJECTOR_COMPONENT = 250  # the fault injector's STATUSTEXT marks in the recording (never sent)
LOCKSTEP_EXEMPT = ("SYSTEM_TIME",)
MAX_LOSS = 0.3  # issue #7: packet loss up to 30 %


class FaultPlanError(ValueError):
    """A fault plan that cannot be applied; the message names the field and what was expected."""


# ------------------------------------------------------------------------------------------------
# The plan


@dataclass(frozen=True)
class JetFault:
    """Jet `unit` (1..k) reaches only `efficiency` x the commanded speed from t0_s (0: dead)."""

    unit: int
    efficiency: float
    t0_s: float


@dataclass(frozen=True)
class StuckJoint:
    """Joint `joint` ("azimuth" or "elevation") of unit `unit` (1..k) stuck from t0_s."""

    unit: int
    joint: str
    t0_s: float


@dataclass(frozen=True)
class DepthJump:
    """The depth sensor reads `offset_m` deeper (pressure + rho g offset) for t0_s <= t < t1_s."""

    t0_s: float
    offset_m: float
    t1_s: float = math.inf


@dataclass(frozen=True)
class FaultPlan:
    """Every fault of one run (empty: none). Windows are (t0_s, t1_s), t0 <= t < t1, vehicle time."""

    # link, both directions
    loss: float = 0.0  # fraction of packets lost, 0..0.3
    loss_window_s: tuple = ALWAYS
    delay_s: float = 0.0  # added to every packet, + U(0, jitter_s)
    jitter_s: float = 0.0
    delay_window_s: tuple = ALWAYS
    duplicate: float = 0.0  # fraction of packets that arrive twice
    duplicate_window_s: tuple = ALWAYS
    reorder: float = 0.0  # fraction of packets that arrive after the next one
    reorder_window_s: tuple = ALWAYS
    # actuators
    jets: tuple = ()  # JetFault
    stuck_joints: tuple = ()  # StuckJoint
    # sensors
    imu_freeze_s: tuple = ()  # windows: HIGHRES_IMU values repeat, fresh time stamps
    imu_nan_s: tuple = ()  # windows: HIGHRES_IMU carries NaN
    depth_jumps: tuple = ()  # DepthJump
    # the older hil.endpoint.Faults
    imu_dropouts_s: tuple = ()  # windows: no IMU message at all
    garbage_times_s: tuple = ()  # instants at which `garbage_bytes` random bytes are written
    garbage_bytes: int = 200

    def __post_init__(self):
        for name in ("loss", "duplicate", "reorder"):
            v = getattr(self, name)
            top = MAX_LOSS if name == "loss" else 1.0
            if not (isinstance(v, (int, float)) and 0.0 <= v <= top):
                raise FaultPlanError(f"FaultPlan.{name} must be a fraction 0..{top:g}, got {v!r}")
        for name in ("delay_s", "jitter_s"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and 0.0 <= v < math.inf):
                raise FaultPlanError(f"FaultPlan.{name} must be a finite time >= 0 s, got {v!r}")
        for name in ("loss_window_s", "delay_window_s", "duplicate_window_s", "reorder_window_s"):
            _check_window(f"FaultPlan.{name}", getattr(self, name))
        for name in ("imu_freeze_s", "imu_nan_s", "imu_dropouts_s"):
            for i, w in enumerate(getattr(self, name)):
                _check_window(f"FaultPlan.{name}[{i}]", w)
        for i, j in enumerate(self.jets):
            if not isinstance(j, JetFault) or not 0.0 <= j.efficiency < 1.0 or not j.t0_s >= 0:
                raise FaultPlanError(f"FaultPlan.jets[{i}] must be a JetFault with 0 <= efficiency < 1 "
                                     f"and t0_s >= 0, got {j!r}")
        for i, s in enumerate(self.stuck_joints):
            if not isinstance(s, StuckJoint) or s.joint not in JOINTS or not s.t0_s >= 0:
                raise FaultPlanError(f"FaultPlan.stuck_joints[{i}] must be a StuckJoint with joint "
                                     f"'azimuth' or 'elevation' and t0_s >= 0, got {s!r}")
        for i, d in enumerate(self.depth_jumps):
            if not isinstance(d, DepthJump) or not math.isfinite(d.offset_m):
                raise FaultPlanError(f"FaultPlan.depth_jumps[{i}] must be a DepthJump with a finite offset, got {d!r}")
            _check_window(f"FaultPlan.depth_jumps[{i}]", (d.t0_s, d.t1_s))
        if not (isinstance(self.garbage_bytes, int) and self.garbage_bytes >= 0):
            raise FaultPlanError(f"FaultPlan.garbage_bytes must be an integer >= 0, got {self.garbage_bytes!r}")

    @property
    def link_faults(self) -> bool:
        """Whether any link fault is asked (then the endpoint wraps its link in a FaultyLink)."""
        return bool(self.loss or self.delay_s or self.jitter_s or self.duplicate or self.reorder)

    @property
    def empty(self) -> bool:
        return all(getattr(self, f.name) == f.default for f in fields(self))

    def check_units(self, n_units: int) -> None:
        """Raise FaultPlanError if a jet or joint fault names a unit the vehicle does not have."""
        for what, items in (("jets", self.jets), ("stuck_joints", self.stuck_joints)):
            for i, f in enumerate(items):
                if not (isinstance(f.unit, int) and 1 <= f.unit <= n_units):
                    raise FaultPlanError(f"FaultPlan.{what}[{i}].unit must be 1..{n_units} "
                                         f"(the vehicle has {n_units} units), got {f.unit!r}")


def _check_window(name: str, w) -> None:
    try:
        t0, t1 = (float(v) for v in w)
    except (TypeError, ValueError):
        raise FaultPlanError(f"{name} must be a window (t0_s, t1_s), got {w!r}") from None
    if not (0.0 <= t0 < t1) or math.isnan(t1):
        raise FaultPlanError(f"{name} must satisfy 0 <= t0 < t1 (s), got {w!r}")


def in_window(w, t: float) -> bool:
    return w[0] <= t + 1e-9 and t + 1e-9 < w[1]


# ------------------------------------------------------------------------------------------------
# What a fault does (pure)


def actuator_command(plan: FaultPlan, command, t: float, stuck_rad: dict) -> np.ndarray:
    """The command the actuators execute at time t: u = [n x k, alpha x k, beta x k].

    Jet j (1-based) with efficiency e from t0: n_j = e * n_cmd_j (the motor reaches e times the
    commanded speed; e = 0: dead). Joint stuck from t0: its command is the angle it had at t0,
    `stuck_rad[(unit, joint)]` (a first-order servo commanded to where it is stays there).
    """
    u = np.array(command, dtype=float)
    k = len(u) // 3
    for j in plan.jets:
        if t + 1e-9 >= j.t0_s:
            u[j.unit - 1] *= j.efficiency
    for s in plan.stuck_joints:
        if t + 1e-9 >= s.t0_s and (s.unit, s.joint) in stuck_rad:
            u[(1 if s.joint == "azimuth" else 2) * k + s.unit - 1] = stuck_rad[(s.unit, s.joint)]
    return u


def joint_index(n_units: int, unit: int, joint: str) -> int:
    """Index in the state's alpha/beta block order [alpha x k, beta x k] of a 1-based unit's joint."""
    return (0 if joint == "azimuth" else n_units) + unit - 1


def imu_fault(plan: FaultPlan, t: float) -> str | None:
    """"nan", "freeze" or None for an IMU sample taken at t (NaN wins where windows overlap)."""
    if any(in_window(w, t) for w in plan.imu_nan_s):
        return "nan"
    if any(in_window(w, t) for w in plan.imu_freeze_s):
        return "freeze"
    return None


def pressure_offset_pa(plan: FaultPlan, t: float, rho_kg_m3: float, g_m_s2: float) -> float:
    """Sum of the depth jumps in force at t, as pressure: dp = rho g offset (spec 5, p = p_atm + rho g d)."""
    return sum(rho_kg_m3 * g_m_s2 * d.offset_m for d in plan.depth_jumps if in_window((d.t0_s, d.t1_s), t))


def injection_events(plan: FaultPlan) -> list:
    """(t_s, text) of every fault's start and end, in time order: the recording's INJECT marks."""
    ev = []

    def window(w, what, short):
        ev.append((float(w[0]), f"INJECT {what}"))
        if math.isfinite(w[1]):
            ev.append((float(w[1]), f"INJECT END {short}"))

    if plan.loss:
        window(plan.loss_window_s, f"link loss {plan.loss:.2f}", "link loss")
    if plan.delay_s or plan.jitter_s:
        window(plan.delay_window_s, f"link delay {plan.delay_s:.3f}s jitter {plan.jitter_s:.3f}s", "link delay")
    if plan.duplicate:
        window(plan.duplicate_window_s, f"link duplicate {plan.duplicate:.2f}", "link duplicate")
    if plan.reorder:
        window(plan.reorder_window_s, f"link reorder {plan.reorder:.2f}", "link reorder")
    for j in plan.jets:
        ev.append((j.t0_s, f"INJECT jet {j.unit} dead" if j.efficiency == 0 else
                   f"INJECT jet {j.unit} weak {j.efficiency:.2f}"))
    for s in plan.stuck_joints:
        ev.append((s.t0_s, f"INJECT joint {s.unit} {s.joint} stuck"))
    for w in plan.imu_freeze_s:
        window(w, "imu frozen", "imu frozen")
    for w in plan.imu_nan_s:
        window(w, "imu nan", "imu nan")
    for w in plan.imu_dropouts_s:
        window(w, "imu dropout", "imu dropout")
    for d in plan.depth_jumps:
        window((d.t0_s, d.t1_s), f"depth jump {d.offset_m:+.3f}m", "depth jump")
    for t in plan.garbage_times_s:
        ev.append((float(t), f"INJECT garbage {plan.garbage_bytes} bytes"))
    return sorted(ev, key=lambda e: e[0])


@dataclass(frozen=True)
class Fate:
    """What the link does to one packet: lost, or delivered `copies` times after `delay_s`,
    possibly held back behind the next packet (`reorder`)."""

    lost: bool = False
    copies: int = 1
    delay_s: float = 0.0
    reorder: bool = False


DRAWS_PER_PACKET = 4  # u_loss, u_duplicate, u_reorder, u_jitter: always drawn, in this order


def link_fate(plan: FaultPlan, t: float, u) -> Fate:
    """The fate of a packet at time t from four uniform draws u in [0, 1).

    lost if u0 < loss; 2 copies if u1 < duplicate; held behind the next packet if u2 < reorder;
    delay = delay_s + u3 * jitter_s; each only inside its own window.
    """
    if plan.loss and in_window(plan.loss_window_s, t) and u[0] < plan.loss:
        return Fate(lost=True, copies=0)
    dup = bool(plan.duplicate and in_window(plan.duplicate_window_s, t) and u[1] < plan.duplicate)
    reo = bool(plan.reorder and in_window(plan.reorder_window_s, t) and u[2] < plan.reorder)
    delay = plan.delay_s + u[3] * plan.jitter_s if in_window(plan.delay_window_s, t) else 0.0
    return Fate(False, 2 if dup else 1, float(delay), reo)


# ------------------------------------------------------------------------------------------------
# The faulty link


@dataclass
class InjectedCounts:
    lost: int = 0
    duplicated: int = 0
    delayed: int = 0
    reordered: int = 0
    passed: int = 0  # packets that went through the fault decisions (not exempt, window or not)
    lost_by_type: dict = field(default_factory=dict)  # message type -> packets lost

    def lose(self, name: str) -> None:
        self.lost += 1
        self.lost_by_type[name] = self.lost_by_type.get(name, 0) + 1

    def as_dict(self) -> dict:
        return {**self.__dict__, "lost_by_type": dict(self.lost_by_type)}


class FaultyLink:
    """An onboard.link.Link with the plan's link faults in both directions (same interface).

    `clock()`: the vehicle time now (the endpoint's). `exempt`: message types never touched (the
    lock-step frame marker). `tap(packet, name)`: every outgoing packet as it goes onto the wire
    (for the recording). `on_arrival(msg)`: every incoming message as it reaches the injector,
    before its fate is drawn; `arrivals` counts them.
    """

    def __init__(self, link, plan: FaultPlan, clock, seed: int = 0, exempt=LOCKSTEP_EXEMPT,
                 tap=None, on_arrival=None):
        self.inner = link
        self.plan = plan
        self.clock = clock
        self.exempt = frozenset(exempt)
        self.tap = tap
        self.on_arrival = on_arrival
        self.arrivals = 0
        self.out = InjectedCounts()
        self.into = InjectedCounts()
        self._rng_out = np.random.default_rng([int(seed), 7, 1])  # one stream per direction, so
        self._rng_in = np.random.default_rng([int(seed), 7, 2])  # one side's timing never moves the other's
        self._out_held: list = []  # heap (due_s, order, packet, name)
        self._in_held: list = []  # heap (due_s, order, msg)
        self._order = 0
        self._out_behind = None  # (packet, name) waiting for the next packet to overtake it
        self._in_behind = None
        self._ready: deque = deque()

    # everything else (has_peer, connection, local_address, garbage_bytes, ...) is the inner link's
    def __getattr__(self, name):
        return getattr(self.inner, name)

    # -- sending ----------------------------------------------------------------------------------
    def send(self, msg) -> bytes:
        packet = self.inner.pack(msg)
        self._outgoing(packet, msg.get_type())
        return packet

    def write_raw(self, data: bytes) -> None:
        self.inner.write_raw(data)  # raw bytes (marker re-sends, ground messages, garbage) pass as is

    @contextmanager
    def batch(self):
        with self.inner.batch():
            self.release_due()
            yield self

    def release_due(self) -> None:
        """Put on the wire every held outgoing packet whose time has come."""
        t = self.clock()
        while self._out_held and self._out_held[0][0] <= t + 1e-9:
            _, _, packet, name = heapq.heappop(self._out_held)
            self._wire(packet, name)

    def _outgoing(self, packet: bytes, name: str) -> None:
        if name in self.exempt:
            self._wire(packet, name)
            return
        t = self.clock()
        fate = link_fate(self.plan, t, self._rng_out.random(DRAWS_PER_PACKET))
        self.out.passed += 1
        if fate.lost:
            self.out.lose(name)
            return
        self.out.duplicated += fate.copies - 1
        if fate.delay_s > 0:
            self.out.delayed += 1
            for _ in range(fate.copies):
                self._order += 1
                heapq.heappush(self._out_held, (t + fate.delay_s, self._order, packet, name))
            if self._out_behind is not None:  # a held packet follows the one that overtook it, delayed or not
                behind, self._out_behind = self._out_behind, None
                self._order += 1
                heapq.heappush(self._out_held, (t + fate.delay_s, self._order, *behind))
            return
        if fate.reorder and self._out_behind is None:
            self.out.reordered += 1
            self._out_behind = (packet, name)
            return
        for _ in range(fate.copies):
            self._wire(packet, name)
        if self._out_behind is not None:  # the held packet follows the one that overtook it
            behind, self._out_behind = self._out_behind, None
            self._wire(*behind)

    def _wire(self, packet: bytes, name: str) -> None:
        self.inner.write_raw(packet)
        if self.tap is not None:
            self.tap(packet, name)

    # -- receiving --------------------------------------------------------------------------------
    def recv(self, timeout_s: float = 0.0):
        """The next delivered message, or None. A message that arrived but was lost or held back
        makes this return None at once (look at `arrivals` to tell it from a timeout)."""
        t = self.clock()
        while self._in_held and self._in_held[0][0] <= t + 1e-9:
            self._ready.append(heapq.heappop(self._in_held)[2])
        if self._ready:
            return self._ready.popleft()
        m = self.inner.recv(timeout_s)
        if m is None:
            return None
        self.arrivals += 1
        if self.on_arrival is not None:
            self.on_arrival(m)
        if m.get_type() in self.exempt:
            return m
        fate = link_fate(self.plan, t, self._rng_in.random(DRAWS_PER_PACKET))
        self.into.passed += 1
        if fate.lost:
            self.into.lose(m.get_type())
            return None
        self.into.duplicated += fate.copies - 1
        if fate.delay_s > 0:
            self.into.delayed += 1
            for _ in range(fate.copies):
                self._order += 1
                heapq.heappush(self._in_held, (t + fate.delay_s, self._order, m))
            if self._in_behind is not None:  # a held packet follows the one that overtook it, delayed or not
                self._order += 1
                heapq.heappush(self._in_held, (t + fate.delay_s, self._order, self._in_behind))
                self._in_behind = None
            return None
        if fate.reorder and self._in_behind is None:
            self.into.reordered += 1
            self._in_behind = m
            return None
        self._ready.extend([m] * (fate.copies - 1))
        if self._in_behind is not None:
            self._ready.append(self._in_behind)
            self._in_behind = None
        return m

    def stats(self) -> dict:
        s = dict(self.inner.stats())
        s["injected"] = {"out": self.out.as_dict(), "in": self.into.as_dict(),
                         # not yet delivered: delayed, or waiting for the next packet to overtake it
                         "held_out": len(self._out_held) + (self._out_behind is not None),
                         "held_in": len(self._in_held) + (self._in_behind is not None)}
        return s

    def close(self) -> None:
        self.inner.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


# ------------------------------------------------------------------------------------------------
# The marks in a recording


def read_injections(path) -> list:
    """(t_s, text) of the fault injector's STATUSTEXT marks in a .tlog (system 1, component 250),
    t_s = log time - hil.tlog.FIXED_EPOCH_US (vehicle time in a simulated recording). Read with
    ground.recording's packet scan, the reader the diagnosis uses."""
    from pathlib import Path

    from ground.recording import decode_message, scan_packets
    from hil.tlog import FIXED_EPOCH_US

    buf, off, plen, mid, src, ts = scan_packets(Path(path).read_bytes())
    arr, sel = decode_message(buf, off, plen, mid, "STATUSTEXT")
    if arr is None:
        return []
    mine = src[sel] == INJECTOR_SYSTEM * 256 + INJECTOR_COMPONENT
    out = []
    for a, t in zip(arr[mine], ts[sel][mine]):
        text = bytes(a["text"]).split(b"\0", 1)[0].decode("ascii", "replace")
        out.append(((int(t) - FIXED_EPOCH_US) / 1e6, text))
    return out


# ------------------------------------------------------------------------------------------------
# What the onboard monitor should say about each injected fault


# onboard.monitor.Fault values (the shared vocabulary of issue #7; a test checks they agree)
FLAG = {"LINK_LOSS": 1, "LINK_DELAY": 2, "LINK_DUPLICATE": 4, "LINK_REORDER": 8, "JET_DEAD": 16,
        "JET_WEAK": 32, "JOINT_STUCK": 64, "IMU_FROZEN": 128, "IMU_NAN": 256, "DEPTH_JUMP": 512,
        "IMU_LOST": 1024}


def expected_detections(plan: FaultPlan) -> list:
    """(t0_s, flag name, what was injected) for every fault the onboard side should report."""
    out = []
    if plan.loss:
        out.append((plan.loss_window_s[0], "LINK_LOSS", f"loss {plan.loss:g}"))
    if plan.delay_s or plan.jitter_s:
        out.append((plan.delay_window_s[0], "LINK_DELAY", f"delay {plan.delay_s:g} s jitter {plan.jitter_s:g} s"))
    if plan.duplicate:
        out.append((plan.duplicate_window_s[0], "LINK_DUPLICATE", f"duplicate {plan.duplicate:g}"))
    if plan.reorder:
        out.append((plan.reorder_window_s[0], "LINK_REORDER", f"reorder {plan.reorder:g}"))
    for j in plan.jets:
        out.append((j.t0_s, "JET_DEAD" if j.efficiency == 0 else "JET_WEAK",
                    f"jet {j.unit} " + ("dead" if j.efficiency == 0 else f"weak {j.efficiency:g}")))
    for s in plan.stuck_joints:
        out.append((s.t0_s, "JOINT_STUCK", f"joint {s.unit} {s.joint} stuck"))
    out += [(w[0], "IMU_FROZEN", f"imu frozen {w[0]:g}-{w[1]:g} s") for w in plan.imu_freeze_s]
    out += [(w[0], "IMU_NAN", f"imu nan {w[0]:g}-{w[1]:g} s") for w in plan.imu_nan_s]
    out += [(w[0], "IMU_LOST", f"imu silent {w[0]:g}-{w[1]:g} s") for w in plan.imu_dropouts_s]
    out += [(d.t0_s, "DEPTH_JUMP", f"depth jump {d.offset_m:+g} m") for d in plan.depth_jumps]
    return sorted(out, key=lambda e: e[0])


def detections(plan: FaultPlan, fault_events) -> list:
    """For each injected fault: dict(injected, flag, t0_s, detected_s or None, latency_s or None),
    from the onboard loop's fault_events [(t_s, flag, text), ...] ("FAULT ..." raises only)."""
    raised = [(float(t), int(flag)) for t, flag, text in fault_events if str(text).startswith("FAULT")]
    out = []
    for t0, name, what in expected_detections(plan):
        hit = next((t for t, flag in raised if flag & FLAG[name] and t + 1e-9 >= t0), None)
        out.append({"injected": what, "flag": name, "t0_s": t0, "detected_s": hit,
                    "latency_s": None if hit is None else round(hit - t0, 3)})
    return out


# ------------------------------------------------------------------------------------------------
# Command-line flags (`jetloop hil`, `jetloop demo`)


FLAG_HELP = {
    "loss": "FRACTION[@T0[:T1]]: lose this fraction (0..0.3) of the packets, both ways",
    "delay": "SECONDS[@T0[:T1]]: delay every packet, both ways",
    "jitter": "SECONDS: add U(0, SECONDS) to the delay (in --delay's window)",
    "duplicate": "FRACTION[@T0[:T1]]: deliver this fraction of the packets twice",
    "reorder": "FRACTION[@T0[:T1]]: deliver this fraction of the packets after the next one",
    "dead-jet": "UNIT@T0: jet UNIT (1..k) stops at T0 (repeatable)",
    "weak-jet": "UNIT:EFFICIENCY@T0: jet UNIT reaches only EFFICIENCY (0..1) of the commanded speed (repeatable)",
    "stuck-joint": "UNIT:azimuth|elevation@T0: that joint stays where it is at T0 (repeatable)",
    "imu-freeze": "T0:T1: the IMU repeats its last values with fresh time stamps (repeatable)",
    "imu-nan": "T0:T1: the IMU sends NaN (repeatable)",
    "depth-jump": "OFFSET_M@T0[:T1]: the depth sensor reads OFFSET_M deeper (repeatable; a negative one as --depth-jump=-0.1@T0)",
}


def add_fault_arguments(parser) -> None:
    """The fault flags; `plan_from_args` turns them into a FaultPlan. Times: s of vehicle time."""
    g = parser.add_argument_group("fault injection (issue #7; times in s of vehicle time)")
    for name, text in FLAG_HELP.items():
        repeat = name in ("dead-jet", "weak-jet", "stuck-joint", "imu-freeze", "imu-nan", "depth-jump")
        meta, _, what = text.partition(": ")
        g.add_argument(f"--{name}", default=[] if repeat else None, action="append" if repeat else "store",
                       metavar=meta, help=what)


def _number(flag: str, text: str, expect: str) -> float:
    try:
        v = float(text)
    except ValueError:
        raise FaultPlanError(f"--{flag} {text!r}: expected {expect}") from None
    if not math.isfinite(v):
        raise FaultPlanError(f"--{flag} {text!r}: expected {expect} (a finite number)")
    return v


def _at(flag: str, value: str, expect: str, window: bool):
    """'X@T0[:T1]' -> ('X', (t0, t1)); without '@' the whole run (only where a window is allowed)."""
    head, sep, when = value.partition("@")
    if not sep:
        if window:
            return head, ALWAYS
        raise FaultPlanError(f"--{flag} {value!r}: expected {expect} (the onset time @T0 is missing)")
    t0s, sep1, t1s = when.partition(":")
    if sep1 and not window:
        raise FaultPlanError(f"--{flag} {value!r}: expected {expect} (this fault has no end time)")
    t0 = _number(flag, t0s, expect)
    t1 = _number(flag, t1s, expect) if sep1 else math.inf
    if not 0.0 <= t0 < t1:
        raise FaultPlanError(f"--{flag} {value!r}: expected {expect} with 0 <= T0 < T1")
    return head, (t0, t1)


def _unit(flag: str, text: str, value: str, expect: str, n_units: int) -> int:
    if not text.strip().isdigit() or not 1 <= int(text) <= n_units:
        raise FaultPlanError(f"--{flag} {value!r}: expected {expect}, UNIT a jet number 1..{n_units}")
    return int(text)


def plan_from_args(args, n_units: int) -> FaultPlan:
    """The FaultPlan of the parsed fault flags; FaultPlanError naming the flag and what it expects."""
    kw: dict = {}
    for name, field_, top in (("loss", "loss", MAX_LOSS), ("duplicate", "duplicate", 1.0), ("reorder", "reorder", 1.0)):
        value = getattr(args, name, None)
        if value is None:
            continue
        expect = f"FRACTION[@T0[:T1]], FRACTION 0..{top:g}"
        head, w = _at(name, value, expect, window=True)
        v = _number(name, head, expect)
        if not 0.0 <= v <= top:
            raise FaultPlanError(f"--{name} {value!r}: expected {expect}")
        kw[field_], kw[f"{field_}_window_s"] = v, w
    if getattr(args, "delay", None) is not None:
        expect = "SECONDS[@T0[:T1]], SECONDS >= 0"
        head, w = _at("delay", args.delay, expect, window=True)
        kw["delay_s"], kw["delay_window_s"] = _number("delay", head, expect), w
        if kw["delay_s"] < 0:
            raise FaultPlanError(f"--delay {args.delay!r}: expected {expect}")
    if getattr(args, "jitter", None) is not None:
        kw["jitter_s"] = _number("jitter", args.jitter, "SECONDS >= 0 (no window: it uses --delay's)")
        if kw["jitter_s"] < 0:
            raise FaultPlanError(f"--jitter {args.jitter!r}: expected SECONDS >= 0")
    jets, stuck, depth = [], [], []
    for value in getattr(args, "dead_jet", None) or []:
        expect = "UNIT@T0"
        head, (t0, _) = _at("dead-jet", value, expect, window=False)
        jets.append(JetFault(_unit("dead-jet", head, value, expect, n_units), 0.0, t0))
    for value in getattr(args, "weak_jet", None) or []:
        expect = "UNIT:EFFICIENCY@T0, EFFICIENCY in (0, 1)"
        head, (t0, _) = _at("weak-jet", value, expect, window=False)
        unit, sep, eff = head.partition(":")
        if not sep:
            raise FaultPlanError(f"--weak-jet {value!r}: expected {expect}")
        e = _number("weak-jet", eff, expect)
        if not 0.0 < e < 1.0:
            raise FaultPlanError(f"--weak-jet {value!r}: expected {expect} (use --dead-jet for 0)")
        jets.append(JetFault(_unit("weak-jet", unit, value, expect, n_units), e, t0))
    for value in getattr(args, "stuck_joint", None) or []:
        expect = "UNIT:azimuth@T0 or UNIT:elevation@T0"
        head, (t0, _) = _at("stuck-joint", value, expect, window=False)
        unit, sep, joint = head.partition(":")
        if not sep or joint not in JOINTS:
            raise FaultPlanError(f"--stuck-joint {value!r}: expected {expect}")
        stuck.append(StuckJoint(_unit("stuck-joint", unit, value, expect, n_units), joint, t0))
    for flag, field_ in (("imu-freeze", "imu_freeze_s"), ("imu-nan", "imu_nan_s")):
        windows = []
        for value in getattr(args, flag.replace("-", "_"), None) or []:
            expect = "T0:T1 with 0 <= T0 < T1"
            t0s, sep, t1s = value.partition(":")
            if not sep:
                raise FaultPlanError(f"--{flag} {value!r}: expected {expect}")
            t0, t1 = _number(flag, t0s, expect), _number(flag, t1s, expect)
            if not 0.0 <= t0 < t1:
                raise FaultPlanError(f"--{flag} {value!r}: expected {expect}")
            windows.append((t0, t1))
        if windows:
            kw[field_] = tuple(windows)
    for value in getattr(args, "depth_jump", None) or []:
        expect = "OFFSET_M@T0[:T1]"
        head, (t0, t1) = _at("depth-jump", value, expect, window=True)
        if "@" not in value:
            raise FaultPlanError(f"--depth-jump {value!r}: expected {expect} (the onset time @T0 is missing)")
        depth.append(DepthJump(t0, _number("depth-jump", head, expect), t1))
    if jets:
        kw["jets"] = tuple(jets)
    if stuck:
        kw["stuck_joints"] = tuple(stuck)
    if depth:
        kw["depth_jumps"] = tuple(depth)
    return FaultPlan(**kw)
