"""Reading recordings (spec/recording.md section 1): real ArduSub logs, damage counted exactly."""

from __future__ import annotations


import numpy as np
import pytest
from pymavlink import mavutil
from pymavlink.dialects.v20 import ardupilotmega as mav

from conftest import ARDUSUB
from ground.recording import G_MSS, RecordingError, read_recording

DATA = ARDUSUB
needs_data = pytest.mark.usefixtures("ardusub_data")


def _pymavlink_bad_data(path, counts=None):
    """(count, bytes) of BAD_DATA that pymavlink's robust parser reports: the reference.
    `counts`, if given, collects pymavlink's count of each message type from system 1 comp 1."""
    m = mavutil.mavlink_connection(str(path), robust_parsing=True, dialect="ardupilotmega")
    n = nbytes = 0
    while True:
        msg = m.recv_msg()
        if msg is None:
            break
        if msg.get_type() == "BAD_DATA":
            n += 1
            nbytes += len(msg.data)
        elif counts is not None and msg.get_srcSystem() == 1 and msg.get_srcComponent() == 1:
            counts[msg.get_type()] = counts.get(msg.get_type(), 0) + 1
    return n, nbytes


def _packet(msg, sys_id=1, comp_id=1) -> bytes:
    link = mav.MAVLink(None, srcSystem=sys_id, srcComponent=comp_id)
    return msg.pack(link)


def _tlog(records) -> bytes:
    """[8-byte big-endian us][packet] for (t_s, msg) pairs."""
    out = b""
    for t, msg in records:
        out += int(1_700_000_000_000_000 + t * 1e6).to_bytes(8, "big") + _packet(msg)
    return out


def _imu(t):
    return mav.MAVLink_highres_imu_message(int(round(t * 1e6)), 0.1, 0.2, -9.8, 0.01, 0.02, 0.03,
                                           0, 0, 0, 0, 0, 0, 0, 0b111111, 0)


def _pressure(t, pa):
    return mav.MAVLink_scaled_pressure2_message(int(round(t * 1e3)), pa / 100.0, 0.0, 2000, 0)


def _servo(t, pwm):
    return mav.MAVLink_servo_output_raw_message(int(round(t * 1e6)), 0, *pwm)


# --- real logs -----------------------------------------------------------------------------------

@needs_data
def test_small_tlog_bad_crc_counted_like_pymavlink_and_the_rest_read():
    path = DATA / "small.tlog"
    rec = read_recording(path)
    counts: dict = {}
    n_bad, bad_bytes = _pymavlink_bad_data(path, counts)
    assert n_bad == 4  # camera messages (ids 259, 260, 269) whose CRC_EXTRA this dialect does not share
    assert rec.skipped.bad_crc_packets == n_bad
    # every skipped byte is a bad packet plus its 8-byte tlog timestamp; nothing else is lost
    assert rec.skipped.skipped_bytes == bad_bytes + 8 * n_bad
    assert rec.format == "tlog" and rec.vehicle_id == (1, 1)
    # the same messages pymavlink reads from the vehicle, type by type
    assert rec.messages == counts
    assert rec.imu.message == "RAW_IMU"  # SCALED_IMU2 is all zeros in this log (no second IMU)
    assert len(rec.attitude.time_s) == rec.messages["ATTITUDE"]


@needs_data
def test_blueos_log_with_2000_bad_crc_packets():
    path = DATA / "2023-04-18_11-03-34.tlog"
    rec = read_recording(path)
    n_bad, bad_bytes = _pymavlink_bad_data(path)
    assert 1900 < n_bad < 2100
    assert rec.skipped.bad_crc_packets == n_bad
    assert rec.skipped.skipped_bytes == bad_bytes + 8 * n_bad
    assert rec.duration_s > 300
    assert len(rec.servo.time_s) == rec.messages["SERVO_OUTPUT_RAW"] > 600
    # the one ATTITUDE sample whose time goes back is counted, not silently dropped
    assert sum(rec.skipped.non_monotonic.values()) == rec.messages["ATTITUDE"] - len(rec.attitude.time_s)


