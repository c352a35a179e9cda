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

1. Onboard step: wall time of estimate + failsafe + control + compensate + allocate per tick
   (`LoopStats.step_time_s`; the encoding and sending of messages are not in it), median / p99 /
   max over the reference mission, for each allocator configuration. Targets: median <= 1 ms,
   p99 <= 3 ms (400 Hz with headroom).
2. Tracking: the reference mission (dive 0.5 m, hold, yaw 90 deg, forward 0.3 m/s for 5 s, stop,
   surface), same seed, RMS depth / yaw / surge-speed errors of the true state after each leg's
   settling time (hil.demo.tracking_errors), side by side for: QP + compensation and QP alone (each
   with the filterpy EKF and with the same EKF compiled in numba), and the baseline (pseudo-inverse
   at the current joint angles, clipped: ArduSub-style fixed mixing).
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import sys
import time
from pathlib import Path


sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from hil.demo import reference_mission, tracking_errors  # noqa: E402
from hil.plant import Plant  # noqa: E402
from onboard import mavlink_codec as codec  # noqa: E402
from onboard.link import Link  # noqa: E402
from onboard.loop import LoopConfig, OnboardLoop, VehicleClock  # noqa: E402
from onboard.vehicle import load_vehicle  # noqa: E402


def fly(vehicle, mission, config: LoopConfig, seed: int):
    """The mission in lock-step, in-process: returns (truth samples, loop)."""
    link = Link("udpin:127.0.0.1:0")  # never spoken to: what the loop sends is counted and dropped
    clock = VehicleClock()
    loop = OnboardLoop(vehicle, link, clock, config)
    plant = Plant(vehicle, dt_s=0.001, seed=seed, depth_m=0.0)
    period = 1.0 / config.control_rate_hz
    setpoints = sorted(mission.setpoints(), key=lambda p: p[0])
    nxt = 0
    truth = []
    n = int(round(mission.duration_s / period))
    for k in range(n):
        t = k * period
        s = plant.advance(t + 1e-9)
        truth.extend(s.truth)
        while nxt < len(setpoints) and setpoints[nxt][0] <= t + 1e-9:
            loop.handle(setpoints[nxt][1])
            nxt += 1
        for p in s.pressure:
            loop.handle(codec.encode_pressure(p))
        for a in s.attitude:
            loop.handle(codec.encode_attitude(a))
        for i in s.imu:
            loop.handle(codec.encode_imu(i))
        clock.observe(t)
        loop.step(t)
        plant.set_command(loop.command)
    link.close()
    return truth, loop


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--rate", type=float, default=100.0, help="control rate in Hz (default 100, the IMU rate)")
    ap.add_argument("--repeat", type=int, default=2,
                    help="fly each configuration this many times and keep the run with the lowest median "
                         "step time (the flights are identical; the machine is shared) (default 2)")
    args = ap.parse_args(argv)
    v = load_vehicle()
    mission = reference_mission()
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
    fly(v, type(mission)(mission.legs[:1], 1.0), configs[0][1], args.seed)  # compile / warm up
    rows = []
    for name, cfg in configs:
        best = None
        for _ in range(max(args.repeat, 1)):
            t0 = time.perf_counter()
            c0 = time.process_time()
            truth, loop = fly(v, mission, cfg, args.seed)
            wall, cpu = time.perf_counter() - t0, time.process_time() - c0
            e = tracking_errors(truth, mission, v.environment.surface_depth)
            s = loop.stats.summary()
            if best is None or s["step_median_ms"] < best[2]["step_median_ms"]:
                best = (name, e, s, wall, cpu)
        rows.append(best)
    print("| allocation | depth RMS | yaw RMS | surge RMS | step median (wall / CPU) | step p99 (wall / CPU) "
          "| step max | QP median | fallbacks | limit violations | run wall / CPU |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for name, e, s, wall, cpu in rows:
        print(f"| {name} | {e['depth_rms_m'] * 100:.1f} cm | {math.degrees(e['yaw_rms_rad']):.2f} deg | "
              f"{e['speed_rms_m_s'] * 100:.1f} cm/s | {s['step_median_ms']:.3f} / {s['step_cpu_median_ms']:.3f} ms | "
              f"{s['step_p99_ms']:.3f} / {s['step_cpu_p99_ms']:.3f} ms | "
              f"{s['step_max_ms']:.2f} ms | {s['solve_median_us']:.0f} us | {s['allocation_fallbacks']} | "
              f"{s['limit_violations']} | {wall:.1f} s / {cpu:.1f} s |")
    base = rows[-1][1]
    best = rows[0][1]
    print()
    for k, label in (("depth_rms_m", "depth"), ("yaw_rms_rad", "yaw"), ("speed_rms_m_s", "surge speed")):
        r = best[k] / base[k] if base[k] > 0 else float("nan")
        print(f"QP + compensation / baseline, RMS {label}: {r:.2f}")
    print()
    for name, _, s, _, _ in rows[:-1]:
        med, p99 = s["step_median_ms"], s["step_p99_ms"]
        print(f"step targets, {name} (wall clock): median {med:.3f} ms <= 1 ms: {'met' if med <= 1 else 'NOT met'}; "
              f"p99 {p99:.3f} ms <= 3 ms: {'met' if p99 <= 3 else 'NOT met'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
