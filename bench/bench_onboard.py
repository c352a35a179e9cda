"""Onboard loop benchmark: the control step's time, and closed-loop tracking QP(+compensation) vs baseline.

Run `python bench/bench_onboard.py` (options: --help; a few minutes on 2 shared cores). Not a
timed test: it prints figures, the baseline's beside the QP's, measured in the same run.

The closed loop here is the onboard loop (`onboard.loop.OnboardLoop`: estimator, controller,
compensation, allocation, failsafe) flying the plant (`hil.plant.Plant`, every effect of the
vehicle file on, seeded sensor noise) in lock-step, driven in one process: the plant's samples
go through the MAVLink codec as message objects into `OnboardLoop.handle`, and each control tick
`OnboardLoop.step` returns the command the plant applies. That is the demo's loop without its
sockets (their cost belongs to the link, not to the robot's step); `jetloop demo` runs the same
mission over UDP.

The configurations fly INTERLEAVED: one control period of each in turn, in one process, so all
of them meet the same machine load and cache state (on 2 shared cores, flights run one after
the other differ by 50% from load alone, more than the differences being measured).

1. Onboard step: wall time of estimate + failsafe + control + compensate + allocate per tick
   (`LoopStats.step_time_s`; the encoding and sending of messages are not in it) and the same
   step's CPU time (thread time: what the step costs, whatever else the machine runs), median /
   p99 / max over the reference mission, for each configuration. Targets: median <= 1 ms,
   p99 <= 3 ms (400 Hz with headroom).
2. Tracking: the reference mission (dive 0.5 m, hold, yaw 90 deg, forward 0.3 m/s for 5 s, stop,
   surface), same seed, RMS depth / yaw / surge-speed errors of the true state after each leg's
   settling time (hil.demo.tracking_errors), side by side for: QP + compensation and QP alone (each
   with the filterpy EKF and with the same EKF compiled in numba), and the baseline (pseudo-inverse
   at the current joint angles, clipped: ArduSub-style fixed mixing).

Before / after a change, in one process: `--against DIR` also flies the four QP configurations of
another checkout's `onboard` package (DIR: a checkout, e.g. `git worktree add /tmp/before HEAD~3`
or `git archive REV | tar -x -C /tmp/before`), interleaved with this one's, rows marked
"(DIR)". Runs one after the other differ by more than the changes being measured on this
shared machine; interleaved, both meet the same load. (Nine flights interleaved press the caches
harder than five: compare the rows of one run, not with another run's.)
"""

from __future__ import annotations

import argparse
import importlib
import math
import os
import platform
import shutil
import sys
import tempfile
import time
from pathlib import Path


sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hil.demo import reference_mission, tracking_errors  # noqa: E402
from hil.plant import Plant  # noqa: E402
from onboard import mavlink_codec as codec  # noqa: E402
from onboard.link import Link  # noqa: E402
from onboard.loop import LoopConfig, OnboardLoop, VehicleClock  # noqa: E402
from onboard.vehicle import load_vehicle  # noqa: E402


class Flight:
    """One configuration flying the mission in lock-step, one control period per `tick()`.

    `loop_class`: the OnboardLoop to fly (default this checkout's; `--against` passes another's)."""

    def __init__(self, vehicle, mission, config: LoopConfig, seed: int, estimator=None, loop_class=None):
        self.link = Link("udpin:127.0.0.1:0")  # never spoken to: what the loop sends is counted and dropped
        self.clock = VehicleClock()
        self.loop = (loop_class or OnboardLoop)(vehicle, self.link, self.clock, config, estimator=estimator)
        self.plant = Plant(vehicle, dt_s=0.001, seed=seed, depth_m=0.0)
        self.period = 1.0 / config.control_rate_hz
        self.setpoints = sorted(mission.setpoints(), key=lambda p: p[0])
        self.next_setpoint = 0
        self.truth = []
        self.k = 0
        self.n = int(round(mission.duration_s / self.period))

    def tick(self) -> bool:
        """One control period: plant samples in, `OnboardLoop.step`, command out. False when done."""
        if self.k >= self.n:
            return False
        t = self.k * self.period
        self.k += 1
        loop = self.loop
        s = self.plant.advance(t + 1e-9)
        self.truth.extend(s.truth)
        while self.next_setpoint < len(self.setpoints) and self.setpoints[self.next_setpoint][0] <= t + 1e-9:
            loop.handle(self.setpoints[self.next_setpoint][1])
            self.next_setpoint += 1
        for p in s.pressure:
            loop.handle(codec.encode_pressure(p))
        for a in s.attitude:
            loop.handle(codec.encode_attitude(a))
        for i in s.imu:
            loop.handle(codec.encode_imu(i))
        self.clock.observe(t)
        loop.step(t)
        self.plant.set_command(loop.command)
        return True

    def finish(self):
        self.link.close()
        return self.truth, self.loop


def fly(vehicle, mission, config: LoopConfig, seed: int, loop_class=None):
    """The mission in lock-step, in-process: returns (truth samples, loop)."""
    flight = Flight(vehicle, mission, config, seed, loop_class=loop_class)
    while flight.tick():
        pass
    return flight.finish()


def fly_interleaved(flights) -> list:
    """Fly several flights at once, one control period of each in turn (the order rotating every
    period), so that every configuration meets the same machine load and the same cache state:
    on a shared machine this is what makes their step times comparable. Returns [(truth, loop)]."""
    k = 0
    busy = list(flights)
    while busy:
        r = k % len(busy)
        busy = [f for f in busy[r:] + busy[:r] if f.tick()]
        k += 1
    return [f.finish() for f in flights]