@needs_data
def test_ardusub_imu_units_mg_and_mrad():
    path = DATA / "small.tlog"
    rec = read_recording(path)
    m = mavutil.mavlink_connection(str(path), dialect="ardupilotmega")
    raw = m.recv_match(type="RAW_IMU")
    assert rec.imu.accel_frd_m_s2[0, 2] == pytest.approx(raw.zacc * 9.80665 / 1000.0)
    assert rec.imu.gyro_frd_rad_s[0, 0] == pytest.approx(raw.xgyro / 1000.0)
    assert rec.imu.time_s[0] == pytest.approx(raw.time_usec * 1e-6)
    # at rest on the bench the specific force is about -g on body z
    assert np.median(rec.imu.accel_frd_m_s2[:, 2]) == pytest.approx(-G_MSS, abs=0.5)
    m = mavutil.mavlink_connection(str(path), dialect="ardupilotmega")
    sp2 = m.recv_match(type="SCALED_PRESSURE2")
    assert rec.pressure.press_abs_pa[0] == pytest.approx(sp2.press_abs * 100.0)  # hPa -> Pa


@needs_data
def test_dataflash_bin():
    rec = read_recording(DATA / "small.BIN")
    assert rec.format == "dataflash"
    assert rec.imu.message == "IMU" and len(rec.imu.time_s) > 500
    assert rec.pressure.message == "BARO"
    assert np.all(np.diff(rec.imu.time_s) > 0)
    assert np.abs(rec.attitude.euler_rad[:, 2]).max() <= np.pi  # degrees became radians
    assert rec.servo.pwm_us.shape[1] == 16 and rec.servo.pwm_us[0, 0] == 1500
    assert rec.skipped.skipped_bytes == 0


# --- damage, built from a known file -------------------------------------------------------------

def _clean(n=50):
    recs = []
    for i in range(n):
        t = i * 0.01
        recs.append((t, _imu(t)))
        if i % 2 == 0:
            recs.append((t, _pressure(t, 101325.0 + i)))
            recs.append((t, _servo(t, [1500 + i] * 8 + [1100 + i] * 8)))
    return recs


def test_clean_synthetic_log_reads_every_field(tmp_path):
    p = tmp_path / "clean.tlog"
    p.write_bytes(_tlog(_clean()))
    rec = read_recording(p)
    assert rec.messages == {"HIGHRES_IMU": 50, "SCALED_PRESSURE2": 25, "SERVO_OUTPUT_RAW": 25}
    assert rec.skipped.skipped_bytes == 0 and rec.skipped.bad_crc_packets == 0
    assert rec.imu.time_s[1] == pytest.approx(0.01)
    assert rec.imu.accel_frd_m_s2[0] == pytest.approx([0.1, 0.2, -9.8], rel=1e-6)
    assert rec.pressure.press_abs_pa[3] == pytest.approx(101325.0 + 6, abs=0.01)  # hPa -> Pa
    assert rec.servo.pwm_us[2, 8] == 1100 + 4  # channel 9: the MAVLink 2 extension field
    assert rec.servo.pwm_us[2, 15] == 1100 + 4  # channel 16


def test_garbage_between_packets_is_skipped_and_counted(tmp_path):
    recs = _clean()
    good = _tlog(recs[:20])
    garbage = bytes(range(1, 38))  # 37 bytes, no MAVLink magic (0xFD = 253, 0xFE = 254)
    p = tmp_path / "garbage.tlog"
    p.write_bytes(good + garbage + _tlog(recs[20:]))
    rec = read_recording(p)
    assert rec.skipped.skipped_bytes == 37
    assert sum(rec.messages.values()) == len(recs)


def test_bad_crc_packet_counted_and_neighbours_kept(tmp_path):
    recs = _clean()
    head, bad, tail = _tlog(recs[:10]), bytearray(_tlog(recs[10:11])), _tlog(recs[11:])
    bad[8 + 12] ^= 0xFF  # a payload byte of the 11th packet (after its timestamp and header)
    p = tmp_path / "crc.tlog"
    p.write_bytes(head + bytes(bad) + tail)
    rec = read_recording(p)
    assert rec.skipped.bad_crc_packets == 1
    assert rec.skipped.skipped_bytes == len(bad)
    assert sum(rec.messages.values()) == len(recs) - 1


def test_truncated_file_reads_up_to_the_torn_packet(tmp_path):
    data = _tlog(_clean())
    p = tmp_path / "torn.tlog"
    p.write_bytes(data[:-7])  # the last packet loses its last 7 bytes
    last = len(_tlog(_clean()[-1:]))
    rec = read_recording(p)
    assert rec.skipped.truncated_bytes == last - 7
    assert rec.skipped.skipped_bytes == last - 7
    assert sum(rec.messages.values()) == len(_clean()) - 1


