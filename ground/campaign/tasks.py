"""What one campaign task does, on whichever process runs it: inputs in, a row and its files out.

`execute(kind, inputs)` is the one function a worker runs. It never raises: a task that fails
is a row with status "error" and the error's text, so one bad task never ends a campaign. Its
files (a mission's recording, a proof case's recording and report) come back as bytes with
the row, so a worker on another machine needs no shared disk for its results.

- missions: `fly_mission` is bench_onboard's lock-step loop in one process (plant samples through
  the MAVLink codec into `OnboardLoop.handle`, `OnboardLoop.step`, the command into the plant),
  with hil.faults' actuator and sensor faults applied where the HIL endpoint applies them and the
  plant side written to mission.tlog as the endpoint writes it; `flight = "loopback"` flies
  `jetloop demo`'s three parties over UDP instead (threads), for the link faults too. Either way
  the figures are `hil.demo.summarise`'s, the ones `jetloop demo` prints.
- prove: `ground.prove.run_family_case` (record and diagnose one benchmark case).
- diagnose: `ground.diagnose.diagnose` of one recording against the campaign's vehicle file.
"""

from __future__ import annotations

import argparse
import os
import socket
import tempfile
import time
import traceback
from dataclasses import replace
from pathlib import Path

MAX_FILE_RETURNED = 512 * 1024 * 1024  # a task's files come back through the scheduler


def execute(kind: str, inputs: dict) -> dict:
    """Run one task: {"row": figures and status, "files": {name: bytes}}. Never raises."""
    t0 = time.perf_counter()
    c0 = time.process_time()  # this process's CPU, every thread: what the task costs whatever the load
    started = time.time()
    files: dict = {}
    try:
        with tempfile.TemporaryDirectory(prefix="jetloop-task-") as tmp:
            figures = RUNNERS[kind](inputs, Path(tmp))
            for p in sorted(Path(tmp).rglob("*")):
                if p.is_file() and p.stat().st_size <= MAX_FILE_RETURNED:
                    files[str(p.relative_to(tmp))] = p.read_bytes()
        error = figures.pop("error", None)
        row = {"status": "error" if error else "ok", "error": error, **figures}
    except Exception as exc:  # the task's failure is its row, never the campaign's end
        tb = traceback.extract_tb(exc.__traceback__)
        where = f" (at {Path(tb[-1].filename).name}:{tb[-1].lineno})" if tb else ""
        row = {"status": "error", "error": f"{type(exc).__name__}: {exc}{where}"}
    row.update(wall_s=round(time.perf_counter() - t0, 3), cpu_s=round(time.process_time() - c0, 3), started_unix=round(started, 3),
               worker=_worker_name(), host=socket.gethostname(), pid=os.getpid())
    return {"row": row, "files": files}


def _worker_name() -> str:
    try:
        from distributed import get_worker

        return get_worker().address
    except (ImportError, ValueError):
        return "serial"


def _vehicle(inputs: dict):
    from onboard.vehicle import load_vehicle, parse_vehicle

    text = inputs.get("vehicle_toml")
    return load_vehicle(None) if text is None else parse_vehicle(text, source="<campaign vehicle>")


# ------------------------------------------------------------------------------------------------
# missions


def mission_of(inputs: dict):
    from hil.demo import hold_mission, reference_mission

    if inputs["mission"] == "demo":
        return reference_mission()
    return hold_mission(inputs["duration_s"], turn_at_s=8.0 if inputs["mission"] == "turn" else None)


def fault_plan(flags: dict, n_units: int):
    """The FaultPlan of a spec's fault table: the flags of `jetloop demo` (hil.faults)."""
    from hil.faults import plan_from_args

    ns = argparse.Namespace(**{k.replace("-", "_"): v for k, v in flags.items()})
    return plan_from_args(ns, n_units)


def run_mission(inputs: dict, out: Path) -> dict:
    from hil.demo import DEMO_CONFIG, run_closed_loop, summarise, summary_json

    base = _vehicle(inputs)
    vehicle = base.with_values(inputs["vehicle_values"]) if inputs["vehicle_values"] else base
    mission = mission_of(inputs)
    plan = fault_plan(inputs["fault_flags"], vehicle.n_units)
    config = replace(DEMO_CONFIG, allocator=inputs["allocator"], compensation=inputs["compensation"])
    if inputs["flight"] == "loopback":
        result = run_closed_loop(vehicle, mission.setpoints(), mission.duration_s, seed=inputs["seed"],
                                 config=config, out_dir=out, faults=plan, processes=False)
        if "error" in result.onboard:
            raise RuntimeError(f"the onboard loop failed: {result.onboard['error']}")
    else:
        result = fly_mission(vehicle, mission, config, inputs["seed"], plan, out / "mission.tlog")
    summary = summarise(result, mission, vehicle)
    (out / "summary.json").write_text(summary_json(summary))
    summary["flight_wall_s"] = summary.pop("wall_s")  # the row's wall_s is the whole task's
    return summary


