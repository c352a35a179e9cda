"""The demo's parties (hil.demo.run_closed_loop, issue 15 item 4): a child that dies at start fails
the run at once with its own error, not after the 300 s start timeout; and when the parent is
killed, its forked children (onboard loop, telemetry recorder) go with it instead of flying on."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from hil.demo import hold_mission, run_closed_loop
from hil.endpoint import EndpointError
from onboard.loop import LoopConfig
from onboard.vehicle import load_vehicle

V = load_vehicle()
ROOT = Path(__file__).resolve().parents[1]


def test_an_onboard_child_that_fails_at_start_fails_the_run_at_once_with_its_error():
    """OnboardLoop refuses the configuration in the child (ground system 0): the run used to wait
    for the whole start timeout before saying so."""
    t0 = time.monotonic()
    with pytest.raises(EndpointError, match=r"the onboard loop failed to start: .*ground_systems: expected system ids"):
        run_closed_loop(V, hold_mission(2.0).setpoints(), 2.0, config=LoopConfig(ground_systems=(0,)),
                        start_timeout_s=60.0)
    assert time.monotonic() - t0 < 30.0


def test_an_onboard_child_killed_at_start_fails_the_run_at_once():
    t0 = time.monotonic()
    with pytest.raises(EndpointError, match=r"the onboard process ended before the flight did \(killed by signal 9\)"):
        run_closed_loop(V, hold_mission(2.0).setpoints(), 2.0, start_timeout_s=60.0,
                        on_start=lambda pids: os.kill(pids["onboard"], signal.SIGKILL))
    assert time.monotonic() - t0 < 30.0


def test_a_recorder_child_killed_in_flight_fails_the_run_at_once():
    """The recorder is supervised as the onboard child is (issue 15, second pass): killed in flight,
    the run used to fly on to the end and write a summary with no telemetry recording behind it.
    Now the flight stops within a second of wall time with the recorder's exit named."""
    pids, periods = {}, []

    def kill_at(ep):
        periods.append(ep.k)
        if ep.k == 100:
            os.kill(pids["recorder"], signal.SIGKILL)

    with pytest.raises(EndpointError, match=r"the recorder process ended before the flight did \(killed by signal 9\)"):
        run_closed_loop(V, hold_mission(120.0).setpoints(), 120.0, start_timeout_s=60.0,
                        on_start=pids.update, on_period=kill_at)
    assert 100 <= periods[-1] < 12_000 - 1  # stopped before the end of the mission
    assert _gone(pids["recorder"]) and _gone(pids["onboard"])


def _gone(pid: int) -> bool:
    """The process no longer runs (absent, or a zombie waiting for whoever adopted it)."""
    try:
        status = Path(f"/proc/{pid}/status").read_text()
    except OSError:
        return True
    return any(line.startswith("State:") and "Z" in line.split()[1] for line in status.splitlines())


SCRIPT = """
import json, sys
from hil.demo import hold_mission, run_closed_loop
from onboard.vehicle import load_vehicle
run_closed_loop(load_vehicle(), hold_mission(600.0).setpoints(), 600.0,
                on_start=lambda pids: print(json.dumps(pids), flush=True))
"""


@pytest.mark.parametrize("when", ["while the onboard starts", "in flight"])
def test_killing_the_parent_leaves_no_orphan(when):
    proc = subprocess.Popen([sys.executable, "-c", SCRIPT], cwd=ROOT, stdout=subprocess.PIPE, text=True)
    children = {}
    try:
        children = json.loads(proc.stdout.readline())
        assert set(children) == {"onboard", "recorder"}
        if when == "in flight":
            time.sleep(5.0)  # the loop starts in ~1 s once compiled (the module's other tests compiled it)
        proc.kill()  # SIGKILL: the parent runs no clean-up at all
        proc.wait(10)
        deadline = time.monotonic() + 15.0
        while time.monotonic() < deadline and not all(_gone(pid) for pid in children.values()):
            time.sleep(0.1)
        alive = {name: pid for name, pid in children.items() if not _gone(pid)}
        assert not alive, f"orphans still running: {alive}"
    finally:
        for pid in children.values():
            if not _gone(pid):
                os.kill(pid, signal.SIGKILL)
        if proc.poll() is None:
            proc.kill()


def test_a_signed_flight_hil_and_onboard_with_the_same_key():
    """With a key the onboard loop refuses every unsigned message, sensor data included (issue 15
    item 1): the plant signs what it sends (HilEndpoint signing_key, `jetloop hil --key`), the
    injected ground setpoints too, and the closed loop flies as without signing."""
    import hashlib

    key = hashlib.sha256(b"signed hil").digest()
    r = run_closed_loop(V, hold_mission(3.0).setpoints(), 3.0, config=LoopConfig(signing_key=key))
    assert r.endpoint["commands_applied"] == r.endpoint["periods"] == 300
    ob = r.onboard
    assert (ob["sig_unsigned"], ob["sig_bad"], ob["sig_replayed"], ob["sensors_refused"]) == (0, 0, 0, 0)
    assert ob["sig_accepted"] > 1000 and ob["failsafe_entries"] == 0
    assert r.truth[-1].pos_ned_m[2] > 0.1  # armed by the signed command, diving towards 0.5 m


def test_jetloop_hil_key_file_errors_are_one_line(tmp_path, capsys):
    from ground.cli import main

    bad = tmp_path / "bad.key"
    bad.write_bytes(b"abc")
    assert main(["hil", "--key", str(bad), "--link", "udpin:127.0.0.1:0"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"jetloop hil: key file {bad}: expected 32 raw bytes or 64 hex digits, got 3 bytes"]


def test_jetloop_hil_peer_is_checked_in_one_line(capsys):
    from ground.cli import main

    assert main(["hil", "--link", "udpout:127.0.0.1:9", "--peer", "127.0.0.1:9"]) == 2
    assert capsys.readouterr().err.strip().splitlines() == [
        "jetloop hil: link 'udpout:127.0.0.1:9': a fixed peer applies to udpin links only"]
