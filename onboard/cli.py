"""`jetloop onboard`: the onboard loop on a MAVLink link, alone (a real autopilot, a HIL plant, a replay).

    jetloop onboard --link udpout:127.0.0.1:14560 [--ground udpout:127.0.0.1:14550] [--vehicle V.toml]
                    [--lockstep | --realtime] [--output hil|pwm] [--allocator qp|baseline]
                    [--no-compensation] [--no-yaw-preview] [--rate HZ] [--duration S] [--key KEYFILE] [--ground-system ID]...
                    [--peer HOST:PORT] [--ground-peer HOST:PORT] [--autopilot SYS[:COMP]]
                    [--identity auto|vehicle|companion] [--params FILE]

`--lockstep` runs on the vehicle clock of the sensor stream and answers every SYSTEM_TIME frame
marker (pair it with `jetloop hil --lockstep`); `--realtime` (default) ticks on the wall clock,
as against a real ArduSub autopilot. Telemetry goes to `--ground` when given, else back on `--link`.

Security (onboard.signing.CommandGate): with `--key`, commands and setpoints must be MAVLink 2
signed with that key; only source systems given by `--ground-system` (default 255, QGroundControl's
and MAVProxy's) may command, and only this vehicle (system 1) or everyone (0) may be addressed;
setpoints outside the vehicle file's [envelope] are refused. With `--key` every inbound message
on either link must be signed (the autopilot or plant too: `jetloop hil --key`). Sensor data and
actuator feedback count only from the autopilot on `--link` (`--autopilot SYS[:COMP]`, else the
first component 1 sending sensor data there), never from `--ground`. A udpin link answers only its peer:
the first sender of valid (with `--key`, signed) MAVLink, until it is silent for 5 s, or the one
`--peer` / `--ground-peer` fixes; other senders are counted, never answered. Every refusal is
counted in the NAMED_VALUE_FLOAT telemetry and in the summary printed at exit, every link's
counts included. Nothing listens on a default address: `--link` is required and both links bind
only the host they name (udpout to 127.0.0.1 binds 127.0.0.1).

Ground stations (onboard.microservices): as the vehicle's controller the loop is component 1,
MAV_TYPE_SUBMARINE, to the ground; beside a flight stack (ArduPilot, PX4 heartbeats on --link) it
is its companion, component 191 (`--identity` fixes either). MAVLink parameters (onboard.params)
persist to `--params FILE` (default: the vehicle file with the suffix .params; asr4.params in the
working directory for the reference vehicle) and are read from it at start.
"""

from __future__ import annotations

import sys
import time


