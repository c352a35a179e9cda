"""The browser dashboard (`jetloop ground --web`): its rows from the station's snapshots, its refusals,
and in a real headless Chromium against a real lock-step flight (three `jetloop` processes on
loopback UDP): the plots update, a button's command is acknowledged by the vehicle, and the page
keeps running through link loss and comes back with the link.

Chromium is a required test tool, as MAVProxy is: `.ci/run` installs the Debian packages
(`chromium`, `chromium-driver`) when /usr/bin/chromium is missing, and the browser test fails (does
not skip) without them. `python3 tests/test_web_dashboard.py docs/dashboard.png` flies the same
scene and writes the README's screenshot.
"""

from __future__ import annotations

import math
import os
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import pytest

if __name__ == "__main__":  # run as a script (the README's screenshot): the package from this checkout
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from ground.station import Station
from ground.web import FLAG_HEIGHT, FLAGS, History, columns, parse_port, row, WebError

sys.path.insert(0, str(Path(__file__).resolve().parent))
from conftest import free_udp_port  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
CHROMIUM = Path("/usr/bin/chromium")
CHROMEDRIVER = Path("/usr/bin/chromedriver")
CHROMIUM_FLAGS = ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync",
                  "--window-size=1600,1350")


def free_tcp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


# -- rows and history (pure) -------------------------------------------------------------------------

def _snapshot(**changes):
    from pymavlink.dialects.v20 import ardupilotmega as mavlink

    from onboard.vehicle import load_vehicle

    st = Station(load_vehicle())
    tx, rx = mavlink.MAVLink(None, 1, 1), mavlink.MAVLink(None)
    msgs = [mavlink.MAVLink_heartbeat_message(12, 3, 128, 4, 4, 3),
            mavlink.MAVLink_attitude_message(1000, 0.1, -0.2, 3.0, 0, 0, 0),
            mavlink.MAVLink_named_value_float_message(0, b"depth", 0.4),
            mavlink.MAVLink_named_value_float_message(0, b"failsafe", 1.0),
            mavlink.MAVLink_named_value_float_message(0, b"faults", 16.0),  # JET_DEAD
            mavlink.MAVLink_servo_output_raw_message(0, 0, *([1500] * 16))]
    for m in msgs:
        st.update(rx.parse_char(m.pack(tx)), 10.0)
        tx.seq += 1
    return st, st.snapshot(10.0)


def test_a_row_holds_the_snapshot_in_plot_units_and_flags_on_their_levels():
    st, s = _snapshot()
    r = row(s, 1000.0, 4)
    assert set(r) == set(columns(4))
    assert r["t_ms"] == 1e6
    assert (r["roll"], r["pitch"], r["yaw"]) == pytest.approx((math.degrees(0.1), math.degrees(-0.2), math.degrees(3.0)))
    assert r["depth"] == pytest.approx(0.4)
    assert r["az0"] == pytest.approx(0.0) and r["thrust0"] >= 0.0  # PWM 1500: joints centred
    assert math.isnan(r["u"])  # nothing sent: a gap, not a zero
    assert s.faults == 16
    level = {name: r[f"flag_{name.replace(' ', '_')}"] for name in FLAGS}
    assert level["link up"] == 0 + FLAG_HEIGHT and level["armed"] == 1 + FLAG_HEIGHT
    assert level["failsafe"] == 2 + FLAG_HEIGHT and level["fault"] == 3 + FLAG_HEIGHT
    assert level["warning"] == 4 + FLAG_HEIGHT  # FAILSAFE active is a warning


def test_through_link_loss_a_row_has_gaps_for_the_vehicle_and_the_links_own_figures():
    st, _ = _snapshot()
    st.tick(13.0)  # 3 s of silence > the 2 s timeout
    s = st.snapshot(13.0)
    assert not s.link_up
    r = row(s, 13.0, 4)
    for name in ("roll", "depth", "thrust0", "az0", "el3", "residual", "step_ms"):
        assert math.isnan(r[name]), name  # the station's last values are not news
    assert r["rate_hz"] == 0.0 and r["loss_pct"] == 0.0  # measured by the ground: still there
    assert r["flag_link_up"] == 0.0 and r["flag_warning"] == 4 + FLAG_HEIGHT  # LINK LOST
    assert math.isnan(r["flag_armed"])  # unknown while the link is down


