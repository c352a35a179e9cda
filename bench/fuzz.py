"""Long coverage-guided fuzzing runs of every input path with atheris (issue 7 part 2).

    pip install -e '.[fuzz]'              # atheris (libFuzzer for Python)
    python bench/fuzz.py TARGET --runs N  # one target; prints runs, crashes, rejections, runs/s
    python bench/fuzz.py all --runs N     # every target, one process each, then a table
    python bench/fuzz.py memory --mb 20   # tracemalloc peak of 20 MB of garbage through a Link
                                          # and through the .tlog / .bin readers

A target takes the fuzzer's bytes and feeds one input path. An exception of the path's documented
type (RecordingError, VehicleFileError, ...) or a counted refusal (link.bad_packets,
loop.stats.rejected_inputs, ...) is a *rejection*; any other exception is a *crash*: counted, its
input saved under bench/fuzz_crashes/TARGET-N.bin, and the run goes on (libFuzzer would stop at
the first). The hypothesis tests (tests/test_fuzz_*.py) are the bounded version that CI runs.
"""

from __future__ import annotations

import argparse
import contextlib
import math
import os
import random
import subprocess
import sys
import tempfile
import time
import traceback
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
SHARED = ROOT.parent / "shared"
CRASH_DIR = ROOT / "bench" / "fuzz_crashes"

STATS = {"runs": 0, "crashes": 0, "rejections": 0, "kinds": {}}
TEMP_FILES: list = []  # removed by report(): the run ends with os._exit, which skips atexit


def _crash(target: str, data: bytes, exc: BaseException) -> None:
    STATS["crashes"] += 1
    kind = f"{type(exc).__name__} at {traceback.extract_tb(exc.__traceback__)[-1].name}"
    STATS["kinds"][kind] = STATS["kinds"].get(kind, 0) + 1
    if STATS["kinds"][kind] == 1:
        CRASH_DIR.mkdir(exist_ok=True)
        path = CRASH_DIR / f"{target}-{STATS['crashes']}.bin"
        path.write_bytes(data)
        print(f"CRASH {kind}: {exc!r} (input saved to {path})", flush=True)
        traceback.print_exc(limit=-4, file=sys.stdout)


# ------------------------------------------------------------------------------------------------
# Building MAVLink messages from the fuzzer's bytes


def _message(fdp, names):
    """A message of one of `names` with every field taken from the fuzzer (any value of its type)."""
    from pymavlink.dialects.v20 import ardupilotmega as mavlink

    name = names[fdp.ConsumeIntInRange(0, len(names) - 1)]
    cls = mavlink.mavlink_map[getattr(mavlink, f"MAVLINK_MSG_ID_{name}")]
    length = dict(zip(cls.ordered_fieldnames, cls.array_lengths))
    values = []
    for f, t in zip(cls.fieldnames, cls.fieldtypes):
        n = length[f]
        if t == "char":
            values.append(fdp.ConsumeBytes(max(n, 1)))
        elif n:
            values.append([_scalar(fdp, t) for _ in range(n)])
        else:
            values.append(_scalar(fdp, t))
    return cls(*values)


def _scalar(fdp, t: str):
    if t in ("float", "double"):
        special = fdp.ConsumeIntInRange(0, 7)
        if special < 4:
            return (math.nan, math.inf, -math.inf, 3.4028234663852886e38)[special]
        v = fdp.ConsumeFloat()
        return v if t == "double" or not math.isfinite(v) or abs(v) < 3.4e38 else math.copysign(3.4e38, v)
    bits = int("".join(c for c in t if c.isdigit()))
    if t.startswith("u"):
        return fdp.ConsumeIntInRange(0, 2 ** bits - 1)
    return fdp.ConsumeIntInRange(-(2 ** (bits - 1)), 2 ** (bits - 1) - 1)


def _packets(fdp, names, sender, count: int) -> bytes:
    out = b""
    for _ in range(count):
        if fdp.remaining_bytes() < 4:
            break
        out += sender.pack(_message(fdp, names))
    return out


# ------------------------------------------------------------------------------------------------
# Targets: name -> (setup() -> state, one(state, data) -> rejected?: bool)


def _link_setup():
    from onboard.link import Link

    return Link("udpin:127.0.0.1:0")