def test_non_monotonic_time_and_gaps_are_counted(tmp_path):
    times = [0.0, 0.01, 0.02, 0.015, 0.03, 0.04, 0.05, 0.30, 0.31, 0.32]
    p = tmp_path / "time.tlog"
    p.write_bytes(_tlog([(i * 0.01, _imu(t)) for i, t in enumerate(times)]))
    rec = read_recording(p)
    assert rec.skipped.non_monotonic == {"imu": 1}
    assert len(rec.imu.time_s) == 9
    assert ("imu", pytest.approx(0.05), pytest.approx(0.30)) in [(g[0], g[1], g[2]) for g in rec.skipped.gaps]


def test_other_components_are_not_mixed_in(tmp_path):
    recs = _clean(10)
    other = int(1_700_000_000_000_000).to_bytes(8, "big") + _packet(_imu(5.0), sys_id=1, comp_id=194)
    hb = int(1_700_000_000_000_000).to_bytes(8, "big") + _packet(mav.MAVLink_heartbeat_message(
        mav.MAV_TYPE_SUBMARINE, mav.MAV_AUTOPILOT_ARDUPILOTMEGA, 0, 0, 4, 3))
    p = tmp_path / "mixed.tlog"
    p.write_bytes(hb + _tlog(recs) + other)
    rec = read_recording(p)
    assert rec.vehicle_id == (1, 1)
    assert len(rec.imu.time_s) == 10 and rec.imu.time_s.max() < 1.0


def test_unusable_files_give_a_clear_error(tmp_path):
    empty = tmp_path / "empty.tlog"
    empty.write_bytes(b"")
    with pytest.raises(RecordingError, match="empty file"):
        read_recording(empty)
    text = tmp_path / "notes.tlog"
    text.write_text("this is not a telemetry log\n" * 20)
    with pytest.raises(RecordingError, match="no MAVLink packet"):
        read_recording(text)
    with pytest.raises(RecordingError, match="cannot read"):
        read_recording(tmp_path / "missing.tlog")


def test_between_cuts_every_stream(tmp_path):
    p = tmp_path / "clean.tlog"
    p.write_bytes(_tlog(_clean()))
    rec = read_recording(p).between(0.1, 0.2)
    assert rec.imu.time_s[0] == pytest.approx(0.1) and rec.imu.time_s[-1] < 0.2
    assert len(rec.servo.time_s) == 5


def test_esc_telemetry_rpm_is_read_and_placed_on_vehicle_time(tmp_path):
    """Our codec (and ArduSub) send rpm as ESC_TELEMETRY_1_TO_4, which has no time field: the
    reader puts it on vehicle time through the logger clock, beside the SERVO_OUTPUT_RAW it
    was sent with, and its rpm equals what pymavlink decodes."""
    import subprocess
    import sys

    import numpy as np
    from pymavlink import mavutil

    from ground.recording import read_recording
    from onboard.vehicle import DEFAULT_VEHICLE

    out = tmp_path / "esc.tlog"
    subprocess.run([sys.executable, "-m", "ground.cli", "sim", "--commands",
                    str(DEFAULT_VEHICLE.with_name("demo_commands.csv")), "--out", str(out)],
                   check=True, capture_output=True)
    rec = read_recording(out)
    conn = mavutil.mavlink_connection(str(out))
    rpm = []
    while (m := conn.recv_match(type="ESC_TELEMETRY_1_TO_4")) is not None:
        rpm.append(list(m.rpm))
    assert rec.esc is not None and len(rec.esc.time_s) == len(rpm) == len(rec.servo.time_s)
    np.testing.assert_array_equal(rec.esc.rpm, np.array(rpm, float))
    assert np.abs(rec.esc.time_s - rec.servo.time_s).max() < 1e-6
    assert rec.esc.rpm.max() > 1000  # the demo spins the jets up


# --- issue 15: damaged and real-world recordings ---------------------------------------------------

def _pymavlink_good(path) -> int:
    """Messages pymavlink's robust parser recovers from a damaged tlog (the reference to beat)."""
    m = mavutil.mavlink_connection(str(path), robust_parsing=True, dialect="ardupilotmega")
    n = 0
    while (msg := m.recv_msg()) is not None:
        n += msg.get_type() != "BAD_DATA"
    return n


def _spans(data: bytes):
    """(start, end) of every packet's own bytes (not its tlog stamp) in clean tlog bytes."""
    from ground.recording import scan_packets

    buf, off, plen, mid, src, ts = scan_packets(data)
    hdr = np.where(buf[off - 10] == 0xFD, 10, 6)
    return off - hdr, off + plen + 2