def other_onboard(checkout: str):
    """(OnboardLoop, LoopConfig) of another checkout's `onboard` package, imported beside this one
    under another name (a copy in a temporary directory: its modules import each other relatively)."""
    src = Path(checkout).expanduser().resolve() / "onboard"
    if not (src / "loop.py").is_file():
        raise SystemExit(f"--against: expected a checkout with onboard/loop.py, got {checkout!r} ({src} has none)")
    tmp = Path(tempfile.mkdtemp(prefix="bench_against_"))
    shutil.copytree(src, tmp / "onboard_against", ignore=shutil.ignore_patterns("__pycache__"))
    sys.path.insert(0, str(tmp))
    loop = importlib.import_module("onboard_against.loop")
    return loop.OnboardLoop, loop.LoopConfig


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--rate", type=float, default=100.0, help="control rate in Hz (default 100, the IMU rate)")
    ap.add_argument("--repeat", type=int, default=2,
                    help="fly all configurations (interleaved) this many times and keep, per configuration, "
                         "the run with the lowest median step time (the flights are identical; the machine "
                         "is shared) (default 2)")
    ap.add_argument("--duration", type=float, default=None,
                    help="fly only the first DURATION s of the mission (default: all of it)")
    ap.add_argument("--against", metavar="DIR", default=None,
                    help="also fly the QP configurations of the onboard package of the checkout DIR, interleaved "
                         "with this one's (a before/after comparison in one process)")
    args = ap.parse_args(argv)
    v = load_vehicle()
    mission = reference_mission()
    if args.duration is not None:
        if not (math.isfinite(args.duration) and 0 < args.duration <= mission.duration_s):
            ap.error(f"--duration: expected seconds in (0, {mission.duration_s:g}], got {args.duration!r}")
        mission = type(mission)(tuple(g for g in mission.legs if g.t0_s < args.duration), args.duration)
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"load average {os.getloadavg()[0]:.2f} {os.getloadavg()[1]:.2f} (shared: wall times rise with load)")
    print(f"vehicle {v.name}, every effect on, seed {args.seed}, control {args.rate:g} Hz, "
          f"mission {mission.duration_s:.0f} s ({int(mission.duration_s * args.rate)} steps)\n")
    configs = [
        ("QP + compensation", LoopConfig(control_rate_hz=args.rate, allocator="qp", compensation=True)),
        ("QP + compensation, compiled EKF", LoopConfig(control_rate_hz=args.rate, allocator="qp", compensation=True,
                                                       estimator_backend="compiled")),
        ("QP alone", LoopConfig(control_rate_hz=args.rate, allocator="qp", compensation=False)),
        ("QP alone, compiled EKF", LoopConfig(control_rate_hz=args.rate, allocator="qp", compensation=False,
                                              estimator_backend="compiled")),
        ("baseline (pinv, clipped)", LoopConfig(control_rate_hz=args.rate, allocator="baseline", compensation=False)),
    ]
    classes = {name: None for name, _ in configs}
    if args.against is not None:
        other_loop, other_config = other_onboard(args.against)
        tag = f" ({args.against})"
        others = [(name + tag, other_config(**{f: getattr(cfg, f) for f in ("control_rate_hz", "allocator",
                                                                           "compensation", "estimator_backend")}))
                  for name, cfg in configs[:-1]]
        classes.update({name: other_loop for name, _ in others})
        configs = configs[:-1] + others + configs[-1:]  # the baseline stays last (the ratios below)
    for name, cfg in configs:  # compile / warm up
        fly(v, type(mission)(mission.legs[:1], 1.0), cfg, args.seed, loop_class=classes[name])
    best = {}
    for rep in range(max(args.repeat, 1)):
        t0 = time.perf_counter()
        flown = fly_interleaved([Flight(v, mission, cfg, args.seed, loop_class=classes[name]) for name, cfg in configs])
        print(f"run {rep + 1}: {len(configs)} configurations interleaved, {time.perf_counter() - t0:.0f} s wall")
        for (name, _), (truth, loop) in zip(configs, flown):
            s = loop.stats.summary()
            if name not in best or s["step_median_ms"] < best[name][2]["step_median_ms"]:
                best[name] = (name, tracking_errors(truth, mission, v.environment.surface_depth), s)
    rows = [best[name] for name, _ in configs]
    print()
    print("| allocation | depth RMS | yaw RMS | surge RMS | step median (wall / CPU) | step p99 (wall / CPU) "
          "| step max | QP median | fallbacks | limit violations |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    for name, e, s in rows:
        print(f"| {name} | {e['depth_rms_m'] * 100:.1f} cm | {math.degrees(e['yaw_rms_rad']):.2f} deg | "
              f"{e['speed_rms_m_s'] * 100:.1f} cm/s | {s['step_median_ms']:.3f} / {s['step_cpu_median_ms']:.3f} ms | "
              f"{s['step_p99_ms']:.3f} / {s['step_cpu_p99_ms']:.3f} ms | "
              f"{s['step_max_ms']:.2f} ms | {s['solve_median_us']:.0f} us | {s['allocation_fallbacks']} | "
              f"{s['limit_violations']} |")
    base = rows[-1][1]
    best = rows[0][1]
    print()
    for k, label in (("depth_rms_m", "depth"), ("yaw_rms_rad", "yaw"), ("speed_rms_m_s", "surge speed")):
        r = best[k] / base[k] if base[k] > 0 else float("nan")
        print(f"QP + compensation / baseline, RMS {label}: {r:.2f}")
    print()
    for name, _, s in rows[:-1]:
        med, p99 = s["step_median_ms"], s["step_p99_ms"]
        print(f"step targets, {name} (wall clock): median {med:.3f} ms <= 1 ms: {'met' if med <= 1 else 'NOT met'}; "
              f"p99 {p99:.3f} ms <= 3 ms: {'met' if p99 <= 3 else 'NOT met'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
