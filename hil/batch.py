"""The batch plant: many vehicles stepped at once, for Monte Carlo campaigns and identification.

Each vehicle is the same compiled model as the single plant (`onboard.model.rk4_step`, spec 6:
fixed-step RK4, command held over a step, quaternion renormalised and joints clipped after it),
with its own state, command schedule and parameter vector. A batch is three arrays:

    states   (N, nx)          nx = StateLayout(k).size
    commands (N, nu)          held for the whole run, nu = 3 k, or
             (S, N, nu)       a schedule: row s holds over steps [s h, (s + 1) h), h = n_steps / S
    params   (N, np)          rows of `onboard.model.pack_params` (e.g. from `monte_carlo`)

The vehicles are independent, so a `prange` over them (numba, `parallel=True`) gives results
that do not depend on the thread count or the scheduling: vehicle i of a batch is bit for bit
the single-vehicle `rk4_steps` run with the same state, command and parameters.

`monte_carlo` draws perturbed vehicles from one seeded generator and packs their parameters;
`perturbed_values` gives the drawn values themselves (the truth an identification should find).
Pure math: arrays in, arrays out; no clock, no files.

Processes: with numba's OpenMP threading layer (the one here unless `tbb` is installed) a process
forked after it ran a batch dies when the child runs one ("fork() called from a process already
using GNU OpenMP"). A process pool over batches uses `multiprocessing.get_context("forkserver")`
or "spawn"; threads within one batch come from numba (`numba.set_num_threads`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Mapping, Sequence

import numpy as np
from numba import njit, prange

from onboard import model
from onboard.jit import MODEL_SOURCE, cache_keyed_on
from onboard.vehicle import Vehicle, VehicleFileError

# Named pieces of the state a recording can ask for (see onboard.model.StateLayout).
STATE_PIECES = ("pos", "quat", "nu", "n", "alpha", "beta", "transient")


# ------------------------------------------------------------------------------------------------
# Compiled kernel

@njit(parallel=True, nogil=True)  # cached on disk below, keyed on this file and onboard/model.py
def _run(states, schedule, params, dt, hold, n_steps, every, idx, record, out):
    """Step every vehicle `n_steps` times; record x[idx] at step 0 and every `every` steps.

    schedule[s, i] is vehicle i's command over steps [s hold, (s + 1) hold). `every` = 0 means
    no recording. Each vehicle runs the same loop as `model.rk4_steps`, one `rk4_step` per step.
    """
    n_vehicles = states.shape[0]
    m = idx.shape[0]
    for i in prange(n_vehicles):
        x = states[i].copy()
        p = params[i]
        if every > 0:
            for j in range(m):
                record[i, 0, j] = x[idx[j]]
        for step in range(n_steps):
            x = model.rk4_step(x, schedule[step // hold, i], p, dt)
            if every > 0 and (step + 1) % every == 0:
                s = (step + 1) // every
                for j in range(m):
                    record[i, s, j] = x[idx[j]]
        for j in range(x.shape[0]):
            out[i, j] = x[j]


cache_keyed_on(_run, MODEL_SOURCE)


# ------------------------------------------------------------------------------------------------
# Checked entry points

@dataclass(frozen=True)
class BatchRecord:
    """A recorded batch run: `values[i, s]` is vehicle i's x[`state_index`] at `time_s[s]`."""

    time_s: np.ndarray  # (samples,) s since the start of the run
    values: np.ndarray  # (N, samples, m)
    state_index: np.ndarray  # (m,) indices into the state vector
    final_state: np.ndarray  # (N, nx) after n_steps


def simulate_batch(states, commands, params, dt_s: float, n_steps: int) -> np.ndarray:
    """Final states (N, nx) after `n_steps` RK4 steps of `dt_s` for every vehicle.

    `commands` is (N, nu), held, or a schedule (S, N, nu) whose rows each hold n_steps / S steps.
    """
    x, sched, p, dt, hold, n = _check(states, commands, params, dt_s, n_steps)
    out = np.empty_like(x)
    _run(x, sched, p, dt, hold, n, 0, np.zeros(0, np.int64), np.zeros((0, 0, 0)), out)
    return out


