"""`jetloop sim`: an open-loop run of a commands CSV through the plant, recorded as a .tlog.

    jetloop sim --vehicle V.toml --commands CMDS.csv --out REC.tlog [--truth TRUTH.csv]
                [--seed S] [--depth Z0] [--dt DT]

CMDS.csv has the header `t,pwm1,...,pwm12` (at least the channels of the vehicle's `[pwm]`
table; pwm13..pwm16 may be added): time in seconds, PWM in microseconds, each row held until
the next. Blank lines and lines starting with `#` are skipped. The run starts at vehicle time 0
(at rest, level, at depth Z0, joints at the first row's angles; the first row is held from 0 if
its time is later) and ends at the last row's time. A row at time t applies from the first
integration step at or after t (spec/vehicle-model.md section 6), and its SERVO_OUTPUT_RAW is
stamped with that step's time.

The recording (spec/recording.md section 1): HEARTBEAT at 1 Hz; HIGHRES_IMU, SCALED_PRESSURE2
and ATTITUDE at the vehicle's sensor rates; SERVO_OUTPUT_RAW and ESC_TELEMETRY_1_TO_4 (rpm) at
every row and every 0.1 s while a row is held. Messages are in vehicle-time order; each tlog
timestamp is 2026-01-01T00:00:00Z + vehicle time, so a seed gives the same file byte for byte.
"""

from __future__ import annotations

import math
import re
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from onboard import mavlink_codec as codec
from onboard.pwm import N_CHANNELS, pwm_to_command
from onboard.vehicle import Vehicle, VehicleFileError, load_vehicle

from .plant import Plant
from .tlog import FIXED_EPOCH_US, TlogWriter
from onboard.files import read_text_bounded

DEMO_COMMANDS = Path(__file__).resolve().parent.parent / "onboard" / "data" / "demo_commands.csv"
PWM_MIN_US = 800
PWM_MAX_US = 2200
ACTUATOR_HOLD_PERIOD_S = 0.1  # SERVO_OUTPUT_RAW at least at 10 Hz while a row is held
HEARTBEAT_PERIOD_S = 1.0
TRUTH_HEADER = "t,x,y,z,roll,pitch,yaw,u,v,w,p,q,r"
PROGRESS_AFTER_S = 2.0  # wall seconds before progress lines start, and between them



class CommandsFileError(ValueError):
    """A commands CSV that cannot be used; the message is `FILE:LINE: what was expected`."""

    def __init__(self, source: str, line: int | None, message: str):
        self.source, self.line = source, line
        super().__init__(f"{source}:{line}: {message}" if line else f"{source}: {message}")


@dataclass(frozen=True)
class CommandSchedule:
    """PWM rows of a commands CSV, each held from its time until the next row's."""

    source: str
    times_s: tuple  # strictly increasing, >= 0
    pwm_us: tuple  # per row: 16 channels (channel c at index c - 1), 0 where the file has no column
    lines: tuple  # line number of each row in the file (1-based)

    @property
    def duration_s(self) -> float:
        return self.times_s[-1]


# --- the commands file (pure) -------------------------------------------------------------------

