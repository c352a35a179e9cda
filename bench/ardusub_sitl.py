"""Fly stock ArduSub SITL against jetloop's plant and print what it measured (issue 17 evidence).

    python3 bench/ardusub_sitl.py --ardusub PATH/TO/build/sitl/bin/ardusub \
        --defaults PATH/TO/Tools/autotest/default_params/sub.parm,PATH/TO/Tools/autotest/default_params/sub-6dof.parm

Without `--ardusub` (ArduPilot is not on the package registries; building it takes about 20 min
on 2 cores) it says so and exits 0 without flying: nothing is measured, nothing is claimed.

What it does, all in one process tree it owns:
1. `JsonSitlBackend` (hil/json_sitl.py) with the vehicle (default bluerov2_heavy) on UDP 9002,
   starting at `--depth` m, noise-free (SITL adds its own sensor noise).
2. The ArduSub binary, `--model JSON:127.0.0.1`, the sea-level home ArduSub's autotest uses
   (33.810313,-118.393867,0,185: a home 584 m above sea level made the barometer read -57617 hPa),
   its default parameters (`--defaults`: sub.parm, plus sub-6dof.parm for the heavy frame).
3. pymavlink on tcp:127.0.0.1:5760: waits for the EKF, arms in MANUAL, waits until ArduSub's
   heading estimate has converged (GPS in use, its ATTITUDE yaw within 1 deg of the plant's for
   5 s; `--no-heading-wait` skips this), then STABILIZE and ALT_HOLD with the sticks centred
   (MANUAL_CONTROL at 10 Hz) for `--hold` s, then forward and lateral stick in ALT_HOLD.
4. Prints from the plant's own state (the truth, not ArduSub's estimate): depth and heading
   change from the mode change over the hold, ArduSub's heading minus the plant's, and the
   body-frame displacement during the forward and lateral inputs.
"""

from __future__ import annotations

import argparse
import math
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

HOME = "33.810313,-118.393867,0,185"  # ArduSub autotest's sea-level home (lat, lon, alt m, heading deg)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ardusub", help="path to the ArduSub SITL binary (build/sitl/bin/ardusub)")
    ap.add_argument("--defaults", default=None, help="comma-separated ArduSub default parameter files")
    ap.add_argument("--vehicle", default="bluerov2_heavy")
    ap.add_argument("--jet-neutral", type=float, default=None, metavar="US",
                    help="the vehicle's [pwm] jet_neutral (asr4 behind ArduSub: 1500)")
    ap.add_argument("--depth", type=float, default=2.0, help="start depth of the plant, m")
    ap.add_argument("--hold", type=float, default=60.0, help="seconds of each hold (STABILIZE, ALT_HOLD)")
    ap.add_argument("--port", type=int, default=9002)
    ap.add_argument("--no-heading-wait", dest="heading_wait", action="store_false",
                    help="enter the holds as soon as the EKF has attitude and depth, before its heading has "
                         "converged (how the first runs were flown)")
    ap.add_argument("--workdir", default="/tmp/jetloop_ardusub_sitl", help="SITL's eeprom and logs go here")
    args = ap.parse_args(argv)
    if not args.ardusub:
        print("bench/ardusub_sitl.py: skipped: no ArduSub SITL binary given (--ardusub PATH); "
              "nothing was flown and nothing is measured")
        return 0
    if not os.access(args.ardusub, os.X_OK):
        print(f"bench/ardusub_sitl.py: skipped: {args.ardusub} is not an executable ArduSub binary; nothing was flown")
        return 0
    from pymavlink import mavutil

    from hil.json_sitl import JsonSitlBackend
    from onboard import model
    from onboard.vehicle import load_vehicle

    vehicle = load_vehicle(args.vehicle)
    if args.jet_neutral is not None:
        vehicle = vehicle.with_values({"pwm.jet_neutral": args.jet_neutral})
    backend = JsonSitlBackend(vehicle, depth_m=args.depth)
    stop = threading.Event()

    def serve():
        while not stop.is_set():
            backend.serve("127.0.0.1", args.port, idle_timeout_s=1.0)

    server = threading.Thread(target=serve, daemon=True)
    server.start()
    Path(args.workdir).mkdir(parents=True, exist_ok=True)
    cmd = [args.ardusub, "--model", "JSON:127.0.0.1", "--home", HOME, "-I0", "--speedup", "1", "--wipe"]
    if args.defaults:
        cmd += ["--defaults", args.defaults]
    print("running:", " ".join(cmd), flush=True)
    sitl = subprocess.Popen(cmd, cwd=args.workdir, stdout=open(Path(args.workdir) / "sitl.out", "w"),
                            stderr=subprocess.STDOUT, start_new_session=True)
    try:
        return _fly(args, backend, vehicle, mavutil, model)
    finally:
        os.killpg(sitl.pid, signal.SIGTERM)
        try:
            sitl.wait(10)
        except subprocess.TimeoutExpired:
            os.killpg(sitl.pid, signal.SIGKILL)
        stop.set()
        server.join(5)
        print(f"backend: {backend.frames} frames, {backend.duplicates} repeated, {backend.lost_frames} lost, "
              f"{backend.resets} restarts, {backend.rate_changes} rate changes, {backend.diverged} diverged, "
              f"frame rate {backend.frame_rate_hz} Hz")