def test_history_gives_each_reader_the_rows_it_has_not_had():
    h = History(("t_ms", "x"), maxlen=3)
    assert h.since(0) == (0, {"t_ms": [], "x": []})
    for i in range(5):
        h.append({"t_ms": i, "x": 10 * i})
    assert h.since(3) == (5, {"t_ms": [3, 4], "x": [30, 40]})
    assert h.since(0) == (5, {"t_ms": [2, 3, 4], "x": [20, 30, 40]})  # only what is kept
    assert h.since(5)[1] == {"t_ms": [], "x": []}


def test_port_is_a_tcp_port_number():
    assert parse_port("8080") == 8080
    for bad in ("0", "65536", "-1", "http", ""):
        with pytest.raises(WebError, match="expected a TCP port number 1-65535"):
            parse_port(bad)


def _ground(args, timeout=60):
    return subprocess.run([sys.executable, "-m", "ground.cli", "ground", *args], cwd=ROOT, capture_output=True,
                          text=True, timeout=timeout)


def test_bad_port_and_port_in_use_are_one_line_each():
    udp = free_udp_port()
    out = _ground(["--web", "--port", "80x", "--link", f"udpin:127.0.0.1:{udp}"])
    assert out.returncode == 2 and out.stderr.splitlines() == [
        "jetloop ground: --port 80x: expected a TCP port number 1-65535"]
    out = _ground(["--port", "8081", "--link", f"udpin:127.0.0.1:{udp}", "--once"])
    assert out.returncode == 2 and out.stderr.splitlines() == ["jetloop ground: --port is the dashboard's: add --web"]
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        out = _ground(["--web", "--port", str(port), "--link", f"udpin:127.0.0.1:{udp}", "--duration", "5"])
    assert out.returncode == 2, out.stdout + out.stderr
    assert out.stderr.splitlines() == [f"jetloop ground: --port {port}: cannot listen on 127.0.0.1:{port}: "
                                       "already in use (another dashboard or server?); choose another with --port"]


# -- in a real browser, against a real flight --------------------------------------------------------

def _until(fn, timeout_s: float, what: str):
    """Poll fn() until it returns something truthy; fail naming `what` and the last value."""
    deadline = time.monotonic() + timeout_s
    last = None
    while time.monotonic() < deadline:
        last = fn()
        if last:
            return last
        time.sleep(0.25)
    pytest.fail(f"{what}: not within {timeout_s:.0f} s (last seen: {last!r})")


