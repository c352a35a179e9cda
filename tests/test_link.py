"""The MAVLink link: connection strings, real UDP sockets on 127.0.0.1, a real pseudo-terminal pair
for the serial line, and corrupt input counted byte for byte without ever raising."""

from __future__ import annotations

import os
import time

import numpy as np
import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from onboard.link import Endpoint, Link, LinkError, parse_connection


def heartbeat(custom_mode: int = 0):
    return mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_SUBMARINE, 0, 0, custom_mode, 0, 3)


def drain(link: Link, timeout_s: float = 0.3) -> list:
    out = []
    deadline = time.monotonic() + 5.0
    while time.monotonic() < deadline:
        m = link.recv(timeout_s)
        if m is None:
            break
        out.append(m)
    return out


# -- connection strings -----------------------------------------------------------------------

def test_connection_strings():
    assert parse_connection("udpin:0.0.0.0:14550") == Endpoint("udpin", host="0.0.0.0", port=14550)
    assert parse_connection("udpout:127.0.0.1:14551") == Endpoint("udpout", host="127.0.0.1", port=14551)
    assert parse_connection("/dev/ttyACM0:115200") == Endpoint("serial", device="/dev/ttyACM0", baud=115200)
    assert parse_connection("serial:/dev/ttyUSB1:57600") == Endpoint("serial", device="/dev/ttyUSB1", baud=57600)
    assert parse_connection("tlog:rec/flight.tlog") == Endpoint("tlog", device="rec/flight.tlog")


@pytest.mark.parametrize("bad", ["udpin:14550", "udpout:host:port", "tcp:1.2.3.4:5", "/dev/ttyS0", "udpin:h:70000", "", "tlog:"])
def test_bad_connection_string_names_what_was_expected(bad):
    with pytest.raises(LinkError, match="expected udpin:HOST:PORT|needs a file path"):
        parse_connection(bad)


def test_serial_device_that_does_not_exist_is_a_clear_error():
    with pytest.raises(LinkError, match="/dev/does-not-exist:9600: cannot open serial port"):
        Link("/dev/does-not-exist:9600")


# -- UDP ----------------------------------------------------------------------------------------

@pytest.fixture
def udp_pair():
    server = Link("udpin:127.0.0.1:0", source_system=1, source_component=1)
    client = Link(f"udpout:127.0.0.1:{server.local_address[1]}", source_system=255, source_component=190)
    yield server, client
    server.close()
    client.close()


def test_udp_round_trip_and_reply_to_last_speaker(udp_pair):
    server, client = udp_pair
    assert not server.has_peer and client.has_peer
    server.send(heartbeat())  # nobody has spoken to udpin yet: counted, not raised
    assert server.send_failures == 1
    client.send(heartbeat(custom_mode=7))
    m = server.recv(1.0)
    assert server.has_peer
    assert m.get_type() == "HEARTBEAT" and m.custom_mode == 7
    assert (m.get_srcSystem(), m.get_srcComponent()) == (255, 190)
    server.send(heartbeat(custom_mode=9))  # goes back to the client's port
    r = client.recv(1.0)
    assert r.custom_mode == 9 and r.get_srcSystem() == 1
    assert client.recv(0.05) is None


def test_udp_datagrams_are_copied_out_of_the_one_receive_buffer(udp_pair):
    """The transport receives every datagram into one buffer: what `read` returns must be a copy
    at the datagram's size, not overwritten by the next one, and the largest datagram still fits."""
    server, client = udp_pair
    io = server._io
    big = os.urandom(65507)  # the largest IPv4 UDP payload
    for payload in (b"first", big, b"x"):
        client.write_raw(payload)
    got = [io.read(1.0) for _ in range(3)]
    assert got == [b"first", big, b"x"]
    assert all(type(g) is bytes for g in got)