def fly_mission(vehicle, mission, config, seed: int, faults, tlog_path: Path | None):
    """The mission in lock-step in this process (bench/bench_onboard.py's Flight), with the fault
    plan's actuator and sensor faults, the plant side recorded as HilEndpoint records it.
    Returns a hil.demo.ClosedLoopResult for `hil.demo.summarise`."""
    import math

    import numpy as np
    from pymavlink.dialects.v20 import ardupilotmega as mavlink

    from hil.demo import ClosedLoopResult
    from hil.endpoint import GCS_COMPONENT, GCS_SYSTEM
    from hil.faults import (INJECTOR_COMPONENT, INJECTOR_SYSTEM, actuator_command, detections, imu_fault,
                            injection_events, joint_index, pressure_offset_pa)
    from hil.plant import Plant
    from hil.tlog import FIXED_EPOCH_US, TlogWriter
    from onboard import mavlink_codec as codec
    from onboard.link import Link
    from onboard.loop import OnboardLoop, VehicleClock
    from onboard.pwm import command_to_pwm

    faults.check_units(vehicle.n_units)
    link = Link("udpin:127.0.0.1:0")  # never spoken to: what the loop sends is counted and dropped
    clock = VehicleClock()
    loop = OnboardLoop(vehicle, link, clock, config)
    plant = Plant(vehicle, dt_s=0.001, seed=seed, depth_m=0.0)
    lay = plant.layout
    period = 1.0 / config.control_rate_hz
    setpoints = sorted(mission.setpoints(), key=lambda p: p[0])
    gcs = mavlink.MAVLink(None, srcSystem=GCS_SYSTEM, srcComponent=GCS_COMPONENT)
    injector = codec.make_mavlink(INJECTOR_SYSTEM, INJECTOR_COMPONENT)
    tlog = TlogWriter(tlog_path) if tlog_path is not None else None
    stamp = lambda t: FIXED_EPOCH_US + int(round(t * 1e6))  # noqa: E731
    marks = injection_events(faults)
    rho_g = (vehicle.environment.rho, vehicle.environment.g)
    mocap_period = 1.0 / vehicle.sensors.attitude_rate
    truth, commands = [], []
    commanded = np.array(plant.command, dtype=float)
    stuck: dict = {}
    frozen = last_imu = None
    next_sp = 0
    next_hb = next_mocap = 0.0
    applied_at = 0.0
    n = int(round(mission.duration_s / period))
    wall0 = time.perf_counter()

    def send(msg, t, mav=None):
        """Record what the endpoint would send at t (packing gives the message its header)."""
        if tlog is not None:
            if mav is None:
                tlog.write(msg, stamp(t))
            else:
                tlog.write_packet(bytes(msg.pack(mav)), stamp(t), msg.get_type())
                mav.seq = (mav.seq + 1) % 256
        elif mav is not None:
            msg.pack(mav)
        return msg

    try:
        for k in range(n):
            t = k * period
            samples = plant.advance(t + 1e-9)
            truth.extend(samples.truth)
            while marks and marks[0][0] <= t + 1e-9:
                text = marks.pop(0)[1]
                if tlog is not None:
                    st = mavlink.MAVLink_statustext_message(mavlink.MAV_SEVERITY_NOTICE, text.encode()[:50], 0, 0)
                    tlog.write_packet(codec.encode(injector, st), stamp(t), "STATUSTEXT")
            if t + 1e-9 >= next_hb:
                send(codec.heartbeat(armed=True), t)
                next_hb += 1.0
            while next_sp < len(setpoints) and setpoints[next_sp][0] <= t + 1e-9:
                loop.handle(send(setpoints[next_sp][1], t, gcs))
                next_sp += 1
            for s in samples.pressure:
                if faults.depth_jumps:
                    s = replace(s, press_abs_pa=s.press_abs_pa + pressure_offset_pa(faults, s.time_s, *rho_g))
                loop.handle(send(codec.encode_pressure(s), t))
            for s in samples.attitude:
                loop.handle(send(codec.encode_attitude(s), t))
            for s in samples.imu:
                if any(t0 <= s.time_s < t1 for t0, t1 in faults.imu_dropouts_s):
                    continue
                what = imu_fault(faults, s.time_s) if (faults.imu_freeze_s or faults.imu_nan_s) else None
                if what == "nan":
                    nan = math.nan
                    msg = mavlink.MAVLink_highres_imu_message(codec.time_usec(s.time_s), nan, nan, nan, nan, nan, nan,
                                                              0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0,
                                                              codec.HIGHRES_IMU_ACCEL_GYRO, 0)
                elif what == "freeze":
                    frozen = frozen or last_imu or s
                    msg = codec.encode_imu(replace(frozen, time_s=s.time_s))
                else:
                    frozen, last_imu = None, s
                    msg = codec.encode_imu(s)
                loop.handle(send(msg, t))
            if tlog is not None:
                act = plant.actuators(command_to_pwm(vehicle, commanded))
                if commands:
                    send(codec.encode_actuators(replace(act, time_s=applied_at))[0], t)
                for msg in codec.encode_actuators(act)[1:]:
                    send(msg, t)
                if t + 1e-9 >= next_mocap:
                    next_mocap += mocap_period
                    x = plant.state
                    send(mavlink.MAVLink_att_pos_mocap_message(
                        codec.time_usec(t), [float(c) for c in x[3:7]], float(x[0]), float(x[1]), float(x[2]),
                        [float("nan")] + [0.0] * 20), t)
            clock.observe(t)
            loop.step(t)
            commanded = np.asarray(loop.command, dtype=float).copy()
            commands.append((t, commanded.copy()))
            applied_at = t
            if faults.jets or faults.stuck_joints:  # hil.endpoint.HilEndpoint._command_plant
                x = plant.state
                for sj in faults.stuck_joints:
                    if t + 1e-9 >= sj.t0_s and (sj.unit, sj.joint) not in stuck:
                        angles = np.concatenate([x[lay.alpha], x[lay.beta]])
                        stuck[(sj.unit, sj.joint)] = float(angles[joint_index(vehicle.n_units, sj.unit, sj.joint)])
                plant.set_command(actuator_command(faults, commanded, t, stuck))
            else:
                plant.set_command(commanded)
    finally:
        wall = time.perf_counter() - wall0
        link.close()
        if tlog is not None:
            tlog.close()
    onboard = loop.stats.summary()
    extra = {} if faults.empty else {"detections": detections(faults, onboard.get("fault_events", []))}
    return ClosedLoopResult(truth, commands, {"periods": n}, onboard, {}, wall, tlog_path, None, extra)


