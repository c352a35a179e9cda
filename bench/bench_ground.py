"""Ground station benchmark: packets per second the recorder and the view ingest, beside pymavlink's
raw parse rate measured in the same run.

Run `python bench/bench_ground.py` (options: --help). Not a timed test: it prints figures.

The traffic is the onboard loop's telemetry mix (one 100 Hz frame: SERVO_OUTPUT_RAW; every 10th
frame ATTITUDE, 15 NAMED_VALUE_FLOAT, DEBUG_FLOAT_ARRAY "wrench"; HEARTBEAT and SYS_STATUS at
1 Hz), packed once and repeated with fresh sequence numbers.

1. pymavlink raw: `MAVLink.parse_buffer` over the byte stream (decode only, nothing kept).
2. ground ingest, in process: the same bytes through `onboard.link.Link.feed` (pymavlink parse +
   the link's garbage/bad-packet bookkeeping), every message recorded to a .tlog
   (`ground.recorder.Recorder`) and applied to the `ground.station.Station`, while the rich view
   is rendered 4 times a second of wall time (to an in-memory console of 120 columns).
3. ground ingest over loopback UDP: a sender process paces datagrams (one 100 Hz frame each,
   frames scaled up to the asked packet rate) to a `GroundSession` (recorder + station) that
   renders the view 4 times a second; sent vs recorded says whether anything was lost.

Every figure is the best of `--repeat` runs (the machine is shared and noisy).
"""

from __future__ import annotations

import argparse
import io
import multiprocessing as mp
import os
import platform
import sys
import tempfile
import time

from pymavlink.dialects.v20 import ardupilotmega as mavlink

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from ground.ground_cli import GroundSession  # noqa: E402
from ground.recorder import Recorder  # noqa: E402
from ground.station import Station  # noqa: E402
from ground.view import render_rich  # noqa: E402
from onboard.link import Link  # noqa: E402
from onboard.vehicle import load_vehicle  # noqa: E402

NAMES = ("depth", "depth_sp", "yaw_sp", "u_sp", "u_est", "alloc_err", "alloc_fb", "qp_us", "step_ms",
         "step_p99", "failsafe", "armed", "est_rej", "in_rej", "link_bad")


def frame_messages(k: int) -> list:
    """The onboard loop's ground telemetry of control tick k (100 Hz)."""
    ms = 10 * k
    out = [mavlink.MAVLink_servo_output_raw_message(ms * 1000, 0, *([1500] * 12 + [0] * 4))]
    if k % 100 == 0:
        out.append(mavlink.MAVLink_heartbeat_message(12, 0, 128, 4, 4, 3))
        out.append(mavlink.MAVLink_sys_status_message(1, 1, 1, 100, 0, -1, -1, 0, 0, 0, 0, 0, 0))
    if k % 10 == 0:
        out.append(mavlink.MAVLink_attitude_message(ms, 0.01, 0.02, 0.3, 0.0, 0.0, 0.01))
        out += [mavlink.MAVLink_named_value_float_message(ms, n.encode(), 0.5) for n in NAMES]
        out.append(mavlink.MAVLink_debug_float_array_message(ms * 1000, b"wrench", 1, [1.0] * 12 + [0.0] * 46))
    return out


def stream(n_frames: int) -> tuple[bytes, int]:
    mav = mavlink.MAVLink(None, 1, 1)
    chunks, count = [], 0
    for k in range(n_frames):
        for m in frame_messages(k):
            chunks.append(bytes(m.pack(mav)))
            mav.seq = (mav.seq + 1) % 256
            count += 1
    return b"".join(chunks), count


def bench_raw(data: bytes, count: int) -> float:
    mav = mavlink.MAVLink(None)
    t0 = time.perf_counter()
    got = 0
    step = 2048  # the same chunks the ingest is fed
    for i in range(0, len(data), step):
        got += len(mav.parse_buffer(data[i:i + step]) or [])
    got += len(mav.parse_buffer(b"") or [])
    dt = time.perf_counter() - t0
    assert got == count, (got, count)
    return count / dt


def bench_ingest(data: bytes, count: int, vehicle, tmp: str) -> tuple[float, int]:
    from rich.console import Console

    link = Link("udpin:127.0.0.1:0")
    station = Station(vehicle)
    console = Console(file=io.StringIO(), width=120, force_terminal=True)
    frames = 0
    console.print(render_rich(station.snapshot(time.time())))  # imports and first-call compiles, untimed
    with Recorder(tmp, prefix="bench") as rec:
        t0 = time.perf_counter()
        next_draw = t0
        step = 2048  # about one UDP datagram of telemetry
        for i in range(0, len(data), step):
            link.feed(data[i:i + step])
            m = link.recv(0.0)
            now = time.time()
            while m is not None:
                rec.record(bytes(m.get_msgbuf()), m.get_type())
                station.update(m, now)
                m = link.recv(0.0) if link._ready else None
            if time.perf_counter() >= next_draw:
                next_draw += 0.25
                console.print(render_rich(station.snapshot(now)))
                frames += 1
        dt = time.perf_counter() - t0
        assert rec.packets == count, (rec.packets, count)
    link.close()
    return count / dt, frames