def test_sequence_numbers_advance_per_packet(udp_pair):
    server, client = udp_pair
    for _ in range(3):
        client.send(heartbeat())
    seqs = [m.get_seq() for m in drain(server)]
    assert seqs == [0, 1, 2]


def test_udp_garbage_and_truncated_packets_are_counted_and_skipped(udp_pair):
    server, client = udp_pair
    good = client.pack(heartbeat(custom_mode=3))
    assert len(good) == 10 + 9 + 2  # MAVLink 2 header + HEARTBEAT payload + CRC
    junk = b"garbage!!"  # 9 bytes, no start marker
    truncated = good[:7]  # a header cut short: the parser must not lose the packet after it
    bad_flags = b"\xfd\x05xx"  # start marker, length 5, invalid incompatibility flags
    client.write_raw(junk + truncated + good + bad_flags + good)
    msgs = drain(server)
    assert [m.custom_mode for m in msgs] == [3, 3]
    assert server.garbage_bytes == len(junk) + len(truncated) + len(bad_flags)  # 20
    assert server.bad_packets + server.unknown_packets == 2  # the cut header and the bad flags
    assert server.packets_in == 2


def test_random_bytes_never_raise_and_are_all_counted():
    link = Link("udpin:127.0.0.1:0")
    rng = np.random.default_rng(1)
    noise = rng.integers(0, 256, 50_000, dtype=np.uint8).tobytes()
    for i in range(0, len(noise), 997):
        link.feed(noise[i:i + 997])
    pending = len(link.mav.buf) - link.mav.buf_index
    assert link.packets_in == 0 and link.bad_packets > 0  # false frames were found and rejected
    assert pending <= 280  # at most one partly framed packet (max MAVLink 2 length) waits
    assert link.garbage_bytes == len(noise) - pending
    # and a good packet afterwards (after enough bytes to complete any false frame) still comes out
    tail = b"".join(link.pack(heartbeat(custom_mode=i)) for i in range(20))
    link.feed(tail)
    modes = [m.custom_mode for m in iter(lambda: link.recv(0.0), None) if m.get_type() == "HEARTBEAT"]
    assert modes[-5:] == [15, 16, 17, 18, 19]


# -- serial through a real pseudo-terminal pair -------------------------------------------------

@pytest.fixture
def pty_link():
    master, slave = os.openpty()
    name = os.ttyname(slave)
    link = Link(f"{name}:115200")
    yield master, link
    link.close()
    os.close(master)
    os.close(slave)


def read_master(fd: int, n: int, timeout_s: float = 2.0) -> bytes:
    import select

    out = b""
    deadline = time.monotonic() + timeout_s
    while len(out) < n and time.monotonic() < deadline:
        ready, _, _ = select.select([fd], [], [], 0.1)
        if ready:
            out += os.read(fd, 4096)
    return out


def test_serial_pty_both_directions(pty_link):
    master, link = pty_link
    link.send(heartbeat(custom_mode=42))
    wire = read_master(master, 21)
    other = mavlink.MAVLink(None)
    m = other.parse_char(wire)
    assert m.get_type() == "HEARTBEAT" and m.custom_mode == 42
    peer = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
    os.write(master, heartbeat(custom_mode=5).pack(peer))
    got = link.recv(1.0)
    assert got.custom_mode == 5 and got.get_srcSystem() == 255


def test_serial_pty_garbage_between_packets(pty_link):
    master, link = pty_link
    peer = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
    rng = np.random.default_rng(7)
    sent_junk = 0
    for i in range(20):
        junk = rng.integers(0, 256, 13, dtype=np.uint8).tobytes().replace(b"\xfd", b"\x00").replace(b"\xfe", b"\x00")
        pkt = heartbeat(custom_mode=i).pack(peer)
        peer.seq = (peer.seq + 1) % 256
        os.write(master, junk + pkt[: 5 + i % 3] + pkt)  # junk, a truncated copy, the real packet
        sent_junk += len(junk) + 5 + i % 3
    msgs = drain(link)
    assert [m.custom_mode for m in msgs] == list(range(20))
    assert link.garbage_bytes == sent_junk