# ------------------------------------------------------------------------------------------------
# prove and diagnose


def run_prove(inputs: dict, out: Path) -> dict:
    from ground.prove import run_family_case

    row = run_family_case(inputs["split"], inputs["index"], out, reference=_vehicle(inputs), draws=inputs["draws"])
    return row  # an "error" key (the case raised) becomes the row's status


def run_diagnose(inputs: dict, out: Path) -> dict:
    import numpy as np

    from ground.diagnose import diagnose
    from ground.diagnose.core import NULL_DRAWS
    from ground.diagnose.report import write_json
    from ground.recording import read_recording
    from ground.campaign.spec import file_sha256

    path = inputs["recording"]
    if file_sha256(path) != inputs["sha256"]:
        raise RuntimeError(f"{path} changed since the campaign was planned (its sha256 differs)")
    rec = read_recording(path)
    with np.errstate(all="ignore"):  # a recording far from the model overflows; the report says so
        rep = diagnose(rec, _vehicle(inputs), draws=NULL_DRAWS if inputs["draws"] is None else inputs["draws"]).report
    write_json(rep, out / "report.json")
    findings = rep.get("findings", [])
    hold = rep.get("fit", {}).get("holdout", {})
    return {
        "recording_s": round(float(rec.duration_s), 3),
        "findings": [f["effect"] for f in findings],
        "n_findings": len(findings),
        "first_finding": findings[0]["effect"] if findings else None,
        "first_confidence": float(findings[0]["confidence"]) if findings else None,
        "untestable": [u["effect"] for u in rep.get("untestable", [])],
        "warnings": len(rep.get("warnings", [])),
        "nrmse_before": hold.get("before", {}).get("total"),
        "nrmse_after": hold.get("after", {}).get("total"),
        "diagnose_s": rep.get("elapsed_s"),
    }


RUNNERS = {"missions": run_mission, "prove": run_prove, "diagnose": run_diagnose}
