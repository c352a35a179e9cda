"""A MAVLink link over UDP or a serial line, chosen by a connection string; never raises on garbage.

Connection strings (the MAVProxy / pymavlink spelling):
    udpin:HOST:PORT     listen on HOST:PORT (port 0: any free port); replies go to the locked peer (below)
    udpout:HOST:PORT    send to HOST:PORT from an ephemeral local port; receive on that port
    /dev/ttyXXX:BAUD    a serial line through pyserial (also `serial:/dev/ttyXXX:BAUD`)
    tlog:PATH           replay a .tlog recording as if it arrived on a link (what is sent is dropped)

The codec is one pymavlink `MAVLink` parser object built from the ardupilotmega dialect module
itself, not from pymavlink's process-wide dialect chosen by an environment variable (STYLE.md).
`Link.recv` returns one decoded message or None; corrupt input is counted and skipped:
`garbage_bytes` (bytes that did not end up in a good packet), `bad_packets` (framed packets
whose CRC or length failed) and `unknown_packets` (ids the dialect does not know). After a bad packet the parser restarts one byte after its start
marker, so a truncated packet does not swallow the good packet that follows it.

A udpin link locks its peer (issue 15): the first sender whose datagram holds a packet of valid
MAVLink (with `signing_key`, one whose MAVLink 2 signature verifies with that key) becomes the
peer; replies, telemetry and actuator output go to it alone, and datagrams from anyone else are
dropped unread and counted (`foreign_datagrams`) until the peer has been silent for
`peer_timeout_s`, when the next sender that proves itself takes over. `peer=(HOST, PORT)` fixes
the peer for good. Junk, or unsigned packets when a key is set, never moves the peer. A udpout
link reads only its peer's datagrams, the same way.
"""

from __future__ import annotations

import math
import re
import select
import socket
import time
from collections import deque
from contextlib import contextmanager
from dataclasses import dataclass

from pymavlink.dialects.v20 import ardupilotmega as mavlink

HEADER_V1_MIN = mavlink.HEADER_LEN_V1 + 2
MAX_DATAGRAM = 60_000  # bytes per UDP datagram when a batch is flushed
START_MARKER = re.compile(rb"[\xfd\xfe]")  # MAVLink 2 / MAVLink 1 start of a packet


class LinkError(ValueError):
    """A connection string that cannot be opened; the message says what was expected."""


@dataclass(frozen=True)
class Endpoint:
    kind: str  # "udpin", "udpout" or "serial"
    host: str = ""
    port: int = 0
    device: str = ""
    baud: int = 0


def parse_peer(peer) -> tuple[str, int]:
    """`HOST:PORT` (or a (host, port) pair) -> (host, port), else a LinkError saying what was expected."""
    if isinstance(peer, tuple) and len(peer) == 2:
        host, port = str(peer[0]), str(peer[1])
    else:
        host, _, port = str(peer).strip().rpartition(":")
    if not host or not port.isdigit() or not 0 < int(port) <= 65535:
        raise LinkError(f"peer {peer!r}: expected HOST:PORT with a port 1..65535")
    try:
        return socket.gethostbyname(host), int(port)
    except OSError as exc:
        raise LinkError(f"peer {peer!r}: unknown host {host!r}") from exc


def parse_connection(text: str) -> Endpoint:
    """`udpin:HOST:PORT`, `udpout:HOST:PORT`, `[serial:]/dev/ttyXXX:BAUD` -> Endpoint."""
    s = str(text).strip()
    expected = "expected udpin:HOST:PORT, udpout:HOST:PORT, /dev/ttyXXX:BAUD or tlog:PATH"
    if s.startswith("tlog:"):
        if not s[5:]:
            raise LinkError(f"link {text!r}: tlog: needs a file path")
        return Endpoint("tlog", device=s[5:])
    for prefix, kind in (("udpin:", "udpin"), ("udp:", "udpin"), ("udpout:", "udpout")):
        if s.startswith(prefix):
            host, sep, port = s[len(prefix):].rpartition(":")
            if not sep or not host or not port.isdigit() or int(port) > 65535:
                raise LinkError(f"link {text!r}: {expected}")
            return Endpoint(kind, host=host, port=int(port))
    if s.startswith("serial:"):
        s = s[len("serial:"):]
    if s.startswith("/") or s.upper().startswith("COM"):
        device, sep, baud = s.rpartition(":")
        if not sep or not device or not baud.isdigit() or int(baud) <= 0:
            raise LinkError(f"link {text!r}: serial needs a baud rate, {expected}")
        return Endpoint("serial", device=device, baud=int(baud))
    raise LinkError(f"link {text!r}: {expected}")


