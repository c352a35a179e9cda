"""The ground recorder: every packet, both directions, into .tlog files rotated by size.

Each packet is stored as it went over the wire (the bytes pymavlink parsed, signature included,
or the bytes the ground packed and sent) behind its 8-byte big-endian microsecond UNIX time,
the .tlog layout MAVProxy and QGroundControl write (spec/recording.md section 1), through
hil.tlog.TlogWriter. `mavlogdump.py`, MAVProxy and QGroundControl read the files.

Files are DIR/PREFIX-YYYYmmdd-HHMMSS-NNN.tlog; a new one starts before a packet would take the
current file past `max_bytes` (a packet is never split across files). Time never goes back in
a file: a wall clock stepped backwards (NTP) is held at the last stamp. The writer buffers
64 KiB and is flushed by `flush_if_due` (every `flush_interval_s`) and on close, so a crash
loses at most that interval, and writing costs no syscall per packet (the full telemetry rate
is kept: bench/bench_ground.py).
"""

from __future__ import annotations

import time
from pathlib import Path

from hil.tlog import TlogWriter

DEFAULT_MAX_BYTES = 64 * 1024 * 1024


class RecorderError(ValueError):
    """A recording directory that cannot be used; the message names it."""


class Recorder:
    def __init__(self, directory, prefix: str = "ground", max_bytes: int = DEFAULT_MAX_BYTES,
                 clock=time.time, flush_interval_s: float = 0.5):
        self.directory = Path(directory)
        if int(max_bytes) < 300:
            raise RecorderError(f"max_bytes {max_bytes}: expected at least 300 (one MAVLink 2 packet + stamp)")
        try:
            self.directory.mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise RecorderError(f"recording directory {self.directory}: cannot create: {exc.strerror or exc}") from exc
        self.prefix = prefix
        self.max_bytes = int(max_bytes)
        self.clock = clock
        self.flush_interval_s = flush_interval_s
        self.files: list[Path] = []
        self.packets = 0
        self.packets_in = 0
        self.packets_out = 0
        self._writer: TlogWriter | None = None
        self._last_us = 0
        self._stem = time.strftime("%Y%m%d-%H%M%S", time.gmtime(clock()))
        self._next_flush = 0.0
        self._open()

    def _open(self) -> None:
        path = self.directory / f"{self.prefix}-{self._stem}-{len(self.files):03d}.tlog"
        try:
            self._writer = TlogWriter(path)
        except OSError as exc:
            raise RecorderError(f"recording file {path}: cannot open: {exc.strerror or exc}") from exc
        self.files.append(path)

    def record(self, packet: bytes, msg_type: str = "?", outgoing: bool = False, timestamp_us: int | None = None) -> None:
        """Store one packet (raw wire bytes) stamped now (or at `timestamp_us`)."""
        w = self._writer
        if w.bytes_written and w.bytes_written + 8 + len(packet) > self.max_bytes:
            w.close()
            self._open()
            w = self._writer
        ts = int(self.clock() * 1e6) if timestamp_us is None else int(timestamp_us)
        ts = max(ts, self._last_us)
        self._last_us = ts
        w.write_packet(packet, ts, msg_type)
        self.packets += 1
        if outgoing:
            self.packets_out += 1
        else:
            self.packets_in += 1

    def record_message(self, msg, outgoing: bool = False) -> None:
        """A received pymavlink message, as the bytes that were parsed."""
        self.record(bytes(msg.get_msgbuf()), msg.get_type(), outgoing)

    def flush_if_due(self, now_s: float | None = None) -> None:
        now = time.monotonic() if now_s is None else now_s
        if now >= self._next_flush:
            self._next_flush = now + self.flush_interval_s
            self._writer.flush()

    def close(self) -> None:
        if self._writer is not None:
            self._writer.close()

    def __enter__(self) -> "Recorder":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