def test_flipped_stamp_bit_and_zeroed_start_marker_lose_one_packet(tmp_path):
    """Issue 15 item 7: a bit of one tlog stamp and a zeroed start marker lost 3089 of 3100
    messages (resync trusted the unprotected stamp). Resync on framing and CRC loses only the
    packet whose marker was zeroed, and pymavlink does no better."""
    data = bytearray(_tlog(_clean(1550)))  # 3100 packets
    start, end = _spans(bytes(data))
    assert len(start) == 3100
    data[start[100] - 8] ^= 0x40  # the stamp of packet 100: 2^62 us later
    data[start[101]] = 0  # packet 101's start marker
    p = tmp_path / "two_bytes.tlog"
    p.write_bytes(bytes(data))
    rec = read_recording(p)
    assert sum(rec.messages.values()) == 3099
    assert sum(rec.messages.values()) >= _pymavlink_good(p)
    assert rec.duration_s == pytest.approx(15.49, abs=0.02)


def test_one_percent_bit_flips_every_intact_packet_recovered(tmp_path):
    """Issue 15 item 7: with a bit flipped in 1 % of the bytes, every packet whose own bytes are
    intact is read (its stamp may be hit: it is only a plausibility check), more than pymavlink."""
    clean = _tlog(_clean(1550))
    start, end = _spans(clean)
    rng = np.random.default_rng(15)
    data = bytearray(clean)
    hit = rng.choice(len(data), size=len(data) // 100, replace=False)
    for i in hit:
        data[i] ^= 1 << int(rng.integers(8))
    hits = np.zeros(len(data) + 1, int)
    hits[hit] = 1
    cum = np.concatenate([[0], np.cumsum(hits)])
    intact = (cum[end] - cum[start]) == 0
    p = tmp_path / "flips.tlog"
    p.write_bytes(bytes(data))
    from ground.recording import scan_packets

    buf, off, plen, mid, src, ts = scan_packets(bytes(data))
    got = set(off.tolist())
    hdr = np.where(np.frombuffer(clean, np.uint8)[start + 0] == 0xFD, 10, 6)
    want = set((start + hdr)[intact].tolist())
    assert 0.5 * len(start) < len(want) < len(start)
    assert want <= got, f"{len(want - got)} intact packets lost"
    ours = sum(read_recording(p).messages.values())
    theirs = _pymavlink_good(p)
    assert ours >= len(want) and ours > theirs, (ours, theirs)


def test_nan_and_impossible_samples_dropped_and_counted(tmp_path):
    """Issue 15 item 6: one NaN IMU sample with a good CRC, press_abs 3.4e38 hPa and an inf
    attitude are dropped and counted in the skip summary; the rest is read."""
    recs = _clean(40)
    bad_imu = mav.MAVLink_highres_imu_message(int(0.105 * 1e6), float("nan"), 0.2, -9.8, 0.01, 0.02, 0.03,
                                              0, 0, 0, 0, 0, 0, 0, 0b111111, 0)
    recs.insert(30, (0.105, bad_imu))
    recs.insert(31, (0.105, _pressure(0.105, 3.4e40)))
    recs.append((0.5, mav.MAVLink_attitude_message(500, float("inf"), 0, 0, 0, 0, 0)))
    recs.append((0.51, mav.MAVLink_attitude_message(510, 0.1, 0, 0, 0, 0, 0)))
    p = tmp_path / "nan.tlog"
    p.write_bytes(_tlog(recs))
    rec = read_recording(p)
    assert rec.skipped.out_of_range == {"imu": 1, "pressure": 1, "attitude": 1}
    assert rec.summary()["out_of_range"] == {"imu": 1, "pressure": 1, "attitude": 1}
    assert len(rec.imu.time_s) == 40 and np.isfinite(rec.imu.accel_frd_m_s2).all()
    assert len(rec.pressure.time_s) == 20 and rec.pressure.press_abs_pa.max() < 2e5
    assert len(rec.attitude.time_s) == 1


def test_servo_uint32_clock_of_a_long_up_vehicle_is_put_on_the_imu_clock(tmp_path):
    """Issue 15 item 8: SERVO_OUTPUT_RAW time_usec is uint32 (wraps every 71.6 min). A vehicle up
    for 8580 s logs 14 s during which the servo clock wraps again: the servo stream lands on the IMU's
    uint64 clock (plot showed 4309 s, diagnose found no usable servo stream)."""
    t0 = 8580.0  # up for 2 h 23 min: one wrap before the log, one 9.9 s into it
    recs = []
    for i in range(1400):
        t = t0 + i * 0.01
        recs.append((i * 0.01, _imu(t)))
        if i % 4 == 0:
            servo = _servo(0.0, [1500] * 16)
            servo.time_usec = int(round(t * 1e6)) % 2 ** 32
            recs.append((i * 0.01, servo))
    p = tmp_path / "uptime.tlog"
    p.write_bytes(_tlog(recs))
    rec = read_recording(p)
    assert rec.servo.time_s[0] == pytest.approx(t0, abs=1e-6)
    assert len(rec.servo.time_s) == 350 and np.all(np.diff(rec.servo.time_s) > 0)
    assert rec.duration_s == pytest.approx(13.99, abs=0.01)
    assert rec.skipped.non_monotonic == {} and rec.skipped.gaps == ()


def test_a_vehicle_time_jump_with_a_wrapping_servo_clock_keeps_the_servo_on_the_imu_clock(tmp_path):
    """Issue 15, second pass: the vehicle's time jumps 1e5 s (23.28 servo-clock periods) while the
    logger's clock runs on, in a log of a vehicle up 8580 s. The servo stretch after the jump was
    placed through the logger offset of the whole log (its median, the first stretch's) and stayed
    on its raw uint32 clock, 1e5 s from the IMU; each stretch now takes the logger offset of the
    streams around it in the log."""
    t0, jump = 8580.0, 1e5
    recs, servo_t = [], []
    for i in range(400):
        t = t0 + i * 0.01 + (jump if i >= 200 else 0.0)
        recs.append((i * 0.01, _imu(t)))
        recs.append((i * 0.01, _pressure(t, 101325.0)))
        if i % 4 == 0:
            servo = _servo(0.0, [1500] * 16)
            servo.time_usec = int(round(t * 1e6)) % 2 ** 32
            recs.append((i * 0.01, servo))
            servo_t.append(t)
    p = tmp_path / "jump_wrap.tlog"
    p.write_bytes(_tlog(recs))
    rec = read_recording(p)
    assert len(rec.servo.time_s) == 100
    np.testing.assert_allclose(rec.servo.time_s, servo_t, atol=1e-6)
    assert [len(s.servo.time_s) for s in rec.segments()] == [50, 50]


def test_time_boot_ms_wrapping_in_the_log_is_unwrapped(tmp_path):
    """time_boot_ms is uint32 ms: it wraps after 49.7 days up. A log across the wrap lost every
    pressure sample after it (out of line); they now follow on the IMU's uint64 clock."""
    wrap_s = 2 ** 32 / 1e3
    t0 = wrap_s - 1.0  # the wrap 1 s into a 3 s log
    recs = []
    for i in range(300):
        t = t0 + i * 0.01
        recs.append((i * 0.01, _imu(t)))
        pr = _pressure(0.0, 101325.0 + i)
        pr.time_boot_ms = int(round(t * 1e3)) % 2 ** 32
        recs.append((i * 0.01, pr))
    p = tmp_path / "wrap_ms.tlog"
    p.write_bytes(_tlog(recs))
    rec = read_recording(p)
    assert len(rec.pressure.time_s) == 300 and rec.skipped.non_monotonic == {} and rec.skipped.bad_time == {}
    np.testing.assert_allclose(rec.pressure.time_s, rec.imu.time_s, atol=1e-3)
    assert rec.duration_s == pytest.approx(2.99, abs=0.01)


def test_time_jump_splits_segments_and_an_out_of_line_stamp_is_dropped(tmp_path):
    """Issue 15 items 5 and 9: vehicle time jumping 1e5 s splits the recording into two segments
    (what diagnose works on, memory by the data); one sample whose time has a flipped high bit is
    dropped and counted, not taken as the latest time (which dropped every later sample)."""
    recs = []
    for i in range(200):
        t = i * 0.01 + (1e5 if i >= 100 else 0.0)
        recs.append((t, _imu(t)))
        recs.append((t, _pressure(t, 101325.0)))
    flipped = _imu(0.3)
    flipped.time_usec += 2 ** 52  # 143 years ahead
    recs.insert(61, (0.3, flipped))
    p = tmp_path / "jump.tlog"
    p.write_bytes(_tlog(recs))
    rec = read_recording(p)
    assert len(rec.imu.time_s) == 200 and rec.skipped.bad_time == {"imu": 1}
    assert rec.segment_bounds() == [(0.0, pytest.approx(0.99)), (pytest.approx(1e5 + 1), pytest.approx(1e5 + 1.99))]
    segs = rec.segments()
    assert [len(s.imu.time_s) for s in segs] == [100, 100]
    assert [len(s.pressure.time_s) for s in segs] == [100, 100]
    assert rec.summary()["segments"] == [[0.0, 0.99], [100001.0, 100001.99]]


def test_dataflash_with_bit_flips_has_no_impossible_time(tmp_path, ardusub_data):
    """Issue 15 item 9: the ArduSub .bin with a bit flipped in 0.5 % of its bytes: plot said
    9.2e12 s and diagnose / identify tried to allocate 419 TiB, and a flipped FMT record made
    DFReader refuse the whole log. Impossible and out-of-line times are dropped and counted,
    damaged FMT records counted: every draw reads, within the clean log's span."""
    clean_path = ardusub_data / "small.BIN"
    clean = read_recording(clean_path)
    for seed in range(12):
        rng = np.random.default_rng(seed)
        data = bytearray(clean_path.read_bytes())
        for i in rng.choice(len(data), size=len(data) // 200, replace=False):
            data[i] ^= 1 << int(rng.integers(8))
        p = tmp_path / f"flips{seed}.BIN"
        p.write_bytes(bytes(data))
        rec = read_recording(p)
        assert sum(rec.skipped.bad_time.values()) > 0
        for name, s in rec.streams.items():
            assert s.time_s[0] >= clean.t_start_s - 1 and s.time_s[-1] <= clean.t_end_s + 1, (seed, name)
        assert rec.duration_s <= clean.duration_s + 1
        assert sum(len(s.time_s) for s in rec.streams.values()) > 0.5 * sum(len(s.time_s) for s in clean.streams.values())


def test_a_stream_of_only_nan_samples_is_absent_and_counted(tmp_path):
    """Every IMU sample NaN: the stream is None (as if never sent), the samples counted, and the
    summary still builds (an empty stream made t_start_s raise)."""
    bad = [(i * 0.01, mav.MAVLink_highres_imu_message(i * 10_000, float("nan"), 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0,
                                                        0, 0b111111, 0)) for i in range(20)]
    p = tmp_path / "allnan.tlog"
    p.write_bytes(_tlog(bad + [(0.2, _pressure(0.2, 101325.0))]))
    rec = read_recording(p)
    assert rec.imu is None and rec.skipped.out_of_range == {"imu": 20}
    assert rec.summary()["duration_s"] == 0.0 and rec.segment_bounds() == [(0.2, 0.2)]


def test_dataflash_nan_and_inf_imu_records_dropped_and_counted(tmp_path, ardusub_data):
    """Issue 15 item 6: a NaN or inf in a dataflash IMU record (CRC-free format) reached diagnose."""
    import struct

    data = bytearray((ardusub_data / "small.BIN").read_bytes())
    i = data.find(b"\xa3\x95\x80")
    while data[i + 5:i + 9] != b"IMU\0":
        i = data.find(b"\xa3\x95\x80", i + 1)
    type_id, fmt = data[i + 3], data[i + 9:i + 25].split(b"\0")[0].decode()
    cols = data[i + 25:i + 89].split(b"\0")[0].decode().split(",")
    sizes = {"Q": 8, "q": 8, "B": 1, "b": 1, "H": 2, "h": 2, "I": 4, "i": 4, "f": 4, "d": 8, "c": 2, "C": 2,
             "e": 4, "E": 4, "L": 4, "M": 1, "n": 4, "N": 16, "Z": 64}
    at = {c: 3 + sum(sizes[f] for f in fmt[:k]) for k, c in enumerate(cols)}
    clean = read_recording(ardusub_data / "small.BIN")
    hits = 0
    j = data.find(bytes([0xA3, 0x95, type_id]))
    while j >= 0 and hits < 3:
        if "I" not in at or data[j + at["I"]] == 0:  # the primary IMU (instance 0)
            value = (float("nan"), float("inf"), 3.4e38)[hits]
            data[j + at["AccX"]:j + at["AccX"] + 4] = struct.pack("<f", value)
            hits += 1
        j = data.find(bytes([0xA3, 0x95, type_id]), j + 3)
    p = tmp_path / "nan.BIN"
    p.write_bytes(bytes(data))
    rec = read_recording(p)
    assert rec.skipped.out_of_range == {"imu": 3}
    assert len(rec.imu.time_s) == len(clean.imu.time_s) - 3 and np.isfinite(rec.imu.accel_frd_m_s2).all()
