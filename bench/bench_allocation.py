"""Allocation benchmark: QP (OSQP) against ArduSub-style fixed mixing, quality and time, same run.

Run `python bench/bench_allocation.py` (options: --help; 400,000 allocations, 10-20 minutes on
2 shared cores; `--cases 1000` for a quick look). Not a timed test: it prints figures, the
baseline's beside the QP's, measured in the same run on the same situations.

Quality, `--cases` random demands (default 10,000) on the reference vehicle at 100 Hz. Each case
starts from random joint angles within the limits with a random velocity through the water, and
its demand is held for `--hold` control steps (default 20 = 0.2 s, time for a joint to travel
1 rad). Two thirds of the demands are wrenches the jets can give from there within the hold: a
random thrust up to T_max(J) on every unit at random angles within the travel the hold allows.
One third lie beyond what the jets can give: a random such direction scaled to 1.5-2.5x the most
the QP's polytope reaches along it over the hold's travel (an LP; the polytope is an inner
approximation, hence the margin). The QP plans every step from its previous command (committed,
warm-started); the baseline is fixed mixing, a pseudo-inverse of the effectiveness at the
joints' current angles, which it never moves. Reported at the end of the hold and over the
whole hold: the mean weighted wrench error sqrt(r' W r) (W: the axis weights; roll, pitch and
heave count 10x surge, sway, yaw) of each allocator and their ratio, the mean cost (the QP's
objective without its change term: weighted error^2 + effort) and its ratio, the effort (total
thrust), limit violations of every command (n in [0, n_max], thrust in [0, T_max(J)], angles
within +-angle_limit, travel within rate_limit * dt per step) and QP fallbacks. The first step of
each hold is also reported: one step alone is the static allocation problem, where both are
bound by the joints' travel in one step.

Time: allocate() wall time and OSQP's own run time per call, over the holds (warm start) and on
the first step of each case (warm start from an unrelated problem), beside the pseudo-inverse's
time; and the compensated allocation (transient prediction and 3 QP solves per step) over a
smooth demand sequence. Medians and 99th percentiles; the machine is shared, so its load average
is printed with the figures, and QP fallbacks are counted by reason: over the wall-clock budget
(`--time-budget`, default the allocator's 1 ms), OSQP's own time limit, or its iteration limit.
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np
from scipy.optimize import linprog

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from onboard.allocation import AllocationConfig, JetGeometry, PseudoInverseAllocator, QpAllocator  # noqa: E402
from onboard.compensation import TransientCompensator, allocate_compensated  # noqa: E402
from onboard.vehicle import load_vehicle  # noqa: E402


def violations(v, alloc, a0, b0, dt, nu_r, geo) -> int:
    """Number of limits a command breaks (0 when every one holds)."""
    lim, step, tol = v.servo.angle_limit, v.servo.rate_limit * dt, 1e-9
    a0, b0 = np.clip(a0, -lim, lim), np.clip(b0, -lim, lim)
    Va = geo.axial_inflow(nu_r, alloc.alpha_rad, alloc.beta_rad)
    checks = [
        np.any(alloc.n_rev_s < 0) or np.any(alloc.n_rev_s > v.thruster.n_max + tol),
        np.any(alloc.thrust_n < -tol) or np.any(alloc.thrust_n > geo.thrust_max(Va) + tol),
        np.any(np.abs(alloc.alpha_rad) > lim + tol) or np.any(np.abs(alloc.beta_rad) > lim + tol),
        np.any(np.abs(alloc.alpha_rad - a0) > step + tol) or np.any(np.abs(alloc.beta_rad - b0) > step + tol),
        not np.all(np.isfinite(alloc.command)),
    ]
    return int(sum(bool(c) for c in checks))


def reachable_wrench(rng, geo, a0, b0, nu_r, step, lim):
    """A wrench the jets can give this step: random thrust up to T_max(J), random joint travel."""
    k = geo.k
    a = np.clip(a0 + rng.uniform(-step, step, k), -lim, lim)
    b = np.clip(b0 + rng.uniform(-step, step, k), -lim, lim)
    Va = geo.axial_inflow(nu_r, a, b)
    T = rng.uniform(0, 1, k) * geo.thrust_max(Va)
    return geo.effectiveness(a, b) @ T


def capacity_along(qp, direction, a0, b0, nu_r) -> float:
    """max s with B f = s * direction and f in the step's polytope (linprog, HiGHS)."""
    A, l, u, _ = qp.constraints(a0, b0, nu_r)
    n = A.shape[1]
    B = qp.geo.B
    c = np.zeros(n + 1)
    c[-1] = -1.0
    A_eq = np.hstack([B, -direction[:, None]])
    fin_u, fin_l = np.isfinite(u), np.isfinite(l)
    A_ub = np.vstack([np.hstack([A[fin_u], np.zeros((fin_u.sum(), 1))]),
                      np.hstack([-A[fin_l], np.zeros((fin_l.sum(), 1))])])
    b_ub = np.concatenate([u[fin_u], -l[fin_l]])
    res = linprog(c, A_ub=A_ub, b_ub=b_ub, A_eq=A_eq, b_eq=np.zeros(6),
                  bounds=[(None, None)] * n + [(0, None)], method="highs")
    return float(res.x[-1]) if res.status == 0 else 0.0