def _link_one(lk, data: bytes) -> bool:
    before = lk.bad_packets + lk.unknown_packets + lk.garbage_bytes
    lk.feed(data, datagram=bool(data) and data[0] & 1)
    lk._ready.clear()
    pending = len(lk.mav.buf) - lk.mav.buf_index
    if lk.bytes_in != lk.good_bytes + lk.garbage_bytes + pending:
        raise AssertionError("link byte accounting broken")
    return lk.bad_packets + lk.unknown_packets + lk.garbage_bytes > before


ONBOARD_READS = ("HIGHRES_IMU", "SCALED_IMU", "SCALED_IMU2", "RAW_IMU", "SCALED_PRESSURE2", "SCALED_PRESSURE",
                 "ATTITUDE", "SYSTEM_TIME", "SET_POSITION_TARGET_LOCAL_NED", "MANUAL_CONTROL", "COMMAND_LONG",
                 "ESC_TELEMETRY_1_TO_4", "ACTUATOR_OUTPUT_STATUS", "HEARTBEAT")


def _onboard_setup():
    import numpy as np
    from pymavlink.dialects.v20 import ardupilotmega as mavlink

    from onboard.link import Link
    from onboard.loop import OnboardLoop, VehicleClock, arm_command
    from onboard.vehicle import load_vehicle

    v = load_vehicle()
    link = Link("udpin:127.0.0.1:0")
    loop = OnboardLoop(v, link, VehicleClock(block_s=0.0))
    senders = {s: mavlink.MAVLink(None, srcSystem=s, srcComponent=1) for s in (1, 255, 7)}
    loop.handle(arm_command(True))
    return {"v": v, "loop": loop, "link": link, "senders": senders, "np": np}


class _Sender:
    def __init__(self, mav):
        self.mav = mav

    def pack(self, msg) -> bytes:
        b = bytes(msg.pack(self.mav))
        self.mav.seq = (self.mav.seq + 1) % 256
        return b


def _onboard_one(st, data: bytes) -> bool:
    import atheris

    fdp = atheris.FuzzedDataProvider(data)
    loop, np, v = st["loop"], st["np"], st["v"]
    sender = _Sender(st["senders"][(1, 255, 7)[fdp.ConsumeIntInRange(0, 2)]])
    before = loop.stats.rejected_inputs + loop.stats.ignored_imu + loop.link.bad_packets
    loop.link.feed(_packets(fdp, ONBOARD_READS, sender, 4), datagram=True)
    while loop.link._ready:
        loop.handle(loop.link._ready.popleft())
    if loop._tick_due():
        loop.poll()
    c = np.asarray(loop.command, dtype=float)
    k = v.n_units
    if not (np.all(np.isfinite(c)) and np.all(c[:k] >= -1e-9) and np.all(c[:k] <= v.thruster.n_max + 1e-9)
            and np.all(np.abs(c[k:]) <= v.servo.angle_limit + 1e-9)):
        raise AssertionError(f"command outside the vehicle's limits: {c}")
    return loop.stats.rejected_inputs + loop.stats.ignored_imu + loop.link.bad_packets > before


SENSOR_READS = ("HIGHRES_IMU", "RAW_IMU", "SCALED_PRESSURE2", "ATTITUDE", "SYSTEM_TIME", "ESC_TELEMETRY_1_TO_4",
                "ACTUATOR_OUTPUT_STATUS")


