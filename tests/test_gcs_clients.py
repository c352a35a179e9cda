"""Real ground-station clients against the robot (tests/gcs_rig.Robot: the real-time HIL plant and
the onboard loop over loopback UDP): MAVProxy from PyPI run headless as a process, and MAVSDK
(the `mavsdk` package: MAVSDK's C++ core in-process through its native binding).

What a user does with each, and what must come back: the vehicle detected as 1:1, every parameter
loaded, a gain set that the running controller then flies, arm and a mode change acknowledged,
telemetry of attitude and depth, and none of the warnings a misread vehicle gives (MAVProxy's
"fence breach", parameter re-fetching, unknown modes)."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import threading
import time

import pytest

from conftest import free_udp_port
from gcs_rig import Robot
from onboard import params as P
from onboard.loop import LoopConfig


def _mavproxy(port: int, cwd):
    proc = subprocess.Popen(
        [sys.executable, shutil.which("mavproxy.py"), f"--master=udpin:127.0.0.1:{port}",
         f"--state-basedir={cwd}", f"--logfile={cwd / 'mavproxy.tlog'}"],
        stdout=subprocess.PIPE, stderr=subprocess.STDOUT, stdin=subprocess.PIPE, text=True, cwd=cwd, bufsize=1)
    lines: list = []
    threading.Thread(target=lambda: [lines.append(ln.rstrip()) for ln in proc.stdout], daemon=True).start()
    return proc, lines


def _wait_for(lines, text: str, timeout_s: float) -> bool:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if any(text in ln for ln in list(lines)):
            return True
        time.sleep(0.1)
    return False


@pytest.mark.slow
@pytest.mark.skipif(shutil.which("mavproxy.py") is None, reason="MAVProxy not installed (pip install '.[test]')")
def test_mavproxy_detects_1_1_loads_every_parameter_sets_a_gain_arms_and_changes_mode(tmp_path):
    port = free_udp_port()
    proc, lines = _mavproxy(port, tmp_path)
    robot = None
    try:
        assert _wait_for(lines, "Waiting for heartbeat", 30), lines
        robot = Robot(port, LoopConfig(parameter_file=str(tmp_path / "asr4.params"))).start()
        assert _wait_for(lines, "Detected vehicle 1:1", 15), lines
        assert _wait_for(lines, f"Received {len(P.PARAMS)} parameters", 20), lines

        def say(cmd: str, expect: str) -> None:
            proc.stdin.write(cmd + "\n")
            proc.stdin.flush()
            assert _wait_for(lines, expect, 10), (cmd, lines[-30:])

        say("param set CTL_DEPTH_BW 2.0", "")  # MAVProxy prints nothing on success; the robot flies it
        deadline = time.monotonic() + 10
        while robot.loop.controller.gains.depth_bandwidth_rad_s != 2.0 and time.monotonic() < deadline:
            time.sleep(0.1)
        assert robot.loop.controller.gains.depth_bandwidth_rad_s == 2.0
        say("arm throttle", "Got COMMAND_ACK: COMPONENT_ARM_DISARM: ACCEPTED")
        assert _wait_for(lines, "ARMED", 5) and robot.loop.armed
        say("mode ALT_HOLD", "Got COMMAND_ACK: DO_SET_MODE: ACCEPTED")
        assert _wait_for(lines, "Mode ALT_HOLD", 5)  # the name MAVProxy shows for custom mode 2
        say("param show CTL_DEPTH_BW", "CTL_DEPTH_BW     2.0")
        say("disarm", "Got COMMAND_ACK: COMPONENT_ARM_DISARM: ACCEPTED")
        time.sleep(1.0)
        assert "CTL_DEPTH_BW 2\n" in (tmp_path / "asr4.params").read_text()
    finally:
        if robot is not None:
            robot.stop()
        proc.kill()
        proc.wait(10)
    text = "\n".join(lines)
    for bad in ("fence breach", "Unknown mode", "Unknown command", "Failed", "timeout", "No ack", "Fetching"):
        assert bad.lower() not in text.lower(), (bad, text)
    assert text.count(f"Received {len(P.PARAMS)} parameters") == 1 and "Detected vehicle 1:191" not in text


# -- MAVSDK ---------------------------------------------------------------------------------------

mavsdk = pytest.importorskip("mavsdk", reason="MAVSDK not installed (pip install '.[test]')")