def simulate_batch_record(
    states, commands, params, dt_s: float, n_steps: int, every: int,
    record: Sequence[str] | Sequence[int] = ("pos", "quat", "nu"),
) -> BatchRecord:
    """Like `simulate_batch`, also recording part of the state at step 0 and every `every` steps.

    `record` names pieces of the state (STATE_PIECES, in the order given) or lists indices.
    The recording has n_steps // every + 1 samples (the initial state first).
    """
    x, sched, p, dt, hold, n = _check(states, commands, params, dt_s, n_steps)
    if isinstance(every, bool) or not isinstance(every, (int, np.integer)) or every < 1:
        raise ValueError(f"every: expected a whole number of steps >= 1, got {every!r}")
    idx = state_indices(record, _units_of_state(x.shape[1]))
    samples = n // int(every) + 1
    rec = np.empty((x.shape[0], samples, idx.shape[0]))
    out = np.empty_like(x)
    _run(x, sched, p, dt, hold, n, int(every), idx, rec, out)
    return BatchRecord(np.arange(samples) * int(every) * dt, rec, idx, out)


def state_indices(record: Sequence[str] | Sequence[int], n_units: int = 4) -> np.ndarray:
    """State-vector indices of named pieces ("pos", "quat", "nu", ...) or of given indices."""
    lay = model.StateLayout(n_units)
    if isinstance(record, str):
        record = (record,)
    out: list[int] = []
    for item in record:
        if isinstance(item, str):
            if item not in STATE_PIECES:
                raise ValueError(f"record: unknown state piece {item!r}; expected one of {STATE_PIECES}")
            out += list(range(lay.size))[getattr(lay, item)]
        elif isinstance(item, (int, np.integer)) and not isinstance(item, bool) and 0 <= item < lay.size:
            out.append(int(item))
        else:
            raise ValueError(
                f"record: expected state piece names {STATE_PIECES} or indices 0..{lay.size - 1}, got {item!r}"
            )
    if not out:
        raise ValueError("record: nothing to record (empty list)")
    return np.array(out, dtype=np.int64)


def _units_of_state(nx: int) -> int:
    k, rem = divmod(nx - 13, 3 + model.N_TF_STATES)
    return k if rem == 0 and k >= 1 else -1


