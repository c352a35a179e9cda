"""`jetloop plot`: every standard panel as a PNG plus index.html, on a real ArduSub vehicle's
recordings (.tlog with ~2000 bad-CRC packets, .tlog, dataflash .BIN), a `jetloop sim` recording and
a recording of the onboard loop's telemetry; panels without data say so; bad input is refused."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from conftest import ARDUSUB
from ground.cli import main
from ground.plot import PANELS, _seq, make_plots, read_extras
from ground.recording import read_recording
from hil.tlog import TlogWriter

needs_ardusub = pytest.mark.usefixtures("ardusub_data")


def _pngs_ok(out: Path):
    for name in PANELS:
        data = (out / f"{name}.png").read_bytes()
        assert data[:8] == b"\x89PNG\r\n\x1a\n" and len(data) > 5000, name
    page = (out / "index.html").read_text()
    assert all(f'src="{n}.png"' in page for n in PANELS)
    return page


@needs_ardusub
@pytest.mark.slow
def test_ardusub_tlog_with_bad_crc_packets_counted_and_the_rest_plotted(tmp_path, capsys):
    src = ARDUSUB / "2023-04-18_11-03-34.tlog"
    assert main(["plot", str(src), "--out", str(tmp_path)]) == 0
    rec = read_recording(src)
    bad = rec.skipped.bad_crc_packets
    assert 1500 < bad < 2500  # "about 2000" packets whose CRC fails
    printed = capsys.readouterr().out
    assert f"bad-CRC packets {bad}" in printed
    page = _pngs_ok(tmp_path)
    assert f"<td>bad-CRC packets</td><td>{bad}</td>" in page
    # ArduSub: attitude, depth (SCALED_PRESSURE2), jets (PWM), link are drawn; joints say why not
    assert "no jet joints: an ArduPilot vehicle" in page
    for drawn in ("attitude", "depth", "jets", "timing", "link"):
        assert f"<h2>{drawn}</h2><img" in page


@needs_ardusub
@pytest.mark.slow
def test_ardusub_small_tlog_and_dataflash_bin(tmp_path):
    s = make_plots(ARDUSUB / "small.tlog", tmp_path / "tlog")
    _pngs_ok(tmp_path / "tlog")
    assert s["panels"]["attitude"] == "" and s["panels"]["depth"] == "" and s["panels"]["jets"] == ""
    s = make_plots(ARDUSUB / "small.BIN", tmp_path / "bin")
    _pngs_ok(tmp_path / "bin")
    assert s["format"] == "dataflash"
    assert s["panels"]["attitude"] == "" and s["panels"]["depth"] == ""
    assert "dataflash log is written on board" in s["panels"]["link"]


def test_sim_recording(tmp_path):
    rec = tmp_path / "sim.tlog"
    assert main(["sim", "--commands", str(Path(__file__).resolve().parents[1] / "onboard" / "data" /
                                          "demo_commands.csv"), "--out", str(rec)]) == 0
    s = make_plots(rec, tmp_path / "plots")
    _pngs_ok(tmp_path / "plots")
    for drawn in ("attitude", "depth", "jets", "joints", "timing", "link"):
        assert s["panels"][drawn] == "", (drawn, s["panels"][drawn])
    assert "no allocation telemetry" in s["panels"]["allocation"]


def _telemetry_tlog(path: Path, drop_every: int = 0):
    """The onboard loop's telemetry names, written as a vehicle would send them (seq increments;
    every `drop_every`-th packet left out of the file, as a lossy link would)."""
    mav = mavlink.MAVLink(None, 1, 1)
    t0 = 1_767_225_600_000_000
    n = 0
    with TlogWriter(path, mav=mav) as w:
        for k in range(50):
            ms = 100 * k
            msgs = [mavlink.MAVLink_attitude_message(ms, 0.01 * k, 0, 0, 0, 0, 0),
                    mavlink.MAVLink_named_value_float_message(ms, b"depth", 0.02 * k),
                    mavlink.MAVLink_named_value_float_message(ms, b"depth_sp", 1.0),
                    mavlink.MAVLink_named_value_float_message(ms, b"step_ms", 1.5),
                    mavlink.MAVLink_named_value_float_message(ms, b"alloc_err", 0.1),
                    mavlink.MAVLink_debug_float_array_message(ms * 1000, b"wrench", 1,
                                                              [3.0, 4.0, 0, 0, 0, 12.0] + [0.0] * 52)]
            for m in msgs:
                n += 1
                if drop_every and n % drop_every == 0:
                    m.pack(mav)  # packed (sequence used) but never arrives
                else:
                    w.write(m, t0 + ms * 1000)
                mav.seq = (mav.seq + 1) % 256
    return n


def test_onboard_telemetry_panels_and_loss_from_sequence_numbers(tmp_path):
    path = tmp_path / "tel.tlog"
    n = _telemetry_tlog(path, drop_every=7)
    ex = read_extras(path)
    t, lost, got = ex.link[(1, 1)]
    # 300 packets sent, every 7th missing: 42 lost (floor(300 / 7)), 258 in the file
    assert (n, int(got[-1]), int(lost[-1])) == (300, 300 - 300 // 7, 300 // 7)
    t, v = ex.named["depth"]
    assert len(t) == len(v) and np.all(np.diff(t) > 0)
    wt, dem, ach = ex.wrench
    # residual of the demand (3, 4, 0 | 0, 0, 12) with nothing achieved: |F| = 5 N, |M| = 12 N m
    assert np.allclose(np.linalg.norm(dem[:, :3] - ach[:, :3], axis=1), 5.0)
    assert np.allclose(np.linalg.norm(dem[:, 3:] - ach[:, 3:], axis=1), 12.0)
    s = make_plots(path, tmp_path / "plots")
    for drawn in ("attitude", "depth", "allocation", "timing", "link"):
        assert s["panels"][drawn] == "", drawn
    assert "no actuator output" in s["panels"]["jets"] and "no actuator output" in s["panels"]["joints"]


def test_sequence_numbers_read_from_v1_and_v2_headers():
    from pymavlink.dialects.v10 import ardupilotmega as v1

    m2 = mavlink.MAVLink(None, 1, 1)
    m2.seq = 200
    m1 = v1.MAVLink(None, 1, 1)
    m1.seq = 77
    p2 = bytes(mavlink.MAVLink_attitude_message(1, 1, 1, 1, 1, 1, 1).pack(m2))
    p1 = bytes(v1.MAVLink_attitude_message(1, 1, 1, 1, 1, 1, 1).pack(m1))
    buf = np.frombuffer(b"\0" * 8 + p2 + b"\0" * 8 + p1, np.uint8)
    off = np.array([8 + 10, 8 + len(p2) + 8 + 6])
    plen = np.array([p2[1], p1[1]])
    mid = np.array([30, 30])
    assert list(_seq(buf, off, plen, mid)) == [200, 77]


def test_empty_panels_say_so_and_bad_input_is_refused(tmp_path, capsys):
    only_hb = tmp_path / "hb.tlog"
    with TlogWriter(only_hb) as w:
        for k in range(3):
            w.write(mavlink.MAVLink_heartbeat_message(12, 0, 0, 0, 4, 3), 1_700_000_000_000_000 + k)
    s = make_plots(only_hb, tmp_path / "hb")
    _pngs_ok(tmp_path / "hb")
    assert all(s["panels"][n] for n in PANELS if n != "link")  # every other panel explains itself
    junk = tmp_path / "junk.tlog"
    junk.write_bytes(bytes(range(256)) * 10)
    assert main(["plot", str(junk), "--out", str(tmp_path / "j")]) == 2
    err = capsys.readouterr().err
    assert "junk.tlog: no MAVLink packet with a good CRC found" in err and "Traceback" not in err
    assert main(["plot", str(tmp_path / "missing.tlog"), "--out", str(tmp_path / "m")]) == 2
    assert "cannot read recording" in capsys.readouterr().err


def test_a_recording_with_a_long_gap_plots_with_memory_by_its_data(tmp_path):
    """Issue 15 item 5: the link panel's packet-rate trace had one bin per second of the log's
    span, so a 3 s log whose clocks jump by 4e6 s (46 days) allocated and drew 4 million bins."""
    import tracemalloc

    from pymavlink.dialects.v20 import ardupilotmega as mav

    path = tmp_path / "gap.tlog"
    with TlogWriter(path) as w:
        for i in range(300):
            t = i * 0.01 + (4e6 if i >= 150 else 0.0)
            stamp = 1_700_000_000_000_000 + int(round(t * 1e6))
            if i % 50 == 0:
                w.write(mavlink.MAVLink_heartbeat_message(12, 3, 0, 0, 4, 3), stamp)
            w.write(mav.MAVLink_highres_imu_message(int(round(t * 1e6)), 0, 0, -9.8, 0, 0, 0, 0, 0, 0,
                                                    0, 0, 0, 0, 0b111111, 0), stamp)
            w.write(mav.MAVLink_scaled_pressure2_message(int(round(t * 1e3)), 1013.25, 0, 2000, 0), stamp)
    make_plots(path, tmp_path / "warm")  # matplotlib's own first-use allocations, not counted
    tracemalloc.start()
    try:
        s = make_plots(path, tmp_path / "out")
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 20e6, peak
    assert s["segments"] == [[0.0, 1.49], [4e6 + 1.5, 4e6 + 2.99]]