MAX_DATAGRAM = 65535  # the largest UDP payload
PEER_TIMEOUT_S = 5.0  # a udpin peer silent this long may be replaced by the next sender that proves itself
# The socket's receive buffer: a process descheduled for a second (a loaded or virtual machine:
# `jetloop soak` saw the telemetry recorder lose 378 packets in minutes with 40 s of hypervisor
# steal) overflows the default 208 kB, which holds about 200 small datagrams (each costs its
# buffer ~1 kB of kernel memory).
RECV_BUFFER_BYTES = 4 << 20


class _Udp:
    def __init__(self, ep: Endpoint, peer=None, peer_timeout_s: float = PEER_TIMEOUT_S):
        try:
            self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            if ep.kind == "udpin":
                if ep.port != 0:  # Linux may give a port-0 bind a port another SO_REUSEADDR socket holds:
                    # two closed loops at once (test workers) then shared one port and stole packets
                    self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                self.sock.bind((ep.host, ep.port))
                self.peer = None if peer is None else (socket.gethostbyname(peer[0]), int(peer[1]))
            else:
                self.sock.bind(("0.0.0.0" if ep.host not in ("127.0.0.1", "localhost") else ep.host, 0))
                self.peer = (socket.gethostbyname(ep.host), ep.port)
        except OSError as exc:
            raise LinkError(f"link {ep.kind}:{ep.host}:{ep.port}: cannot open UDP socket: {exc.strerror or exc}") from exc
        self.sock.setblocking(False)
        try:  # room for ~4000 small datagrams while this process is not scheduled (default ~200)
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, RECV_BUFFER_BYTES)
        except OSError:
            pass  # the kernel caps it at net.core.rmem_max; refusing it is not an error
        # Datagrams are received into one buffer and copied out at their size: recvfrom(65535)
        # mallocs 64 kB per datagram and shrinks it in place; small objects that settle in the
        # freed tails fragment malloc's heap, and a later 64 kB request then extends it (suspected
        # in the onboard RSS creep hil.soak measured while link faults changed the traffic).
        self._buf = bytearray(MAX_DATAGRAM)
        self._view = memoryview(self._buf)
        self.fixed_peer = ep.kind == "udpout" or peer is not None
        self.peer_timeout_s = float(peer_timeout_s)
        self.peer_heard = -math.inf  # monotonic time of the peer's last datagram
        self.candidate = None  # udpin: the sender of the datagram just read, not (yet) the peer
        self.foreign_datagrams = 0  # datagrams from anyone but the peer, dropped unread (or unproven)
        self.peer_changes = 0  # udpin: times a new peer was locked (the first one included)

    @property
    def local_address(self):
        return self.sock.getsockname()

    def write(self, data: bytes) -> bool:
        if self.peer is None:
            return False  # udpin: nobody has proven itself yet
        try:
            self.sock.sendto(data, self.peer)
            return True
        except OSError:
            return False  # e.g. ICMP port unreachable reported late: the link stays up

    def read(self, timeout_s: float) -> bytes:
        """The next datagram from the peer, or from a sender that may become it (`candidate` set);
        b"" when none came. Another sender's datagram, while the peer holds the link, is dropped."""
        wait = max(timeout_s, 0.0)
        while True:
            try:
                ready, _, _ = select.select([self.sock], [], [], wait)
                if not ready:
                    return b""
                n, addr = self.sock.recvfrom_into(self._buf)
            except (OSError, ValueError):
                return b""
            now = time.monotonic()
            if addr == self.peer:
                self.peer_heard = now
                return bytes(self._view[:n])
            if self.fixed_peer or now - self.peer_heard < self.peer_timeout_s:
                self.foreign_datagrams += 1  # never read, never answered
                wait = 0.0  # what else is already queued may be the peer's
                continue
            self.candidate = addr  # no peer yet, or a silent one: the link decides (Link.lock_peer)
            return bytes(self._view[:n])

    def lock(self, addr) -> None:
        if addr != self.peer:
            self.peer_changes += 1
        self.peer = addr
        self.peer_heard = time.monotonic()

    def close(self) -> None:
        self.sock.close()