def configure(parser) -> None:
    parser.add_argument("--link", required=True, metavar="CONN",
                        help="autopilot / plant link: udpin:HOST:PORT, udpout:HOST:PORT, /dev/ttyXXX:BAUD, "
                             "or tlog:PATH to replay a recording (with --lockstep)")
    parser.add_argument("--ground", default=None, metavar="CONN", help="separate telemetry link to the ground station")
    parser.add_argument("--vehicle", default=None, help="vehicle TOML (default: the reference vehicle asr4)")
    mode = parser.add_mutually_exclusive_group()
    mode.add_argument("--lockstep", action="store_true", help="run on the sensor stream's vehicle clock (HIL lock-step, replay)")
    mode.add_argument("--realtime", action="store_true", help="run on the wall clock (default)")
    parser.add_argument("--output", choices=("hil", "pwm"), default="hil",
                        help="hil: HIL_ACTUATOR_CONTROLS + SERVO_OUTPUT_RAW (default); pwm: SERVO_OUTPUT_RAW only")
    parser.add_argument("--allocator", choices=("qp", "baseline"), default="qp")
    parser.add_argument("--no-compensation", action="store_true", help="turn the seed-004 transient compensation off")
    parser.add_argument("--no-yaw-preview", action="store_true",
                        help="compensate without cancelling the azimuths' yaw reaction ahead (onboard.compensation.YawPreview)")
    parser.add_argument("--estimator", choices=("filterpy", "compiled"), default="filterpy",
                        help="EKF backend: filterpy (default) or the same equations compiled with numba")
    parser.add_argument("--key", default=None, metavar="KEYFILE",
                        help="MAVLink 2 signing key (32 raw bytes or 64 hex digits): unsigned, forged or "
                             "replayed commands are refused and counted")
    parser.add_argument("--ground-system", type=int, action="append", default=None, metavar="ID",
                        help="source system id allowed to command (repeatable; default 255, QGroundControl/MAVProxy); "
                             "commands and setpoints from any other system are ignored and counted")
    parser.add_argument("--peer", default=None, metavar="HOST:PORT",
                        help="with --link udpin: the only peer read and answered (default: the first that speaks "
                             "valid MAVLink, until silent for 5 s)")
    parser.add_argument("--ground-peer", default=None, metavar="HOST:PORT", help="the same for --ground udpin")
    parser.add_argument("--autopilot", default=None, metavar="SYS[:COMP]",
                        help="the only source of sensor data on --link (default: the first system sending it there)")
    parser.add_argument("--identity", choices=("auto", "vehicle", "companion"), default="auto",
                        help="to the ground: component 1 as the vehicle, 191 as a flight stack's companion "
                             "(default auto: companion once --link shows an ArduPilot/PX4 heartbeat)")
    parser.add_argument("--params", default=None, metavar="FILE",
                        help="MAVLink parameter file, read at start and written on each PARAM_SET "
                             "(default: beside the vehicle file, V.params)")
    parser.add_argument("--rate", type=float, default=None, metavar="HZ", help="control rate (default: the IMU rate)")
    parser.add_argument("--duration", type=float, default=None, metavar="S", help="stop after S seconds of loop time")
    parser.add_argument("--idle-exit", type=float, default=None, metavar="S",
                        help="stop when nothing arrives for S seconds (default: 10 in lock-step, never in real time)")


def run(args) -> int:
    from onboard.link import Link, LinkError
    from onboard.params import ParameterFileError, default_path
    from onboard.loop import LoopConfig, OnboardLoop, VehicleClock, WallClock
    from onboard.signing import GCS_SYSTEMS, SigningError, load_key
    from onboard.vehicle import VehicleFileError, load_vehicle, require_jets

    try:
        vehicle = load_vehicle(args.vehicle)
        require_jets(vehicle, "onboard")
        key = load_key(args.key) if args.key else None
        ground_systems = tuple(args.ground_system) if args.ground_system else GCS_SYSTEMS
        for sysid in ground_systems:
            if not 1 <= sysid <= 255:
                raise SigningError(f"--ground-system {sysid}: expected a MAVLink system id 1..255")
        autopilot = _autopilot(args.autopilot, ground_systems) if args.autopilot else None
    except (VehicleFileError, SigningError) as exc:
        print(f"jetloop onboard: {exc}", file=sys.stderr)
        return 2
    rate = args.rate if args.rate is not None else vehicle.sensors.imu_rate
    if not (rate > 0):
        print(f"jetloop onboard: --rate must be > 0 Hz, got {args.rate}", file=sys.stderr)
        return 2
    if args.ground_peer and not args.ground:
        print("jetloop onboard: --ground-peer needs --ground udpin:HOST:PORT", file=sys.stderr)
        return 2
    link = ground = None
    try:
        link = Link(args.link, source_system=1, source_component=191, peer=args.peer, signing_key=key)
        if link.endpoint.kind == "tlog":
            _check_recording(link)
        ground = Link(args.ground, source_system=1, source_component=191, peer=args.ground_peer,
                      signing_key=key) if args.ground else None
    except LinkError as exc:
        if link is not None:
            link.close()
        print(f"jetloop onboard: {exc}", file=sys.stderr)
        return 2
    config = LoopConfig(control_rate_hz=rate, output=args.output, allocator=args.allocator,
                        compensation=not args.no_compensation, yaw_preview=not args.no_yaw_preview,
                        estimator_backend=args.estimator,
                        signing_key=key, ground_systems=ground_systems, autopilot=autopilot,
                        identity=args.identity, parameter_file=str(args.params or default_path(args.vehicle)))
    clock = VehicleClock() if args.lockstep else WallClock()
    try:
        loop = OnboardLoop(vehicle, link, clock, config, ground=ground)
    except ParameterFileError as exc:
        link.close()
        if ground is not None:
            ground.close()
        print(f"jetloop onboard: {exc}", file=sys.stderr)
        return 2
    print(f"jetloop onboard: {vehicle.name} on {args.link} ({'lock-step' if args.lockstep else 'real time'}, "
          f"{rate:g} Hz, {args.allocator}{'' if config.compensation else ', no compensation'}"
          f"{', commands must be signed' if key else ''})", flush=True)
    if loop.yaw_preview_off:
        print(f"jetloop onboard: yaw preview off for {vehicle.name}, the compensation runs without it: "
              f"{loop.yaw_preview_off}", flush=True)
    t0 = time.monotonic()
    idle = args.idle_exit if args.idle_exit is not None else (10.0 if args.lockstep else None)
    why = "interrupted"
    try:
        if args.duration is not None and not args.lockstep:
            why = loop.run(stop=lambda: time.monotonic() - t0 >= args.duration, idle_exit_s=idle)
        else:
            why = loop.run(duration_s=args.duration, idle_exit_s=idle)
    except KeyboardInterrupt:
        pass
    finally:
        for line in summary_lines(why, loop, loop.links()):
            print(line, flush=True)
        link.close()
        if ground is not None:
            ground.close()
    if link.endpoint.kind == "tlog" and link.packets_in == 0:
        print(f"jetloop onboard: {args.link}: no MAVLink packet could be read from the recording", file=sys.stderr)
        return 1
    return 0


