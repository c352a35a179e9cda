"""Running a campaign: serial in this process, on a local Dask cluster, or on an existing one.

    DIR/tasks/ID/row.json   one finished task (written last, atomically: its presence means done)
    DIR/tasks/ID/...        the task's files (recording, report)
    DIR/results.parquet     one row per task of the spec, rewritten as results land
    DIR/campaign.json       the plan: kind, spec file, every task's id, label and inputs
    DIR/index.html          the report (ground.campaign.report)

Resuming is reading DIR/tasks: a task whose row.json exists is done (ok or error: a task that
raises raises again), unless its worker was lost more often than the scheduler retries
(status "lost"), which is tried again. Task ids are content addresses (spec.task_id), so a
changed sweep reuses every task it shares with the old one.

The engine is dask.distributed's: a `LocalCluster` of worker processes (one thread each: the
loop and the plant hold the GIL) when no scheduler is given, else a `Client` of the scheduler at
`tcp://HOST:PORT` started with `dask scheduler` / `dask worker`. Worker processes are spawned,
never forked (numba's OpenMP layer kills a child forked after it ran, hil/batch.py), and each
loads the compiled model from numba's on-disk cache on its first task. A worker that dies
mid-task costs that task a retry on another worker (the scheduler's allowed-failures). A vehicle
file's text goes to the cluster once, held by one task the others depend on (`_same`), not in
every task's inputs.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from .spec import Campaign, Task
from .tasks import execute

META_COLUMNS = ("task_id", "kind", "label", "status", "error", "wall_s", "cpu_s", "worker", "host", "pid", "started_unix")
LOST = "lost"


@dataclass
class Outcome:
    rows: list  # one dict per task of the campaign, in the spec's order
    ran: int = 0  # tasks run this time
    skipped: int = 0  # already done (resume)
    wall_s: float = 0.0
    mode: str = ""
    counts: dict = field(default_factory=dict)


# ------------------------------------------------------------------------------------------------
# The store


def task_dir(out: Path, task: Task) -> Path:
    return out / "tasks" / task.id


def read_row(out: Path, task: Task) -> dict | None:
    """The task's row if it is done; None (run it) when absent or not a row this engine wrote for
    it (a damaged or hand-edited file, another task's row)."""
    p = task_dir(out, task) / "row.json"
    try:
        row = json.loads(p.read_text())
    except (OSError, ValueError):
        return None
    if not (isinstance(row, dict) and row.get("task_id") == task.id and row.get("status") in ("ok", "error", LOST)
            and isinstance(row.get("label"), str)):
        return None
    return row


def store(out: Path, task: Task, result: dict) -> dict:
    """Write a finished task's files, then its row (atomically: the row is the done marker)."""
    d = task_dir(out, task)
    d.mkdir(parents=True, exist_ok=True)
    files = result.get("files", {})
    for name, data in files.items():
        target = (d / name).resolve()
        if d.resolve() not in target.parents:  # a file name from a worker never leaves its task's folder
            continue
        target.parent.mkdir(parents=True, exist_ok=True)
        target.write_bytes(data)
    row = {"task_id": task.id, "kind": task.kind, "label": task.label, **input_columns(task), **result["row"],
           "files": sorted(files)}
    tmp = d / "row.json.tmp"
    tmp.write_text(json.dumps(_jsonable(row), indent=1, allow_nan=False) + "\n")
    os.replace(tmp, d / "row.json")
    return row


def input_columns(task: Task) -> dict:
    """The task's inputs as table columns: the vehicle file by its hash, not its text."""
    cols = {}
    for k, v in task.inputs.items():
        if k == "vehicle_toml":
            cols["vehicle_sha256"] = None if v is None else hashlib.sha256(v.encode()).hexdigest()[:16]
        else:
            cols[k] = v
    return cols


def _jsonable(v):
    if isinstance(v, float) and not math.isfinite(v):
        return None
    if isinstance(v, dict):
        return {str(k): _jsonable(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_jsonable(x) for x in v]
    if hasattr(v, "item") and not isinstance(v, (str, bytes)):  # numpy scalars
        return _jsonable(v.item())
    return v


def write_table(out: Path, rows: list[dict]) -> Path:
    """results.parquet: one row per task; scalars keep their type, lists and tables are JSON text."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    names: list[str] = list(META_COLUMNS)
    for r in rows:
        for k in r:
            if k not in names:
                names.append(k)
    cols = {}
    for name in names:
        vals = [r.get(name) for r in rows]
        present = [v for v in vals if v is not None]
        if present and all(isinstance(v, bool) for v in present):
            cols[name] = pa.array(vals, pa.bool_())
        elif present and all(isinstance(v, int) and not isinstance(v, bool) for v in present):
            cols[name] = pa.array(vals, pa.int64())
        elif present and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in present):
            cols[name] = pa.array([None if v is None else float(v) for v in vals], pa.float64())
        elif all(isinstance(v, str) for v in present):
            cols[name] = pa.array(vals, pa.string())
        else:
            cols[name] = pa.array([None if v is None else json.dumps(v, sort_keys=True) for v in vals], pa.string())
    path = out / "results.parquet"
    tmp = out / "results.parquet.tmp"
    pq.write_table(pa.table(cols), tmp)
    os.replace(tmp, path)
    return path


def read_table(out) -> list[dict]:
    """results.parquet back as a list of dicts (columns written as JSON text stay text)."""
    import pyarrow.parquet as pq

    return pq.read_table(Path(out) / "results.parquet").to_pylist()


# ------------------------------------------------------------------------------------------------
# Progress: done, failed, running, ETA


class Progress:
    """A rich progress bar on a terminal; a line per finished task otherwise (logs, CI)."""

    def __init__(self, total: int, already: int, failed: int, quiet: bool = False):
        self.total, self.done, self.failed, self.running = total, already, failed, 0
        self.already = already
        self.t0 = time.monotonic()
        self.quiet = quiet
        self.bar = None
        if not quiet and sys.stderr.isatty():
            from rich.console import Console
            from rich.progress import BarColumn, Progress as Bar, TextColumn

            self.bar = Bar(TextColumn("campaign"), BarColumn(), TextColumn("{task.fields[text]}"),
                           console=Console(file=sys.stderr), transient=False)
            self.bar.start()
            self.bar_task = self.bar.add_task("campaign", total=total, completed=already, text=self.text())

    def eta_s(self) -> float | None:
        ran = self.done - self.already
        left = self.total - self.done
        if ran <= 0:
            return None
        return (time.monotonic() - self.t0) / ran * left

    def text(self) -> str:
        eta = self.eta_s()
        eta_text = "?" if eta is None else _duration(eta)
        return (f"{self.done}/{self.total} done, {self.failed} failed, {self.running} running, "
                f"{_duration(time.monotonic() - self.t0)} elapsed, ETA {eta_text}")

    def finished(self, row: dict) -> None:
        self.done += 1
        self.failed += row.get("status") != "ok"
        self.running = max(self.running - 1, 0)
        if self.bar is not None:
            self.bar.update(self.bar_task, completed=self.done, text=self.text())
        elif not self.quiet:
            what = "ok" if row.get("status") == "ok" else f"{row.get('status')}: {str(row.get('error'))[:120]}"
            print(f"[{self.text()}] {row.get('label')}: {what} ({row.get('wall_s', 0):.1f} s on {row.get('worker')})",
                  file=sys.stderr, flush=True)

    def update(self, running: int) -> None:
        self.running = running
        if self.bar is not None:
            self.bar.update(self.bar_task, text=self.text())

    def close(self) -> None:
        if self.bar is not None:
            self.bar.stop()


def _duration(s: float) -> str:
    s = int(round(s))
    return f"{s // 3600}:{s % 3600 // 60:02d}:{s % 60:02d}" if s >= 3600 else f"{s // 60}:{s % 60:02d}"


# ------------------------------------------------------------------------------------------------
# Running


def run_campaign(campaign: Campaign, out, scheduler: str | None = None, workers: int | None = None,
                 quiet: bool = False, on_row=None, report: bool = True) -> Outcome:
    """Run every task of `campaign` not already done in `out`; the table and report after.

    `workers` = 0 runs serially in this process; otherwise a LocalCluster of `workers` processes
    (default: the cores, at most 8; never more than the tasks to run), unless `scheduler` names
    an existing cluster's address.
    `on_row(row)` is called as each task lands (the tests use it)."""
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "campaign.json").write_text(json.dumps(
        {"kind": campaign.kind, "spec": campaign.source, "skipped_by_spec": campaign.skipped,
         "tasks": [{"id": t.id, "label": t.label, "inputs": input_columns(t)} for t in campaign.tasks]},
        indent=1) + "\n")
    rows: dict[str, dict] = {}
    todo: list[Task] = []
    for t in campaign.tasks:
        r = read_row(out, t)
        if r is not None and r.get("status") != LOST:
            rows[t.id] = r
        else:
            todo.append(t)
    t0 = time.perf_counter()
    prog = Progress(len(campaign.tasks), len(rows), sum(r.get("status") != "ok" for r in rows.values()), quiet)
    last_write = [0.0]

    def landed(task: Task, result: dict) -> None:
        row = store(out, task, result)
        rows[task.id] = row
        prog.finished(row)
        if on_row is not None:
            on_row(row)
        if time.monotonic() - last_write[0] > 2.0:  # the table follows the results as they land
            write_table(out, [rows[t.id] for t in campaign.tasks if t.id in rows])
            last_write[0] = time.monotonic()

    mode = "serial"
    try:
        if todo and workers == 0 and scheduler is None:
            for t in todo:
                prog.update(1)
                landed(t, execute(t.kind, t.inputs))
        elif todo:
            mode = _run_dask(todo, scheduler, workers, prog, landed)
    finally:
        prog.close()
        if rows:
            write_table(out, [rows[t.id] for t in campaign.tasks if t.id in rows])
    ordered = [rows[t.id] for t in campaign.tasks if t.id in rows]
    counts = {s: sum(r.get("status") == s for r in ordered) for s in ("ok", "error", LOST)}
    outcome = Outcome(ordered, len(todo), len(campaign.tasks) - len(todo), time.perf_counter() - t0, mode, counts)
    if report and ordered:
        from .report import write_report

        write_report(campaign, out, ordered)
    return outcome


def _same(x):
    """A task that holds a value (the vehicle file's text) for the tasks that need it: recomputed
    from its own spec if the worker holding it dies (scattered data would be lost with it)."""
    return x


def _execute_with_vehicle(kind: str, inputs: dict, vehicle_toml: str) -> dict:
    """`execute` of a task whose vehicle text came as a dependency (the same inputs, so the same row)."""
    return execute(kind, {**inputs, "vehicle_toml": vehicle_toml})


def _run_dask(todo: list[Task], scheduler: str | None, workers: int | None, prog: Progress, landed) -> str:
    import logging

    import dask
    from distributed import Client, LocalCluster, wait

    cluster = None
    with dask.config.set({"distributed.worker.multiprocessing-method": "spawn",
                          "distributed.scheduler.allowed-failures": 3}):
        if scheduler is None:
            n = workers if workers is not None else min(os.cpu_count() or 1, 8)
            n = max(1, min(n, len(todo)))  # a worker with no task to run is a spawned process for nothing
            cluster = LocalCluster(n_workers=n, threads_per_worker=1, processes=True, dashboard_address=None,
                                   silence_logs=logging.ERROR)
            client = Client(cluster)
            mode = f"local cluster of {n} worker process{'es' if n != 1 else ''}"
        else:
            try:
                client = Client(scheduler, timeout="20s")
            except TypeError as exc:  # tls:// with no TLS set up in Dask's config: distributed raises TypeError
                raise ConnectionError(f"{scheduler.partition('://')[0]}:// needs Dask's TLS configuration "
                                      f"(distributed.comm.tls.*): {str(exc)[:160]}") from None
            info = client.scheduler_info()
            mode = f"scheduler {scheduler} ({len(info.get('workers', {}))} workers)"
        try:
            by_key = {}
            # the costliest first (submitted first, at a higher priority), so a long case never starts
            # last and holds up the end; equal costs in the spec's order
            order = sorted(todo, key=lambda t: -t.cost)
            vehicles: dict = {}  # the vehicle file's text -> the one task that holds it
            for r, t in enumerate(order):
                key, priority = f"jetloop-{t.kind}-{t.id}", len(order) - r
                text = t.inputs.get("vehicle_toml")
                if text is None:
                    fut = client.submit(execute, t.kind, t.inputs, key=key, pure=False, priority=priority)
                else:  # the text (up to 1 MB) travels once, not with each of a million tasks
                    if text not in vehicles:
                        digest = hashlib.sha256(text.encode()).hexdigest()[:16]
                        vehicles[text] = client.submit(_same, text, key=f"jetloop-vehicle-{digest}", pure=False,
                                                       priority=len(order) + 1)
                    rest = {k: v for k, v in t.inputs.items() if k != "vehicle_toml"}
                    fut = client.submit(_execute_with_vehicle, t.kind, rest, vehicles[text], key=key, pure=False,
                                        priority=priority)
                by_key[fut.key] = (fut, t)
            pending = {f for f, _ in by_key.values()}
            while pending:
                try:
                    done, pending = wait(pending, timeout=1.0, return_when="FIRST_COMPLETED")
                except TimeoutError:
                    done = set()
                for fut in done:
                    task = by_key[fut.key][1]
                    try:
                        result = fut.result()
                    except Exception as exc:  # KilledWorker: lost more often than retried; tried again on resume
                        result = {"row": {"status": LOST, "error": f"{type(exc).__name__}: {exc}", "worker": None},
                                  "files": {}}
                    landed(task, result)
                    fut.release()
                try:  # assigned to a worker, at most one per worker thread (the rest wait in its queue)
                    threads = client.nthreads()
                    busy = sum(min(len(v), threads.get(w, 1)) for w, v in client.processing().items())
                except Exception:
                    busy = len(pending)
                prog.update(min(busy, len(pending)))
        finally:
            client.close()
            if cluster is not None:
                cluster.close()
    return mode


# ------------------------------------------------------------------------------------------------
# `jetloop prove --split ... --dask / --scheduler`: the benchmark's cases on this engine


def run_prove_family(split: str, n: int, out, workers: int = 2, first: int = 0, scheduler: str | None = None,
                     vehicle_path=None, quiet: bool = False) -> list[dict]:
    """Cases first..first+n-1 of `split` as a prove campaign (resumable, results.parquet,
    index.html in `out`); returns their rows in `ground.prove.run_family`'s form."""
    from .spec import Task, _Problems, _vehicle

    p = _Problems("jetloop prove")
    text, _ = _vehicle(p, None if vehicle_path is None else str(Path(vehicle_path).resolve()), Path.cwd(), "--vehicle")
    p.raise_if_any()
    from ground.prove import family_case

    cases = [(i, family_case(split, i)) for i in range(first, first + n)]
    tasks = tuple(Task("prove", c[0].name, {"split": split, "index": i, "draws": None, "vehicle_toml": text},
                       cost=c[1].duration_s) for i, c in cases)
    campaign = Campaign("prove", f"jetloop prove --split {split} --first {first} --cases {n}", tasks,
                        {"split": split, "first": first, "cases": n})
    outcome = run_campaign(campaign, out, scheduler=scheduler, workers=None if scheduler else workers, quiet=quiet)
    return [family_row(r) for r in outcome.rows]


def family_row(row: dict) -> dict:
    """A prove campaign's row as ground.prove.family_table reads it ("error" only when it raised)."""
    if row.get("status") == "ok":
        return {k: v for k, v in row.items() if k != "error"}
    return {**row, "case": row.get("case") or row.get("label"), "expect": row.get("expect") or [],
            "error": row.get("error") or row.get("status")}