class _Serial:
    def __init__(self, ep: Endpoint):
        import serial  # pyserial; imported here so UDP-only use never needs it

        try:
            self.port = serial.Serial(ep.device, ep.baud, timeout=0, write_timeout=1.0)
        except (serial.SerialException, OSError, ValueError) as exc:
            raise LinkError(f"link {ep.device}:{ep.baud}: cannot open serial port: {exc}") from exc
        self.local_address = (ep.device, ep.baud)

    def write(self, data: bytes) -> bool:
        try:
            self.port.write(data)
            return True
        except Exception:  # SerialTimeoutException, OSError on a vanished device: keep running
            return False

    def read(self, timeout_s: float) -> bytes:
        try:
            if not self.port.in_waiting:
                ready, _, _ = select.select([self.port.fileno()], [], [], max(timeout_s, 0.0))
                if not ready:
                    return b""
            return self.port.read(max(self.port.in_waiting, 1))
        except Exception:
            return b""

    def close(self) -> None:
        self.port.close()


MAX_REPLAY_BYTES = 16_000_000_000  # as ground.recording.MAX_RECORDING_BYTES: a day of telemetry is ~1.5 GB


class _Replay:
    """A .tlog read back packet by packet (8-byte big-endian time, then one MAVLink packet)."""

    def __init__(self, ep: Endpoint):
        from .files import read_bounded

        try:
            # a regular file only: `tlog:/dev/zero` read until the kernel's OOM killer stopped it
            # at 23 GB (issue 15 re-run), and a FIFO with no writer blocked open() for good
            self.data = read_bounded(ep.device, MAX_REPLAY_BYTES)
        except OSError as exc:
            raise LinkError(f"link tlog:{ep.device}: cannot read recording: {exc.strerror or exc}") from exc
        self.pos = 0
        self.local_address = (ep.device, 0)

    def write(self, data: bytes) -> bool:
        return True  # a recording does not listen

    def read(self, timeout_s: float) -> bytes:
        d, i = self.data, self.pos
        if i + 9 > len(d):
            self.pos = len(d)
            return d[i + 8:] if i + 8 < len(d) else b""
        start = i + 8
        magic = d[start]
        if magic == 0xFD and start + 3 <= len(d):
            n = 12 + d[start + 1] + (13 if d[start + 2] & 0x01 else 0)
        elif magic == 0xFE and start + 2 <= len(d):
            n = 8 + d[start + 1]
        else:  # not a packet where one should be: hand the rest to the parser, which counts it
            self.pos = len(d)
            return d[start:]
        self.pos = start + n
        return d[start:start + n]

    def close(self) -> None:
        pass


