"""A fresh onboard process meets its first control deadlines: OnboardLoop warms its compiled
kernels up when built (numba loads cached code at the first call; unwarmed, the first two ticks
of a fresh process cost about 70 and 50 ms of CPU, measured)."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

from hil.soak import stolen_explains

REPO = Path(__file__).resolve().parents[1]

SCRIPT = r"""
import json
import os
import time
from hil.soak import StealClock
from onboard import mavlink_codec as codec
from onboard.link import Link
from onboard.loop import OnboardLoop, VehicleClock, arm_command, depth_yaw_target
from onboard.sensors import ImuSample, PressureSample
from onboard.vehicle import load_vehicle

os.sched_setaffinity(0, {0})  # one vCPU, whose stolen time is read around each tick
steal = StealClock()
stolen = []
v = load_vehicle(None)
e = v.environment
with Link("udpin:127.0.0.1:0") as link:
    loop = OnboardLoop(v, link, VehicleClock())
    for i in range(8):
        t = 0.01 * i
        loop.handle(codec.encode_imu(ImuSample(t, (0.0, 0.0, -9.81), (0.0, 0.0, 0.0))))
        loop.handle(codec.encode_pressure(PressureSample(t, e.p_atm + e.rho * e.g * 0.2, 20.0)))
        if i == 2:
            loop.handle(arm_command(True))
            loop.handle(depth_yaw_target(0.4, 0.3))
        s0 = steal.read()[0]
        loop.step(t)
        time.sleep(0.005)  # a stall's steal is booked at the vCPU's next tick (4 ms at 250 Hz)
        stolen.append(steal.read()[0] - s0)
    cpu_ms = [float(x) * 1e3 for x in loop.stats.step_cpu_s]
print(json.dumps({"cpu_ms": cpu_ms, "stolen_ticks": stolen, "armed": loop.armed, "errors": loop.stats.step_errors}))
"""


def test_the_first_ticks_of_a_fresh_onboard_process_fit_the_control_period():
    out = subprocess.run([sys.executable, "-c", SCRIPT], cwd=REPO, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-2000:]
    r = json.loads(out.stdout.strip().splitlines()[-1])
    assert r["armed"] and r["errors"] == 0, r  # the armed path (control, allocation) was taken
    assert len(r["cpu_ms"]) == 8
    # 100 Hz: every tick, the first ones included, within 10 ms of CPU, unless time stolen from
    # the vCPU around it makes the excess up (on a VM the thread's CPU clock counts the stall:
    # bench/bench_cpu_clock.py; the rule is the soak's). A compile or a cache load is 50-70 ms with no steal.
    median = sorted(r["cpu_ms"])[4]
    late = [(c, k) for c, k in zip(r["cpu_ms"], r["stolen_ticks"]) if c >= 10.0 and not stolen_explains(c - median, k)]
    assert not late, r