def _check(states, commands, params, dt_s, n_steps):
    """Validated, contiguous float arrays and the schedule hold; clear errors otherwise."""
    x = _float_array("states", states, 2, "(N, nx)")
    n_veh, nx = x.shape
    k = _units_of_state(nx)
    if k < 1:
        raise ValueError(
            f"states: {nx} values per vehicle is not a state vector (expected 13 + {3 + model.N_TF_STATES} k, e.g. "
            f"{model.StateLayout(4).size} for 4 units)"
        )
    p = _float_array("params", params, 2, "(N, np)")
    n_par = model.P_UNITS + (6 + model.UNIT_TAIL) * k  # per unit: 6 of geometry, UNIT_TAIL of thruster kind
    if p.shape != (n_veh, n_par):
        raise ValueError(
            f"params: expected shape ({n_veh}, {n_par}) (one pack_params row per vehicle, {k} units), "
            f"got {p.shape}"
        )
    nu = 3 * k
    c = _float_array("commands", commands, None, f"({n_veh}, {nu}) or (S, {n_veh}, {nu})")
    if c.ndim == 2:
        c = c[None]
    if c.ndim != 3 or c.shape[1:] != (n_veh, nu) or c.shape[0] < 1:
        raise ValueError(
            f"commands: expected shape ({n_veh}, {nu}) held, or (S, {n_veh}, {nu}) a schedule of S rows "
            f"({n_veh} vehicles, {k} units), got {np.shape(commands)}"
        )
    if isinstance(n_steps, bool) or not isinstance(n_steps, (int, np.integer)) or n_steps < 0:
        raise ValueError(f"n_steps: expected a whole number >= 0, got {n_steps!r}")
    n = int(n_steps)
    segments = c.shape[0]
    if n % segments:
        raise ValueError(
            f"commands: a schedule of {segments} rows must divide n_steps = {n} evenly "
            f"(each row holds n_steps / S steps)"
        )
    hold = max(n // segments, 1)
    try:
        dt = float(dt_s)
    except (TypeError, ValueError):
        dt = float("nan")
    if not (np.isfinite(dt) and dt > 0):
        raise ValueError(f"dt_s: expected a finite step > 0 s, got {dt_s!r}")
    return x, c, p, dt, hold, n


def _float_array(name: str, value, ndim: int | None, shape_text: str) -> np.ndarray:
    try:
        a = np.ascontiguousarray(value, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{name}: expected a float array {shape_text}, got {type(value).__name__}: {exc}") from None
    if ndim is not None and a.ndim != ndim:
        raise ValueError(f"{name}: expected a {ndim}-D array {shape_text}, got shape {a.shape}")
    if not np.all(np.isfinite(a)):
        bad = tuple(int(i) for i in np.argwhere(~np.isfinite(a))[0])
        raise ValueError(f"{name}: every value must be finite; {name}[{', '.join(map(str, bad))}] is {a[bad]}")
    return a


# ------------------------------------------------------------------------------------------------
# Monte Carlo over vehicle parameters

def perturbed_values(
    vehicle: Vehicle, perturb: Mapping[str, float], n: int, seed: int
) -> dict[str, np.ndarray]:
    """n draws of each perturbed key: value = nominal (1 + sigma z), z ~ N(0, 1) per element.

    `perturb` maps a dotted vehicle key (e.g. "hydro.added_mass") to a relative 1-sigma. The keys
    are drawn in sorted order from `np.random.default_rng(seed)`, each as an (n, size) block, so
    the draws depend on the seed and the set of keys, not on the order the dict lists them.
    Returns key -> (n, size) array (size 1 for a scalar key). A zero nominal value stays zero.
    """
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
        raise ValueError(f"n: expected a whole number of vehicles >= 1, got {n!r}")
    rng = np.random.default_rng(seed)
    out: dict[str, np.ndarray] = {}
    for key in sorted(perturb):
        sigma = perturb[key]
        try:
            sigma_f = float(sigma)
        except (TypeError, ValueError):
            sigma_f = float("nan")
        if not (np.isfinite(sigma_f) and sigma_f >= 0):
            raise ValueError(f"perturb[{key!r}]: expected a relative sigma >= 0, got {sigma!r}")
        try:
            nominal = vehicle.get(key)
        except AttributeError:
            raise VehicleFileError(f"perturb: {key}: unknown vehicle key") from None
        if isinstance(nominal, bool) or not isinstance(nominal, (int, float, tuple, list)):
            raise ValueError(f"perturb: {key}: not a numeric vehicle key (value {nominal!r})")
        nom = np.atleast_1d(np.asarray(nominal, dtype=float))
        z = rng.standard_normal((n, nom.size))
        out[key] = nom[None, :] * (1.0 + sigma_f * z)
    return out


def monte_carlo(vehicle: Vehicle, perturb: Mapping[str, float], n: int, seed: int) -> np.ndarray:
    """Parameter rows (n, np) of n perturbed copies of `vehicle` (see `perturbed_values`).

    Each row is `pack_params(vehicle.with_values(draw))`, so every draw is validated like a
    vehicle file: a draw the file would reject (a negative mass from a large sigma) raises
    `VehicleFileError` naming the key and the draw.
    """
    values = perturbed_values(vehicle, perturb, n, seed)
    rows = []
    for i in range(n):
        draw = {key: (float(v[i, 0]) if _is_scalar(vehicle.get(key)) else tuple(float(c) for c in v[i]))
                for key, v in values.items()}
        try:
            rows.append(model.pack_params(vehicle.with_values(draw)))
        except VehicleFileError as exc:
            raise VehicleFileError(f"monte_carlo draw {i} (seed {seed}): {exc}") from None
    return np.array(rows)


def _is_scalar(value) -> bool:
    return not isinstance(value, (tuple, list))


__all__ = [
    "BatchRecord",
    "STATE_PIECES",
    "monte_carlo",
    "perturbed_values",
    "simulate_batch",
    "simulate_batch_record",
    "state_indices",
]