def test_tlog_replay_reads_packets_in_order_and_counts_a_torn_tail(tmp_path):
    src = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    path = tmp_path / "r.tlog"
    blob = b""
    for i in range(5):
        pkt = heartbeat(custom_mode=i).pack(src)
        src.seq += 1
        blob += (1_000_000 + i).to_bytes(8, "big") + pkt
    path.write_bytes(blob + (2_000_000).to_bytes(8, "big") + pkt[:9])  # a packet cut by a crash
    link = Link(f"tlog:{path}")
    link.send(heartbeat())  # a recording does not listen: dropped, not an error
    assert [m.custom_mode for m in drain(link, 0.0)] == [0, 1, 2, 3, 4]
    assert link.garbage_bytes == 0 and len(link.mav.buf) - link.mav.buf_index == 9  # waiting, not lost
    with pytest.raises(LinkError, match="cannot read recording"):
        Link(f"tlog:{tmp_path / 'missing.tlog'}")


def test_udp_false_start_marker_does_not_hold_the_rest_of_the_datagram(udp_pair):
    """A 0xFD in garbage announces a 255-byte frame that never comes; on a stream the parser would
    wait for it, but a UDP datagram holds whole packets, so the packet after it is out at once."""
    server, client = udp_pair
    good1 = client.pack(heartbeat(custom_mode=1))
    good2 = client.pack(heartbeat(custom_mode=2))
    client.write_raw(good1 + b"\xfd\xff\x00" + good2)  # one datagram, nothing after it
    msgs = drain(server, 0.2)
    assert [m.custom_mode for m in msgs] == [1, 2]
    assert server.garbage_bytes == 3
    assert len(server.mav.buf) - server.mav.buf_index == 0  # nothing left waiting


def test_a_udpout_link_reads_only_its_peer_and_counts_the_rest():
    """udpout talks to one peer: a datagram from another host (127.0.0.2 here) is dropped unread
    and counted, so nobody but the configured peer can feed the robot MAVLink over that link."""
    import socket

    from pymavlink.dialects.v20 import ardupilotmega as mavlink

    peer = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    stranger = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    peer.bind(("127.0.0.1", 0))
    stranger.bind(("127.0.0.2", 0))
    link = Link(f"udpout:127.0.0.1:{peer.getsockname()[1]}", source_system=1, source_component=1)
    try:
        packet = bytes(mavlink.MAVLink_heartbeat_message(12, 0, 0, 0, 0, 3).pack(mavlink.MAVLink(None, 255, 190)))
        stranger.sendto(packet, link.local_address)
        assert link.recv(0.5) is None
        assert link.stats()["foreign_datagrams"] == 1
        assert link.stats()["packets_in"] == 0
        peer.sendto(packet, link.local_address)
        m = link.recv(1.0)
        assert m is not None and m.get_type() == "HEARTBEAT"
        assert link.stats()["foreign_datagrams"] == 1
    finally:
        link.close()
        peer.close()
        stranger.close()


# -- a udpin link's peer is locked (issue 15 item 2) ----------------------------------------------

def _sock(host: str = "127.0.0.1"):
    import socket

    s = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    s.bind((host, 0))
    s.settimeout(0.3)
    return s


def _got(sock) -> list:
    """Datagrams waiting on a plain socket (what a sender would get back)."""
    import socket

    out = []
    while True:
        try:
            out.append(sock.recv(65535))
        except (socket.timeout, BlockingIOError):
            return out


def _hb(src: int = 255, key: bytes | None = None) -> bytes:
    mav = mavlink.MAVLink(None, src, 190)
    if key is not None:
        from onboard.signing import enable_signing

        enable_signing(mav, key)
    return bytes(heartbeat().pack(mav))