def _peers_setup():
    """A robot (OnboardLoop) with a main udpin link and a ground udpin link, each locked to its peer
    (an autopilot socket, a station socket), and an intruder socket: real UDP on 127.0.0.1."""
    import socket

    import numpy as np
    from pymavlink.dialects.v20 import ardupilotmega as mavlink

    from onboard import mavlink_codec as codec
    from onboard.link import Link
    from onboard.loop import OnboardLoop, VehicleClock
    from onboard.vehicle import load_vehicle

    v = load_vehicle()
    # the peers hold their links however long the fuzzer runs between their datagrams (a silent
    # peer's hand-over after PEER_TIMEOUT_S is tests/test_link.py's)
    main, ground = (Link("udpin:127.0.0.1:0", peer_timeout_s=1e9) for _ in range(2))
    loop = OnboardLoop(v, main, VehicleClock(block_s=0.0), ground=ground)
    socks = {}
    for name in ("autopilot", "station", "intruder"):
        socks[name] = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        socks[name].bind(("127.0.0.1", 0))
        socks[name].setblocking(False)
    hello = lambda src, comp: bytes(codec.heartbeat().pack(mavlink.MAVLink(None, src, comp)))  # noqa: E731
    socks["autopilot"].sendto(hello(1, 1), main.local_address)
    socks["station"].sendto(hello(255, 190), ground.local_address)
    from onboard.sensors import ImuSample  # the autopilot's first sample starts the clock (poll then never waits)

    imu = codec.encode_imu(ImuSample(0.0, (0.0, 0.0, -9.81), (0.0, 0.0, 0.0)))
    socks["autopilot"].sendto(bytes(imu.pack(mavlink.MAVLink(None, 1, 1))), main.local_address)
    for lk in (main, ground):
        m = lk.recv(0.5)
        while m is not None:
            loop.handle(m, "main" if lk is main else "ground")
            m = lk.recv(0.1)
    senders = {s: mavlink.MAVLink(None, srcSystem=s, srcComponent=1) for s in (1, 255, 7, 99)}
    return {"v": v, "loop": loop, "main": main, "ground": ground, "socks": socks, "senders": senders, "np": np}


def _peers_one(st, data: bytes) -> bool:
    """Datagrams from the autopilot, the station or an intruder, to either link, holding junk or any
    sensor or ground message from any system. Properties: every intruder datagram is counted and
    never read; sensor data from anyone but the autopilot (system 1 on the main link) never moves
    the loop's clock or IMU ordering; the command stays inside the vehicle's limits."""
    import atheris

    fdp = atheris.FuzzedDataProvider(data)
    loop, main, ground, socks, np, v = st["loop"], st["main"], st["ground"], st["socks"], st["np"], st["v"]
    foreign0 = main.foreign_datagrams + ground.foreign_datagrams
    time0 = (loop.clock.now(), loop._last_imu_stamp)
    refused0 = loop.stats.security.sensors_refused + loop.stats.rejected_inputs
    intruded, autopilot_sensors = 0, False
    for _ in range(fdp.ConsumeIntInRange(1, 4)):
        who = ("autopilot", "station", "intruder")[fdp.ConsumeIntInRange(0, 2)]
        to = main if who == "autopilot" else ground if who == "station" else (main, ground)[fdp.ConsumeIntInRange(0, 1)]
        sysid = (1, 255, 7, 99)[fdp.ConsumeIntInRange(0, 3)]
        if fdp.ConsumeBool():
            payload = fdp.ConsumeBytes(fdp.ConsumeIntInRange(1, 300))
        else:
            names = SENSOR_READS if fdp.ConsumeBool() else ONBOARD_READS
            payload = _packets(fdp, names, _Sender(st["senders"][sysid]), 2)
            autopilot_sensors |= who == "autopilot" and sysid == 1
        if not payload:
            continue
        socks[who].sendto(payload, to.local_address)
        intruded += who == "intruder"
    quiet = 0
    for _ in range(40):  # read and handle what came (bounded); a poll that steps reads nothing
        before = main.bytes_in + ground.bytes_in + main.foreign_datagrams + ground.foreign_datagrams
        loop.poll()
        idle = main.bytes_in + ground.bytes_in + main.foreign_datagrams + ground.foreign_datagrams == before \
            and not loop._tick_due() and not main._ready and not ground._ready
        quiet = quiet + 1 if idle else 0
        if quiet >= 2:
            break
    if main.foreign_datagrams + ground.foreign_datagrams != foreign0 + intruded:
        raise AssertionError("an intruder's datagram was read (or a peer's counted as foreign)")
    if not autopilot_sensors and (loop.clock.now(), loop._last_imu_stamp) != time0:
        raise AssertionError(f"sensor data from another party moved the time: {time0} -> {loop.clock.now()}")
    c = np.asarray(loop.command, dtype=float)
    k = v.n_units
    if not (np.all(np.isfinite(c)) and np.all(c[:k] >= -1e-9) and np.all(c[:k] <= v.thruster.n_max + 1e-9)
            and np.all(np.abs(c[k:]) <= v.servo.angle_limit + 1e-9)):
        raise AssertionError(f"command outside the vehicle's limits: {c}")
    return intruded > 0 or loop.stats.security.sensors_refused + loop.stats.rejected_inputs > refused0