class Link:
    """send(msg) / recv(timeout_s) of MAVLink messages over one transport; counts what was bad."""

    def __init__(self, connection: str, source_system: int = 1, source_component: int = 1, peer=None,
                 peer_timeout_s: float = PEER_TIMEOUT_S, signing_key: bytes | None = None):
        """`peer`: "HOST:PORT" or (host, port), a udpin link's fixed peer; `signing_key`: a udpin
        peer must prove itself with a packet signed with it; `peer_timeout_s`: how long a silent
        udpin peer keeps the link from other senders."""
        self.endpoint = parse_connection(connection)
        self.connection = connection
        kind = self.endpoint.kind
        if peer is not None:
            if kind != "udpin":
                raise LinkError(f"link {connection!r}: a fixed peer applies to udpin links only")
            peer = parse_peer(peer)
        if not (peer_timeout_s > 0):
            raise LinkError(f"peer timeout: expected > 0 s, got {peer_timeout_s!r}")
        self.signing_key = signing_key
        self._io = (_Serial(self.endpoint) if kind == "serial" else _Replay(self.endpoint) if kind == "tlog"
                    else _Udp(self.endpoint, peer, peer_timeout_s))
        self.mav = mavlink.MAVLink(None, srcSystem=source_system, srcComponent=source_component)
        self.mav.robust_parsing = True
        self._ready: deque = deque()
        self._held: list | None = None  # packets waiting for the end of a batch
        self._datagrams = kind in ("udpin", "udpout")  # reads are whole datagrams
        self.bytes_in = 0
        self.good_bytes = 0
        self.bad_packets = 0
        self.unknown_packets = 0
        self.packets_in = 0
        self.packets_out = 0
        self.send_failures = 0

    # -- properties ---------------------------------------------------------------------------
    @property
    def local_address(self):
        return self._io.local_address

    @property
    def has_peer(self) -> bool:
        """Whether sends can go anywhere: always, except a udpin link nobody has spoken to yet."""
        return getattr(self._io, "peer", True) is not None

    @property
    def garbage_bytes(self) -> int:
        """Bytes received that are neither in a good packet nor waiting in the parser."""
        pending = len(self.mav.buf) - self.mav.buf_index
        return self.bytes_in - self.good_bytes - pending

    # -- sending ------------------------------------------------------------------------------
    def pack(self, msg) -> bytes:
        """The wire bytes of `msg` with this link's system/component and sequence number."""
        buf = msg.pack(self.mav)
        self.mav.seq = (self.mav.seq + 1) % 256
        return bytes(buf)

    def send(self, msg) -> bytes:
        """Send one message; returns its wire bytes (for a recording). Never raises on IO errors."""
        buf = self.pack(msg)
        if self._held is not None:
            self._held.append(buf)
        elif self._io.write(buf):
            self.packets_out += 1
        else:
            self.send_failures += 1
        return buf

    @contextmanager
    def batch(self):
        """Messages sent inside go out together: one datagram per frame on UDP (MAVLink is a byte
        stream, so a datagram may carry several packets), one write on a serial line."""
        if self._held is not None:  # already batching: the outer batch flushes
            yield self
            return
        self._held = []
        try:
            yield self
        finally:
            held, self._held = self._held, None
            chunk: list = []
            size = 0
            for buf in held + [None]:  # whole packets per datagram, at most MAX_DATAGRAM bytes
                if buf is None or (chunk and size + len(buf) > MAX_DATAGRAM):
                    if chunk and not self._io.write(b"".join(chunk)):
                        self.send_failures += len(chunk)
                    else:
                        self.packets_out += len(chunk)
                    chunk, size = [], 0
                if buf is not None:
                    chunk.append(buf)
                    size += len(buf)

    def write_raw(self, data: bytes) -> None:
        """Put raw bytes on the line (another sender's packets, tests, fault injection)."""
        if self._held is not None:
            self._held.append(bytes(data))
        else:
            self._io.write(bytes(data))

    # -- receiving ----------------------------------------------------------------------------
    def recv(self, timeout_s: float = 0.0):
        """The next good message, waiting up to `timeout_s` for bytes; None when none came."""
        if self._ready:
            return self._ready.popleft()
        data = self._io.read(timeout_s)
        if data:
            self._take(data)
        # drain what is already in the OS buffer without waiting again
        while not self._ready:
            data = self._io.read(0.0)
            if not data:
                break
            self._take(data)
        return self._ready.popleft() if self._ready else None

    def _take(self, data: bytes) -> None:
        """Parse what the transport read; a udpin datagram from a sender that is not the peer
        makes it the peer if it holds a packet that proves it (`proves_peer`), else its packets
        are dropped and the datagram counted as foreign."""
        io = self._io
        candidate = getattr(io, "candidate", None)
        if candidate is None:
            self.feed(data, datagram=self._datagrams)
            return
        io.candidate = None
        n0 = len(self._ready)
        self.feed(data, datagram=True)
        if any(self.proves_peer(self._ready[i]) for i in range(n0, len(self._ready))):
            io.lock(candidate)
            return
        io.foreign_datagrams += 1
        while len(self._ready) > n0:  # an unproven sender's packets are not delivered
            self._ready.pop()

    def proves_peer(self, msg) -> bool:
        """Whether `msg` may make its sender a udpin link's peer: any good MAVLink packet, or with
        `signing_key` one whose MAVLink 2 signature verifies with the key."""
        if self.signing_key is None:
            return True
        from .signing import signature_fields, signature_ok

        buf = bytes(msg.get_msgbuf())
        return signature_fields(buf) is not None and signature_ok(buf, self.signing_key)

    @property
    def peer(self):
        """Where sends go: (host, port), or None (udpin nobody proved itself to yet; serial, replay)."""
        return getattr(self._io, "peer", None)

    def feed(self, data: bytes, datagram: bool = False) -> None:
        """Parse bytes (from the transport or a replay) into the queue of good messages.

        `datagram`: the bytes are one whole UDP datagram, and MAVLink senders put whole packets in
        a datagram; a frame still incomplete at its end therefore began with a false start
        marker, so it is rescanned from its next byte at once, rather than left waiting for the
        next datagram (in lock-step nothing more may come until this one is answered).
        """
        self.bytes_in += len(data)
        m = self._parse(bytes(data))
        while m is not None:
            self._accept(m)
            m = self._parse(b"")
        while datagram and len(self.mav.buf) - self.mav.buf_index > 0:
            self.bad_packets += 1  # a frame that runs past the end of its datagram (length failed)
            self._resync(bytes(self.mav.buf[self.mav.buf_index + 1:]), drop_pending=True)
            m = self._parse(b"")
            while m is not None:
                self._accept(m)
                m = self._parse(b"")

    def _parse(self, data: bytes):
        mav = self.mav
        if data:
            mav.buf.extend(data)  # what parse_char does first, done here so that
        i = mav.buf_index  # bytes before the next start marker are skipped at C speed (pymavlink
        if i < len(mav.buf) and mav.buf[i] not in (0xFD, 0xFE):  # walks them in Python: ~10 us/byte)
            found = START_MARKER.search(mav.buf, i)
            mav.buf_index = found.start() if found else len(mav.buf)
            mav.expected_length = HEADER_V1_MIN
        try:
            return mav.parse_char(b"")
        except Exception:  # pymavlink raises on a few malformed headers even when robust
            self.mav.buf_index = min(self.mav.buf_index + 1, len(self.mav.buf))
            self._resync(b"")
            return None

    def _accept(self, m) -> None:
        if m.get_type() == "BAD_DATA":
            if not str(m.reason).startswith("Bad prefix"):
                self.bad_packets += 1
                self._rescan(bytes(m.data))
            return
        if isinstance(m, mavlink.MAVLink_unknown):
            # pymavlink cannot check the CRC of an id it does not know, so a truncated packet can
            # pose as one while swallowing the next good packet: rescan it like a bad packet.
            self.unknown_packets += 1
            self._rescan(bytes(m.get_msgbuf()))
            return
        self.packets_in += 1
        self.good_bytes += len(m.get_msgbuf())
        self._ready.append(m)

    def _rescan(self, packet: bytes) -> None:
        """Parse again from one byte past the start of `packet`, which the parser just consumed:
        by stepping back in its buffer when the packet is still there (no copy: a stream of
        garbage with a start marker every ~128 bytes stays linear), else by putting it back."""
        mav, n = self.mav, len(packet)
        i = mav.buf_index
        if n and i >= n and mav.buf[i - n:i] == packet:
            mav.buf_index = i - n + 1
            mav.expected_length = HEADER_V1_MIN
            mav.have_prefix_error = False
        else:
            self._resync(packet[1:])

    def _resync(self, rescan: bytes, drop_pending: bool = False) -> None:
        """Restart parsing at `rescan` + what is still unparsed (one byte past a bad packet's start).
        With `drop_pending`, `rescan` replaces the unparsed bytes instead of going before them."""
        mav = self.mav
        rest = b"" if drop_pending else bytes(mav.buf[mav.buf_index:])
        mav.buf = bytearray(rescan + rest)
        mav.buf_index = 0
        mav.expected_length = HEADER_V1_MIN
        mav.have_prefix_error = False

    def stats(self) -> dict:
        return {
            "packets_in": self.packets_in,
            "packets_out": self.packets_out,
            "bad_packets": self.bad_packets,
            "unknown_packets": self.unknown_packets,
            "garbage_bytes": self.garbage_bytes,
            "send_failures": self.send_failures,
            "foreign_datagrams": getattr(self._io, "foreign_datagrams", 0),
            "peer_changes": getattr(self._io, "peer_changes", 0),
        }

    @property
    def foreign_datagrams(self) -> int:
        """Datagrams from senders other than the peer: dropped unread, or unproven (udpin, udpout)."""
        return getattr(self._io, "foreign_datagrams", 0)

    def close(self) -> None:
        self._io.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
