"""jetloop campaign (issue 14): the same per-task results serially, on a local Dask cluster and on a
real `dask scheduler` with two `dask worker` processes on loopback; resume after an interrupted
run; a killed worker costs a retry; a task that raises is a row; a bad spec is one line."""

from __future__ import annotations

import json
import os
import shutil
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

from ground.campaign import CampaignSpecError, load_spec, parse_spec, read_table, run_campaign
from ground.campaign.cli import EXAMPLES
from ground.cli import main

REPO = Path(__file__).resolve().parents[1]
# the figures a flight computes (not its timing): equal whichever way the task ran
FIGURES = ("depth_rms_m", "yaw_rms_rad", "speed_rms_m_s", "depth_max_abs_m", "tilt_max_rad", "control_steps",
           "allocation_weighted_error_mean", "allocation_fallbacks", "failsafe_entries", "faults_seen",
           "limit_violations", "detections")

SMALL = """
kind = "missions"
seed = 3
[missions]
mission = "hold"
duration_s = 7.0
draws = 2
allocators = ["qp"]
seeds = [0]
[missions.perturb]
"hydro.added_mass" = 0.1
[missions.faults]
none = {}
"jet 2 dead" = { dead-jet = "2@4" }
"""


def write_spec(tmp_path: Path, text: str, name: str = "spec.toml") -> Path:
    p = tmp_path / name
    p.write_text(text)
    return p


def by_id(rows):
    return {r["task_id"]: r for r in rows}


def assert_same_results(a_dir: Path, b_dir: Path) -> None:
    a, b = by_id(read_table(a_dir)), by_id(read_table(b_dir))
    assert a.keys() == b.keys()
    for tid, ra in a.items():
        rb = b[tid]
        assert ra["status"] == rb["status"] == "ok", (ra["error"], rb["error"])
        for k in FIGURES:
            assert ra[k] == rb[k], (ra["label"], k, ra[k], rb[k])
        # the recording itself, byte for byte
        assert (a_dir / "tasks" / tid / "mission.tlog").read_bytes() == (b_dir / "tasks" / tid / "mission.tlog").read_bytes()


def free_tcp_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# ------------------------------------------------------------------------------------------------
# The spec


def test_a_spec_becomes_content_addressed_tasks(tmp_path):
    c = load_spec(write_spec(tmp_path, SMALL))
    assert c.kind == "missions" and len(c.tasks) == 4  # 2 draws x 1 allocator x 2 faults x 1 seed
    again = parse_spec(SMALL, tmp_path / "elsewhere.toml")
    assert [t.id for t in c.tasks] == [t.id for t in again.tasks]  # the address is the content, not the file
    wider = parse_spec(SMALL.replace('seeds = [0]', 'seeds = [0, 1]'), tmp_path / "x.toml")
    assert {t.id for t in c.tasks} < {t.id for t in wider.tasks}  # a wider sweep keeps the old tasks' ids
    # the draws are hil.batch's: draw i of perturbed_values(vehicle, perturb, n, seed)
    from hil.batch import perturbed_values
    from onboard.vehicle import load_vehicle

    drawn = perturbed_values(load_vehicle(), {"hydro.added_mass": 0.1}, 2, 3)["hydro.added_mass"]
    got = [t.inputs["vehicle_values"]["hydro.added_mass"] for t in c.tasks if t.inputs["fault"] == "none"]
    assert got == [list(drawn[0]), list(drawn[1])]


def test_the_shipped_example_specs_parse(tmp_path):
    names = sorted(p.name for p in EXAMPLES.glob("*.toml"))
    assert names == ["diagnose.toml", "missions.toml", "prove.toml"]
    m = load_spec(EXAMPLES / "missions.toml")
    assert m.kind == "missions" and len(m.tasks) == 8 * 2 * 3 * 2
    p = load_spec(EXAMPLES / "prove.toml")
    assert p.kind == "prove" and len(p.tasks) + p.skipped == 300
    d = tmp_path / "diagnose.toml"
    shutil.copy(EXAMPLES / "diagnose.toml", d)
    (tmp_path / "pool-week" / "monday").mkdir(parents=True)
    (tmp_path / "pool-week" / "monday" / "a.tlog").write_bytes(b"x")
    (tmp_path / "pool-week" / "b.tlog").write_bytes(b"y")
    assert [t.label for t in load_spec(d).tasks] == ["pool-week/b.tlog", "pool-week/monday/a.tlog"]


