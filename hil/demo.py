"""`jetloop demo`: the plant, the onboard loop and a ground recorder over loopback UDP, in lock-step.

Three parties talk MAVLink over real sockets on 127.0.0.1:
- the plant (hil.endpoint.HilEndpoint around hil.plant.Plant, every effect of the vehicle file on)
  plays the autopilot's sensor side and injects the scripted mission's ground setpoints;
- the onboard loop (onboard.loop.OnboardLoop: estimator, controller, transient compensation, QP
  allocation) flies it, answering every frame with HIL_ACTUATOR_CONTROLS;
- a recorder plays the ground station, writing the onboard telemetry to its own .tlog.
The onboard loop and the recorder run in their own processes (forked; threads where fork is not
available). The plant advances only when the controller has answered, so the run is
deterministic and as fast as the CPU allows; the same seed gives the same recording byte for byte.

Mission (reference vehicle): arm at 1 s; dive to 0.5 m; hold; yaw to 90 deg; forward at 0.3 m/s
for 5 s; stop; surface. Tracking errors are RMS of the plant's true state against the setpoint,
over each leg after a settling allowance (`Leg.settle_s`), so they measure holding, not the
reference's own transition time.
"""

from __future__ import annotations

import json
import math
import multiprocessing as mp
import os
import queue
import sys
import threading
import time
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from hil.endpoint import EndpointError, HilEndpoint
from hil.faults import FaultPlan, detections
from hil.plant import Plant
from onboard.link import Link
from onboard.loop import LoopConfig, OnboardLoop, VehicleClock, arm_command, body_velocity_target, depth_yaw_target
from onboard.vehicle import Vehicle, load_vehicle


# ------------------------------------------------------------------------------------------------
# The mission


@dataclass(frozen=True)
class Leg:
    """From t0_s on, the ground asks for this (None: not part of this leg's demand)."""

    t0_s: float
    name: str
    depth_m: float | None = None
    yaw_rad: float | None = None
    surge_m_s: float | None = None
    settle_s: float = 4.0  # excluded from the tracking statistics after the leg starts


@dataclass(frozen=True)
class Mission:
    legs: tuple
    duration_s: float
    arm_s: float = 1.0

    def setpoints(self) -> list:
        """(vehicle time, ground message) pairs the plant endpoint injects."""
        out = [(self.arm_s, arm_command(True))]
        for leg in self.legs:
            if leg.depth_m is not None or leg.yaw_rad is not None:
                out.append((leg.t0_s, depth_yaw_target(leg.depth_m, leg.yaw_rad)))
            if leg.surge_m_s is not None:
                out.append((leg.t0_s, body_velocity_target(leg.surge_m_s, 0.0)))
        return out

    def demand_at(self, t: float) -> dict:
        """The setpoint in force at t (legs carry forward what they do not change) and its leg."""
        cur = {"depth_m": None, "yaw_rad": None, "surge_m_s": None, "leg": None}
        for leg in self.legs:
            if leg.t0_s <= t + 1e-9:
                for k in ("depth_m", "yaw_rad", "surge_m_s"):
                    if getattr(leg, k) is not None:
                        cur[k] = getattr(leg, k)
                cur["leg"] = leg
        return cur


# The onboard configuration the demo flies (and the mission test checks).
DEMO_CONFIG = LoopConfig()


def hold_mission(duration_s: float = 20.0, depth_m: float = 0.5, turn_at_s: float | None = None) -> Mission:
    """Arm at 1 s, dive to `depth_m`, hold depth and heading (from `turn_at_s`, 45 deg to
    starboard, so the joints move): the scene for a fault scenario."""
    legs = [Leg(1.0, "dive", depth_m=depth_m, yaw_rad=0.0, surge_m_s=0.0, settle_s=5.0)]
    if turn_at_s is not None:
        legs.append(Leg(turn_at_s, "turn 45", yaw_rad=math.pi / 4, settle_s=3.0))
    return Mission(legs=tuple(legs), duration_s=duration_s)


