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