GROUND_READS = ("HEARTBEAT", "ATTITUDE", "NAMED_VALUE_FLOAT", "DEBUG_FLOAT_ARRAY", "SERVO_OUTPUT_RAW",
                "SCALED_PRESSURE2", "LOCAL_POSITION_NED", "VFR_HUD", "SYS_STATUS", "COMMAND_ACK", "STATUSTEXT")


def _ground_setup():
    from pymavlink.dialects.v20 import ardupilotmega as mavlink

    from ground.station import Station
    from onboard.link import Link
    from onboard.vehicle import load_vehicle

    return {"station": Station(load_vehicle()), "link": Link("udpin:127.0.0.1:0"), "t": 0.0,
            "sender": _Sender(mavlink.MAVLink(None, srcSystem=1, srcComponent=1))}


def _ground_one(st, data: bytes) -> bool:
    import atheris

    from ground.view import render_text

    fdp = atheris.FuzzedDataProvider(data)
    station, link = st["station"], st["link"]
    link.feed(_packets(fdp, GROUND_READS, st["sender"], 4), datagram=True)
    events = len(station.events)
    while link._ready:
        st["t"] += 0.01
        station.update(link._ready.popleft(), st["t"])
    station.tick(st["t"])
    render_text(station.snapshot(st["t"]))
    return any("could not be read" in e for _, e in list(station.events)[events:])


def _endpoint_setup():
    from pymavlink.dialects.v20 import ardupilotmega as mavlink

    from hil.endpoint import HilEndpoint
    from hil.plant import Plant
    from onboard.link import Link
    from onboard.vehicle import load_vehicle

    v = load_vehicle()
    eps = [HilEndpoint(v, Link("udpin:127.0.0.1:0"), Plant(v, dt_s=0.001, noise=False), actuators=a, history=False)
           for a in ("hil", "pwm")]
    return {"v": v, "eps": eps, "sender": _Sender(mavlink.MAVLink(None, srcSystem=1, srcComponent=1))}


def _endpoint_one(st, data: bytes) -> bool:
    import atheris
    import numpy as np

    fdp = atheris.FuzzedDataProvider(data)
    ep = st["eps"][fdp.ConsumeIntInRange(0, 1)]
    before = ep.stats.bad_commands + ep.stats.stale_replies
    ep.link.feed(_packets(fdp, ("HIL_ACTUATOR_CONTROLS", "SERVO_OUTPUT_RAW"), st["sender"], 3), datagram=True)
    while ep.link._ready:
        ep._handle(ep.link._ready.popleft(), fdp.ConsumeIntInRange(0, 10 ** 6) / 100.0, record=False)
    c = np.asarray(ep.plant.command, dtype=float)
    if not np.all(np.isfinite(c)):
        raise AssertionError(f"plant command not finite: {c}")
    return ep.stats.bad_commands + ep.stats.stale_replies > before


def _sitl_setup():
    from hil.json_sitl import JsonSitlBackend
    from onboard.vehicle import load_vehicle

    return JsonSitlBackend(load_vehicle())


def _sitl_one(backend, data: bytes) -> bool:
    before = backend.bad_packets
    reply = backend.handle(data)
    if reply is None and backend.bad_packets != before + 1:
        raise AssertionError("SITL frame refused but not counted")
    return reply is None


def _file_setup(suffix: str):
    def setup():
        fd, name = tempfile.mkstemp(suffix=suffix)
        os.close(fd)
        TEMP_FILES.append(name)
        return Path(name)
    return setup


def _recording_one(path: Path, data: bytes) -> bool:
    from ground.recording import RecordingError, read_recording

    path.write_bytes(data)
    try:
        rec = read_recording(path)
    except RecordingError:
        return True
    rec.summary()
    s = rec.skipped
    return bool(s.skipped_bytes or s.bad_crc_packets or s.unknown_packets or s.non_monotonic or s.bad_records
                or s.out_of_range or s.bad_time)