def reference_mission() -> Mission:
    """Dive to 0.5 m, hold, yaw 90 deg, forward 0.3 m/s for 5 s, stop, surface."""
    return Mission(
        legs=(
            Leg(1.0, "dive", depth_m=0.5, yaw_rad=0.0, surge_m_s=0.0, settle_s=5.0),
            Leg(8.0, "hold", settle_s=0.0),
            Leg(11.0, "yaw 90", yaw_rad=math.pi / 2, settle_s=4.0),
            Leg(17.0, "forward", surge_m_s=0.3, settle_s=2.0),
            Leg(22.0, "stop", surge_m_s=0.0, settle_s=2.0),
            Leg(26.0, "surface", depth_m=0.0, settle_s=4.0),
        ),
        duration_s=32.0,
    )


# ------------------------------------------------------------------------------------------------
# Scoring (pure)


def _wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def tracking_errors(truth, mission: Mission, surface_m: float = 0.0) -> dict:
    """RMS errors of the true state against the setpoint, leg by leg after its settling time.

    depth: over legs asking for a depth below the surface; yaw: wherever a yaw is asked;
    speed: body surge u wherever a surge speed is asked.
    """
    e_depth, e_yaw, e_speed = [], [], []
    for s in truth:
        d = mission.demand_at(s.time_s)
        leg = d["leg"]
        if leg is None or s.time_s < leg.t0_s + leg.settle_s:
            continue
        depth = s.pos_ned_m[2] - surface_m
        if d["depth_m"] is not None and d["depth_m"] > 0:
            e_depth.append(depth - d["depth_m"])
        if d["yaw_rad"] is not None:
            e_yaw.append(float(_wrap(s.euler_rad[2] - d["yaw_rad"])))
        if d["surge_m_s"] is not None:
            e_speed.append(s.nu[0] - d["surge_m_s"])
    rms = lambda e: float(np.sqrt(np.mean(np.square(e)))) if e else float("nan")  # noqa: E731
    return {"depth_rms_m": rms(e_depth), "yaw_rms_rad": rms(e_yaw), "speed_rms_m_s": rms(e_speed),
            "depth_max_m": float(np.max(np.abs(e_depth))) if e_depth else float("nan")}


# ------------------------------------------------------------------------------------------------
# The three parties


def _die_with_parent(parent_pid: int | None):
    """In a forked party: never outlive the parent (issue 15: killing `jetloop demo` left its
    onboard child flying for good). Linux: the kernel sends SIGTERM when the parent dies
    (PR_SET_PDEATHSIG; the jetloop commands turn SIGTERM into Ctrl-C); everywhere, the party's
    own loop also stops once its parent is gone. Returns stop's extra condition. (Linux signals
    when the forking *thread* ends: run_closed_loop must run in a thread that outlives the flight,
    as the main thread does.)"""
    if parent_pid is None:  # a thread: it dies with its process
        return lambda: False
    try:
        import ctypes
        import signal

        libc = ctypes.CDLL(None, use_errno=True)
        libc.prctl(1, int(signal.SIGTERM), 0, 0, 0)  # PR_SET_PDEATHSIG = 1
    except (OSError, AttributeError):
        pass  # not Linux: the check below alone
    orphaned = lambda: os.getppid() != parent_pid  # noqa: E731
    if orphaned():  # the parent died before prctl took effect
        os._exit(1)
    return orphaned


def _onboard_main(vehicle, link, ground, config, stop, results, parent_pid=None):
    """The onboard process: build the loop (compiles on a first run), fly until told to stop.
    Reports the loop's whole stats.summary() (with the fault monitor's faults_seen and
    fault_events) plus the links' counts."""
    orphaned = _die_with_parent(parent_pid)
    try:
        loop = OnboardLoop(vehicle, link, VehicleClock(), config, ground=ground)
        loop.run(stop=lambda: stop.is_set() or orphaned())
        summary = loop.stats.summary()
        summary["link"] = link.stats()
        summary["ground_link"] = ground.stats()  # what the telemetry recorder should have got
        summary["estimator_rejected"] = int(loop.estimator.health.rejected_total)
        results.put(("onboard", summary))
    except KeyboardInterrupt:  # Ctrl-C reaches the whole process group: the parent says so
        pass
    except Exception as exc:  # reported to the parent, which prints it
        results.put(("onboard", {"error": f"{type(exc).__name__}: {exc}"}))


