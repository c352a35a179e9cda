"""Writing .tlog recordings: each MAVLink packet preceded by its 8-byte big-endian microsecond time.

The format is the one QGroundControl and MAVProxy write (spec/recording.md section 1), so
pymavlink's `mavutil.mavlink_connection(path)` and `mavlogdump.py` read it. The timestamp is
wall-clock UNIX time in those tools; a simulated recording uses `FIXED_EPOCH_US` + vehicle time
instead, so the same run gives the same file byte for byte.
"""

from __future__ import annotations

import struct
from collections import Counter
from pathlib import Path

from onboard import mavlink_codec

FIXED_EPOCH_US = 1_767_225_600 * 1_000_000  # 2026-01-01T00:00:00Z, the base of simulated tlog time
_TIMESTAMP = struct.Struct(">Q")


class TlogWriter:
    """Append packets to a .tlog; a context manager that flushes and closes on exit.

    `write(msg, timestamp_us)` packs a pymavlink message with this writer's MAVLink object
    (system 1 component 1 by default, its own sequence numbers); `write_packet` stores bytes
    already packed elsewhere (a live link). `counts` says how many of each message were written.
    With `autoflush`, every packet reaches the OS at once (a live recording survives a crash).
    """

    def __init__(self, path: str | Path, mav=None, autoflush: bool = False):
        self.path = Path(path)
        self.mav = mavlink_codec.make_mavlink() if mav is None else mav
        self.autoflush = autoflush
        self.counts: Counter = Counter()
        self.bytes_written = 0
        self._last_us = -1
        self._file = open(self.path, "wb", buffering=1 << 16)

    def write(self, msg, timestamp_us: int) -> None:
        self.write_packet(mavlink_codec.encode(self.mav, msg), timestamp_us, msg.get_type())

    def write_packet(self, packet: bytes, timestamp_us: int, msg_type: str) -> None:
        ts = int(timestamp_us)
        if ts < self._last_us:
            raise ValueError(f"{self.path}: tlog time must not go back ({ts} us after {self._last_us} us)")
        self._last_us = ts
        self._file.write(_TIMESTAMP.pack(ts))
        self._file.write(packet)
        self.bytes_written += _TIMESTAMP.size + len(packet)
        self.counts[msg_type] += 1
        if self.autoflush:
            self._file.flush()

    def flush(self) -> None:
        self._file.flush()

    def close(self) -> None:
        if not self._file.closed:
            self._file.flush()
            self._file.close()

    def __enter__(self) -> "TlogWriter":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