def _truth(backend, model):
    """(depth m, heading deg, NED position) of the plant now."""
    x = backend.plant.state
    _, _, yaw = model.quat_to_euler(x[3:7])
    return float(x[2] - backend.vehicle.environment.surface_depth), math.degrees(yaw), x[0:3].copy()


def _wrap(deg: float) -> float:
    """An angle difference in (-180, 180] deg."""
    return ((deg + 180.0) % 360.0) - 180.0


def _param(mav, name: str, timeout_s: float = 5.0) -> float:
    """One ArduSub parameter read over MAVLink (nan if it does not answer)."""
    mav.param_fetch_one(name)
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        m = mav.recv_match(type="PARAM_VALUE", blocking=True, timeout=1)
        if m is not None and m.param_id == name:
            return float(m.param_value)
    return float("nan")


def ekf_gps(mav) -> bool:
    """True once ArduSub's last EKF_STATUS_REPORT says it has an absolute horizontal position (GPS in use)."""
    m = mav.messages.get("EKF_STATUS_REPORT")
    return m is not None and bool(m.flags & 0x10)


def _fly(args, backend, vehicle, mavutil, model) -> int:
    mav = None
    deadline = time.monotonic() + 120
    while mav is None and time.monotonic() < deadline:
        try:
            mav = mavutil.mavlink_connection("tcp:127.0.0.1:5760", source_system=255)
        except OSError:
            time.sleep(1)
    if mav is None or mav.wait_heartbeat(timeout=60) is None:
        print("FAILED: no heartbeat from ArduSub on tcp:127.0.0.1:5760 within 120 s")
        return 1
    print(f"heartbeat from system {mav.target_system}; waiting for the EKF", flush=True)
    mav.mav.request_data_stream_send(mav.target_system, mav.target_component, mavutil.mavlink.MAV_DATA_STREAM_ALL, 10, 1)
    t_end = time.monotonic() + 180
    while time.monotonic() < t_end:
        m = mav.recv_match(type="EKF_STATUS_REPORT", blocking=True, timeout=2)
        if m is not None and (m.flags & 0x25) == 0x25:  # attitude, vertical velocity, vertical position
            break
    else:
        print("FAILED: the EKF did not report attitude and vertical position within 180 s")
        return 1
    print(f"EKF ready at plant time {backend.time_s:.1f} s", flush=True)
    stick = {"x": 0, "y": 0, "z": 500, "r": 0}
    sending = threading.Event()

    def pilot():
        while not sending.is_set():
            mav.mav.manual_control_send(mav.target_system, stick["x"], stick["y"], stick["z"], stick["r"], 0)
            time.sleep(0.1)

    threading.Thread(target=pilot, daemon=True).start()

    def set_mode(name):
        mav.set_mode(mav.mode_mapping()[name])
        t0 = time.monotonic()
        while time.monotonic() - t0 < 10:
            hb = mav.recv_match(type="HEARTBEAT", blocking=True, timeout=1)
            if hb is not None and mav.flightmode == name:
                return True
        return False

    ok = set_mode("MANUAL")
    forced = False
    for attempt in range(2):
        mav.mav.command_long_send(mav.target_system, mav.target_component,
                                  mavutil.mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 21196 if attempt else 0,
                                  0, 0, 0, 0, 0)
        t0 = time.monotonic()
        while time.monotonic() - t0 < 10 and not mav.motors_armed():
            mav.recv_match(type="HEARTBEAT", blocking=True, timeout=1)
        if mav.motors_armed():
            forced = bool(attempt)
            break
    print(f"MANUAL: {'ok' if ok else 'not confirmed'}; armed: {mav.motors_armed()}"
          f"{' (forced: the arming checks refused)' if forced else ''}", flush=True)
    if not mav.motors_armed():
        print("FAILED: ArduSub did not arm")
        return 1
    if args.heading_wait:
        # SITL gives ArduSub a GPS; until its fix the compass declination is COMPASS_DEC (0), so the
        # EKF's first heading is the magnetic one, off the true heading by the home's declination
        # (11.5 deg here); armed, the EKF aligns its yaw in flight and converges over about a minute
        # once the GPS is in use. A heading hold entered before then holds that wrong heading and
        # turns the vehicle as the estimate converges. MANUAL with the sticks centred sends 1500 us,
        # inside the T200's dead band: the wait pushes nothing (the vehicle sinks, 0.98 N heavy).
        t_end = time.monotonic() + 300
        agree_since, first_gap, t_print = None, None, 0.0
        while time.monotonic() < t_end:
            m = mav.recv_match(type=["EKF_STATUS_REPORT", "ATTITUDE"], blocking=True, timeout=2)
            if m is None or m.get_type() != "ATTITUDE":
                continue
            gap = _wrap(math.degrees(m.yaw) - _truth(backend, model)[1])
            first_gap = gap if first_gap is None else first_gap
            if backend.time_s >= t_print:
                print(f"  plant time {backend.time_s:5.1f} s: ArduSub's heading minus the plant's {gap:+6.2f} deg, "
                      f"GPS in use: {ekf_gps(mav)}", flush=True)
                t_print = backend.time_s + 10.0
            if abs(gap) < 1.0 and ekf_gps(mav):
                agree_since = agree_since if agree_since is not None else backend.time_s
                if backend.time_s - agree_since >= 5.0:
                    break
            else:
                agree_since = None
        else:
            print("FAILED: ArduSub's heading did not come within 1 deg of the plant's with the GPS in use within 300 s")
            return 1
        print(f"ArduSub's heading within 1 deg of the plant's for 5 s, GPS in use, at plant time "
              f"{backend.time_s:.1f} s (at arming it was {first_gap:+.2f} deg off; COMPASS_DEC now "
              f"{math.degrees(_param(mav, 'COMPASS_DEC')):.2f} deg)", flush=True)
    results = {}
    for mode in ("STABILIZE", "ALT_HOLD"):
        ok = set_mode(mode)
        times, depths, headings, gaps = [], [], [], []
        t0 = backend.time_s  # plant (simulated) time: lock-step may run slower than the wall clock
        while backend.time_s - t0 < args.hold:
            m = mav.recv_match(blocking=True, timeout=0.1)
            d, h, _ = _truth(backend, model)
            if m is not None and m.get_type() == "ATTITUDE":
                gaps.append(_wrap(math.degrees(m.yaw) - h))
            times.append(backend.time_s - t0)
            depths.append(d)
            headings.append(h)
        d0, h0 = depths[0], headings[0]  # at the mode change: what ALT_HOLD and the heading hold keep
        dd = [d - d0 for d in depths]
        dh = [((h - h0 + 180) % 360) - 180 for h in headings]
        late = [i for i, t in enumerate(times) if t >= 10.0]  # after 10 s of settling
        results[mode] = (max(map(abs, dd)), max(map(abs, dh)))
        print(f"{mode} ({'ok' if ok else 'mode not confirmed'}), sticks centred for {args.hold:.0f} s of plant time: "
              f"depth {min(depths):.3f}..{max(depths):.3f} m, largest change from the {d0:.3f} m at entry "
              f"{max(map(abs, dd)):.3f} m (after 10 s: {max(abs(dd[i]) for i in late):.3f} m); heading: largest "
              f"change from entry {max(map(abs, dh)):.2f} deg (after 10 s: {max(abs(dh[i]) for i in late):.2f} deg), "
              f"{dh[-1]:+.2f} deg at the end; ArduSub's heading minus the plant's: {gaps[0] if gaps else float('nan'):+.2f} deg "
              f"at entry, {max(map(abs, gaps)) if gaps else float('nan'):.2f} deg at most", flush=True)
    for name, key, value in (("forward", "x", 500), ("lateral", "y", 500)):
        _, h0, p0 = _truth(backend, model)
        stick[key] = value
        t0 = backend.time_s
        while backend.time_s - t0 < 5.0:
            mav.recv_match(blocking=True, timeout=0.1)
        stick[key] = 0
        _, _, p1 = _truth(backend, model)
        dn, de = p1[0] - p0[0], p1[1] - p0[1]
        c, s = math.cos(math.radians(h0)), math.sin(math.radians(h0))
        fwd, right = c * dn + s * de, -s * dn + c * de
        print(f"ALT_HOLD, {name} stick half way for 5 s: moved {fwd:+.3f} m forward, {right:+.3f} m right "
              f"(body axes at the start)", flush=True)
        t0 = backend.time_s
        while backend.time_s - t0 < 3.0:
            mav.recv_match(blocking=True, timeout=0.1)
    sending.set()
    mav.arducopter_disarm()
    return 0


if __name__ == "__main__":
    sys.exit(main())