def _recorder_main(link, path, stop, results, parent_pid=None):
    """The ground recorder: every telemetry packet into a .tlog, stamped with vehicle time."""
    from hil.tlog import FIXED_EPOCH_US, TlogWriter

    orphaned = _die_with_parent(parent_pid)
    counts: dict = {}
    t_us = 0
    try:
        with TlogWriter(path) as tlog:
            while not stop.is_set() and not orphaned():
                m = link.recv(0.1)
                while m is not None:
                    name = m.get_type()
                    counts[name] = counts.get(name, 0) + 1
                    if hasattr(m, "time_usec") and name != "SERVO_OUTPUT_RAW":
                        t_us = max(t_us, int(m.time_usec))
                    elif hasattr(m, "time_boot_ms"):
                        t_us = max(t_us, int(m.time_boot_ms) * 1000)
                    tlog.write_packet(bytes(m.get_msgbuf()), FIXED_EPOCH_US + t_us, name)
                    m = link.recv(0.0)
        results.put(("recorder", {"messages": counts, "link": link.stats()}))
    except KeyboardInterrupt:
        pass
    except Exception as exc:
        results.put(("recorder", {"error": f"{type(exc).__name__}: {exc}"}))


@dataclass
class ClosedLoopResult:
    truth: list
    commands: list  # (t, command applied by the plant)
    endpoint: dict
    onboard: dict
    recorder: dict
    wall_s: float
    tlog: Path | None = None
    telemetry_tlog: Path | None = None
    extra: dict = field(default_factory=dict)


