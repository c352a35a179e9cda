"""SIGTERM stops a jetloop command as Ctrl-C does, wherever it lands (ground/cli.py)."""

from __future__ import annotations

import signal
import subprocess
import sys
import time

# A process that spends half its time in garbage collection with onboard.loop's gc timer
# installed: a signal pending during a collection is handled at the first Python line after it,
# which is the gc callback's (the interpreter swallows an exception raised there). Without the
# handler's deferral about half of the SIGTERMs sent to it are lost.
CHILD = r"""
import gc, sys, time
import onboard.loop  # installs the gc timer callback
from ground import cli
cli._stop_on_sigterm()
heap = [[i, [i]] for i in range(300_000)]
t = time.perf_counter(); gc.collect(); busy = time.perf_counter() - t
print("ready", flush=True)
try:
    while True:
        gc.collect()
        t = time.perf_counter()
        while time.perf_counter() - t < busy:
            pass
except KeyboardInterrupt:
    print("interrupted", flush=True)
    sys.exit(130)
"""


def test_sigterm_during_garbage_collection_still_stops_the_command():
    for k in range(10):
        proc = subprocess.Popen([sys.executable, "-c", CHILD], stdout=subprocess.PIPE, text=True)
        try:
            assert proc.stdout.readline().strip() == "ready"
            time.sleep(0.2 + 0.037 * k)  # land anywhere in the cycle
            proc.send_signal(signal.SIGTERM)
            out, _ = proc.communicate(timeout=10)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.communicate()
            raise AssertionError("SIGTERM during a garbage collection was swallowed: the process ran on")
        assert proc.returncode == 130 and "interrupted" in out