def _sender(port: int, rate_pps: float, seconds: float, ready, result):
    link = Link(f"udpout:127.0.0.1:{port}")
    ready.wait()
    frame = [m for m in frame_messages(0)] + [m for m in frame_messages(10)][1:]
    per_dgram = max(1, int(round(rate_pps / 100.0)))  # 100 datagrams/s
    msgs = (frame * (per_dgram // len(frame) + 1))[:per_dgram]
    sent = 0
    t0 = time.monotonic()
    k = 0
    while time.monotonic() - t0 < seconds:
        with link.batch():
            for m in msgs:
                link.send(m)
        sent += len(msgs)
        k += 1
        time.sleep(max(0.0, t0 + k * 0.01 - time.monotonic()))
    link.close()
    result.put((sent, time.monotonic() - t0))


def bench_udp(rate_pps: float, seconds: float, vehicle, tmp: str) -> dict:
    import socket

    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind(("127.0.0.1", 0))
    port = s.getsockname()[1]
    s.close()
    from rich.console import Console

    session = GroundSession(f"udpin:127.0.0.1:{port}", vehicle, record_dir=tmp)
    console = Console(file=io.StringIO(), width=120, force_terminal=True)
    ctx = mp.get_context("spawn")
    ready, result = ctx.Event(), ctx.Queue()
    proc = ctx.Process(target=_sender, args=(port, rate_pps, seconds, ready, result))
    proc.start()
    ready.set()
    frames = 0
    next_draw = time.monotonic()
    done = None
    t_drain = None
    while t_drain is None or time.monotonic() < t_drain:  # until the sender is done, then 0.5 s more
        session.poll(0.01)
        if time.monotonic() >= next_draw:
            next_draw += 0.25
            console.print(render_rich(session.snapshot()))
            frames += 1
        if done is None and not result.empty():
            done = result.get()
            t_drain = time.monotonic() + 0.5
    sent, dt = done
    proc.join(5)
    session.close()
    got = session.recorder.packets_in
    return {"asked_pps": rate_pps, "sent": sent, "recorded": got, "lost": sent - got,
            "pps": got / dt, "view_frames": frames}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seconds", type=float, default=200.0, help="telemetry seconds in the in-process stream (default 200)")
    ap.add_argument("--udp-rates", default="2000,5000,10000", help="packet rates for the UDP runs (default 2000,5000,10000)")
    ap.add_argument("--udp-seconds", type=float, default=3.0, help="length of each UDP run (default 3 s)")
    ap.add_argument("--repeat", type=int, default=3, help="best of N (default 3)")
    args = ap.parse_args(argv)
    if not (args.seconds > 0 and args.udp_seconds > 0 and args.repeat >= 1):
        ap.error("--seconds and --udp-seconds must be > 0, --repeat >= 1")
    try:
        rates = [float(r) for r in args.udp_rates.split(",") if r.strip()]
    except ValueError:
        ap.error(f"--udp-rates {args.udp_rates!r}: expected comma-separated packets/s, e.g. 2000,5000")
    vehicle = load_vehicle()
    data, count = stream(int(args.seconds * 100))
    print(f"machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, Python {platform.python_version()}")
    print(f"stream: {count} packets, {len(data)} bytes ({count / args.seconds:.0f} packets/s of telemetry)")
    raw = max(bench_raw(data, count) for _ in range(args.repeat))
    with tempfile.TemporaryDirectory() as tmp:
        runs = [bench_ingest(data, count, vehicle, tmp) for _ in range(args.repeat)]
    ingest, frames = max(runs)
    print(f"pymavlink raw parse            {raw:10.0f} packets/s")
    print(f"ground ingest (record + model + rich view 4/s, in process)"
          f" {ingest:10.0f} packets/s  ({ingest / raw:.0%} of raw, {frames} view frames)")
    for r in rates:
        with tempfile.TemporaryDirectory() as tmp:
            res = bench_udp(r, args.udp_seconds, vehicle, tmp)
        print(f"ground over loopback UDP at {res['asked_pps']:6.0f}/s asked: {res['pps']:8.0f} packets/s recorded, "
              f"{res['lost']} lost of {res['sent']}, {res['view_frames']} view frames")
    return 0


if __name__ == "__main__":
    sys.exit(main())