def run_closed_loop(
    vehicle: Vehicle,
    setpoints,
    duration_s: float,
    seed: int = 0,
    config: LoopConfig = LoopConfig(),
    out_dir: Path | None = None,
    faults: FaultPlan = FaultPlan(),
    depth_m: float = 0.0,
    processes: bool = True,
    start_timeout_s: float = 300.0,
    progress=None,
    frame_period_s: float | None = None,
    history: bool = True,
    on_period=None,
    on_start=None,
    halt=None,
) -> ClosedLoopResult:
    """Plant + onboard + recorder over loopback UDP in lock-step; returns what happened.

    `history=False`: the endpoint keeps no truth/command lists (long runs); `on_period(endpoint)`
    runs after every period; `on_start({"onboard": pid, "recorder": pid})` once the parties run
    (empty with threads); `halt()` true ends the flight early, as finished. For soaks (hil.soak).
    """
    use_fork = processes and "fork" in mp.get_all_start_methods()
    ctx = mp.get_context("fork") if use_fork else None
    ep_link = Link("udpin:127.0.0.1:0", source_system=1, source_component=1)
    ob_link = Link(f"udpout:127.0.0.1:{ep_link.local_address[1]}", source_system=1, source_component=191)
    rec_link = Link("udpin:127.0.0.1:0", source_system=255, source_component=190)
    gnd_link = Link(f"udpout:127.0.0.1:{rec_link.local_address[1]}", source_system=1, source_component=191)
    tlog_path = telemetry_path = None
    if out_dir is not None:
        out_dir = Path(out_dir)
        out_dir.mkdir(parents=True, exist_ok=True)
        tlog_path = out_dir / "mission.tlog"
        telemetry_path = out_dir / "telemetry.tlog"
    if use_fork:
        stop, results = ctx.Event(), ctx.Queue()
        start = lambda target, args: ctx.Process(target=target, args=args, daemon=True)  # noqa: E731
    else:
        stop, results = threading.Event(), queue.Queue()
        start = lambda target, args: threading.Thread(target=target, args=args, daemon=True)  # noqa: E731
    rec_target = telemetry_path if telemetry_path is not None else Path("/dev/null")
    parent = os.getpid() if use_fork else None
    parties = [
        start(_recorder_main, (rec_link, rec_target, stop, results, parent)),
        start(_onboard_main, (vehicle, ob_link, gnd_link, config, stop, results, parent)),
    ]
    for p in parties:
        p.start()
    if on_start is not None:
        on_start({"recorder": parties[0].pid, "onboard": parties[1].pid} if use_fork else {})
    if use_fork:  # the children own these now
        ob_link.close()
        gnd_link.close()
        rec_link.close()
    from hil.tlog import TlogWriter

    tlog = TlogWriter(tlog_path) if tlog_path is not None else None
    plant = Plant(vehicle, dt_s=0.001, seed=seed, depth_m=depth_m)
    frame_s = frame_period_s if frame_period_s is not None else 1.0 / config.control_rate_hz
    got: dict = {}
    ep = HilEndpoint(vehicle, ep_link, plant, control_period_s=frame_s, lockstep=True,
                     setpoints=setpoints, faults=faults, tlog=tlog, seed=seed, give_up_s=90.0,
                     history=history, on_period=on_period, signing_key=config.signing_key,
                     abort=lambda: _party_failure(dict(zip(("recorder", "onboard"), parties)), results, got))
    wall0 = time.perf_counter()
    finished = False
    try:
        if progress:
            progress("waiting for the onboard loop (its first start compiles the model, up to a minute)")
        try:
            ep.start(wait_s=start_timeout_s)
        except EndpointError:
            _drain(results, got, 0.5)
            if "onboard" in got and "error" in got["onboard"]:
                raise EndpointError(f"the onboard loop failed to start: {got['onboard']['error']}") from None
            raise
        wall0 = time.perf_counter()
        if progress:
            progress(f"flying {duration_s:.0f} s of mission in lock-step")
        n = int(round(duration_s / frame_s))
        supervise = dict(zip(("recorder", "onboard"), parties))
        next_check = time.monotonic() + PARTY_CHECK_S
        try:
            while ep.k < n and not (halt is not None and halt()):
                ep.step()
                if time.monotonic() >= next_check:  # a party that needs nothing from the plant (the
                    next_check = time.monotonic() + PARTY_CHECK_S  # recorder) may die unseen otherwise
                    why = _party_failure(supervise, results, got)
                    if why:
                        raise EndpointError(why)
                if progress and ep.k % int(round(5 / frame_s)) == 0:
                    progress(f"  t = {ep.time_s:5.1f} s")
        except EndpointError as exc:
            stop.set()
            _drain(results, got, 10.0, want=("onboard",))
            why = got.get("onboard", {}).get("error")
            raise EndpointError(f"{exc}" + (f"; the onboard loop failed: {why}" if why else "")) from None
        finished = True
    finally:
        wall = time.perf_counter() - wall0
        stop.set()
        if tlog is not None:
            tlog.close()
        # a finished flight waits for the parties' reports; an interrupted one does not linger
        _drain(results, got, 20.0 if finished else 1.0, want=("onboard", "recorder"))
        for p in parties:
            p.join(5.0 if finished else 1.0)
            if use_fork and p.is_alive():
                p.terminate()
        ep_link.close()
    st = ep.stats
    endpoint = {"periods": st.periods, "commands_applied": st.commands_applied, "resends": st.resends,
                "stale_replies": st.stale_replies, "bad_commands": st.bad_commands, "link": ep.link.stats()}
    onboard = got.get("onboard", {})
    extra = {}
    if not faults.empty:  # what was injected, and when the onboard side reported each fault
        extra["detections"] = detections(faults, onboard.get("fault_events", []))
    return ClosedLoopResult(ep.truth, ep.commands, endpoint, onboard, got.get("recorder", {}),
                            wall, tlog_path, telemetry_path, extra)


PARTY_CHECK_S = 0.5  # wall time between checks of the parties in flight


def _party_failure(parties: dict, results, got: dict) -> str | None:
    """Why the flight cannot go on, or None: a party reported an error, or died (a process's exit
    code, a thread that ended) before it was told to stop. Checked while the plant waits."""
    def error():
        while True:
            try:
                who, what = results.get_nowait()
            except queue.Empty:
                break
            got[who] = what
        for name, report in got.items():
            if isinstance(report, dict) and "error" in report:
                return f"the {name} failed: {report['error']}"
        return None

    if error():
        return error()
    for name, p in parties.items():
        if not p.is_alive():
            _drain(results, got, 1.0, want=(name,))  # its last report may still be on its way
            if error():
                return error()
            code = getattr(p, "exitcode", None)
            how = ("" if code is None else f" (killed by signal {-code})" if code < 0 else f" (exit code {code})")
            return f"the {name} {'process' if code is not None else 'thread'} ended before the flight did{how}"
    return None