@pytest.mark.parametrize("text, says", [
    ("kind = 'missions'\n[missions]\ndraws = -1\n", "missions.draws: expected a whole number 0..100000, got -1"),
    ("kind = 'missile'\n", "kind: expected one of missions, prove, diagnose, got 'missile'"),
    ("[missions]\n", "kind: missing; expected one of missions, prove, diagnose"),
    ("kind = 'missions'\n[missions]\ndraw = 3\n", "missions.draw: unknown key; allowed here:"),
    ("kind = 'missions'\n[missions]\nallocators = ['pinv']\n", "missions.allocators: expected a list of distinct values from qp, baseline"),
    ("kind = 'missions'\n[missions.faults]\nbad = { weak-jet = '3:1.5@2' }\n", "missions.faults.bad: weak-jet '3:1.5@2': expected UNIT:EFFICIENCY@T0"),
    ("kind = 'missions'\n[missions.faults]\nbad = { loss = '0.1' }\n", "missions.faults.bad.loss: expected no link fault with flight = \"inprocess\""),
    ("kind = 'missions'\n[missions]\ndraws = 2\n[missions.perturb]\n'hydro.mass' = 0.1\n", "missions.perturb: perturb: hydro.mass: unknown vehicle key"),
    ("kind = 'missions'\nvehicle = 'nowhere.toml'\n", "vehicle: expected the path of a readable vehicle TOML file"),
    ("kind = 'prove'\n[prove]\nsplit = 'test'\n", "prove.split: expected one of dev, eval, got 'test'"),
    ("kind = 'diagnose'\n[diagnose]\nrecordings = 'none/*.tlog'\n", "diagnose.recordings: expected a glob that matches at least one recording file"),
    ("kind = 'missions'\n[missions\n", "not valid TOML"),
    # TOML nests dotted keys thousands deep: a RecursionError traceback before the fix
    pytest.param("kind = 'missions'\n[missions]\ndraws = 2\n[missions.perturb]\n" + "a." * 5000 + "b = 0.1\n",
                 "missions.perturb: expected dotted vehicle keys", id="perturb-nested-5000-deep"),
    (f"kind = 'missions'\nvehicle = '{REPO / 'onboard' / 'data' / 'bluerov2_heavy.toml'}'\n",
     "vehicle: " + str(REPO / "onboard" / "data" / "bluerov2_heavy.toml") + ": bluerov2_heavy has fixed thrusters only"),
])
def test_a_bad_spec_is_one_line_naming_file_and_key(tmp_path, capsys, text, says):
    spec = write_spec(tmp_path, text)
    with pytest.raises(CampaignSpecError):
        load_spec(spec)
    rc = main(["campaign", str(spec), "--out", str(tmp_path / "out")])
    err = capsys.readouterr().err
    assert rc == 2
    assert "Traceback" not in err
    assert len(err.strip().splitlines()) == 1, err
    assert err.startswith(f"jetloop campaign: {spec}: ") and says in err, err
    assert not (tmp_path / "out" / "results.parquet").exists()


