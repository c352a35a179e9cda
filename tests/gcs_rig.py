"""A robot for ground-station tests: the HIL plant in real time and the onboard loop, each in a
thread of this process, talking MAVLink over loopback UDP; the loop's ground link goes to the
client under test (MAVProxy, MAVSDK, a QGroundControl replay), which listens on `ground_port`.

    plant (udpin, 1:1)  <--HIL-->  onboard loop (main 1:191, ground udpout -> client)  --> client
"""

from __future__ import annotations

import threading

from hil.endpoint import HilEndpoint
from hil.plant import Plant
from onboard.link import Link
from onboard.loop import LoopConfig, OnboardLoop, WallClock
from onboard.vehicle import load_vehicle


class Robot:
    def __init__(self, ground_port: int, config: LoopConfig = LoopConfig(), vehicle=None, seed: int = 3):
        self.vehicle = vehicle or load_vehicle()
        self.plant_link = Link("udpin:127.0.0.1:0", source_system=1, source_component=1)
        self.main = Link(f"udpout:127.0.0.1:{self.plant_link.local_address[1]}", 1, 191)
        self.ground = Link(f"udpout:127.0.0.1:{ground_port}", 1, 191)
        self.endpoint = HilEndpoint(self.vehicle, self.plant_link, Plant(self.vehicle, seed=seed), lockstep=False,
                                    history=False)
        self.loop = OnboardLoop(self.vehicle, self.main, WallClock(), config, ground=self.ground)
        self._stop = threading.Event()
        self.errors: list = []
        self._threads = [threading.Thread(target=self._run, args=(f,), daemon=True)
                         for f in (self._plant, self._robot)]

    def _run(self, f) -> None:
        try:
            f()
        except Exception as exc:  # surfaced by stop()
            self.errors.append(exc)

    def _plant(self) -> None:
        self.endpoint.run(1e6, stop=self._stop.is_set)

    def _robot(self) -> None:
        self.loop.run(stop=self._stop.is_set)

    def start(self) -> "Robot":
        # one time origin: the plant's vehicle time and the loop's wall clock start together (the
        # recorded and reported times agree; the monitor itself counts an IMU sample at its arrival)
        self.loop.clock = WallClock()
        self.loop.start()  # its hello makes the plant start
        self.endpoint.start()
        for t in self._threads:
            t.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(10)
        for lk in (self.main, self.ground, self.plant_link):
            lk.close()
        assert not self.errors, self.errors

    def __enter__(self):
        return self.start()

    def __exit__(self, *exc):
        self.stop()