def _drain(results, got: dict, timeout_s: float, want=()) -> None:
    deadline = time.monotonic() + timeout_s
    while True:
        left = deadline - time.monotonic()
        if want and all(w in got for w in want):
            return
        if left <= 0:
            return
        try:
            who, what = results.get(timeout=min(left, 0.5) if want else 0.05)
            got[who] = what
        except queue.Empty:
            if not want:
                return


# ------------------------------------------------------------------------------------------------
# Summary, plot, CLI


def summarise(result: ClosedLoopResult, mission: Mission, vehicle: Vehicle) -> dict:
    err = tracking_errors(result.truth, mission, vehicle.environment.surface_depth)
    ob = result.onboard
    return {
        **{k: err[k] for k in ("depth_rms_m", "yaw_rms_rad", "speed_rms_m_s")},
        "step_median_ms": ob.get("step_median_ms", float("nan")),
        "step_p99_ms": ob.get("step_p99_ms", float("nan")),
        "limit_violations": ob.get("limit_violations", -1),
        "step_cpu_median_ms": ob.get("step_cpu_median_ms", float("nan")),
        "step_cpu_p99_ms": ob.get("step_cpu_p99_ms", float("nan")),
        "depth_max_abs_m": err["depth_max_m"],
        "qp_solve_median_us": ob.get("solve_median_us", float("nan")),
        "qp_solve_p99_us": ob.get("solve_p99_us", float("nan")),
        "allocation_fallbacks": ob.get("allocation_fallbacks", -1),
        "allocation_weighted_error_mean": ob.get("weighted_error_mean", float("nan")),
        "failsafe_entries": ob.get("failsafe_entries", -1),
        "control_steps": ob.get("steps", 0),
        "lockstep_periods": result.endpoint["periods"],
        "tilt_max_rad": _tilt_max(result.truth, mission),
        "faults_seen": ob.get("faults_seen", 0),
        "detections": result.extra.get("detections", []),
        "mission_s": mission.duration_s,
        "wall_s": result.wall_s,
    }


def _tilt_max(truth, mission: Mission) -> float:
    """Largest |roll| or |pitch| after the first leg's settling time (rad)."""
    first = mission.legs[0]
    tilt = [max(abs(s.euler_rad[0]), abs(s.euler_rad[1])) for s in truth if s.time_s >= first.t0_s + first.settle_s]
    return float(max(tilt)) if tilt else float("nan")


def summary_json(summary: dict) -> str:
    """summary.json text: strict JSON, a figure that could not be measured (NaN, inf: a mission
    with no settled leg, an onboard loop that reported nothing) is null, not the invalid NaN."""
    def clean(v):
        if isinstance(v, float) and not math.isfinite(v):
            return None
        if isinstance(v, dict):
            return {k: clean(x) for k, x in v.items()}
        if isinstance(v, (list, tuple)):
            return [clean(x) for x in v]
        return v

    return json.dumps(clean(summary), indent=2, allow_nan=False) + "\n"


class _Figure(float):
    """A figure for the console table: formats as usual, or as 'n/a' when not measured (NaN)."""

    def __format__(self, spec: str) -> str:
        return super().__format__(spec) if math.isfinite(self) else "n/a"

    def __mul__(self, k):
        return _Figure(float(self) * k)


