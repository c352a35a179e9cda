"""Does this machine's thread CPU clock count time the hypervisor stole? Constant work, timed.

Run `python bench/bench_cpu_clock.py [--duration S] [--work-ms W]` (default 120 s). One thread,
pinned to one vCPU, repeats the same pure-Python work (about 1 ms, the size of an onboard control
step) with a short sleep between, and times each repetition in thread CPU time
(`time.thread_time`, what onboard.loop counts deadlines in). Around each repetition it reads the
vCPU's stolen time (/proc/stat: the time the hypervisor ran something else while this vCPU had
work). The work never changes, so on a machine whose CPU clock counts only this thread's own
work every repetition costs the same; a repetition far over the median that coincides with
stolen time says the CPU clock counted the hypervisor's stall too.

It prints the median, p99.9 and maximum of the repetition's CPU time, the repetitions over 5x
the median, and of those how many had time stolen from their vCPU around them (the same window
`hil.soak.stolen_around` gives a control step) and how many had enough stolen to make up their
excess over the median (`hil.soak.stolen_explains`, the soak's test), beside the fraction of all repetitions with
steal around them (the baseline: what chance alone would give). Not a timed test; CI does not
run it. Load the machine to see more (e.g. the test suite in another shell).
"""

from __future__ import annotations

import argparse
import os
import statistics
import time

from hil.soak import StealClock, stolen_around, stolen_explains


def work(n: int) -> float:
    s = 0.0
    for i in range(n):
        s += i * 0.5
    return s


def calibrate(work_ms: float) -> int:
    n = 1000
    while True:
        c0 = time.thread_time()
        work(n)
        c = time.thread_time() - c0
        if c > 0.02:
            return max(1, int(n * work_ms / 1e3 / c))
        n *= 2


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--duration", type=float, default=120.0, help="seconds to run (default 120)")
    ap.add_argument("--work-ms", type=float, default=1.0, help="CPU time of one repetition on a quiet machine")
    ap.add_argument("--cpu", type=int, default=0, help="the vCPU to pin to (default 0)")
    args = ap.parse_args(argv)
    os.sched_setaffinity(0, {args.cpu})
    n = calibrate(args.work_ms)
    steal = StealClock()
    cpu_ms, stolen = [], []
    s_prev = steal.read()[args.cpu]
    t_end = time.monotonic() + args.duration
    while time.monotonic() < t_end:
        c0 = time.thread_time()
        work(n)
        cpu_ms.append((time.thread_time() - c0) * 1e3)
        time.sleep(0.002)  # the steal of a stall is booked at the vCPU's next tick (4 ms at 250 Hz)
        s = steal.read()[args.cpu]
        stolen.append(s - s_prev)
        s_prev = s
    steal.close()
    k = len(cpu_ms)
    med = statistics.median(cpu_ms)
    over = [i for i, c in enumerate(cpu_ms) if c > 5 * med]
    near = stolen_around(range(k), 1.0, stolen)  # repetition i as "period" i: the soak's window
    around = near.__getitem__
    with_steal = sum(1 for i in range(k) if around(i) > 0)
    over_steal = sum(1 for i in over if around(i) > 0)
    tick_ms = 1000.0 / os.sysconf("SC_CLK_TCK")
    made_up = sum(1 for i in over if stolen_explains(cpu_ms[i] - med, around(i), tick_ms))
    q = sorted(cpu_ms)
    print(f"vCPU {args.cpu}, {k} repetitions of the same work over {args.duration:.0f} s, "
          f"load average {os.getloadavg()[0]:.2f}")
    print(f"CPU time per repetition: median {med:.3f} ms, p99.9 {q[min(k - 1, int(0.999 * k))]:.3f} ms, "
          f"max {q[-1]:.3f} ms ({q[-1] / med:.0f}x the median)")
    print(f"repetitions over 5x the median: {len(over)}")
    if over:
        print(f"  with time stolen from the vCPU around them: {over_steal} of {len(over)} "
              f"({100 * over_steal / len(over):.0f} %); the excess made up by it "
              f"(hil.soak.stolen_explains): {made_up} of {len(over)}")
    print(f"baseline, all repetitions with time stolen around them: {with_steal} of {k} ({100 * with_steal / k:.1f} %)")
    if over and with_steal:
        print(f"ratio: {over_steal / len(over) / (with_steal / k):.1f}x more often than chance")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
