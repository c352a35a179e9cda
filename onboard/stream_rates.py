"""Telemetry stream rates on the robot: which message is due when, set by SET_MESSAGE_INTERVAL."""

from __future__ import annotations

import math

from pymavlink.dialects.v20 import ardupilotmega as mavlink


class StreamRates:
    """Which telemetry message is due: defaults per message name, changed by SET_MESSAGE_INTERVAL.

    `handle(msg)` takes a COMMAND_LONG and returns a MAV_RESULT (None if it is not one);
    `due(name, t_s)` is True when `name` should be sent at time t_s (and books it).
    """

    def __init__(self, default_hz: dict):
        self.default_hz = {k.upper(): float(v) for k, v in default_hz.items()}
        self.rate_hz = dict(self.default_hz)
        self._next: dict = {}

    def handle(self, msg):
        if msg.get_type() != "COMMAND_LONG" or int(msg.command) != mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
            return None
        if not (math.isfinite(msg.param1) and math.isfinite(msg.param2)):  # int(round(inf)) raises
            return mavlink.MAV_RESULT_DENIED
        cls = mavlink.mavlink_map.get(int(round(msg.param1)))
        if cls is None:
            return mavlink.MAV_RESULT_DENIED
        name, interval = cls.msgname, float(msg.param2)
        if interval < 0:
            self.rate_hz[name] = 0.0
        elif interval == 0:
            self.rate_hz[name] = self.default_hz.get(name, 0.0)
        else:
            self.rate_hz[name] = 1e6 / interval
        self._next.pop(name, None)
        return mavlink.MAV_RESULT_ACCEPTED

    def set_hz(self, name: str, hz: float, default: bool = False) -> None:
        """Set a stream's rate directly (REQUEST_DATA_STREAM, a MAVLink parameter); `default`: also
        the rate an interval of 0 returns to."""
        self.rate_hz[name] = float(hz)
        if default:
            self.default_hz[name] = float(hz)
        self._next.pop(name, None)

    def due(self, name: str, t_s: float) -> bool:
        hz = self.rate_hz.get(name, self.default_hz.get(name, 0.0))
        if hz <= 0:
            return False
        nxt = self._next.get(name, -math.inf)
        if t_s + 1e-9 < nxt:
            return False
        # next slot on the rate's grid (no drift), or from now when a slot was missed
        self._next[name] = max(nxt + 1.0 / hz, t_s + 0.5 / hz) if math.isfinite(nxt) else t_s + 1.0 / hz
        return True