def test_a_udpin_link_keeps_the_first_peer_that_speaks_mavlink():
    """Today's hijack: one junk byte from another port redirected every reply to its sender.
    The first sender of valid MAVLink keeps the link; junk before it locks nothing; another
    sender's datagrams (junk or valid MAVLink) are dropped unread, counted, and never answered."""
    server = Link("udpin:127.0.0.1:0")
    ground, attacker = _sock(), _sock()
    addr = server.local_address
    try:
        attacker.sendto(b"\x00", addr)  # junk before anyone: proves nothing
        assert server.recv(0.3) is None and not server.has_peer
        ground.sendto(_hb(), addr)
        assert server.recv(1.0).get_type() == "HEARTBEAT" and server.peer == ground.getsockname()
        attacker.sendto(b"\x00", addr)
        attacker.sendto(_hb(src=99), addr)
        assert server.recv(0.3) is None  # neither is read
        server.send(heartbeat(custom_mode=5))
        assert len(_got(ground)) == 1 and _got(attacker) == []
        assert server.stats()["foreign_datagrams"] == 3  # the first junk byte (unproven) and both later ones
        assert server.stats()["peer_changes"] == 1
        ground.sendto(_hb(), addr)
        assert server.recv(1.0) is not None  # the peer is still read
    finally:
        server.close()
        ground.close()
        attacker.close()


def test_a_silent_udpin_peer_is_replaced_after_its_timeout():
    server = Link("udpin:127.0.0.1:0", peer_timeout_s=0.3)
    first, second = _sock(), _sock()
    try:
        first.sendto(_hb(), server.local_address)
        assert server.recv(1.0) is not None
        second.sendto(_hb(), server.local_address)
        assert server.recv(0.1) is None and server.peer == first.getsockname()  # within the timeout
        time.sleep(0.35)
        second.sendto(b"junk", server.local_address)  # junk does not take a silent peer's place
        assert server.recv(0.2) is None and server.peer == first.getsockname()
        second.sendto(_hb(), server.local_address)
        assert server.recv(1.0) is not None and server.peer == second.getsockname()
        assert server.stats()["peer_changes"] == 2
    finally:
        server.close()
        first.close()
        second.close()


def test_with_a_signing_key_only_a_signed_sender_becomes_the_peer():
    import hashlib

    key = hashlib.sha256(b"link peer").digest()
    server = Link("udpin:127.0.0.1:0", signing_key=key)
    attacker, ground = _sock(), _sock()
    try:
        attacker.sendto(_hb(), server.local_address)  # unsigned
        attacker.sendto(_hb(key=hashlib.sha256(b"other").digest()), server.local_address)  # wrong key
        assert server.recv(0.3) is None and not server.has_peer
        ground.sendto(_hb(key=key), server.local_address)
        m = server.recv(1.0)
        assert m is not None and server.peer == ground.getsockname()
        assert server.stats()["foreign_datagrams"] == 2
    finally:
        server.close()
        attacker.close()
        ground.close()


def test_a_fixed_udpin_peer_is_the_only_one_read():
    ground, other = _sock(), _sock()
    host, port = ground.getsockname()
    server = Link("udpin:127.0.0.1:0", peer=f"{host}:{port}")
    try:
        assert server.has_peer  # it can send before the peer speaks
        other.sendto(_hb(), server.local_address)
        assert server.recv(0.3) is None and server.stats()["foreign_datagrams"] == 1
        server.send(heartbeat())
        assert len(_got(ground)) == 1 and _got(other) == []
        ground.sendto(_hb(), server.local_address)
        assert server.recv(1.0) is not None
    finally:
        server.close()
        ground.close()
        other.close()
    for bad in ("nohost", "127.0.0.1:0", "127.0.0.1:99999"):
        with pytest.raises(LinkError, match="expected HOST:PORT"):
            Link("udpin:127.0.0.1:0", peer=bad)
    with pytest.raises(LinkError, match="udpin links only"):
        Link("udpout:127.0.0.1:9", peer="127.0.0.1:9")
