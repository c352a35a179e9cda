"""`jetloop hil`: the plant alone, as a MAVLink sensor endpoint or as SITL JSON physics.

    jetloop hil --link udpin:127.0.0.1:14560 [--lockstep | --realtime] [--out REC.tlog] [--mission demo]
    jetloop hil --json-sitl [--link udpin:127.0.0.1:9002]        (ArduSub SITL: --model JSON:127.0.0.1)

MAVLink mode plays the autopilot's sensor side for a controller (`jetloop onboard`, or your own):
HEARTBEAT, HIGHRES_IMU, SCALED_PRESSURE2, ATTITUDE, ESC telemetry and a SYSTEM_TIME frame marker
out; HIL_ACTUATOR_CONTROLS (or, with `--actuators pwm`, SERVO_OUTPUT_RAW) in. `--lockstep`
advances the plant only when the controller has answered each frame.

Fault injection (hil.faults, issue #7): --loss, --delay, --jitter, --duplicate, --reorder on the
link; --dead-jet, --weak-jet, --stuck-joint on the actuators; --imu-freeze, --imu-nan, --depth-jump
on the sensors. E.g. `jetloop hil --loss 0.2 --dead-jet 2@5 --out hil.tlog`: each fault's start is
marked in the recording (STATUSTEXT "INJECT ..." from component 250, never sent).
"""

from __future__ import annotations

import sys
import time


def configure(parser) -> None:
    parser.add_argument("--link", default=None, metavar="CONN",
                        help="udpin:HOST:PORT, udpout:HOST:PORT or /dev/ttyXXX:BAUD "
                             "(default udpin:127.0.0.1:14560; with --json-sitl udpin:127.0.0.1:9002)")
    mode = parser.add_mutually_exclusive_group()
    mode.add_argument("--lockstep", action="store_true", help="advance only when the controller answers (default)")
    mode.add_argument("--realtime", action="store_true", help="follow the wall clock")
    parser.add_argument("--json-sitl", action="store_true", help="speak ArduPilot's SITL JSON physics interface instead")
    parser.add_argument("--out", default=None, metavar="REC.tlog", help="record everything sent and received")
    parser.add_argument("--vehicle", default=None,
                        help="vehicle TOML or a packaged vehicle's name: asr4 (default), bluerov2_heavy")
    parser.add_argument("--jet-neutral", type=float, default=None, metavar="US",
                        help="set the vehicle's [pwm] jet_neutral: PWM at which a one-way jet stops (1500 for "
                             "ArduSub's two-way motor outputs)")
    parser.add_argument("--seed", type=int, default=0, help="sensor noise seed (default 0)")
    parser.add_argument("--depth", type=float, default=0.0, help="initial depth in m (default 0: at the surface)")
    parser.add_argument("--rate", type=float, default=None, metavar="HZ", help="frame rate (default: the IMU rate)")
    parser.add_argument("--actuators", choices=("hil", "pwm"), default="hil",
                        help="apply HIL_ACTUATOR_CONTROLS (default) or SERVO_OUTPUT_RAW PWM")
    parser.add_argument("--mission", choices=("none", "demo"), default="none",
                        help="inject the demo mission's ground setpoints (arm, dive, yaw, forward, surface)")
    parser.add_argument("--duration", type=float, default=None, metavar="S", help="stop after S s of vehicle time")
    parser.add_argument("--peer", default=None, metavar="HOST:PORT",
                        help="with --link udpin: the only controller read and answered (default: the first that "
                             "speaks valid MAVLink, until silent for 5 s)")
    parser.add_argument("--key", default=None, metavar="KEYFILE",
                        help="sign everything sent with this MAVLink 2 key (32 raw bytes or 64 hex digits), as an "
                             "autopilot with signing does: for `jetloop onboard --key`, which refuses unsigned input")
    parser.add_argument("--wait", type=float, default=300.0, metavar="S",
                        help="how long to wait for a controller, and in lock-step for each answer (default 300 s)")
    from hil.faults import add_fault_arguments

    add_fault_arguments(parser)