def _stop(proc: subprocess.Popen) -> str:
    """End a process this test started (resumed first if it was stopped); its output."""
    if proc.poll() is None:
        try:
            os.kill(proc.pid, signal.SIGCONT)
        except ProcessLookupError:
            pass
        proc.terminate()
        try:
            proc.wait(10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(5)
    return proc.stdout.read() if proc.stdout else ""


def _browser():
    if not CHROMIUM.exists() or not CHROMEDRIVER.exists():
        pytest.fail(f"{CHROMIUM} and {CHROMEDRIVER} are required: apt-get install chromium chromium-driver "
                    "(.ci/run installs them)")
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    opts = webdriver.ChromeOptions()
    opts.binary_location = str(CHROMIUM)
    for f in CHROMIUM_FLAGS:
        opts.add_argument(f)
    profile = tempfile.mkdtemp(prefix="jetloop-chromium-")  # a fresh profile, removed after quit()
    opts.add_argument(f"--user-data-dir={profile}")
    driver = webdriver.Chrome(service=Service(str(CHROMEDRIVER)), options=opts)
    driver.profile_dir = profile
    return driver


# JavaScript run in the page: the Bokeh document's models are what the plots draw. A column's
# summary: [rows, finite values, min, max, last finite value, gaps at the end]
JS_SUMMARY = """
const doc = window.Bokeh && Bokeh.documents && Bokeh.documents[0];
const src = doc && doc.get_model_by_name('telemetry');
if (!src) return null;
const out = {};
for (const k of arguments[0]) {
  const a = Array.from(src.data[k] || []);
  const f = a.filter(Number.isFinite);
  let gaps = 0;
  while (gaps < a.length && !Number.isFinite(a[a.length - 1 - gaps])) gaps++;
  out[k] = [a.length, f.length, f.length ? Math.min(...f) : null, f.length ? Math.max(...f) : null,
            f.length ? f[f.length - 1] : null, gaps];
}
return out;"""
JS_ANY = ("const a = Bokeh.documents[0].get_model_by_name('telemetry').data[arguments[0]];"
          "return Array.from(a).some(x => Math.abs(x - arguments[1]) < 1e-6);")
JS_TEXT = "const m = Bokeh.documents[0].get_model_by_name(arguments[0]); return m ? m.text : null;"
JS_BUTTON = "return Bokeh.index.find_one(Bokeh.documents[0].get_model_by_name(arguments[0])).button_el;"
JS_INPUT = "return Bokeh.index.find_one(Bokeh.documents[0].get_model_by_name(arguments[0])).input_el;"

PANEL_COLUMNS = ("t_ms", "roll", "depth", "depth_sp", "u", "thrust0", "az0", "el0", "residual", "step_ms", "rate_hz",
                 "flag_link_up", "flag_armed")
ROWS, FINITE, MIN, MAX, LAST, GAPS = range(6)


def fly_and_watch(screenshot: Path, settle_s: float = 0.0) -> dict:
    """Plant, onboard loop and `jetloop ground --web` as three processes; Chromium on the page.
    Returns what the page showed (the assertions are the test's)."""
    g, h, http = free_udp_port(), free_udp_port(), free_tcp_port()
    cli = [sys.executable, "-m", "ground.cli"]

    def popen(args, nice=0):
        return subprocess.Popen(cli + args, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.STDOUT,
                                stdin=subprocess.DEVNULL, text=True, preexec_fn=(lambda: os.nice(nice)) if nice else None)
    procs, driver, seen = {}, None, {"timeline": []}
    t0 = time.monotonic()
    mark = lambda what: seen["timeline"].append((round(time.monotonic() - t0, 1), what))  # noqa: E731
    try:
        procs["ground"] = popen(["ground", "--web", "--port", str(http), "--link", f"udpin:127.0.0.1:{g}",
                                 "--duration", "300"])
        # lock-step flies as fast as the CPU allows: below the page and the dashboard under test, so
        # on a busy machine the flight slows down rather than the page
        procs["hil"] = popen(["hil", "--link", f"udpin:127.0.0.1:{h}", "--lockstep", "--mission", "demo",
                              "--duration", "300"], nice=10)
        procs["onboard"] = popen(["onboard", "--link", f"udpout:127.0.0.1:{h}", "--lockstep",
                                  "--ground", f"udpout:127.0.0.1:{g}"], nice=10)
        driver = _browser()
        mark("browser up")

        def listening():  # a connection only: each page request builds a document on the server
            if procs["ground"].poll() is not None:
                pytest.fail("the dashboard ended: " + procs["ground"].stdout.read())
            try:
                socket.create_connection(("127.0.0.1", http), timeout=1).close()
                return True
            except OSError:
                return False
        _until(listening, 60, "the dashboard listening")
        driver.get(f"http://127.0.0.1:{http}/")
        mark("page loaded")
        summary = lambda: driver.execute_script(JS_SUMMARY, PANEL_COLUMNS)  # noqa: E731
        text = lambda name: driver.execute_script(JS_TEXT, name) or ""  # noqa: E731
        # the flight's telemetry reaches the plots' data source ...
        seen["first"] = _until(lambda: (d := summary()) and d["thrust0"][FINITE] >= 20 and d, 90,
                               "20 rows of jet thrust in the page")
        mark("telemetry in the page")
        time.sleep(3.0)
        seen["second"] = summary()
        # ... a button sends a command the vehicle acknowledges (MAV_CMD_DO_SET_MODE = 176) ...
        driver.execute_script(JS_BUTTON, "mode-guided").click()
        seen["ack"] = _until(lambda: "command 176: accepted" in (t := text("events")) and t, 60,
                             "the mode command's COMMAND_ACK in the events")
        seen["feedback"] = text("feedback")
        mark("ack shown")
        # ... a typed command line is sent too: the vehicle's depth setpoint telemetry follows it
        box = driver.execute_script(JS_INPUT, "in-command")
        box.clear()
        box.send_keys("depth 0.35")
        driver.execute_script(JS_BUTTON, "cmd-send").click()
        _until(lambda: driver.execute_script(JS_ANY, "depth_sp", 0.35), 60, "depth setpoint 0.35 in the plots")
        seen["feedback_depth"] = text("feedback")
        mark("typed depth flown")
        time.sleep(settle_s)
        driver.save_screenshot(str(screenshot))
        # the link is lost: the onboard loop is frozen (SIGSTOP), the page goes on
        os.kill(procs["onboard"].pid, signal.SIGSTOP)
        seen["lost_status"] = _until(lambda: "LINK LOST" in (t := text("status")) and t, 30, "LINK LOST on the page")
        mark("link lost shown")
        seen["during0"] = summary()
        time.sleep(2.0)
        seen["during1"] = summary()
        driver.execute_script(JS_BUTTON, "cmd-disarm").click()  # the page still takes commands
        seen["feedback_lost"] = _until(lambda: "disarm" in (t := text("feedback")) and t, 30, "the disarm click answered")
        # and the link comes back
        os.kill(procs["onboard"].pid, signal.SIGCONT)
        seen["back_status"] = _until(lambda: "link UP" in (t := text("status")) and t, 60, "link UP again on the page")
        seen["back_events"] = text("events")
        mark("link back shown")
        seen["after"] = _until(lambda: (d := summary()) and d["roll"][GAPS] == 0 and d["thrust0"][GAPS] == 0 and d, 60,
                               "attitude and thrust rows again after the link came back")
        mark("attitude again")
        seen["browser_log"] = [e for e in driver.get_log("browser") if e.get("level") == "SEVERE"]
        return seen
    finally:
        if driver is not None:
            driver.quit()
            shutil.rmtree(driver.profile_dir, ignore_errors=True)
        print("timeline (s):", seen["timeline"])
        for name, p in procs.items():  # shown by pytest when the test fails
            print(f"--- jetloop {name} (exit {p.poll()}):\n{_stop(p)[-3000:]}")


@pytest.mark.slow
def test_dashboard_in_chromium_plots_a_live_flight_sends_commands_and_rides_out_link_loss(tmp_path):
    png = tmp_path / "dashboard.png"
    seen = fly_and_watch(png)
    first, second = seen["first"], seen["second"]
    # the plots' data source grows and its values change (the flight moves)
    assert second["t_ms"][ROWS] >= first["t_ms"][ROWS] + 10, (first["t_ms"], second["t_ms"])  # 3 s at 10 rows/s
    assert second["t_ms"][LAST] > first["t_ms"][LAST]
    for k in ("roll", "depth", "thrust0", "az0", "step_ms", "rate_hz"):
        assert second[k][FINITE] > first[k][FINITE], (k, first[k], second[k])  # new values came
        assert second[k][MAX] > second[k][MIN], (k, second[k])  # and they move: not a flat line
    for k in PANEL_COLUMNS:  # every panel has data
        assert second[k][FINITE] > 0, k
    # the button: COMMAND_LONG out, COMMAND_ACK back from the vehicle, shown in the events
    assert "command 176: accepted" in seen["ack"]
    assert "sent <b>mode guided</b>" in seen["feedback"]
    assert "sent <b>depth 0.35</b>" in seen["feedback_depth"]
    # link loss: rows keep coming, the vehicle's values are gaps, the link flag is down
    d0, d1 = seen["during0"], seen["during1"]
    assert d1["t_ms"][LAST] > d0["t_ms"][LAST] and d1["t_ms"][GAPS] == 0
    assert d1["roll"][GAPS] >= 10 and d1["thrust0"][GAPS] >= 10, (d1["roll"], d1["thrust0"])  # 2 s of gaps at least
    assert d1["flag_link_up"][LAST] == 0.0 and d1["rate_hz"][GAPS] == 0
    assert "LINK LOST" in seen["lost_status"]
    assert "sent <b>disarm</b>" in seen["feedback_lost"]
    # the link back: the status says so and the lines resume
    assert "link UP" in seen["back_status"]
    # the lines resume: the gaps at the end of the attitude and thrust columns are gone (a count of
    # finite values would not do: a full window rolls over, and old finite rows leave as the gaps came)
    after = seen["after"]
    assert after["roll"][GAPS] == 0 and after["thrust0"][GAPS] == 0 and after["t_ms"][LAST] > d1["t_ms"][LAST]
    assert seen["browser_log"] == []  # no errors in the page (websocket, scripts)
    head = png.read_bytes()[:8]
    assert head == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 50_000  # a page of plots, not a blank one


if __name__ == "__main__":  # the README's screenshot: python3 tests/test_web_dashboard.py docs/dashboard.png
    target = Path(sys.argv[1] if len(sys.argv) > 1 else "docs/dashboard.png")
    target.parent.mkdir(parents=True, exist_ok=True)
    got = fly_and_watch(target, settle_s=10.0)  # the dive and the turn in the plots
    print(got["timeline"])
    print(f"wrote {target}: {got['second']['t_ms'][ROWS]} rows in the page, ack: {'command 176: accepted' in got['ack']}")
