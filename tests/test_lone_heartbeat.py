"""A real-time onboard loop with no sensor input still says HEARTBEAT at 1 Hz (issue #3)."""

from __future__ import annotations

import threading
import time

from onboard.link import Link
from onboard.loop import OnboardLoop, WallClock
from onboard.vehicle import load_vehicle


def test_lone_real_time_loop_sends_heartbeat_at_1_hz_over_udp():
    """No autopilot, no plant: only a listener on a real UDP socket. Over ~2.5 s a loop that sent
    HEARTBEAT at 1 Hz gives its hello at start plus one at t = 0, 1, 2 s of its ticks: >= 3 in all,
    and >= 2 after the hello (before the fix, the ticks waited for a first sample: the hello only)."""
    listener = Link("udpin:127.0.0.1:0")
    link = Link(f"udpout:127.0.0.1:{listener.local_address[1]}")
    loop = OnboardLoop(load_vehicle(), link, WallClock())
    done = threading.Event()
    robot = threading.Thread(target=loop.run, kwargs=dict(stop=done.is_set), daemon=True)
    beats = []
    t0 = time.monotonic()
    robot.start()
    try:
        while time.monotonic() - t0 < 2.5:
            m = listener.recv(0.05)
            if m is not None and m.get_type() == "HEARTBEAT":
                beats.append(time.monotonic() - t0)
    finally:
        done.set()
        robot.join(5)
        link.close()
        listener.close()
    assert not robot.is_alive()
    assert len(beats) >= 3, beats  # hello + 1 Hz
    gaps = [b - a for a, b in zip(beats[1:], beats[2:])]  # between the 1 Hz ones (after the hello)
    assert all(0.8 < g < 1.5 for g in gaps), beats
    assert loop.stats.steps > 0 and not loop.armed  # it ticked, disarmed: the safe command