def run(args) -> int:
    from onboard.link import Link, LinkError
    from onboard.vehicle import VehicleFileError, load_vehicle

    from onboard.signing import SigningError, load_key

    try:
        vehicle = load_vehicle(args.vehicle)
        if getattr(args, "jet_neutral", None) is not None:
            if not vehicle.n_jets:  # a two-way thruster's neutral is its curve's dead band
                raise VehicleFileError(f"--jet-neutral: {vehicle.name} has no water-jets (its fixed thrusters "
                                       "stop in their thrust curve's dead band)")
            vehicle = vehicle.with_values({"pwm.jet_neutral": args.jet_neutral})
        key = load_key(args.key) if getattr(args, "key", None) else None
    except (VehicleFileError, SigningError) as exc:
        print(f"jetloop hil: {exc}", file=sys.stderr)
        return 2
    from hil.faults import FaultPlanError, plan_from_args

    try:
        faults = plan_from_args(args, vehicle.n_units)
    except FaultPlanError as exc:
        print(f"jetloop hil: {exc}", file=sys.stderr)
        return 2
    if args.json_sitl:
        if not faults.empty or key is not None:
            print("jetloop hil: fault injection and --key work on the MAVLink endpoint, not with --json-sitl",
                  file=sys.stderr)
            return 2
        return _json_sitl(args, vehicle)
    from hil.endpoint import EndpointError, HilEndpoint
    from hil.plant import Plant
    from hil.tlog import TlogWriter

    rate = args.rate if args.rate is not None else vehicle.sensors.imu_rate
    if not rate > 0:
        print(f"jetloop hil: --rate must be > 0 Hz, got {args.rate}", file=sys.stderr)
        return 2
    conn = args.link or "udpin:127.0.0.1:14560"
    try:
        link = Link(conn, source_system=1, source_component=1, peer=getattr(args, "peer", None))
    except LinkError as exc:
        print(f"jetloop hil: {exc}", file=sys.stderr)
        return 2
    setpoints = []
    if args.mission == "demo":
        from hil.demo import reference_mission

        setpoints = reference_mission().setpoints()
    try:
        tlog = TlogWriter(args.out, autoflush=True) if args.out else None
    except OSError as exc:
        print(f"jetloop hil: cannot write {args.out}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    plant = Plant(vehicle, seed=args.seed, depth_m=args.depth)
    ep = HilEndpoint(vehicle, link, plant, control_period_s=1.0 / rate, lockstep=not args.realtime,
                     actuators=args.actuators, setpoints=setpoints, tlog=tlog, seed=args.seed, history=False,
                     faults=faults, give_up_s=max(args.wait, 10.0),  # a controller's first step may compile
                     signing_key=key)
    print(f"jetloop hil: {vehicle.name} on {conn}, {'real time' if args.realtime else 'lock-step'}, "
          f"{rate:g} Hz; waiting for a controller", flush=True)
    if not faults.empty:
        from hil.faults import injection_events

        print("jetloop hil: faults: " + "; ".join(f"{t:g} s {text[len('INJECT '):]}"
                                                 for t, text in injection_events(faults)), flush=True)
    code = 0
    t0 = time.monotonic()
    try:
        ep.start(wait_s=args.wait)
        print("jetloop hil: controller connected", flush=True)
        n = None if args.duration is None else int(round(args.duration * rate))
        while n is None or ep.k < n:
            ep.step()
    except EndpointError as exc:
        print(f"jetloop hil: {exc}", file=sys.stderr)
        code = 1
    except KeyboardInterrupt:
        pass
    finally:
        if tlog is not None:
            tlog.close()
        wall = time.monotonic() - t0
        s = ep.stats
        print(f"jetloop hil: {ep.time_s:.2f} s of vehicle time in {wall:.1f} s, {s.commands_applied} commands, "
              f"{s.resends} resends, link {ep.link.stats()}" + (f", recorded {args.out}" if args.out else ""), flush=True)
        link.close()
    return code


def _json_sitl(args, vehicle) -> int:
    from hil.json_sitl import JsonSitlBackend
    from onboard.link import LinkError, parse_connection

    if args.out:
        print("jetloop hil: --out is not available with --json-sitl (ArduPilot SITL logs the flight itself)",
              file=sys.stderr)
        return 2
    try:
        ep = parse_connection(args.link or "udpin:127.0.0.1:9002")
    except LinkError as exc:
        print(f"jetloop hil: {exc}", file=sys.stderr)
        return 2
    if ep.kind != "udpin":
        print("jetloop hil: --json-sitl listens for SITL's servo packets: use --link udpin:HOST:PORT", file=sys.stderr)
        return 2
    backend = JsonSitlBackend(vehicle, seed=args.seed, depth_m=args.depth)
    heavy = len(vehicle.fixed) == 8  # ArduSub's default frame drives six thrusters, the heavy frame eight
    print(f"jetloop hil: SITL JSON physics for {vehicle.name} on udp {ep.host}:{ep.port} (start ArduSub SITL "
          f"with --model JSON:127.0.0.1 -l 33.810313,-118.393867,0,185{' -f vectored_6dof' if heavy else ''}: "
          f"a sea-level home{', the eight-thruster heavy frame' if heavy else ''})", flush=True)
    try:
        backend.serve(ep.host, ep.port, duration_s=args.duration)
    except OSError as exc:
        print(f"jetloop hil: cannot listen on {ep.host}:{ep.port}: {exc.strerror or exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        pass
    print(f"jetloop hil: {backend.frames} frames, {backend.duplicates} repeated, {backend.lost_frames} lost, "
          f"{backend.resets} restarts, {backend.bad_packets} bad packets", flush=True)
    return 0