def summary_lines(why: str, loop, links: dict) -> list[str]:
    """What `jetloop onboard` prints at exit: the run, every link's counts, the security counts."""
    s = loop.stats.summary()
    errors = {name: lk.bad_packets + lk.unknown_packets for name, lk in links.items()}
    lines = [f"jetloop onboard: {why}; {s['steps']} steps, step median {s['step_median_ms']:.2f} ms, "
             f"p99 {s['step_p99_ms']:.2f} ms, failsafes {s['failsafe_entries']}, "
             f"rejected inputs {s['rejected_inputs']}, stamps held {s['stamps_held']}, "
             f"link errors {sum(errors.values())} ({', '.join(f'{k} {v}' for k, v in errors.items())})"]
    for name, lk in links.items():
        lines.append(f"jetloop onboard: {name} {lk.connection}: "
                     + ", ".join(f"{k} {v}" for k, v in lk.stats().items()))
    lines.append("jetloop onboard: security " + ", ".join(f"{k} {v}" for k, v in loop.stats.security.summary().items()))
    return lines


def _autopilot(text: str, ground_systems) -> tuple:
    """`SYS` or `SYS:COMP` -> (system, component; 0 = any), a SigningError saying what was expected."""
    from onboard.signing import SigningError

    sys_, _, comp = str(text).partition(":")
    comp = comp or "0"
    if not (sys_.isdigit() and comp.isdigit() and 1 <= int(sys_) <= 255 and 0 <= int(comp) <= 255):
        raise SigningError(f"--autopilot {text!r}: expected SYS[:COMP], system 1..255, component 0..255")
    if int(sys_) in ground_systems:
        raise SigningError(f"--autopilot {text!r}: system {sys_} is a ground system (--ground-system)")
    return int(sys_), int(comp)


def _check_recording(link) -> None:
    """A `tlog:` link must hold MAVLink: an empty file, or one with no good packet in its first
    1 MB, is a LinkError at once (it ran to the idle timeout and exited 0 before). The probe is a
    second replay of the same file, so the link itself starts at the beginning untouched."""
    from onboard.link import Link, LinkError

    size = len(link._io.data)
    if not size:
        raise LinkError(f"link {link.connection}: the recording is empty")
    limit = 1 << 20
    with Link(link.connection) as probe:
        while probe.packets_in == 0 and probe._io.pos < min(size, limit):
            probe.recv(0.0)
        if probe.packets_in == 0:
            raise LinkError(f"link {link.connection}: no MAVLink packet in its first {min(size, limit)} bytes "
                            "(not a .tlog recording?)")