def pct(x, q):
    return float(np.percentile(np.asarray(x), q))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--cases", type=int, default=10_000, help="random demands (default 10000)")
    ap.add_argument("--dt", type=float, default=0.01, help="control period in s (default 0.01)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--time-budget", type=float, default=None,
                    help="QP time budget in s (default: the allocator's, 1 ms); over it the QP falls back")
    ap.add_argument("--hold", type=int, default=20, help="control steps each demand is held (default 20)")
    ap.add_argument("--steps", type=int, default=2000, help="compensated sequence length (default 2000)")
    args = ap.parse_args(argv)

    v = load_vehicle()
    dt = args.dt
    cfg = AllocationConfig.from_vehicle(v) if args.time_budget is None else \
        AllocationConfig.from_vehicle(v, time_budget_s=args.time_budget)
    qp = QpAllocator(v, dt, cfg)
    pinv = PseudoInverseAllocator(v, dt, cfg)
    geo = JetGeometry(v)
    lim, step = v.servo.angle_limit, v.servo.rate_limit * dt
    W = cfg.weight_matrix()
    Fs2 = cfg.force_scale_n ** 2
    rng = np.random.default_rng(args.seed)

    # warm up the compiled kernels so the first case's time is not a compile
    qp.allocate(np.zeros(6), np.zeros(4), np.zeros(4), commit=False)
    pinv.allocate(np.zeros(6), np.zeros(4), np.zeros(4), commit=False)

    N, H = args.cases, args.hold
    beyond = np.arange(N) % 3 == 2
    qp_hold = QpAllocator(v, H * dt, cfg)  # its polytope: the travel of a whole hold (for the LP)
    keys = ("err_end", "err_hold", "err_first", "cost_end", "effort_end")
    rec = {name: {**{k: np.zeros(N) for k in keys}, "viol": 0, "fallback": 0, "wall": [], "wall_first": [],
                  "qp": [], "qp_first": [], "why": Counter()} for name in ("qp", "pinv")}
    t_gen = 0.0
    for i in range(N):
        a0, b0 = rng.uniform(-lim, lim, 4), rng.uniform(-lim, lim, 4)
        nu_r = np.concatenate([rng.normal(0, 0.15, 3), rng.normal(0, 0.3, 3)])
        tau = reachable_wrench(rng, geo, a0, b0, nu_r, H * step, lim)
        if beyond[i]:
            t0 = time.perf_counter()
            norm = np.linalg.norm(tau)
            direction = tau / norm if norm > 0 else np.eye(6)[2]
            s_max = capacity_along(qp_hold, direction, a0, b0, nu_r)
            tau = direction * s_max * rng.uniform(1.5, 2.5)
            t_gen += time.perf_counter() - t0
        for name, alloc_ in (("qp", qp), ("pinv", pinv)):
            alloc_.reset()
            r = rec[name]
            a_prev, b_prev = a0, b0
            errs = []
            for h in range(H):
                alloc = alloc_.allocate(tau, a0 if h == 0 else None, b0 if h == 0 else None, nu_r)
                errs.append(alloc.weighted_error)
                r["viol"] += violations(v, alloc, a_prev, b_prev, dt, nu_r, geo)
                r["fallback"] += int(alloc.fallback)
                if alloc.fallback:
                    r["why"][alloc.status.split("(")[0].split(";")[0].replace("fallback: ", "").strip()] += 1
                (r["wall_first"] if h == 0 else r["wall"]).append(alloc.solve_time_s)
                (r["qp_first"] if h == 0 else r["qp"]).append(alloc.qp_time_s)
                a_prev, b_prev = alloc.alpha_rad, alloc.beta_rad
            res = alloc.residual_wrench
            f = np.asarray(alloc.force_body_n)
            r["err_first"][i], r["err_end"][i], r["err_hold"][i] = errs[0], errs[-1], float(np.mean(errs))
            r["cost_end"][i] = res @ W @ res + cfg.effort_weight / Fs2 * float(np.sum(f * f))
            r["effort_end"][i] = float(np.sum(alloc.thrust_n))

    # Compensated allocation over a smooth demand sequence (the onboard loop's use).
    def demand(t):
        return np.array([1.5 * np.sin(0.7 * t), 0.8 * np.sin(0.45 * t + 1), -2.0 + 1.0 * np.sin(0.3 * t),
                         0.05 * np.sin(1.1 * t), 0.05 * np.cos(0.9 * t), 0.12 * np.sin(0.5 * t + 2)])

    comp_wall, comp_fallback = [], 0
    qc, comp = QpAllocator(v, dt, cfg), TransientCompensator(v, dt)
    for s in range(args.steps):
        t0 = time.perf_counter()
        out = allocate_compensated(qc, comp, demand(s * dt), iterations=2)
        comp_wall.append(time.perf_counter() - t0)
        comp_fallback += int(out.allocation.fallback)

    q, p = rec["qp"], rec["pinv"]
    ok = ~beyond
    us = 1e6
    load = os.getloadavg()
    print(f"# Allocation benchmark ({platform.processor() or platform.machine()}, {os.cpu_count()} cores, "
          f"load average {load[0]:.2f} {load[1]:.2f} {load[2]:.2f})")
    print(f"vehicle {v.name}, dt = {dt * 1e3:.0f} ms (joint travel <= {step:.3f} rad/step), {N} random demands "
          f"held {H} steps ({ok.sum()} reachable within the hold, {beyond.sum()} beyond reach: 1.5-2.5x the LP "
          f"capacity), seed {args.seed}, QP time budget {cfg.time_budget_s * 1e3:g} ms\n")
    print("| figure | QP (OSQP) | fixed mixing: pinv + clip | ratio QP / baseline |")
    print("|---|---|---|---|")

    def row(label, a, b, fmt="{:.4f}", ratio=True):
        r = f"{a / b:.3f}" if ratio and b else "-"
        print(f"| {label} | {fmt.format(a)} | {fmt.format(b)} | {r} |")

    row("**mean weighted wrench error, end of hold, all**", q["err_end"].mean(), p["err_end"].mean())
    row("... reachable demands", q["err_end"][ok].mean(), p["err_end"][ok].mean())
    row("... beyond-reach demands", q["err_end"][beyond].mean(), p["err_end"][beyond].mean())
    row("mean weighted wrench error over the hold, all", q["err_hold"].mean(), p["err_hold"].mean())
    row("mean weighted wrench error, first step only, all", q["err_first"].mean(), p["err_first"].mean())
    row("**mean cost (error^2 + effort), end of hold**", q["cost_end"].mean(), p["cost_end"].mean())
    row("mean effort (sum of thrusts, N), end of hold", q["effort_end"].mean(), p["effort_end"].mean(), "{:.3f}")
    row("**limit violations** (all steps)", q["viol"], p["viol"], "{:d}", ratio=False)
    row("fallbacks (all steps)", q["fallback"], p["fallback"], "{:d}", ratio=False)
    row("**allocate() median (us)**, warm steps", np.median(q["wall"]) * us, np.median(p["wall"]) * us, "{:.0f}")
    row("allocate() p99 (us), warm steps", pct(q["wall"], 99) * us, pct(p["wall"], 99) * us, "{:.0f}")
    row("allocate() median / p99 (us), first step", np.median(q["wall_first"]) * us, np.median(p["wall_first"]) * us,
        "{:.0f}")
    print(f"| **OSQP run time median / p99 (us)**, warm steps | {np.median(q['qp']) * us:.0f} / "
          f"{pct(q['qp'], 99) * us:.0f} | - | - |")
    print(f"| OSQP run time median / p99 (us), first step | {np.median(q['qp_first']) * us:.0f} / "
          f"{pct(q['qp_first'], 99) * us:.0f} | - | - |")
    print(f"| compensated allocation median / p99 (us), {args.steps} steps | {np.median(comp_wall) * us:.0f} / "
          f"{pct(comp_wall, 99) * us:.0f} ({comp_fallback} fallbacks) | - | - |")
    if q["why"]:
        print("\nQP fallbacks by reason: " + ", ".join(f"{why}: {n}" for why, n in q["why"].most_common()))
    print(f"\n(LP capacity search for the beyond-reach demands took {t_gen:.1f} s; not part of any figure.)")
    print("targets: error ratio <= 0.5 with zero violations; QP solve median <= 150 us")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