def _flight(n: int, gap_s: float, uptime_s: float):
    """A tlog of n 100 Hz IMU samples (+ pressure and uint32-clocked SERVO_OUTPUT_RAW every 2nd)
    from vehicle time uptime_s, jumping by gap_s halfway: the truth the damage target checks
    against. Returns (bytes, first time, last time)."""
    from pymavlink.dialects.v20 import ardupilotmega as mav

    link = mav.MAVLink(None, srcSystem=1, srcComponent=1)
    out = bytearray()
    times = [uptime_s + i * 0.01 + (gap_s if i >= n // 2 else 0.0) for i in range(n)]
    for i, t in enumerate(times):
        stamp = (1_700_000_000_000_000 + int(round(t * 1e6))).to_bytes(8, "big")
        msgs = [mav.MAVLink_highres_imu_message(int(round(t * 1e6)), 0.1, 0.2, -9.8, 0.01, 0.02, 0.03,
                                                0, 0, 0, 0, 0, 0, 0, 0b111111, 0)]
        if i % 2 == 0:
            msgs.append(mav.MAVLink_scaled_pressure2_message(int(round(t * 1e3)) % 2 ** 32, 1013.25, 0, 2000, 0))
            msgs.append(mav.MAVLink_servo_output_raw_message(int(round(t * 1e6)) % 2 ** 32, 0, *([1500] * 16)))
        for m in msgs:
            out += stamp + m.pack(link)
    return bytes(out), times[0], times[-1]


_FLIGHTS: dict = {}


def _damage_one(path: Path, data: bytes) -> bool:
    """Issue 15: the fuzzer's bytes choose a flight (length, gap, uptime past a uint32 wrap) and
    where bits flip in it (up to 1 % of its bytes). Every packet whose own bytes are intact must
    be read and no stream may leave the true time span; a failed check is a crash."""
    import numpy as np

    from ground.recording import RecordingError, read_recording, scan_packets

    if len(data) < 4:
        return True
    n = 50 + data[0] * 2
    gap_s = (0.0, 0.5, 2.0, 1e5, 4e6)[data[1] % 5]
    uptime_s = (0.0, 4290.0, 4294.9, 9000.0)[data[2] % 4]
    key = (n, gap_s, uptime_s)
    if key not in _FLIGHTS:
        clean, t0, t1 = _flight(n, gap_s, uptime_s)
        buf, off, plen, *_ = scan_packets(clean)
        hdr = np.where(buf[off - 10] == 0xFD, 10, 6)
        _FLIGHTS[key] = (clean, t0, t1, off, off - hdr, off + plen + 2)
    clean, t0, t1, off, start, end = _FLIGHTS[key]
    body = bytearray(clean)
    flips = data[3:3 + 3 * (len(clean) // 100)]
    hit = np.zeros(len(body) + 1, np.int64)
    for j in range(0, len(flips) - 2, 3):
        i = (flips[j] << 8 | flips[j + 1]) * len(body) // 65536
        body[i] ^= 1 << (flips[j + 2] % 8)
        hit[i] = 1
    cum = np.concatenate([[0], np.cumsum(hit)])
    intact = set(off[(cum[end] - cum[start]) == 0].tolist())
    lost = intact - set(scan_packets(bytes(body))[1].tolist())
    assert not lost, f"{len(lost)} intact packets lost"
    path.write_bytes(bytes(body))
    try:
        rec = read_recording(path)
    except RecordingError:
        assert not intact, "refused with intact packets"
        return True
    for name, st in rec.streams.items():
        assert t0 - 1e-6 <= st.time_s[0] and st.time_s[-1] <= t1 + 1e-6, f"{name} outside the true span"
    return bool(rec.skipped.bad_crc_packets or rec.skipped.skipped_bytes)


def _text_one(parse, error):
    def one(_state, data: bytes) -> bool:
        try:
            parse(data.decode("utf-8", "replace"))
        except error:
            return True
        return False
    return one


def _vehicle_parse(text):
    from onboard.vehicle import parse_vehicle

    return parse_vehicle(text, "fuzz.toml")


def _commands_parse(text):
    from hil.sim import parse_commands

    return parse_commands(text, "fuzz.csv")


def _command_line_parse(text):
    from ground.commands import parse_command
    from pymavlink.dialects.v20 import ardupilotmega as mavlink

    mav = mavlink.MAVLink(None)
    for m in parse_command(text):
        m.pack(mav)


def _errors(*names):
    import importlib

    out = []
    for n in names:
        mod, _, cls = n.rpartition(".")
        out.append(getattr(importlib.import_module(mod), cls))
    return tuple(out)


def _seeds(target: str) -> list[bytes]:
    """Real inputs to start from: recordings, the reference vehicle, the demo commands."""
    from onboard.vehicle import DEFAULT_VEHICLE

    if target == "tlog":
        return [(SHARED / "data/ardusub/small.tlog").read_bytes()[:20_000]]
    if target == "dataflash":
        return [(SHARED / "data/ardusub/small.BIN").read_bytes()[:20_000]]
    if target == "damage":
        return [bytes([100, 3, 2]) + bytes(range(256)) * 2, bytes([10, 0, 0]) + b"\x00" * 30]
    if target == "vehicle":
        return [DEFAULT_VEHICLE.read_bytes()]
    if target == "commands":
        return [(ROOT / "onboard/data/demo_commands.csv").read_bytes()]
    if target == "command_line":
        return [b"depth 1.5 yaw 90", b"rate ATTITUDE 10", b"manual 100 0 500 0", b"mode guided"]
    if target == "peers":  # the fuzzed data provider's choices: long enough for four datagrams of messages
        return [random.Random(i).randbytes(2000) for i in range(4)]
    if target == "sitl":
        from hil.json_sitl import pack_servo_packet

        return [pack_servo_packet(400, i, [1500] * 16) for i in range(3)]
    return []


TARGETS = {
    "link": (_link_setup, _link_one),
    "onboard": (_onboard_setup, _onboard_one),
    "peers": (_peers_setup, _peers_one),
    "ground": (_ground_setup, _ground_one),
    "endpoint": (_endpoint_setup, _endpoint_one),
    "sitl": (_sitl_setup, _sitl_one),
    "tlog": (_file_setup(".tlog"), _recording_one),
    "dataflash": (_file_setup(".bin"), _recording_one),
    "damage": (_file_setup(".tlog"), _damage_one),
    "vehicle": (lambda: None, None),
    "commands": (lambda: None, None),
    "command_line": (lambda: None, None),
}
TEXT_TARGETS = {
    "vehicle": (_vehicle_parse, ("onboard.vehicle.VehicleFileError",)),
    "commands": (_commands_parse, ("hil.sim.CommandsFileError",)),
    "command_line": (_command_line_parse, ("ground.commands.CommandError",)),
}


# Modules whose coverage guides the fuzzer. atheris' instrumentation reaches numba-compiled functions
# imported with them (their bytecode then calls atheris and does not compile), so targets that run
# the model or the compiled tlog scanner (onboard, endpoint, sitl, ground's jet panel, tlog,
# dataflash) are fuzzed by mutating the seeds without coverage feedback.
GUIDED = ("link", "vehicle", "commands", "command_line")
INSTRUMENTED = ["onboard.link", "onboard.loop", "onboard.mavlink_codec", "onboard.vehicle", "onboard.signing",
                "onboard.failsafe", "onboard.pwm", "hil.json_sitl", "hil.endpoint", "hil.sim", "ground.station",
                "ground.view", "ground.commands", "ground.recorder", "pymavlink.DFReader"]


def run_target(target: str, runs: int, max_len: int, max_time_s: float = math.inf) -> None:
    import atheris

    setup, one = TARGETS[target]
    parse = None
    if target in TEXT_TARGETS:
        parse, errs = TEXT_TARGETS[target]
    guided = target in GUIDED
    with atheris.instrument_imports(include=INSTRUMENTED) if guided else contextlib.nullcontext():
        state = setup()
        if parse is not None:
            try:
                parse("")  # import the reader inside the instrumented block
            except Exception:
                pass
            one = _text_one(parse, _errors(*errs))
    t0 = time.perf_counter()

    def report():
        dt = time.perf_counter() - t0
        line = (f"{target} ({'coverage-guided' if guided else 'mutation'}): runs {STATS['runs']}  crashes {STATS['crashes']}  rejections {STATS['rejections']}  "
                f"{STATS['runs'] / max(dt, 1e-9):.0f} runs/s  ({dt:.1f} s)")
        print(line, flush=True)
        for kind, n in STATS["kinds"].items():
            print(f"  crash kind: {kind} x{n}", flush=True)
        for name in TEMP_FILES:
            if os.path.exists(name):
                os.remove(name)

    def test_one(data: bytes) -> None:
        STATS["runs"] += 1
        try:
            STATS["rejections"] += bool(one(state, data))
        except Exception as exc:  # a crash: count it, keep the input, fuzz on
            _crash(target, data, exc)
        if STATS["runs"] >= runs or time.perf_counter() - t0 > max_time_s:  # libFuzzer ends with C exit(),
            report()  # which skips Python's atexit: report here
            os._exit(1 if STATS["crashes"] else 0)

    corpus = Path(tempfile.mkdtemp(prefix=f"fuzz-{target}-"))
    for i, seed in enumerate(_seeds(target)):
        (corpus / f"seed{i}").write_bytes(seed)
    args = [sys.argv[0], str(corpus), f"-runs={runs + 100}", f"-max_len={max_len}", "-seed=1", "-print_final_stats=0",
            f"-artifact_prefix={corpus}/"]  # libFuzzer's slow-unit-* files stay out of the checkout
    if not os.environ.get("FUZZ_VERBOSE"):  # libFuzzer's progress lines (crashes are counted here)
        with open(os.devnull, "w") as null:
            os.dup2(null.fileno(), 2)
    atheris.Setup(args, test_one)
    atheris.Fuzz()


def memory(mb: float) -> None:
    """tracemalloc peak and time of `mb` MB of random garbage through a Link (UDP datagrams and a
    serial stream) and through the .tlog and .bin readers."""
    import tracemalloc

    from ground.recording import RecordingError, read_recording
    from onboard.link import Link

    n = int(mb * 1_000_000)
    data = random.Random(0).randbytes(n)
    for name, chunk in (("link, 60 kB datagrams", 60_000), ("link, 1 kB serial reads", 1024)):
        with Link("udpin:127.0.0.1:0") as lk:
            tracemalloc.start()
            t0 = time.perf_counter()
            for i in range(0, n, chunk):
                lk.feed(data[i:i + chunk], datagram=chunk > 4096)
                lk._ready.clear()
            dt = time.perf_counter() - t0
            _, peak = tracemalloc.get_traced_memory()
            tracemalloc.stop()
            print(f"{name}: {mb:g} MB garbage in {dt:.1f} s ({dt / n * 1e6:.2f} us/byte), tracemalloc peak "
                  f"{peak / 1e6:.2f} MB, garbage_bytes {lk.garbage_bytes}, bad_packets {lk.bad_packets}, "
                  f"packets_in {lk.packets_in}", flush=True)
    header = (SHARED / "data/ardusub/small.BIN").read_bytes()[:2000]
    # DFReader walks unframed bytes in Python (~100 us/byte under tracemalloc): 1 MB of it at most
    for suffix, body in ((".tlog", data), (".bin", header + data[:min(n, 1_000_000)])):
        with tempfile.TemporaryDirectory() as tmp:
            path = Path(tmp) / f"garbage{suffix}"
            path.write_bytes(body)
            tracemalloc.start()
            t0 = time.perf_counter()
            try:
                rec = read_recording(path)
                result = f"read, skipped_bytes {rec.skipped.skipped_bytes}"
            except RecordingError as exc:
                result = f"RecordingError: {str(exc)[len(str(path)) + 2:][:60]}"
            dt = time.perf_counter() - t0
            _, peak = tracemalloc.get_traced_memory()
            tracemalloc.stop()
            print(f"read_recording {suffix}: {len(body) / 1e6:g} MB garbage in {dt:.1f} s (under tracemalloc), "
                  f"peak {peak / 1e6:.1f} MB, {result}", flush=True)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("target", choices=sorted(TARGETS) + ["all", "memory"])
    ap.add_argument("--runs", type=int, default=10_000, help="inputs per target (libFuzzer -runs)")
    ap.add_argument("--max-len", type=int, default=4096, help="longest input (libFuzzer -max_len)")
    ap.add_argument("--mb", type=float, default=20.0, help="memory: megabytes of garbage")
    ap.add_argument("--max-time", type=float, default=math.inf, help="stop a target after this many seconds")
    args = ap.parse_args(argv)
    if args.target == "memory":
        memory(args.mb)
        return 0
    try:
        import atheris  # noqa: F401
    except ImportError:
        print("atheris is not installed: pip install -e '.[fuzz]'", file=sys.stderr)
        return 2
    if args.target == "all":
        for t in sorted(TARGETS):
            max_len = 40_000 if t in ("tlog", "dataflash", "vehicle") else args.max_len
            subprocess.run([sys.executable, __file__, t, "--runs", str(args.runs), "--max-len", str(max_len),
                            "--max-time", str(args.max_time)], check=False)
        return 0
    run_target(args.target, args.runs, args.max_len, args.max_time)
    return 0


if __name__ == "__main__":
    sys.exit(main())