def table(summary: dict) -> str:
    summary = {k: _Figure(v) if isinstance(v, float) else v for k, v in summary.items()}
    rows = [
        ("tracking", "depth RMS", f"{summary['depth_rms_m'] * 100:.1f} cm"),
        ("", "depth max |error|", f"{summary['depth_max_abs_m'] * 100:.1f} cm"),
        ("", "yaw RMS", f"{summary['yaw_rms_rad'] * (180 / math.pi):.2f} deg"),
        ("", "surge speed RMS", f"{summary['speed_rms_m_s'] * 100:.1f} cm/s"),
        ("", "max |roll|, |pitch|", f"{summary['tilt_max_rad'] * (180 / math.pi):.1f} deg"),
        ("allocation", "QP solve median / p99", f"{summary['qp_solve_median_us']:.0f} / {summary['qp_solve_p99_us']:.0f} us"),
        ("", "fallbacks", f"{summary['allocation_fallbacks']}"),
        ("", "mean weighted wrench error", f"{summary['allocation_weighted_error_mean']:.3f}"),
        ("", "limit violations", f"{summary['limit_violations']}"),
        ("loop", "onboard step median / p99", f"{summary['step_median_ms']:.2f} / {summary['step_p99_ms']:.2f} ms"),
        ("", "  the same in CPU time", f"{summary['step_cpu_median_ms']:.2f} / {summary['step_cpu_p99_ms']:.2f} ms"),
        ("", "control steps", f"{summary['control_steps']}"),
        ("", "failsafe entries", f"{summary['failsafe_entries']}"),
        ("run", "mission / wall time", f"{summary['mission_s']:.0f} s / {summary['wall_s']:.1f} s"),
    ]
    w0 = max(len(r[0]) for r in rows)
    w1 = max(len(r[1]) for r in rows)
    return "\n".join(f"  {a:<{w0}}  {b:<{w1}}  {c}" for a, b, c in rows)


def detection_table(rows) -> str:
    """Injected faults and when the onboard fault monitor reported each (hil.faults.detections)."""
    lines = [f"  {'injected':<34}  {'at':>6}  {'onboard flag':<14}  detected after"]
    for r in rows:
        seen = "NOT DETECTED" if r["detected_s"] is None else f"{r['latency_s']:.2f} s"
        lines.append(f"  {r['injected']:<34}  {r['t0_s']:>5.1f}s  {r['flag']:<14}  {seen}")
    return "\n".join(lines)


