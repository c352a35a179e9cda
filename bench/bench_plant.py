"""Plant benchmarks: real-time factor of one vehicle and throughput of the batch plant.

Run `python bench/bench_plant.py` (options: --help). Not a timed test: it prints figures, each
beside a baseline measured in the same run: the same `onboard/model.py` source executed by the
plain Python interpreter (its source loaded a second time as its own module, with numba's `njit`
replaced by an identity decorator), stepped one RK4 step at a time from Python.

Every figure is the best of `--repeat` runs (default 3): the machine is shared and noisy, and the
best run is the one least disturbed by others.
"""

from __future__ import annotations

import argparse
import importlib.util
import os
import platform
import sys
import time
import types
from pathlib import Path

import numba
import numpy as np

from hil import batch
from hil.plant import Plant
from onboard import model
from onboard.vehicle import EFFECT_IDS, load_vehicle


def interpreted_model() -> types.ModuleType:
    """onboard/model.py loaded again as `onboard._model_interpreted`, numba decorators as identity.

    numba's `.py_func` un-jits only the outer function (its callees stay compiled), so the whole
    source is executed afresh against a stand-in `numba` module whose `njit` returns the plain
    function; `prange` is `range`. The real numba module is put back afterwards.
    """
    def njit(*args, **kwargs):
        if len(args) == 1 and callable(args[0]) and not kwargs:
            return args[0]
        return lambda f: f

    stub = types.ModuleType("numba")
    stub.njit = njit
    stub.jit = njit
    stub.prange = range
    path = Path(model.__file__)
    spec = importlib.util.spec_from_file_location("onboard._model_interpreted", path)
    module = importlib.util.module_from_spec(spec)
    real = sys.modules["numba"]
    sys.modules["numba"] = stub
    sys.modules[spec.name] = module  # dataclasses look their module up while the class is built
    try:
        spec.loader.exec_module(module)
    finally:
        sys.modules["numba"] = real
    assert not hasattr(module.rk4_step, "py_func"), "the interpreted model is still compiled"
    return module


def best_of(repeat: int, fn) -> tuple[float, float]:
    """Smallest wall time and smallest process CPU time (s) over `repeat` calls of fn().

    CPU time is summed over threads; on a shared machine it shows what the work itself costs
    while the wall time also counts the time other programs held the cores.
    """
    wall = cpu = float("inf")
    for _ in range(repeat):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        wall = min(wall, time.perf_counter() - t0)
        cpu = min(cpu, time.process_time() - c0)
    return wall, cpu


def setup():
    """The reference vehicle with every effect on, a current, and joints commanded to move."""
    v = load_vehicle().with_effects(**{e: True for e in EFFECT_IDS})
    v = v.with_values({"environment.current": (0.1, 0.05, 0.0)})
    u = np.array([45.0, 50.0, 55.0, 60.0, 0.4, -0.3, 0.2, -0.1, 0.15, -0.25, 0.3, -0.05])
    x0 = model.initial_state(v, 0.5)  # joints start at 0 and slew to the command: transients run
    return v, u, x0


def cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown CPU"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--dt", type=float, default=0.001, help="step (s), default 0.001")
    ap.add_argument("--repeat", type=int, default=3, help="runs per figure, best taken (default 3)")
    ap.add_argument("--single-s", type=float, default=10.0, help="simulated seconds, single vehicle")
    ap.add_argument("--python-steps", type=int, default=200, help="steps of the interpreted baseline")
    ap.add_argument("--vehicles", type=int, default=256, help="vehicles in the batch")
    ap.add_argument("--batch-s", type=float, default=1.0, help="simulated seconds per batch vehicle")
    ap.add_argument("--coarse-dt", type=float, default=0.01, help="second batch step (s); 0 to skip")
    args = ap.parse_args(argv)
    if min(args.dt, args.single_s, args.batch_s) <= 0 or args.coarse_dt < 0:
        ap.error("--dt, --single-s and --batch-s must be > 0, --coarse-dt >= 0")
    if min(args.repeat, args.vehicles, args.python_steps) < 1:
        ap.error("--repeat, --vehicles and --python-steps must be >= 1")

    dt, rep = args.dt, args.repeat
    load_start = os.getloadavg()[0]
    v, u, x0 = setup()
    p = model.pack_params(v)
    py = interpreted_model()
    rows: list[tuple] = []  # (what, dt, horizon, simulated (vehicle-)s, wall s, CPU s, unit)

    # -- baseline: the same model, interpreted, one RK4 step per Python call -----------------------
    n_py = args.python_steps

    def run_python():
        x = x0.copy()
        for _ in range(n_py):
            x = py.rk4_step(x, u, p, dt)
        return x

    x_py = run_python()
    x_c = model.rk4_steps(x0.copy(), u, p, dt, n_py)  # also compiles or loads the cache
    same = float(np.abs(x_py - x_c).max())
    py_first = best_of(rep, run_python)  # measured again at the end: the best of both is kept

    # -- (a) single vehicle, compiled -----------------------------------------------------------
    n_single = int(round(args.single_s / dt))
    t, c = best_of(rep, lambda: model.rk4_steps(x0.copy(), u, p, dt, n_single))
    rows.append(("compiled `model.rk4_steps`, 1 vehicle", dt, f"{args.single_s:g} s", args.single_s, t, c, "RTF"))

    def run_plant():
        plant = Plant(v, dt_s=dt, seed=1, command=u)
        plant.advance(args.single_s)
        return plant

    run_plant()  # warm
    t, c = best_of(rep, run_plant)
    s = v.sensors
    rows.append((f"`Plant.advance` with sensors (IMU {s.imu_rate:g} Hz, pressure {s.pressure_rate:g} Hz, "
                 f"attitude {s.attitude_rate:g} Hz, noise on), 1 vehicle", dt, f"{args.single_s:g} s",
                 args.single_s, t, c, "RTF"))

    # -- (b) batch ------------------------------------------------------------------------------
    nv = args.vehicles
    params = batch.monte_carlo(v, {"hydro.added_mass": 0.1, "hydro.linear_damping": 0.2}, nv, seed=0)
    states = np.tile(x0, (nv, 1))
    commands = np.tile(u, (nv, 1))
    threads = numba.get_num_threads()

    def batch_row(step: float, n_threads: int, record: bool = False) -> None:
        n_steps = int(round(args.batch_s / step))
        numba.set_num_threads(n_threads)
        try:
            if record:
                def go():
                    batch.simulate_batch_record(states, commands, params, step, n_steps, 10)
            else:
                def go():
                    batch.simulate_batch(states, commands, params, step, n_steps)
            batch.simulate_batch(states[:2], commands[:2], params[:2], step, 2)  # warm
            t, c = best_of(rep, go)
        finally:
            numba.set_num_threads(threads)
        what = "`simulate_batch_record` (pos, quat, nu every 10 steps)" if record else "`simulate_batch`"
        th = f"{n_threads} thread" + ("s" if n_threads > 1 else "")
        rows.append((f"{what}, {nv} vehicles, {th}", step, f"{args.batch_s:g} s each", nv * n_steps * step,
                     t, c, "vehicle-s/s"))

    for n_threads in sorted({1, threads}):
        batch_row(dt, n_threads)
    batch_row(dt, threads, record=True)
    if args.coarse_dt > 0:
        batch_row(args.coarse_dt, threads)

    if args.coarse_dt > 0:  # what the coarse step costs in accuracy: 2 s against a 0.1 ms reference
        ref = model.rk4_steps(x0.copy(), u, p, 1e-4, 20000)
        errs = {}
        for step in (dt, args.coarse_dt):
            x = model.rk4_steps(x0.copy(), u, p, step, int(round(2.0 / step)))
            errs[step] = (np.abs(x[:3] - ref[:3]).max(), np.abs(x[7:13] - ref[7:13]).max())

    py_last = best_of(rep, run_python)
    t_py, c_py = min(py_first[0], py_last[0]), min(py_first[1], py_last[1])
    step_py, step_py_cpu = t_py / n_py, c_py / n_py  # s per RK4 step, interpreted; the same at any dt
    rows.insert(0, ("plain Python RK4 (interpreted model.py), 1 vehicle", dt, f"{n_py * dt:g} s", n_py * dt,
                    t_py, c_py, "RTF"))

    # -- report ---------------------------------------------------------------------------------
    print(f"machine: {cpu_name()}, {os.cpu_count()} cores (os.cpu_count), numba {numba.__version__} "
          f"with {threads} threads ({numba.threading_layer()} layer), Python {platform.python_version()}, "
          f"numpy {np.__version__}")
    print(f"vehicle: {v.name}, every effect on ({', '.join(EFFECT_IDS)}), current 0.1 m/s, joints slewing; "
          f"state {x0.size} values")
    print(f"baseline: interpreted model.py, {step_py * 1e3:.2f} ms per RK4 step ({step_py_cpu * 1e3:.2f} ms "
          f"CPU); it agrees with the compiled model to {same:.1e} after {n_py} steps")
    print(f"each figure: best of {rep} runs (the baseline: of {2 * rep}, at the start and at the end); "
          f"1-minute load average {load_start:.1f} at the start, {os.getloadavg()[0]:.1f} at the end "
          f"(other work on the machine lowers the wall-clock figures)\n")
    if args.coarse_dt > 0:
        print("step accuracy, same run, 2 s against RK4 at 0.1 ms: " + "; ".join(
            f"dt {step * 1e3:g} ms: position {e[0]:.1e} m, nu {e[1]:.1e} (m/s, rad/s)" for step, e in errs.items()
        ) + "\n")
    head = ("what", "dt (ms)", "horizon", "speed (wall clock)", "x plain Python", "per CPU-second",
            "x plain Python (CPU)")
    print("| " + " | ".join(head) + " |")
    print("|" + "|".join("---" for _ in head) + "|")
    for what, step, horizon, sim_s, wall, cpu, unit in rows:
        rate, rate_cpu = sim_s / wall, sim_s / cpu
        base, base_cpu = step / step_py, step / step_py_cpu  # the baseline's speed at this dt
        print(f"| {what} | {step * 1e3:g} | {horizon} | {_fmt(rate)} {unit} | {rate / base:.0f} | "
              f"{_fmt(rate_cpu)} | {rate_cpu / base_cpu:.0f} |")
    print("\nRTF = simulated seconds per wall-clock second; vehicle-s/s = simulated vehicle-seconds per "
          "wall-clock second summed over the batch; per CPU-second = the same per second of process CPU "
          "time (summed over threads, so it does not count time other programs held the cores); "
          "x plain Python = that speed over the interpreted baseline's at the same dt (its cost per step "
          "does not depend on dt).")
    return 0


def _fmt(r: float) -> str:
    return f"{r:.3g}" if r < 10 else f"{r:.0f}"


if __name__ == "__main__":
    sys.exit(main())