PLAIN_NUMBER = re.compile(r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?|[+-]?(?:nan|inf)", re.I)
MAX_COMMAND_TIME_S = 86_400.0  # a day of vehicle time: a row at t = 1e300 must not mean "run forever"


def parse_commands(text: str, source: str = "<string>", channels=range(1, 13)) -> CommandSchedule:
    """Parse a commands CSV; `channels` are the PWM columns that must be present.

    Raises CommandsFileError naming `source`, the line and what was expected.
    """
    rows = [
        (i, line) for i, line in enumerate(text.splitlines(), start=1)
        if line.strip() and not line.lstrip().startswith("#")
    ]
    needed = ", ".join(["t"] + [f"pwm{c}" for c in channels])
    if not rows:
        raise CommandsFileError(source, None, f"empty file: expected a header line with columns {needed}")
    head_line, head = rows[0]
    names = [n.strip() for n in head.split(",")]
    allowed = {"t", *(f"pwm{c}" for c in range(1, N_CHANNELS + 1))}
    for n in names:
        if n not in allowed:
            raise CommandsFileError(
                source, head_line, f"unknown column {n!r} in the header: expected {needed} (pwm13..pwm16 optional)"
            )
        if names.count(n) > 1:
            raise CommandsFileError(source, head_line, f"column {n!r} appears twice in the header")
    for n in ["t"] + [f"pwm{c}" for c in channels]:
        if n not in names:
            raise CommandsFileError(source, head_line, f"missing column {n!r}: the header must have {needed}")
    if len(rows) < 2:
        raise CommandsFileError(source, head_line, "no command rows after the header")
    col_t = names.index("t")
    col_ch = [(i, int(n[3:])) for i, n in enumerate(names) if n != "t"]
    times, pwms, lines = [], [], []
    for line_no, line in rows[1:]:
        values = [v.strip() for v in line.split(",")]
        if len(values) != len(names):
            raise CommandsFileError(
                source, line_no, f"expected {len(names)} values ({', '.join(names)}), got {len(values)}"
            )
        nums = []
        for name, v in zip(names, values):
            try:  # a plain decimal number: Python's float() also reads "1_0" as 10 and Arabic-Indic digits
                x = float(v) if PLAIN_NUMBER.fullmatch(v) else float("invalid")
            except ValueError:
                shown = repr(v) if len(v) <= 40 else repr(v[:36]) + "..."
                raise CommandsFileError(source, line_no, f"column {name}: {shown} is not a number") from None
            if not math.isfinite(x):
                raise CommandsFileError(source, line_no, f"column {name}: {v!r} is not a finite number")
            nums.append(x)
        t = nums[col_t]
        if not 0 <= t <= MAX_COMMAND_TIME_S:
            raise CommandsFileError(source, line_no, f"time t = {t} s: expected 0 <= t <= {MAX_COMMAND_TIME_S:g} s "
                                                     f"(the simulation runs until the last row)")
        if times and t <= times[-1]:
            raise CommandsFileError(
                source, line_no,
                f"time t = {t} s does not increase (previous row, line {lines[-1]}: t = {times[-1]} s)",
            )
        row = [0] * N_CHANNELS
        for i, ch in col_ch:
            p = nums[i]
            if not PWM_MIN_US <= p <= PWM_MAX_US:
                raise CommandsFileError(
                    source, line_no, f"column pwm{ch}: {values[i]} us is outside {PWM_MIN_US}..{PWM_MAX_US} us"
                )
            row[ch - 1] = int(round(p))
        times.append(t)
        pwms.append(tuple(row))
        lines.append(line_no)
    if times[-1] <= 0:
        raise CommandsFileError(
            source, lines[-1], "the run lasts until the last row's time, which must be > 0 s"
        )
    return CommandSchedule(source, tuple(times), tuple(pwms), tuple(lines))


def vehicle_channels(v: Vehicle) -> list[int]:
    return sorted({*v.pwm.jet_channels, *v.pwm.azimuth_channels, *v.pwm.elevation_channels})


MAX_COMMANDS_BYTES = 512_000_000  # a commands CSV of a day at 1 kHz is ~100 MB


def read_commands(path: str | Path, v: Vehicle) -> CommandSchedule:
    """Read and parse a commands CSV for vehicle `v` (its `[pwm]` channels are required)."""
    try:
        text = read_text_bounded(path, MAX_COMMANDS_BYTES)
    except (OSError, UnicodeDecodeError) as exc:
        reason = getattr(exc, "strerror", None) or exc
        raise CommandsFileError(str(path), None, f"cannot read commands file: {reason}") from None
    return parse_commands(text, str(path), vehicle_channels(v))


# --- the open-loop run --------------------------------------------------------------------------

@dataclass(frozen=True)
class Chunk:
    """What one stretch of the run produced, up to vehicle time `time_s` inclusive."""

    time_s: float
    messages: list  # (vehicle time_us, pymavlink message), in time order
    truth: list  # TruthSample at the IMU instants


@dataclass(frozen=True)
class Event:
    row: int | None = None  # index of the schedule row applied at this step
    actuators: bool = False  # write SERVO_OUTPUT_RAW + ESC telemetry
    heartbeat: bool = False


def event_steps(schedule: CommandSchedule, dt_s: float) -> dict:
    """Integration steps where something happens: {step: Event}, up to the last row's step.

    Row i is applied at the first step at or after its time (spec 6); while a row is held the
    actuators are reported every `ACTUATOR_HOLD_PERIOD_S` after it (rounded down to whole steps,
    so at least that often); HEARTBEAT at every whole `HEARTBEAT_PERIOD_S` (nearest step).
    Raises CommandsFileError if two rows fall on one step.
    """
    step_of = [int(math.ceil(t / dt_s - 1e-9)) for t in schedule.times_s]
    for i in range(1, len(step_of)):
        if step_of[i] == step_of[i - 1]:
            raise CommandsFileError(
                schedule.source, schedule.lines[i],
                f"rows at t = {schedule.times_s[i - 1]} s and t = {schedule.times_s[i]} s fall on the "
                f"same integration step (dt = {dt_s} s): space them at least one step apart",
            )
    starts = list(zip(step_of, range(len(step_of))))
    if step_of[0] > 0:
        starts.insert(0, (0, 0))  # the first row is held from vehicle time 0
    end = step_of[-1]
    hold = max(1, int(math.floor(ACTUATOR_HOLD_PERIOD_S / dt_s + 1e-9)))
    events: dict = {}
    for k, (start, row) in enumerate(starts):
        events[start] = Event(row=row, actuators=True)
        nxt = starts[k + 1][0] if k + 1 < len(starts) else end + 1
        for s in range(start + hold, nxt, hold):
            events[s] = Event(actuators=True)
    for k in range(int(end * dt_s / HEARTBEAT_PERIOD_S + 1e-9) + 1):
        s = int(round(k * HEARTBEAT_PERIOD_S / dt_s))
        if s <= end:
            e = events.get(s, Event())
            events[s] = Event(e.row, e.actuators, heartbeat=True)
    return events


def simulate(vehicle: Vehicle, schedule: CommandSchedule, seed: int = 0, depth_m: float = 0.5,
             dt_s: float = 0.001):
    """Run the schedule open loop; yield `Chunk`s in vehicle-time order, one per event step."""
    commands = [pwm_to_command(vehicle, row) for row in schedule.pwm_us]
    plant = Plant(vehicle, dt_s=dt_s, seed=seed, depth_m=depth_m, command=commands[0])
    events = event_steps(schedule, dt_s)
    pwm = schedule.pwm_us[0]
    heartbeat = codec.heartbeat()
    time_usec = codec.time_usec
    for step in sorted(events):
        ev = events[step]
        samples = plant.advance(step * dt_s)
        out = []  # (time_us, rank, msg); rank orders messages of one instant, fixed for identical files
        out += [(time_usec(s.time_s), 3, codec.encode_imu(s)) for s in samples.imu]
        out += [(time_usec(s.time_s), 4, codec.encode_pressure(s)) for s in samples.pressure]
        out += [(time_usec(s.time_s), 5, codec.encode_attitude(s)) for s in samples.attitude]
        t_us = time_usec(plant.time_s)
        if ev.heartbeat:
            out.append((t_us, 0, heartbeat))
        if ev.row is not None:
            pwm = schedule.pwm_us[ev.row]
            plant.set_command(commands[ev.row])
        if ev.actuators:  # SERVO_OUTPUT_RAW (rank 1), then the ESC telemetry (rank 2)
            for k, msg in enumerate(codec.encode_actuators(plant.actuators(pwm))):
                out.append((t_us, 1 + min(k, 1), msg))
        out.sort(key=lambda e: (e[0], e[1]))
        yield Chunk(plant.time_s, [(t, m) for t, _, m in out], samples.truth)


# --- the command line ---------------------------------------------------------------------------

def configure(parser) -> None:
    parser.add_argument("--vehicle", default=None, metavar="V.toml",
                        help="vehicle file (default: the packaged reference vehicle asr4)")
    parser.add_argument("--commands", required=True, metavar="CMDS.csv",
                        help="header t,pwm1,...,pwm12: time (s) and PWM (us), each row held until the next; "
                        f"example: {DEMO_COMMANDS}")
    parser.add_argument("--out", required=True, metavar="REC.tlog", help="recording to write")
    parser.add_argument("--truth", default=None, metavar="TRUTH.csv",
                        help="also write the true state at the IMU rate (t,x,y,z,roll,pitch,yaw,u,v,w,p,q,r)")
    parser.add_argument("--seed", type=int, default=0, help="sensor noise seed (default 0)")
    parser.add_argument("--depth", type=float, default=0.5, metavar="Z0",
                        help="initial depth below the surface, m (default 0.5)")
    parser.add_argument("--dt", type=float, default=0.001, metavar="DT",
                        help="integration step, s (default 0.001)")


def run(args) -> int:
    try:
        vehicle = load_vehicle(args.vehicle)
        schedule = read_commands(args.commands, vehicle)
        _check_options(args, vehicle)
        event_steps(schedule, args.dt)  # checks the rows against the step
    except (VehicleFileError, CommandsFileError, _OptionError) as exc:
        print(f"jetloop sim: error: {exc}", file=sys.stderr)
        return 2
    truth_file = None
    try:
        truth_file = open(args.truth, "w", encoding="utf-8", newline="\n") if args.truth else None
        writer = TlogWriter(args.out)
    except OSError as exc:
        if truth_file:
            truth_file.close()
        print(f"jetloop sim: error: cannot write {exc.filename}: {exc.strerror}", file=sys.stderr)
        return 2
    wall0 = time.perf_counter()
    next_progress = math.inf
    first = None  # wall time when the t = 0 chunk is out (the compiled model is loaded by then)
    last_truth = None
    try:
        with writer:
            if truth_file:
                truth_file.write(TRUTH_HEADER + "\n")
            for chunk in simulate(vehicle, schedule, args.seed, args.depth, args.dt):
                for t_us, msg in chunk.messages:
                    writer.write(msg, FIXED_EPOCH_US + t_us)
                if chunk.truth:
                    last_truth = chunk.truth[-1]
                    if truth_file:
                        truth_file.write("".join(_truth_line(s) for s in chunk.truth))
                now = time.perf_counter()
                if first is None:
                    first, next_progress = now, now + PROGRESS_AFTER_S
                elif now >= next_progress:
                    next_progress = now + PROGRESS_AFTER_S
                    print(f"  t = {chunk.time_s:.1f} / {schedule.duration_s:.1f} s "
                          f"({100 * chunk.time_s / schedule.duration_s:.0f} %), "
                          f"{chunk.time_s / (now - first):.0f}x real time", file=sys.stderr, flush=True)
    except codec.CodecError as exc:  # the plant produced NaN / inf: it diverged
        print(f"jetloop sim: error: the simulation diverged ({exc}); try a smaller --dt. "
              f"{args.out} holds the run up to that point.", file=sys.stderr)
        return 1
    finally:
        if truth_file:
            truth_file.close()
    end = time.perf_counter()
    _summary(args, vehicle, schedule, writer, last_truth, end - wall0, end - first)
    return 0


class _OptionError(ValueError):
    pass


def _check_options(args, vehicle: Vehicle) -> None:
    s = vehicle.sensors
    fastest = max(s.imu_rate, s.pressure_rate, s.attitude_rate)
    if not (math.isfinite(args.dt) and 0 < args.dt <= 1.0 / fastest):
        raise _OptionError(f"--dt {args.dt}: expected a step in seconds, 0 < dt <= {1.0 / fastest:g} "
                           f"(the period of the fastest sensor, {fastest:g} Hz)")
    if not math.isfinite(args.depth):
        raise _OptionError(f"--depth {args.depth}: expected a finite depth in metres")
    if args.seed < 0:
        raise _OptionError(f"--seed {args.seed}: expected an integer >= 0")


def _truth_line(s) -> str:
    v = (*s.pos_ned_m, *s.euler_rad, *s.nu)
    return f"{s.time_s:.6f}," + ",".join(f"{c:.9g}" for c in v) + "\n"


def _summary(args, vehicle: Vehicle, schedule, writer: TlogWriter, truth, wall_s: float, run_s: float) -> None:
    dur = schedule.duration_s
    counts = ", ".join(f"{n} {c}" for n, c in sorted(writer.counts.items()))
    print(f"jetloop sim: {dur:.3f} s of vehicle time -> {args.out} ({writer.bytes_written} bytes, "
          f"{sum(writer.counts.values())} messages)")
    print(f"  messages: {counts}")
    if truth is not None:
        r, p, y = (math.degrees(a) for a in truth.euler_rad)
        print(f"  final (t = {truth.time_s:.3f} s): depth {truth.pos_ned_m[2] - vehicle.environment.surface_depth:.3f} m, "
              f"roll {r:.1f} deg, pitch {p:.1f} deg, yaw {y:.1f} deg")
    if args.truth:
        print(f"  truth: {args.truth}")
    print(f"  wall time {wall_s:.2f} s ({wall_s - run_s:.2f} s loading the compiled model), "
          f"{dur / max(run_s, 1e-9):.0f}x real time after loading")