def plot(result: ClosedLoopResult, mission: Mission, vehicle: Vehicle, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t = np.array([s.time_s for s in result.truth])
    depth = np.array([s.pos_ned_m[2] for s in result.truth]) - vehicle.environment.surface_depth
    yaw = np.degrees([s.euler_rad[2] for s in result.truth])
    u = np.array([s.nu[0] for s in result.truth])
    dem = [mission.demand_at(x) for x in t]
    sp = lambda k, f=lambda v: v: np.array([f(d[k]) if d[k] is not None else np.nan for d in dem])  # noqa: E731
    k = vehicle.n_units
    ct = np.array([c[0] for c in result.commands])
    cmd = np.array([c[1] for c in result.commands]) if result.commands else np.zeros((0, 3 * k))
    fig, ax = plt.subplots(5, 1, figsize=(9, 11), sharex=True)
    ax[0].plot(t, depth, label="depth (true)")
    ax[0].plot(t, sp("depth_m"), "--", label="setpoint")
    ax[0].invert_yaxis()
    ax[0].set_ylabel("depth (m)")
    ax[1].plot(t, yaw, label="yaw (true)")
    ax[1].plot(t, sp("yaw_rad", math.degrees), "--", label="setpoint")
    ax[1].set_ylabel("yaw (deg)")
    ax[2].plot(t, u, label="surge u (true)")
    ax[2].plot(t, sp("surge_m_s"), "--", label="setpoint")
    ax[2].set_ylabel("u (m/s)")
    if len(ct):
        ax[3].plot(ct, cmd[:, :k])
        ax[4].plot(ct, np.degrees(cmd[:, k:2 * k]), "-")
        ax[4].plot(ct, np.degrees(cmd[:, 2 * k:]), ":")
    ax[3].set_ylabel("jet n_cmd (rev/s)")
    ax[4].set_ylabel("joints (deg)\naz -, el :")
    ax[4].set_xlabel("vehicle time (s)")
    for a in ax[:3]:
        a.legend(loc="best", fontsize=8)
    for a in ax:
        a.grid(alpha=0.3)
        for leg in mission.legs:
            a.axvline(leg.t0_s, color="grey", lw=0.5)
    ax[0].set_title(f"jetloop demo: {vehicle.name}, lock-step HIL over loopback UDP")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def configure(parser) -> None:
    parser.add_argument("--out", default="jetloop-demo", metavar="DIR",
                        help="directory for mission.tlog, telemetry.tlog, mission.png, summary.json (default ./jetloop-demo/)")
    parser.add_argument("--vehicle", default=None, help="vehicle TOML (default: the reference vehicle asr4)")
    parser.add_argument("--seed", type=int, default=0, help="noise seed of the plant (default 0)")
    parser.add_argument("--allocator", choices=("qp", "baseline"), default="qp",
                        help="qp: OSQP allocation (default); baseline: pseudo-inverse with clipping")
    parser.add_argument("--compensation", choices=("on", "off"), default="on" if DEMO_CONFIG.compensation else "off",
                        help="seed-004 azimuth-transient compensation (default: %(default)s)")
    parser.add_argument("--no-compensation", dest="compensation", action="store_const", const="off",
                        help="the same as --compensation off")
    parser.add_argument("--no-yaw-preview", dest="yaw_preview", action="store_false",
                        help="compensate without cancelling the azimuths' yaw reaction ahead (onboard.compensation.YawPreview)")
    parser.add_argument("--threads", action="store_true", help="run the parties as threads instead of processes")
    parser.add_argument("--mission", choices=("demo", "hold", "turn"), default="demo",
                        help="demo: the reference mission (default); hold: dive to 0.5 m and hold; turn: the same "
                             "and a 45 deg turn at 8 s (fault scenarios)")
    parser.add_argument("--duration", type=float, default=None, metavar="S",
                        help="mission length with --mission hold or turn (default 20 s)")
    from hil.faults import add_fault_arguments

    add_fault_arguments(parser)


def run(args) -> int:
    from onboard.vehicle import VehicleFileError, require_jets

    try:
        vehicle = load_vehicle(args.vehicle)
        require_jets(vehicle, "demo")
    except VehicleFileError as exc:
        print(f"jetloop demo: {exc}", file=sys.stderr)
        return 2
    from ground.cli import make_output_dir

    out = make_output_dir(args.out, "jetloop demo")
    if out is None:
        return 2
    from hil.faults import FaultPlanError, injection_events, plan_from_args

    try:
        faults = plan_from_args(args, vehicle.n_units)
    except FaultPlanError as exc:
        print(f"jetloop demo: {exc}", file=sys.stderr)
        return 2
    if args.duration is not None and not (args.mission != "demo" and 2.0 <= args.duration <= 3600.0):
        print(f"jetloop demo: --duration {args.duration}: expected 2..3600 s, with --mission hold or turn",
              file=sys.stderr)
        return 2
    mission = (reference_mission() if args.mission == "demo" else
               hold_mission(args.duration or 20.0, turn_at_s=8.0 if args.mission == "turn" else None))
    config = replace(DEMO_CONFIG, allocator=args.allocator, compensation=args.compensation == "on",
                     yaw_preview=args.yaw_preview)
    say = lambda s: print(s, flush=True)  # noqa: E731
    comp = "off" if not config.compensation else "on" if config.yaw_preview else "on, yaw preview off"
    say(f"jetloop demo: plant + onboard + recorder over 127.0.0.1, lock-step, vehicle {vehicle.name}, seed {args.seed}, "
        f"allocation {config.allocator}, compensation {comp}")
    if not faults.empty:
        say("faults: " + "; ".join(f"{t:g} s {text[len('INJECT '):]}" for t, text in injection_events(faults)))
    try:
        result = run_closed_loop(vehicle, mission.setpoints(), mission.duration_s, seed=args.seed, config=config,
                                 out_dir=out, processes=not args.threads, progress=say, faults=faults)
    except EndpointError as exc:
        print(f"jetloop demo: {exc}", file=sys.stderr)
        return 1
    if "error" in result.onboard:
        print(f"jetloop demo: the onboard loop failed: {result.onboard['error']}", file=sys.stderr)
        return 1
    summary = summarise(result, mission, vehicle)
    plot(result, mission, vehicle, out / "mission.png")
    (out / "summary.json").write_text(summary_json(summary))
    say("")
    say(table(summary))
    if summary["detections"]:
        say("")
        say(detection_table(summary["detections"]))
    say("")
    say(f"wrote {out / 'mission.tlog'} (plant side: sensors, commands, truth), {out / 'telemetry.tlog'} (ground),")
    say(f"      {out / 'mission.png'}, {out / 'summary.json'}")
    return 0
