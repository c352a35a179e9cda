"""Fuzzing ground.recording's .tlog and dataflash .bin readers (issue 7 part 2) on real recordings:
a short `jetloop sim` tlog, the ArduSub BlueROV2 tlog and dataflash log (shared/data/ardusub),
truncated, bit-flipped, byte-overwritten, spliced, duplicated, zero-length, and with huge jumps in
the tlog's timestamps; and synthetic flights with bit flips in a fraction of the bytes, vehicle-time
gaps and SERVO_OUTPUT_RAW uint32 clock wraps, whose truth is known. Properties:
- read_recording returns a Recording or raises RecordingError with a message naming the file;
  never another exception, never longer than the example's deadline;
- what was skipped is counted: a tlog read from damaged bytes accounts for every byte (the good
  packets' bytes + skipped_bytes + unknown packets' bytes = the file), and streams stay time-ordered;
- every packet whose own bytes are intact is read, whatever damage precedes it; no sample lands
  outside the true vehicle-time span; a gap > 1 s splits the recording into segments;
- 20 MB-scale garbage: memory stays proportional to the file (tracemalloc), time linear.
"""

from __future__ import annotations

import functools
import random
import tempfile
import time
import tracemalloc
from datetime import timedelta
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from conftest import ARDUSUB, shared_file
from ground.recording import RecordingError, read_recording, scan_packets
from hil.sim import FIXED_EPOCH_US, parse_commands, simulate, vehicle_channels
from hil.tlog import TlogWriter
from onboard.vehicle import load_vehicle

