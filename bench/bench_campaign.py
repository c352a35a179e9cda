"""Campaign benchmark: tasks per second and per-task overhead of `jetloop campaign`, serial vs Dask.

Run `python3 bench/bench_campaign.py` (options: --help; about 5 minutes on 2 shared cores). Not a
timed test: it prints figures, and ratios against the baseline measured in the same run.

Two kinds of task, each run three ways on fresh output folders (nothing resumed):
- serial in this process (`--workers 0`): the baseline; the process has compiled and loaded
  everything before it starts (a warm-up task runs first), so it carries no start-up cost;
- a `LocalCluster` of 1 worker process, then of 2 (spawned processes, one thread each), started
  by the campaign as `jetloop campaign` starts it: cluster start, imports and numba's on-disk
  cache load are inside the wall time.
Tasks: a short mission (the 10 s hold of `jetloop demo --mission hold`, lock-step in one process,
seeds 0..N-1) and prove cases (the benchmark's 60 s cases of the dev split, diagnose's default
null draws).

Figures: wall time of the campaign, tasks per second, the mean time a task takes inside its
worker (`wall_s` of the row), and the per-task overhead: (workers x wall - sum of task times) /
tasks, i.e. what the engine costs per task beyond the work, start-up and an idle tail included.
Last, what a 64-core cluster would take for the 300-case evaluation benchmark, from the measured
cost of a prove case scaled by the family's flight durations.
"""

from __future__ import annotations

import argparse
import math
import os
import platform
import shutil
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from ground.campaign import parse_spec, run_campaign  # noqa: E402
from ground.campaign.tasks import execute  # noqa: E402
from ground.prove import DURATION_P, DURATIONS_S  # noqa: E402

# The family's flight durations and their probabilities: ground.prove's, which family_case draws from.
FAMILY_DURATIONS = tuple(zip(DURATIONS_S, DURATION_P))


def measure(spec_text: str, workers: int, root: Path, label: str) -> dict:
    campaign = parse_spec(spec_text, root / "spec.toml")
    out = Path(tempfile.mkdtemp(prefix=f"bench-{label}-", dir=root))
    landed = []
    t0 = time.perf_counter()
    outcome = run_campaign(campaign, out, workers=workers, quiet=True, report=False,
                           on_row=lambda r: landed.append(time.perf_counter() - t0))
    wall = time.perf_counter() - t0
    rows = outcome.rows
    bad = [r for r in rows if r["status"] != "ok"]
    if bad:
        raise SystemExit(f"{label}: {len(bad)} tasks failed, e.g. {bad[0]['error']}")
    work = sum(r["wall_s"] for r in rows)
    cpu = sum(r["cpu_s"] for r in rows)
    n = len(rows)
    lanes = max(workers, 1)
    return {"label": label, "workers": workers, "tasks": n, "wall_s": wall, "rate": n / wall,
            "task_mean_s": work / n, "task_cpu_s": cpu / n, "cores_used": cpu / wall,
            "overhead_s": (lanes * wall - work) / n,
            "first_s": landed[0] if landed else math.nan, "mode": outcome.mode}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--missions", type=int, default=8, help="mission tasks per configuration (default 8)")
    ap.add_argument("--mission-s", type=float, default=10.0, help="mission length, s (default 10)")
    ap.add_argument("--prove", type=int, default=4, help="prove cases per configuration, 0 to skip (default 4)")
    args = ap.parse_args(argv)
    la = os.getloadavg()
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, load average "
          f"{la[0]:.2f} {la[1]:.2f} {la[2]:.2f} (shared: wall times rise with load)\n")
    root = Path(tempfile.mkdtemp(prefix="bench_campaign_"))
    try:
        missions = (f'kind = "missions"\n[missions]\nmission = "hold"\nduration_s = {args.mission_s}\n'
                    f'allocators = ["qp"]\nseeds = {list(range(args.missions))}\n')
        from ground.prove import family_case

        sixty = [i for i in range(200) if family_case("dev", i)[1].duration_s == 60.0][:args.prove]
        prove = f'kind = "prove"\n[prove]\nsplit = "dev"\nindices = {sixty}\n'
        kinds = [("mission", missions)] + ([("prove case", prove)] if args.prove else [])
        # warm this process (imports, numba's cache) so the serial baseline carries no start-up
        for _, text in kinds:
            t = parse_spec(text, root / "w.toml").tasks[0]
            execute(t.kind, t.inputs)
        results = []
        for name, text in kinds:
            for workers in (0, 1, 2):
                label = f"{name}, " + ("serial in-process" if workers == 0 else f"local cluster, {workers} worker"
                                       + ("s" if workers > 1 else ""))
                r = measure(text, workers, root, label)
                results.append((name, r))
                print(f"  {label}: {r['tasks']} tasks in {r['wall_s']:.1f} s", flush=True)
        print()
        print("| tasks | run | wall | tasks/s | task inside its worker, wall / CPU (mean) | cores the tasks got "
              "| per-task overhead | first result after |")
        print("|---|---|---|---|---|---|---|---|")
        for name, r in results:
            print(f"| {r['tasks']} x {name} | {r['label'].split(', ', 1)[1]} | {r['wall_s']:.1f} s | {r['rate']:.3f} | "
                  f"{r['task_mean_s']:.2f} / {r['task_cpu_s']:.2f} s | {r['cores_used']:.2f} | {r['overhead_s']:.2f} s | "
                  f"{r['first_s']:.1f} s |")
        print()
        for name in dict(results):
            rs = [r for n, r in results if n == name]
            base, one, two = rs
            print(f"{name}: tasks/s, 2 workers / 1 worker = {two['rate'] / one['rate']:.2f}; "
                  f"2 workers / serial = {two['rate'] / base['rate']:.2f}; 1 worker / serial = {one['rate'] / base['rate']:.2f}")
        if args.prove:
            rs = [r for n, r in results if n == "prove case"]
            c60 = sum(r["task_cpu_s"] for r in rs) / len(rs)  # CPU per 60 s case, all three runs
            over = rs[2]["overhead_s"]
            mean_d = sum(d * p for d, p in FAMILY_DURATIONS)
            c_mean = c60 * mean_d / 60.0
            c_max = c60 * 600.0 / 60.0
            total = 300 * c_mean
            t64 = max(300 * c_mean / 64 + 300 / 64 * over, c_max)
            print()
            print(f"300-case benchmark, from the CPU a 60 s case costs ({c60:.1f} s, mean of the three runs; the "
                  f"cost grows with the flight's duration, the family's mean flight is {mean_d:.0f} s): {c_mean:.1f} "
                  f"CPU-s a case, {total / 3600:.2f} CPU-hours in all: {total / 3600:.2f} h on one idle core, "
                  f"{total / 2 / 3600:.2f} h on two; on 64 workers about {t64 / 60:.1f} min, bounded below by the "
                  f"longest case (a 600 s flight, ~{c_max / 60:.1f} min) and adding {over:.1f} s of overhead per task "
                  f"(the 2-worker figure here)")
    finally:
        shutil.rmtree(root, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