def test_a_long_fault_name_is_shortened_in_the_error(tmp_path, capsys):
    """The line names the key, not 100 kB of it (before the fix the whole name was echoed)."""
    spec = write_spec(tmp_path, "kind = 'missions'\n[missions.faults]\n" + "n" * 100_000 + " = { dead-jet = 'x' }\n")
    assert main(["campaign", str(spec), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "missions.faults.nnnn" in err and " ...: dead-jet 'x'" in err, err[:300]
    assert len(err) < 400, len(err)


def test_an_absurd_vehicle_file_in_a_spec_is_one_line(tmp_path, capsys, reference_text):
    bad = tmp_path / "bad.toml"
    assert "mass = 6.5 " in reference_text
    bad.write_text(reference_text.replace("mass = 6.5 ", "mass = 6500.0 ", 1))
    spec = write_spec(tmp_path, "kind = 'missions'\nvehicle = 'bad.toml'\n")
    assert main(["campaign", str(spec), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    assert f"{spec}: invalid campaign spec: vehicle: {bad}: invalid vehicle file: body.mass" in err, err


def test_bad_command_lines_are_one_line(tmp_path, capsys):
    spec = write_spec(tmp_path, SMALL)
    for argv, says in ((["--workers", "-1"], "--workers -1: expected"),
                       (["--scheduler", "localhost:8786"], "expected tcp://HOST:PORT"),
                       (["--scheduler", "tcp://127.0.0.1:8786", "--workers", "2"], "--workers with --scheduler")):
        assert main(["campaign", str(spec), "--out", str(tmp_path / "o"), *argv]) == 2
        err = capsys.readouterr().err
        assert len(err.strip().splitlines()) == 1 and says in err, err
    assert main(["campaign", str(tmp_path / "missing.toml"), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "missing.toml: cannot read campaign spec" in err and len(err.strip().splitlines()) == 1


def test_a_tls_scheduler_without_tls_set_up_is_one_line(tmp_path, capsys):
    """--scheduler accepts tls://; with no TLS in Dask's config distributed raises TypeError at once
    (a traceback before the fix)."""
    spec = write_spec(tmp_path, SMALL)
    rc = main(["campaign", str(spec), "--out", str(tmp_path / "o"), "--scheduler", "tls://127.0.0.1:1", "--quiet"])
    err = capsys.readouterr().err
    assert rc == 1 and "Traceback" not in err and len(err.strip().splitlines()) == 1, err
    assert "cannot reach the scheduler tls://127.0.0.1:1: tls:// needs Dask's TLS configuration" in err, err


@pytest.mark.slow  # the client waits its 20 s connect timeout
def test_no_scheduler_there_is_one_line(tmp_path, capsys):
    spec = write_spec(tmp_path, SMALL)
    rc = main(["campaign", str(spec), "--out", str(tmp_path / "o"), "--scheduler", f"tcp://127.0.0.1:{free_tcp_port()}",
               "--quiet"])
    err = capsys.readouterr().err
    assert rc == 1 and "cannot reach the scheduler" in err and "Traceback" not in err, err


# ------------------------------------------------------------------------------------------------
# Running


@pytest.mark.slow
def test_serial_and_local_cluster_agree_and_an_interrupted_run_resumes(tmp_path, capsys):
    spec = write_spec(tmp_path, SMALL)
    campaign = load_spec(spec)
    # serial, interrupted (Ctrl-C) after its second task: what landed stays
    landed = []

    def interrupt(row):
        landed.append(row["task_id"])
        if len(landed) == 2:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        run_campaign(campaign, tmp_path / "serial", workers=0, on_row=interrupt)
    assert len(read_table(tmp_path / "serial")) == 2
    # the same command again: only the two missing tasks run
    assert main(["campaign", str(spec), "--out", str(tmp_path / "serial"), "--workers", "0"]) == 0
    out = capsys.readouterr()
    assert "ran 2 now (2 already done)" in out.out
    assert "4/4 done, 0 failed" in out.err and "ETA" in out.err and "running" in out.err  # the progress lines
    rows = read_table(tmp_path / "serial")
    assert [r["task_id"] for r in rows] == [t.id for t in campaign.tasks]  # one row per task, the spec's order
    assert {r["worker"] for r in rows} == {"serial"}
    # a local cluster of two spawned worker processes: the same figures, the same recordings
    assert main(["campaign", str(spec), "--out", str(tmp_path / "local"), "--workers", "2", "--quiet"]) == 0
    assert "ran 4 now" in capsys.readouterr().out
    assert_same_results(tmp_path / "serial", tmp_path / "local")
    assert all(r["worker"].startswith("tcp://127.0.0.1:") for r in read_table(tmp_path / "local"))
    # done is done: nothing runs again
    assert main(["campaign", str(spec), "--out", str(tmp_path / "local"), "--workers", "2", "--quiet"]) == 0
    assert "ran 0 now (4 already done)" in capsys.readouterr().out
    # the report: tracking plots per allocator and fault, the failure cases with their recordings
    page = (tmp_path / "local" / "index.html").read_text()
    assert "plots/tracking.png" in page and (tmp_path / "local" / "plots" / "tracking.png").stat().st_size > 1000
    assert "jet 2 dead" in page and "Failure cases" in page


@pytest.fixture
def dask_cluster(tmp_path):
    """A real `dask scheduler` and two `dask worker` processes (one thread each) on 127.0.0.1,
    each in its own process group (a worker's nanny and its worker process die together)."""
    port = free_tcp_port()
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), os.environ.get("PYTHONPATH", "")])}
    bindir = Path(sys.executable).parent
    dask_cmd = [str(bindir / "dask")] if (bindir / "dask").exists() else [sys.executable, "-m", "distributed.cli.dask_scheduler"]
    logs = tmp_path / "dask-logs"
    logs.mkdir()
    procs = []

    def start(args, name):
        f = open(logs / f"{name}.log", "w")
        p = subprocess.Popen(args, stdout=f, stderr=subprocess.STDOUT, env=env, cwd=tmp_path, start_new_session=True)
        procs.append(p)
        return p

    address = f"tcp://127.0.0.1:{port}"
    if dask_cmd[0].endswith("dask"):
        start(dask_cmd + ["scheduler", "--host", "127.0.0.1", "--port", str(port), "--no-dashboard"], "scheduler")
        workers = [start(dask_cmd + ["worker", address, "--nthreads", "1", "--nworkers", "1", "--no-dashboard",
                                     "--host", "127.0.0.1", "--local-directory", str(tmp_path / f"w{i}")], f"worker{i}")
                   for i in range(2)]
    else:  # pragma: no cover - the console script is installed with distributed
        pytest.fail("the `dask` command (dask[distributed]) is not installed")
    from distributed import Client

    try:
        deadline = time.monotonic() + 120
        while True:
            try:
                with Client(address, timeout="5s") as c:
                    c.wait_for_workers(2, timeout=max(1.0, deadline - time.monotonic()))
                    break
            except (OSError, TimeoutError):
                if time.monotonic() > deadline:
                    pytest.fail("the dask scheduler and workers did not start: " +
                                " | ".join(p.read_text()[-400:] for p in logs.iterdir()))
                time.sleep(0.5)
        yield address, workers
    finally:
        for p in procs:
            if p.poll() is None:
                try:
                    os.killpg(p.pid, signal.SIGTERM)
                except ProcessLookupError:
                    pass
        for p in procs:
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait(5)


@pytest.mark.slow
def test_a_real_scheduler_with_two_workers_survives_a_killed_worker(tmp_path, dask_cluster):
    address, workers = dask_cluster
    text = SMALL.replace("draws = 2", "draws = 3")  # 6 tasks
    spec = write_spec(tmp_path, text)
    campaign = load_spec(spec)
    killed = {}

    def kill_one(row):
        # the worker that just delivered a task has taken its next one: kill it mid-task, nanny and all
        if not killed:
            pgid = os.getpgid(row["pid"])
            assert pgid in {w.pid for w in workers}
            os.killpg(pgid, signal.SIGKILL)
            killed.update(worker=row["worker"], pgid=pgid, at=time.monotonic())

    outcome = run_campaign(campaign, tmp_path / "cluster", scheduler=address, quiet=True, on_row=kill_one)
    assert killed, "no task landed"
    assert [w.wait(10) for w in workers if w.pid == killed["pgid"]] == [-signal.SIGKILL]
    rows = read_table(tmp_path / "cluster")
    assert outcome.counts == {"ok": 6, "error": 0, "lost": 0}
    assert len(rows) == 6 and all(r["status"] == "ok" for r in rows)
    survivors = {r["worker"] for r in rows} - {killed["worker"]}
    assert len(survivors) == 1  # the tasks after the kill ran on the other worker
    # the scheduler's own story: a task was processing on the killed worker and went back to the
    # queue when it died (a retry), not to an error
    from distributed import Client

    with Client(address, timeout="10s") as c:
        story = c.run_on_scheduler(lambda dask_scheduler: [tuple(map(str, e)) for e in dask_scheduler.transition_log])
    retried = {e[0].rsplit("-", 1)[1] for e in story
               if e[1] == "processing" and e[2] == "released" and e[4].startswith("handle-worker-cleanup")}
    assert retried and retried <= {r["task_id"] for r in rows}  # taken back from the dead worker, then done
    # the same per-task results as a serial run in this process
    run_campaign(campaign, tmp_path / "serial", workers=0, quiet=True)
    assert_same_results(tmp_path / "serial", tmp_path / "cluster")


@pytest.mark.slow
def test_a_task_that_raises_is_a_row_and_diagnose_finds_recurrences(tmp_path, capsys):
    """diagnose campaign over two short mission recordings and a damaged file, on a local cluster."""
    from ground.campaign.tasks import execute

    rec = tmp_path / "rec"
    rec.mkdir()
    base = parse_spec(SMALL, tmp_path / "m.toml")
    for t in base.tasks[:2]:  # two 7 s recordings flown by the campaign's own mission task
        (rec / f"{t.id}.tlog").write_bytes(execute(t.kind, t.inputs)["files"]["mission.tlog"])
    (rec / "damaged.tlog").write_bytes(bytes(range(256)) * 12)
    spec = write_spec(tmp_path, "kind = 'diagnose'\n[diagnose]\nrecordings = 'rec/*.tlog'\ndraws = 2\n")
    assert main(["campaign", str(spec), "--out", str(tmp_path / "out"), "--workers", "1"]) == 0
    cap = capsys.readouterr()
    assert "3/3 tasks have a row: 2 ok, 1 raised, 0 lost" in cap.out
    rows = {r["label"]: r for r in read_table(tmp_path / "out")}
    bad = rows["rec/damaged.tlog"]
    assert bad["status"] == "error" and bad["error"].startswith("RecordingError: ") and "damaged.tlog" in bad["error"]
    good = [r for r in rows.values() if r["status"] == "ok"]
    assert len(good) == 2 and all(r["error"] is None and r["recording_s"] > 6 for r in good)
    assert all((tmp_path / "out" / "tasks" / r["task_id"] / "report.json").exists() for r in good)
    # one worker: the largest recording (the costliest task) first, the small damaged file last
    by_start = sorted(rows.values(), key=lambda r: r["started_unix"])
    sizes = [(tmp_path / r["label"]).stat().st_size for r in by_start]
    assert sizes == sorted(sizes, reverse=True) and by_start[-1]["label"] == "rec/damaged.tlog"
    page = (tmp_path / "out" / "index.html").read_text()
    assert "Findings that recur" in page and "Tasks that raised" in page and "RecordingError" in page


@pytest.mark.slow
def test_a_prove_case_on_the_local_cluster_gives_the_benchmark_table(tmp_path, capsys):
    spec = write_spec(tmp_path, "kind = 'prove'\n[prove]\nsplit = 'dev'\nindices = [0, 14, 15]\n"
                                "max_duration_s = 60\ndraws = 2\n")  # dev-000 flies 180 s: left out
    assert main(["campaign", str(spec), "--out", str(tmp_path / "out"), "--workers", "1", "--quiet"]) == 0
    rows = read_table(tmp_path / "out")
    assert [r["index"] for r in rows] == [14, 15] and all(r["status"] == "ok" for r in rows)
    assert rows[0]["case"] == "dev-014 surface_proximity x1.0"
    assert json.loads((tmp_path / "out" / "campaign.json").read_text())["skipped_by_spec"] == 1
    files = set(os.listdir(tmp_path / "out" / "tasks" / rows[0]["task_id"]))
    assert {"dev_014.tlog", "dev_014.json", "dev_014.nominal.toml", "row.json"} <= files
    page = (tmp_path / "out" / "index.html").read_text()
    assert "controls: false findings" in page and "confusion" in page  # family_table with its intervals


@pytest.mark.slow
def test_jetloop_prove_runs_the_benchmark_on_the_campaign_engine(tmp_path, capsys):
    """issue 18: `jetloop prove --split` on the campaign engine (--dask), resumable like a campaign."""
    argv = ["prove", "--split", "dev", "--first", "15", "--cases", "1", "--dask", "--workers", "1", "--quiet",
            "--out", str(tmp_path / "p")]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "1 cases (0 raised)" in out and "| sensors: ardusub | 1 |" in out  # ground.prove.family_table
    fam = json.loads((tmp_path / "p" / "family.json").read_text())["cases"]
    assert [c["index"] for c in fam] == [15] and "error" not in fam[0]
    assert [r["status"] for r in read_table(tmp_path / "p")] == ["ok"]
    started = read_table(tmp_path / "p")[0]["started_unix"]
    assert main(argv) == 0  # again: resumed, nothing recomputed
    assert "1 cases (0 raised)" in capsys.readouterr().out
    assert read_table(tmp_path / "p")[0]["started_unix"] == started


@pytest.mark.slow
def test_a_loopback_flight_takes_link_faults(tmp_path):
    """flight = "loopback": jetloop demo's parties over UDP (threads) in the task, so the link faults of
    hil.faults apply; the onboard monitor reports the loss, the ground's telemetry is a file too."""
    spec = write_spec(tmp_path, 'kind = "missions"\n[missions]\nmission = "hold"\nduration_s = 8\nseeds = [0]\n'
                                'flight = "loopback"\n[missions.faults]\n"loss" = { loss = "0.1@2:6" }\n')
    outcome = run_campaign(load_spec(spec), tmp_path / "out", workers=0, quiet=True)
    (row,) = outcome.rows
    assert row["status"] == "ok" and row["lockstep_periods"] == 800
    assert [d["flag"] for d in row["detections"]] == ["LINK_LOSS"] and row["detections"][0]["detected_s"] is not None
    assert {"mission.tlog", "telemetry.tlog", "summary.json"} <= set(row["files"])


def test_a_damaged_row_file_means_run_it_again_not_a_traceback(tmp_path):
    """row.json is the done marker: one that is not this task's row (a JSON list, a foreign or
    hand-edited row) is not done (before the fix the resume ended in AttributeError / KeyError)."""
    from ground.campaign.engine import read_row, task_dir

    task = parse_spec(SMALL, tmp_path / "s.toml").tasks[0]
    d = task_dir(tmp_path, task)
    d.mkdir(parents=True)
    for text in ("[]", '{"status": 5}', '{"task_id": "0123", "status": "ok", "label": "x"}', "{not json"):
        (d / "row.json").write_text(text)
        assert read_row(tmp_path, task) is None, text
    good = {"task_id": task.id, "status": "error", "label": task.label, "error": "E"}
    (d / "row.json").write_text(json.dumps(good))
    assert read_row(tmp_path, task) == good


def test_a_local_cluster_starts_no_more_workers_than_tasks(tmp_path, monkeypatch):
    """--workers 64 for 4 tasks spawned 64 processes (each loads numpy, numba and the model) for 60
    to sit idle; the cluster is asked for as many as there are tasks to run."""
    import distributed

    from ground.campaign.engine import Progress, _run_dask

    asked = {}

    class Refused(Exception):
        pass

    def fake_cluster(n_workers, **kw):
        asked["n"] = n_workers
        raise Refused

    monkeypatch.setattr(distributed, "LocalCluster", fake_cluster)
    todo = list(parse_spec(SMALL, tmp_path / "s.toml").tasks)
    with pytest.raises(Refused):
        _run_dask(todo, None, 64, Progress(len(todo), 0, 0, quiet=True), lambda t, r: None)
    assert asked["n"] == len(todo) == 4


@pytest.mark.slow
def test_the_vehicle_file_goes_to_the_cluster_once_not_with_every_task(tmp_path, monkeypatch, reference_text):
    """Each task's inputs carried the vehicle file's text (up to 1 MB): a million-task spec put a
    million copies in the scheduler's memory. Now one task holds it and the others depend on it;
    the figures and recordings are those of the serial run."""
    import pickle

    import distributed

    vehicle = tmp_path / "v.toml"
    vehicle.write_text(reference_text)
    spec = write_spec(tmp_path, "kind = 'missions'\nvehicle = 'v.toml'\n[missions]\nmission = 'hold'\n"
                                "duration_s = 2.0\nseeds = [0, 1, 2]\n")
    campaign = load_spec(spec)
    carried = []
    submit = distributed.Client.submit

    def counting_submit(self, func, *args, **kw):
        carried.append(reference_text in pickle.dumps(args).decode("latin-1"))
        return submit(self, func, *args, **kw)

    monkeypatch.setattr(distributed.Client, "submit", counting_submit)
    outcome = run_campaign(campaign, tmp_path / "local", workers=1, quiet=True, report=False)
    assert outcome.counts == {"ok": 3, "error": 0, "lost": 0}
    assert len(carried) == 4 and sum(carried) == 1  # three tasks and the vehicle's holder
    run_campaign(campaign, tmp_path / "serial", workers=0, quiet=True, report=False)
    a, b = by_id(read_table(tmp_path / "serial")), by_id(read_table(tmp_path / "local"))
    assert a.keys() == b.keys() == {t.id for t in campaign.tasks}
    def same(x, y):  # a 2 s hold has no settled window: some figures are NaN on both
        return x == y or (isinstance(x, float) and isinstance(y, float) and x != x and y != y)

    for tid in a:
        assert all(same(a[tid][k], b[tid][k]) for k in FIGURES), (a[tid], b[tid])
        assert a[tid]["control_steps"] == 200
        assert (tmp_path / "serial" / "tasks" / tid / "mission.tlog").read_bytes() == \
            (tmp_path / "local" / "tasks" / tid / "mission.tlog").read_bytes()


@pytest.mark.parametrize("entry, make", [
    ("results.parquet", lambda p: p.mkdir()),
    ("tasks", lambda p: p.write_text("not a folder")),
])
def test_an_output_entry_of_the_wrong_kind_is_one_line_before_any_task(tmp_path, capsys, entry, make):
    """A directory named results.parquet failed the table's first write after every task had run:
    exit 1 and '[Errno 21] Is a directory: .../results.parquet.tmp' -> ...'."""
    spec = write_spec(tmp_path, "kind = 'missions'\n[missions]\nmission = 'hold'\nduration_s = 2.0\ndraws = 0\n"
                                "allocators = ['qp']\nseeds = [0]\n[missions.faults]\nnone = {}\n")
    out = tmp_path / "out"
    out.mkdir()
    make(out / entry)
    t0 = time.monotonic()
    assert main(["campaign", str(spec), "--out", str(out), "--workers", "0", "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "Errno" not in err, err
    assert err.startswith(f"jetloop campaign: {out / entry} is ") and "move it away or choose another --out" in err
    assert not (out / "campaign.json").exists() and time.monotonic() - t0 < 5  # nothing ran


@pytest.mark.parametrize("argv", [["campaign", str(EXAMPLES / "missions.toml"), "--quiet"], ["demo"],
                                  ["soak", "--duration", "200"], ["prove", "--split", "dev", "--cases", "1"]])
def test_an_output_directory_that_cannot_be_made_is_one_line(tmp_path, capsys, argv):
    """campaign, demo, soak and prove share ground.cli.make_output_dir: --out under a regular file."""
    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    assert main([*argv, "--out", str(blocker / "out")]) == 2
    err = capsys.readouterr().err.strip()
    assert err == f"jetloop {argv[0]}: cannot create output directory {blocker / 'out'}: Not a directory", err
