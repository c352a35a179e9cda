"""MAVProxy (from PyPI), run headless, sees our onboard telemetry as a submarine with attitude.

The telemetry is the onboard loop's own (OnboardLoop.start + step on a udpout link, no sensors:
disarmed, level). MAVProxy listens with `--master=udpin:127.0.0.1:PORT --non-interactive` and
writes what it receives to its telemetry log; `mavlogdump.py` (pymavlink's tool) reads that log.
"""

from __future__ import annotations

import shutil
import subprocess
import sys
import time

import pytest

from onboard.link import Link
from onboard.loop import LoopConfig, OnboardLoop, WallClock
from onboard.vehicle import load_vehicle
from conftest import free_udp_port

pytestmark = pytest.mark.skipif(shutil.which("mavproxy.py") is None or shutil.which("mavlogdump.py") is None,
                                reason="MAVProxy not installed (pip install '.[test]')")


@pytest.mark.slow  # MAVProxy takes ~15 s to start here
def test_mavproxy_headless_sees_a_submarine_heartbeat_and_attitude(tmp_path):
    port = free_udp_port()
    log = tmp_path / "mavproxy.tlog"
    proc = subprocess.Popen(
        [sys.executable, shutil.which("mavproxy.py"), f"--master=udpin:127.0.0.1:{port}", "--non-interactive",
         f"--logfile={log}", f"--state-basedir={tmp_path}"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, text=True, cwd=tmp_path)
    try:
        deadline = time.monotonic() + 30.0
        while not log.exists() and time.monotonic() < deadline:  # MAVProxy is listening once it logs
            time.sleep(0.1)
        assert log.exists(), "MAVProxy did not start"
        link = Link(f"udpout:127.0.0.1:{port}")
        loop = OnboardLoop(load_vehicle(), link, WallClock(), LoopConfig())
        loop.start()
        for k in range(300):  # 3 s at 100 Hz: 3 heartbeats, 30 ATTITUDE at the default 10 Hz
            loop.step(0.01 * k)
            time.sleep(0.01)
        link.close()
        time.sleep(1.0)
    finally:
        proc.terminate()
        try:
            out, _ = proc.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            out, _ = proc.communicate()
    assert "Detected vehicle 1:1" in out, out
    assert "online system 1" in out, out
    dump = subprocess.run([sys.executable, shutil.which("mavlogdump.py"), "--types", "HEARTBEAT,ATTITUDE", str(log)],
                          capture_output=True, text=True, timeout=60)
    assert dump.returncode == 0, dump.stderr
    sub = [ln for ln in dump.stdout.splitlines() if "HEARTBEAT" in ln and "type : 12" in ln]  # MAV_TYPE_SUBMARINE
    att = [ln for ln in dump.stdout.splitlines() if "ATTITUDE" in ln]
    assert len(sub) >= 2 and len(att) >= 20