FUZZ = settings(max_examples=60, deadline=timedelta(seconds=30),  # a hang, not a slow shared machine
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
TLOG_PREFIX = 40_000  # bytes of the ArduSub tlog used (a few seconds of flight)
BIN_PREFIX = 40_000


@functools.cache
def sim_tlog() -> bytes:
    """A short real `jetloop sim` recording (1 s, the reference vehicle, jets on). (Sources are
    cached functions, not fixtures, so a failing example does not print 40 kB of bytes.)"""
    v = load_vehicle()
    chans = vehicle_channels(v)
    head = "t," + ",".join(f"pwm{c}" for c in chans)
    text = f"{head}\n0,{','.join('1500' for _ in chans)}\n0.5,{','.join('1600' for _ in chans)}\n"
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "short.tlog"
        with TlogWriter(path) as w:
            for chunk in simulate(v, parse_commands(text, "fuzz", chans)):
                for t_us, msg in chunk.messages:
                    w.write(msg, FIXED_EPOCH_US + t_us)
        return path.read_bytes()


@functools.cache
def ardusub_tlog() -> bytes:
    return shared_file(ARDUSUB / "small.tlog").read_bytes()[:TLOG_PREFIX]


@functools.cache
def ardusub_bin() -> bytes:
    return shared_file(ARDUSUB / "small.BIN").read_bytes()[:BIN_PREFIX]


def mutate(data: bytes, ops: list) -> bytes:
    """Apply (kind, a, b, value) edits: positions are fractions of the current length."""
    d = bytearray(data)
    for kind, a, b, value in ops:
        n = len(d)
        i, j = sorted((int(a * n), int(b * n)))
        if kind == "flip" and n:
            d[min(i, n - 1)] ^= 1 << (value % 8)
        elif kind == "byte" and n:
            d[min(i, n - 1)] = value % 256
        elif kind == "truncate":
            del d[i:]
        elif kind == "cut":
            del d[i:j]
        elif kind == "splice":  # a stretch copied elsewhere (a torn write replayed)
            d[i:i] = d[i:j][:4096]
        elif kind == "stamp" and n >= 8:  # a tlog timestamp jump: 8 bytes of any time
            d[min(i, n - 8):min(i, n - 8) + 8] = (value * 0x9E3779B97F4A7C15 % 2 ** 64).to_bytes(8, "big")
        elif kind == "zeros":
            d[i:j] = bytes(min(j - i, 4096))
    return bytes(d)


OPS = st.lists(st.tuples(st.sampled_from(["flip", "byte", "truncate", "cut", "splice", "stamp", "zeros"]),
                         st.floats(0, 1), st.floats(0, 1), st.integers(0, 2 ** 64 - 1)), min_size=1, max_size=12)


def _read(tmp_path, name: str, data: bytes):
    path = tmp_path / name
    path.write_bytes(data)
    try:
        rec = read_recording(path)
    except RecordingError as exc:
        assert str(path) in str(exc) and len(str(exc)) > len(str(path)) + 10
        return None
    rec.summary()  # the report block builds from anything read
    for s in rec.streams.values():
        assert np.all(np.diff(s.time_s) > 0)  # streams are time-ordered: out-of-order samples counted
    return rec


def _tlog_accounting(data: bytes, rec) -> None:
    """Every byte is a good packet's (with its 8-byte stamp), skipped, or an unknown packet's."""
    buf, off, plen, mid, src, ts = scan_packets(data)
    good = 0
    for o, p in zip(off, plen):
        hdr = 10 if buf[o - 10] == 0xFD else 6  # o is the payload offset
        sig = 13 if hdr == 10 and buf[o - 8] & 1 else 0
        good += 8 + hdr + p + 2 + sig
    assert good + rec.skipped.skipped_bytes <= len(data)
    if rec.skipped.unknown_packets == 0:
        assert good + rec.skipped.skipped_bytes == len(data)


@FUZZ
@given(ops=OPS, source=st.sampled_from(["sim", "ardusub"]))
@example(ops=[("truncate", 0.0, 0.0, 0)], source="sim")  # zero-length file
@example(ops=[("stamp", 0.5, 0.5, 2 ** 63)], source="ardusub")  # a timestamp jump of centuries
def test_damaged_tlog_is_read_as_far_as_it_is_sound(tmp_path, ops, source):
    data = mutate(sim_tlog() if source == "sim" else ardusub_tlog(), ops)
    rec = _read(tmp_path, "damaged.tlog", data)
    if rec is not None:
        _tlog_accounting(data, rec)


# -- bit flips, gaps and clock wraps on a log whose truth is known (issue 15 items 5-9) -------------

def _flight(n: int, gap_at: float, gap_s: float, uptime_s: float) -> tuple[bytes, float]:
    """A tlog of n IMU samples at 100 Hz (+ pressure, servo every 2nd), vehicle time starting at
    uptime_s, jumping by gap_s at fraction gap_at; SERVO_OUTPUT_RAW's time_usec is uint32 and
    wraps as ArduSub's does. Returns the bytes and the vehicle-time span (first, last)."""
    from pymavlink.dialects.v20 import ardupilotmega as mav

    link = mav.MAVLink(None, srcSystem=1, srcComponent=1)
    out = bytearray()
    times = []
    for i in range(n):
        t = uptime_s + i * 0.01 + (gap_s if i >= int(gap_at * n) else 0.0)
        times.append(t)
        stamp = (1_700_000_000_000_000 + int(round(t * 1e6))).to_bytes(8, "big")
        msgs = [mav.MAVLink_highres_imu_message(int(round(t * 1e6)), 0.1, 0.2, -9.8, 0.01, 0.02, 0.03,
                                                0, 0, 0, 0, 0, 0, 0, 0b111111, 0)]
        if i % 2 == 0:
            msgs.append(mav.MAVLink_scaled_pressure2_message(int(round(t * 1e3)) % 2 ** 32, 1013.25 + i * 1e-3, 0, 2000, 0))
            msgs.append(mav.MAVLink_servo_output_raw_message(int(round(t * 1e6)) % 2 ** 32, 0, *([1500] * 16)))
        for m in msgs:
            out += stamp + m.pack(link)
    return bytes(out), (times[0], times[-1])


FLIGHT = st.tuples(st.integers(50, 400), st.floats(0.1, 0.9), st.sampled_from([0.0, 0.5, 2.0, 1e5, 4e6]),
                   st.sampled_from([0.0, 4290.0, 4294.9, 9000.0]), st.sampled_from([0.0, 0.001, 0.01, 0.03]),
                   st.integers(0, 2 ** 32 - 1))


@FUZZ
@given(flight=FLIGHT)
@example(flight=(300, 0.5, 1e5, 4294.9, 0.01, 15))  # a gap, a wrap and 1 % bit flips at once
def test_bit_flips_gaps_and_wraps_keep_every_intact_packet_and_the_true_clock(tmp_path, flight):
    """Bit flips in a fraction of the bytes, a jump of vehicle time, a vehicle up for more than
    71.6 min (SERVO_OUTPUT_RAW's uint32 clock wrapped): every packet whose own bytes are intact
    is read; no sample lands outside the true time span (no impossible time, no unaligned servo
    stream); the recording splits into one segment per side of a gap longer than 1 s.
    At 3 % of the bytes (a quarter of the tlog stamps hit) a SERVO_OUTPUT_RAW stretch of a few
    samples whose stamps are mostly damaged cannot be placed on the vehicle clock: there only the
    streams with a clock of their own are held to the true span (8,000 draws pass at <= 1 %)."""
    n, gap_at, gap_s, uptime_s, rate, seed = flight
    clean, (t_first, t_last) = _flight(n, gap_at, gap_s, uptime_s)
    buf0, off0, plen0, *_ = scan_packets(clean)
    hdr = np.where(buf0[off0 - 10] == 0xFD, 10, 6)
    start, end = off0 - hdr, off0 + plen0 + 2
    rng = np.random.default_rng(seed)
    data = bytearray(clean)
    hit = rng.choice(len(data), size=int(rate * len(data)), replace=False)
    for i in hit:
        data[i] ^= 1 << int(rng.integers(8))
    cum = np.concatenate([[0], np.cumsum(np.isin(np.arange(len(data)), hit))])
    intact = set(off0[(cum[end] - cum[start]) == 0].tolist())
    assert intact <= set(scan_packets(bytes(data))[1].tolist())
    rec = _read(tmp_path, "flight.tlog", bytes(data))
    if rec is None:
        assert not intact
        return
    _tlog_accounting(bytes(data), rec)
    for name, s in rec.streams.items():
        if name == "servo" and rate > 0.01:
            continue
        assert t_first - 1e-6 <= s.time_s[0] and s.time_s[-1] <= t_last + 1e-6, name
    if rate == 0.0:
        assert rec.skipped.bad_time == {} and rec.skipped.non_monotonic == {}
        assert len(rec.segment_bounds()) == (2 if gap_s > 1.0 else 1)
        assert len(rec.servo.time_s) == len(rec.pressure.time_s)
        assert np.abs(rec.servo.time_s - rec.pressure.time_s).max() < 1e-3  # on one clock


@settings(max_examples=25, deadline=timedelta(seconds=30),
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(ops=OPS)
@example(ops=[("truncate", 0.001, 0.0, 0)])  # only part of the first FMT record
def test_damaged_dataflash_is_read_or_refused_with_a_reason(tmp_path, ops, capfd):
    _read(tmp_path, "damaged.bin", mutate(ardusub_bin(), ops))
    assert capfd.readouterr() == ("", "")  # DFReader's line per skipped byte goes nowhere


@functools.cache
def _clean_bin_span() -> tuple:
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "clean.BIN"
        path.write_bytes(shared_file(ARDUSUB / "small.BIN").read_bytes())
        rec = read_recording(path)
        return rec.t_start_s, rec.t_end_s


@settings(max_examples=25, deadline=timedelta(seconds=30), derandomize=True, database=None,
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(rate=st.sampled_from([0.001, 0.003, 0.005]), seed=st.integers(0, 2 ** 32 - 1))
@example(rate=0.005, seed=1)  # a flipped FMT record: DFReader refused the whole log
@example(rate=0.005, seed=15366251)  # the CI rehearsal's draw: an IMU stamp at 1.4e8 s survived
def test_dataflash_with_bit_flips_stays_within_its_true_span(tmp_path, rate, seed):
    """Issue 15 item 9: bit flips in a fraction of the .bin's bytes: the log is read (a damaged FMT
    record is counted, not fatal) and no stream leaves the clean log's time span (an impossible or
    out-of-line time is dropped and counted: 9.2e12 s before). 300 draws pass at <= 0.5 % (the
    issue's rate); at 1 % a stream whose records are damaged every other one (no run of 5 good
    stamps to judge by) can still keep an isolated wrong time."""
    data = bytearray(shared_file(ARDUSUB / "small.BIN").read_bytes())  # the whole log: its streams
    rng = np.random.default_rng(seed)
    for i in rng.choice(len(data), size=max(1, int(rate * len(data))), replace=False):
        data[i] ^= 1 << int(rng.integers(8))
    rec = _read(tmp_path, "flipped.bin", bytes(data))
    if rec is None:
        return
    t0, t1 = _clean_bin_span()
    for name, s in rec.streams.items():
        assert t0 - 1 <= s.time_s[0] and s.time_s[-1] <= t1 + 1, name


def _fmt_offset(data: bytes, name: bytes) -> int:
    """Offset of the FMT record (0xA3 0x95 0x80 type len name[4] format[16] columns[64]) of NAME."""
    i = data.find(b"\xa3\x95\x80")
    while i >= 0 and data[i + 5:i + 9] != name.ljust(4, b"\0"):
        i = data.find(b"\xa3\x95\x80", i + 1)
    assert i >= 0, name
    return i


@pytest.mark.parametrize("name", [b"IMU", b"BARO", b"RCOU", b"ATT"])
def test_dataflash_with_renamed_columns_counts_the_records(tmp_path, name):
    """Regression (found by fuzzing): damage to an FMT record's column names made the reader
    raise KeyError 'TimeUS'; those records are now counted in skipped.bad_records. (TimeUS into
    TimeUX, 3 bits, is now mended from ArduPilot's definition of the stream, so the rename here
    is too far from it to mend: 'Zzzzzz'.)"""
    clean = shared_file(ARDUSUB / "small.BIN").read_bytes()
    data = bytearray(clean)
    i = _fmt_offset(bytes(data), name)
    cols = bytes(data[i + 25:i + 89])
    data[i + 25:i + 89] = cols.replace(b"TimeUS", b"TimeUX")
    near = _read(tmp_path, "near.bin", bytes(data))
    key = {b"IMU": "imu", b"BARO": "pressure", b"RCOU": "servo", b"ATT": "attitude"}[name]
    np.testing.assert_array_equal(near.streams[key].time_s, _read(tmp_path, "clean.bin", clean).streams[key].time_s)
    data[i + 25:i + 89] = cols.replace(b"TimeUS", b"Zzzzzz")
    rec = _read(tmp_path, "renamed.bin", bytes(data))
    key = name.decode()
    assert rec is not None and rec.messages[key] > 0
    assert rec.skipped.bad_records == rec.messages[key]  # every record of that type, and no other
    assert rec.summary()["bad_records"] == rec.messages[key]
    stream = {"IMU": rec.imu, "BARO": rec.pressure, "RCOU": rec.servo, "ATT": rec.attitude}[key]
    assert stream is None


@pytest.mark.slow
@pytest.mark.parametrize("suffix, small_mb, big_mb", [(".tlog", 0.5, 4), (".bin", 0.02, 0.1)])
def test_megabytes_of_garbage_memory_proportional_and_time_linear(tmp_path, suffix, small_mb, big_mb):
    """Random garbage (the .bin one behind a real FMT header so DFReader scans it all): the
    reader's peak memory is a bounded multiple of the file, and its time is linear in it (the
    .bin reader walks garbage byte by byte in Python, ~3 us/byte, ~100 us under tracemalloc:
    bench/fuzz.py measures it on megabytes).
    Regression: DFReader printed a line per unframed byte, ~8 minutes for 8 MB under pytest."""
    header = shared_file(ARDUSUB / "small.BIN").read_bytes()[:2000] if suffix == ".bin" else b""
    out = {}
    for mb in (small_mb, big_mb):
        n = int(mb * 1_000_000)
        path = tmp_path / f"garbage{mb}{suffix}"
        path.write_bytes(header + random.Random(n).randbytes(n))
        tracemalloc.start()
        t0 = time.perf_counter()
        try:
            read_recording(path)
        except RecordingError:
            pass
        elapsed = time.perf_counter() - t0
        _, peak = tracemalloc.get_traced_memory()
        tracemalloc.stop()
        out[mb] = (peak, elapsed)
    n_big = big_mb * 1_000_000
    assert out[big_mb][0] < 12 * n_big, out  # a few copies of the file at most, no per-byte objects
    ratio = big_mb / small_mb
    assert out[big_mb][1] < ratio * out[small_mb][1] * 2.5 + 1.0, out


# (offset in the FMT record, bit): header, type id, length, name, format character, column, comma
ONE_BIT_FMT_FLIPS = [(1, 3), (3, 2), (4, 1), (5, 0), (6, 2), (25, 0), (28, 1), (31, 0)]


@pytest.mark.parametrize("name", [b"IMU", b"BARO", b"RCOU", b"ATT"])
def test_one_flipped_bit_in_a_dataflash_fmt_record_keeps_the_stream(tmp_path, name):
    """Issue 15, second pass: one flipped bit in a stream's FMT record lost the stream (495 of the
    712 bits of the IMU's). An FMT record carries its own redundancy (length = its format's size,
    a column per format character, ASCII names, its type heading the records after it): the
    flips above are mended and the stream reads whole, as in the clean log. (What the record
    cannot tell, a format character flipped into one of the same size or a column into its
    neighbour's name, is mended from ArduPilot's definitions: the tests below.)"""
    clean_bytes = shared_file(ARDUSUB / "small.BIN").read_bytes()
    clean = _read(tmp_path, "clean.bin", clean_bytes)
    key = {b"IMU": "imu", b"BARO": "pressure", b"RCOU": "servo", b"ATT": "attitude"}[name]
    i = _fmt_offset(clean_bytes, name)
    for at, bit in ONE_BIT_FMT_FLIPS:
        data = bytearray(clean_bytes)
        data[i + at] ^= 1 << bit
        rec = _read(tmp_path, "flipped.bin", bytes(data))
        assert rec is not None and key in rec.streams, (at, bit)
        np.testing.assert_array_equal(rec.streams[key].time_s, clean.streams[key].time_s)


def _imu_fmt_flips(data: bytes, name: bytes = b"IMU"):
    """Each of the 712 one-bit flips of NAME's FMT record in DATA: (offset, bit, flipped bytes)."""
    i = _fmt_offset(data, name)
    for at in range(89):
        for bit in range(8):
            d = bytearray(data)
            d[i + at] ^= 1 << bit
            yield at, bit, bytes(d)


def test_every_one_bit_flip_of_the_imu_fmt_record_is_mended():
    """Issue 15, second pass: 46 of the 712 one-bit flips of small.BIN's IMU FMT record still
    lost the IMU stream, the flips the record cannot tell from another record (`f` into `n`,
    `d` or `g`, `I` into `H`, the format's NUL into a 16th character, `GyrX` into `GyrY`). An FMT
    one bit from ArduPilot's own IMU definition is mended to it: all 712 restore the clean bytes
    (on the first 80 kB of the log: its FMT records and the first 72 IMU records)."""
    from ground.recording import _repair_fmts

    clean = shared_file(ARDUSUB / "small.BIN").read_bytes()[:80_000]
    assert _repair_fmts(clean) == (clean, 0)  # nothing to mend in the clean log
    wrong = [(at, bit) for at, bit, data in _imu_fmt_flips(clean) if _repair_fmts(data)[0] != clean]
    assert not wrong, f"{len(wrong)} of 712 flips not mended: {wrong}"


def test_every_one_bit_flip_of_fmts_own_record_keeps_every_stream(tmp_path):
    """DFReader reads every FMT record after the first with what the FMT record of FMT says:
    'l' of its Columns flipped into ',' lost every stream of small.BIN (and a damaged one lost
    whole logs at 2 % byte flips). That record is a constant of the format: every flip but
    those of its type id restores the clean bytes, and with those 8 (a record defining type 0x81
    as FMT, harmless) and the ',' the streams read as from the clean log (80 kB prefix)."""
    from ground.recording import _repair_fmts

    clean_bytes = shared_file(ARDUSUB / "small.BIN").read_bytes()[:80_000]
    clean = _read(tmp_path, "clean.bin", clean_bytes)
    wrong, lost = [], []
    for at, bit, data in _imu_fmt_flips(clean_bytes, b"FMT"):
        if at != 3 and _repair_fmts(data)[0] != clean_bytes:
            wrong.append((at, bit))
        if at == 3 or (at, bit) == (51, 6):
            rec = _read(tmp_path, "flipped.bin", data)
            if rec is None or set(rec.streams) != set(clean.streams) or any(
                    not np.array_equal(rec.streams[k].time_s, clean.streams[k].time_s) for k in clean.streams):
                lost.append((at, bit))
    assert (wrong, lost) == ([], []), (len(wrong), wrong, lost)


def test_a_comma_flipped_into_any_fmt_records_columns_keeps_every_stream(tmp_path):
    """One bit turns 'l' into ',' (0x6C ^ 0x40): an FMT record then has more columns than format
    characters, and DFReader, which indexes the format by column, raised IndexError at open: in
    69 of the 70 FMT records of small.BIN whose columns hold an 'l' (UNIT's, PARM's, GPS's as well
    as a stream's) that one bit refused the whole log (issue 15, adversarial re-run). Such a
    record is now left unframed (its type unread, counted) and every stream reads as clean."""
    clean_bytes = shared_file(ARDUSUB / "small.BIN").read_bytes()[:80_000]
    clean = _read(tmp_path, "clean.bin", clean_bytes)
    i = clean_bytes.find(b"\xa3\x95\x80")
    lost, n = [], 0
    while i >= 0:
        k = clean_bytes[i + 25:i + 89].find(b"l")
        if k >= 0:
            n += 1
            data = bytearray(clean_bytes)
            data[i + 25 + k] ^= 0x40
            rec = _read(tmp_path, "comma.bin", bytes(data))
            if rec is None or set(rec.streams) != set(clean.streams) or any(
                    not np.array_equal(rec.streams[s].time_s, clean.streams[s].time_s) for s in clean.streams):
                lost.append(clean_bytes[i + 5:i + 9].rstrip(b"\0").decode())
        i = clean_bytes.find(b"\xa3\x95\x80", i + 3)
    assert n == 70 and not lost, (n, lost)


def test_a_damaged_log_that_dfreader_frames_but_cannot_decode_is_counted_not_raised(tmp_path):
    """2 % of small.BIN's bytes flipped (seed 17): DFReader framed records whose FMT, met in the
    middle of the log, has more columns than format characters, and to_dict() raised IndexError
    out of read_recording (a traceback in diagnose, plot and identify). Now: the IMU record, 5
    bits off ArduPilot's definition, is mended (the IMU stream reads), and records whose type id
    flipped into ESC's (11 million rpm; the clean log has no ESC) are dropped as out of range."""
    import random

    data = bytearray(shared_file(ARDUSUB / "small.BIN").read_bytes())
    rng = random.Random(17)
    for _ in range(int(0.02 * len(data))):
        k = rng.randrange(len(data))
        data[k] ^= 1 << rng.randrange(8)
    rec = _read(tmp_path, "two_percent.bin", bytes(data))
    assert rec is not None and len(rec.streams["imu"].time_s) > 400 and rec.skipped.bad_records > 0
    assert "esc" not in rec.streams and rec.skipped.out_of_range.get("esc") == 3


# One flipped bit in FMT records of types no stream reads (FMT record name, offset, bit), each of
# which made DFReader refuse the whole log (found sampling 1,824 flips over all of small.BIN's FMT
# records): a renamed FMTU column, a format character into one of another size, a comma lost or
# into a control character, a type id flipped into MULT's.
ONE_BIT_FLIPS_THAT_REFUSED_THE_LOG = [(b"FMTU", 46, 5), (b"GPS", 10, 0), (b"RASI", 36, 4), (b"RRNI", 45, 3),
                                      (b"RGPI", 42, 1), (b"RGPJ", 3, 5), (b"RGPJ", 55, 5), (b"RMGI", 27, 0),
                                      (b"RMGI", 42, 0), (b"RBCI", 36, 5), (b"RBCI", 15, 0)]


def _same_streams(rec, clean) -> bool:
    return rec is not None and set(rec.streams) == set(clean.streams) and all(
        np.array_equal(rec.streams[k].time_s, clean.streams[k].time_s) for k in clean.streams)


def test_one_flipped_bit_in_an_unread_types_fmt_record_keeps_the_log(tmp_path):
    """Issue 15 re-run: DFReader refused the whole log for one inconsistent FMT record of a type
    nothing reads. Such a record is now mended (UNIT, FMTU and MULT, which DFReader reads itself,
    from ArduPilot's definitions) or left unframed, and every stream reads as from the clean log."""
    clean_bytes = shared_file(ARDUSUB / "small.BIN").read_bytes()[:80_000]
    clean = _read(tmp_path, "clean.bin", clean_bytes)
    lost = []
    for name, at, bit in ONE_BIT_FLIPS_THAT_REFUSED_THE_LOG:
        data = bytearray(clean_bytes)
        data[_fmt_offset(clean_bytes, name) + at] ^= 1 << bit
        if not _same_streams(_read(tmp_path, "flipped.bin", bytes(data)), clean):
            lost.append((name, at, bit))
    assert not lost, lost


@pytest.mark.slow
def test_one_flipped_bit_in_any_fmt_record_keeps_every_stream(tmp_path):
    """12 random bits of each of the 152 FMT records of small.BIN's first 80 kB (1,824 flips,
    seeded): every stream reads as from the clean log (18 lost one before the second pass's
    re-run, 16 of them refusing the whole log; about 2 minutes)."""
    import random

    clean_bytes = shared_file(ARDUSUB / "small.BIN").read_bytes()[:80_000]
    clean = _read(tmp_path, "clean.bin", clean_bytes)
    starts, i = [], clean_bytes.find(b"\xa3\x95\x80")
    while i >= 0:
        starts.append(i)
        i = clean_bytes.find(b"\xa3\x95\x80", i + 1)
    rng = random.Random(1)
    lost = []
    for s in starts:
        for _ in range(12):
            at, bit = rng.randrange(89), rng.randrange(8)
            data = bytearray(clean_bytes)
            data[s + at] ^= 1 << bit
            if not _same_streams(_read(tmp_path, "flipped.bin", bytes(data)), clean):
                lost.append((clean_bytes[s + 5:s + 9].rstrip(b"\0"), at, bit))
    assert len(starts) == 152 and not lost, lost


@pytest.mark.slow
def test_every_one_bit_flip_of_the_imu_fmt_record_keeps_the_imu_stream(tmp_path):
    """The same 712 flips read end to end from the whole small.BIN: the IMU stream equal to the
    clean log's in every one (666 of 712 before the known definitions; about 3 minutes)."""
    clean_bytes = shared_file(ARDUSUB / "small.BIN").read_bytes()
    clean = _read(tmp_path, "clean.bin", clean_bytes).streams["imu"]
    lost = []
    for at, bit, data in _imu_fmt_flips(clean_bytes):
        rec = _read(tmp_path, "flipped.bin", data)
        imu = rec.streams.get("imu") if rec is not None else None
        if imu is None or not (np.array_equal(imu.time_s, clean.time_s) and np.array_equal(imu.accel_frd_m_s2, clean.accel_frd_m_s2)
                               and np.array_equal(imu.gyro_frd_rad_s, clean.gyro_frd_rad_s)):
            lost.append((at, bit))
    assert not lost, f"{len(lost)} of 712 flips lose the IMU stream: {lost}"
