"""Ground recorder: raw packets both directions, 8-byte big-endian stamps, rotation by size, no loss
at the full telemetry rate, and mavlogdump.py (pymavlink's own tool) reads the files."""

from __future__ import annotations

import shutil
import struct
import subprocess
import sys
import time

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from ground.ground_cli import GroundSession
from ground.recorder import Recorder, RecorderError
from ground.recording import read_recording
from onboard.link import Link
from conftest import free_udp_port


def _att(i):
    return mavlink.MAVLink_attitude_message(i, 0.01 * i, 0.02, 0.03, 0.1, 0.2, 0.3)


def _split_tlog(data: bytes):
    """[(stamp_us, packet bytes)] of a clean tlog, framing by the packet's own length byte."""
    out, p = [], 0
    while p < len(data):
        (ts,) = struct.unpack(">Q", data[p:p + 8])
        magic, plen = data[p + 8], data[p + 9]
        n = (12 + plen + (13 if data[p + 10] & 1 else 0)) if magic == 0xFD else 8 + plen
        out.append((ts, data[p + 8:p + 8 + n]))
        p += 8 + n
    return out


def test_packets_stored_raw_with_big_endian_stamps_and_time_never_backwards(tmp_path):
    now = iter([100.0, 100.5, 99.0, 101.0, 101.0])  # the wall clock steps back once
    mav = mavlink.MAVLink(None, 1, 1)
    pk = [bytes(_att(i).pack(mav)) for i in range(4)]
    with Recorder(tmp_path, clock=lambda: next(now)) as rec:  # one clock read for the file name
        for i, p in enumerate(pk):
            rec.record(p, "ATTITUDE", outgoing=(i == 1))
    (f,) = rec.files
    got = _split_tlog(f.read_bytes())
    assert [p for _, p in got] == pk
    assert [t for t, _ in got] == [100_500_000, 100_500_000, 101_000_000, 101_000_000]  # 99.0 held at 100.5
    assert (rec.packets, rec.packets_in, rec.packets_out) == (4, 3, 1)


def test_rotation_by_size_never_splits_a_packet(tmp_path):
    mav = mavlink.MAVLink(None, 1, 1)
    pk = [bytes(_att(i).pack(mav)) for i in range(100)]
    size = 8 + len(pk[0])  # every record the same size: 8 + 40 = 48 bytes
    assert size == 48
    max_bytes = 1000  # 20 records fit (960 bytes), a 21st would make 1008
    with Recorder(tmp_path, max_bytes=max_bytes, clock=lambda: 1.7e9) as rec:
        for p in pk:
            rec.record(p, "ATTITUDE")
    per_file = max_bytes // size  # 20 records fit (960 bytes), a 21st would make 1008
    assert len(rec.files) == len(pk) // per_file  # 100 / 20 = 5
    assert all(f.stat().st_size == per_file * size for f in rec.files)
    joined = [p for f in rec.files for _, p in _split_tlog(f.read_bytes())]
    assert joined == pk
    assert [f.name[-9:] for f in rec.files] == ["-000.tlog", "-001.tlog", "-002.tlog", "-003.tlog", "-004.tlog"]
    with pytest.raises(RecorderError, match="at least 300"):
        Recorder(tmp_path, max_bytes=100)


@pytest.mark.skipif(shutil.which("mavlogdump.py") is None, reason="pymavlink's mavlogdump.py not on PATH")
def test_full_rate_both_directions_no_loss_and_mavlogdump_reads_it(tmp_path):
    """The onboard loop's telemetry at its full rate: 100 Hz frames of 20 packets (2000 packets/s),
    each frame one datagram (onboard.link batch). Every packet must be in the .tlog, in order."""
    port = free_udp_port()
    session = GroundSession(f"udpin:127.0.0.1:{port}", record_dir=tmp_path / "rec")
    tx = Link(f"udpout:127.0.0.1:{port}")
    frames, per_frame = 150, 20
    try:
        t0 = time.monotonic()
        for k in range(frames):
            with tx.batch():
                for j in range(per_frame):
                    tx.send(_att(k * per_frame + j))
            session.poll(0.0)
            time.sleep(max(0.0, t0 + (k + 1) * 0.01 - time.monotonic()))
        deadline = time.monotonic() + 3.0
        while session.recorder.packets_in < frames * per_frame and time.monotonic() < deadline:
            session.poll(0.05)
        session.send(mavlink.MAVLink_command_long_message(1, 1, 400, 0, 1, 0, 0, 0, 0, 0, 0))
    finally:
        tx.close()
        session.close()
    rec = session.recorder
    assert rec.packets_in == frames * per_frame
    assert session.station.sources[(1, 1)].lost == 0
    r = read_recording(rec.files[0])
    assert r.messages["ATTITUDE"] == frames * per_frame  # the vehicle's packets, CRC-checked
    assert r.skipped.bad_crc_packets == 0 and r.skipped.skipped_bytes == 0
    out = subprocess.run([sys.executable, shutil.which("mavlogdump.py"), "--types", "ATTITUDE,COMMAND_LONG,HEARTBEAT",
                          str(rec.files[0])], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    lines = out.stdout.splitlines()
    att = [ln for ln in lines if "ATTITUDE" in ln]
    assert len(att) == frames * per_frame
    assert sum("COMMAND_LONG" in ln for ln in lines) == 1  # the ground's own packet, recorded
    assert sum("HEARTBEAT" in ln and "type : 6" in ln for ln in lines) >= 1  # the ground's GCS heartbeat
    # in order: time_boot_ms counts 0, 1, 2, ...
    ms = [int(ln.split("time_boot_ms : ")[1].split(",")[0]) for ln in att]
    assert ms == list(range(frames * per_frame))
