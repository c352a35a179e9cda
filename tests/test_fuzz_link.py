"""Fuzzing onboard.link's MAVLink parsing (issue 7 part 2): garbage, torn and bit-flipped packets.

Properties, for any bytes in any chunking (whole UDP datagrams or a serial byte stream):
- nothing raises;
- every byte is accounted for: bytes_in = good_bytes + garbage_bytes + bytes still pending;
- what is delivered passed its CRC; a good packet placed after garbage, after a torn packet or
  after a bit-flipped copy of itself is still delivered, in order, and the damage is counted;
- 1 MB of garbage (20 MB in bench/fuzz.py) keeps the parser's memory flat (tracemalloc peak) and its time linear.
The datagram path is exercised through real UDP sockets on 127.0.0.1.
"""

from __future__ import annotations

import random
import socket
import time
import tracemalloc
from datetime import timedelta

import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from onboard.link import Link

FUZZ = settings(max_examples=100, deadline=timedelta(seconds=30),
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
MAX_FRAME = 280  # MAVLink 2: 10 header + 255 payload + 2 CRC + 13 signature


def _packets(n: int, seed: int = 0) -> list[bytes]:
    """n distinct good packets (HEARTBEAT, ATTITUDE, SYSTEM_TIME), MAVLink 2, sequence 0..n-1."""
    mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    rng = random.Random(seed)
    out = []
    for i in range(n):
        kind = i % 3
        if kind == 0:
            msg = mavlink.MAVLink_heartbeat_message(12, 0, 0, i, 0, 3)
        elif kind == 1:
            msg = mavlink.MAVLink_attitude_message(i, rng.uniform(-1, 1), 0.1, 0.2, 0.0, 0.0, 0.0)
        else:
            msg = mavlink.MAVLink_system_time_message(0, i)
        out.append(bytes(msg.pack(mav)))
        mav.seq = (mav.seq + 1) % 256
    return out


def _accounted(link: Link) -> None:
    pending = len(link.mav.buf) - link.mav.buf_index
    assert link.garbage_bytes >= 0 and pending >= 0
    assert link.bytes_in == link.good_bytes + link.garbage_bytes + pending


def _drain(link: Link) -> list:
    out = []
    while link._ready:
        out.append(link._ready.popleft())
    return out


def _is_subsequence(wanted: list[bytes], got: list[bytes]) -> bool:
    it = iter(got)
    return all(any(w == g for g in it) for w in wanted)


@pytest.fixture(scope="module")
def link():
    with Link("udpin:127.0.0.1:0") as lk:
        yield lk


def _fresh(link: Link) -> Link:
    """The module's link with its parser and counters back at the start (a socket per example
    would cost more than the parsing under test)."""
    link.mav = mavlink.MAVLink(None, srcSystem=1, srcComponent=1)
    link.mav.robust_parsing = True
    link._ready.clear()
    link.bytes_in = link.good_bytes = link.bad_packets = link.unknown_packets = link.packets_in = 0
    return link


@FUZZ
@given(data=st.binary(max_size=4000), cuts=st.lists(st.integers(0, 4000), max_size=8), datagram=st.booleans())
@example(data=b"\xfd\xff" + b"\x00" * 20, cuts=[], datagram=False)  # a v2 header declaring 255 bytes
@example(data=b"\xfd\x00\xfe" * 50, cuts=[1, 2], datagram=True)  # only start markers and bad flags
@example(data=b"\xfe\x09\x00\x01\x01\x00" + b"\x00" * 9 + b"\xfe", cuts=[], datagram=False)
def test_random_bytes_never_raise_and_every_byte_is_counted(link, data, cuts, datagram):
    lk = _fresh(link)
    bounds = sorted({0, len(data), *(c for c in cuts if c <= len(data))})
    for a, b in zip(bounds, bounds[1:]):
        lk.feed(data[a:b], datagram=datagram)
        _accounted(lk)
    for m in _drain(lk):  # only decoded packets come out, never the parser's BAD_DATA
        assert m.get_type() != "BAD_DATA"
    if datagram:
        assert len(lk.mav.buf) - lk.mav.buf_index == 0  # a datagram leaves nothing waiting


@FUZZ
@given(garbage=st.lists(st.binary(max_size=300), min_size=4, max_size=4), datagram=st.booleans(),
       seed=st.integers(0, 2 ** 16))
def test_good_packets_between_garbage_all_arrive_in_order(link, garbage, datagram, seed):
    lk = _fresh(link)
    good = _packets(3, seed)
    stream = garbage[0] + good[0] + garbage[1] + good[1] + garbage[2] + good[2] + garbage[3]
    lk.feed(stream, datagram=datagram)
    if not datagram:  # a serial line: the next bytes complete any frame a false marker opened
        lk.feed(b"\x00" * MAX_FRAME)
    _accounted(lk)
    got = [bytes(m.get_msgbuf()) for m in _drain(lk)]
    assert _is_subsequence(good, got)
    # garbage is counted, never delivered (a random packet with a good CRC is a 1 in 65536 event
    # per start marker; hypothesis does not aim for it, so extra deliveries are not expected)
    assert len(got) == 3
    assert lk.garbage_bytes == len(stream) - sum(map(len, good)) + (0 if datagram else MAX_FRAME)


@FUZZ
@given(n_keep=st.integers(1, 60), which=st.integers(0, 2), datagram=st.booleans())
def test_torn_packet_is_counted_and_does_not_swallow_the_next(link, n_keep, which, datagram):
    lk = _fresh(link)
    good = _packets(3)
    torn = good[which][: min(n_keep, len(good[which]) - 1)]
    lk.feed(torn + good[0] + good[1] + good[2], datagram=datagram)
    if not datagram:
        lk.feed(b"\x00" * MAX_FRAME)
    _accounted(lk)
    got = [bytes(m.get_msgbuf()) for m in _drain(lk)]
    assert got == good
    assert lk.garbage_bytes == len(torn) + (0 if datagram else MAX_FRAME)


@FUZZ
@given(which=st.integers(0, 2), bit=st.integers(0, 8 * 60 - 1), datagram=st.booleans())
@example(which=0, bit=8 * 1 + 7, datagram=False)  # the length byte: the frame runs past its end
@example(which=1, bit=8 * 2, datagram=True)  # incompat flags: "signed", 13 bytes longer
def test_bit_flip_is_rejected_and_counted_and_the_next_packet_arrives(link, which, bit, datagram):
    lk = _fresh(link)
    good = _packets(3)
    flipped = bytearray(good[which])
    byte = bit // 8 % len(flipped)
    flipped[byte] ^= 1 << (bit % 8)
    lk.feed(bytes(flipped) + good[0] + good[1] + good[2], datagram=datagram)
    if not datagram:
        lk.feed(b"\x00" * MAX_FRAME)
    _accounted(lk)
    got = [bytes(m.get_msgbuf()) for m in _drain(lk)]
    # one flipped bit always changes the X.25 CRC (it detects every single-bit error), so the
    # damaged copy is never delivered, and its bytes are counted as garbage
    assert got == good
    assert lk.garbage_bytes == len(flipped) + (0 if datagram else MAX_FRAME)
    assert lk.bad_packets + lk.unknown_packets >= (1 if byte > 0 else 0)


@settings(max_examples=40, deadline=timedelta(seconds=30))
@given(datagrams=st.lists(st.binary(min_size=1, max_size=2000), min_size=1, max_size=6), seed=st.integers(0, 99))
def test_real_udp_datagrams_of_garbage_then_a_good_packet(datagrams, seed):
    """Through real sockets: whatever datagrams come first, the good one after them arrives."""
    with Link("udpin:127.0.0.1:0") as server, socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as tx:
        good = _packets(1, seed)[0]
        for d in datagrams:
            tx.sendto(d, server.local_address)
        tx.sendto(good, server.local_address)
        got, deadline = [], time.monotonic() + 3.0
        while time.monotonic() < deadline and good not in got:
            m = server.recv(0.2)
            if m is not None:
                got.append(bytes(m.get_msgbuf()))
        assert good in got
        _accounted(server)
        assert server.bytes_in == sum(map(len, datagrams)) + len(good)


def _garbage_peak(n_bytes: int, chunk: int) -> tuple[int, float]:
    """tracemalloc peak (bytes) and wall time of feeding n_bytes of seeded random garbage."""
    data = random.Random(n_bytes).randbytes(n_bytes)
    with Link("udpin:127.0.0.1:0") as lk:
        tracemalloc.start()
        t0 = time.perf_counter()
        try:
            for i in range(0, n_bytes, chunk):
                lk.feed(data[i:i + chunk], datagram=chunk > 4096)
                _drain(lk)
            _, peak = tracemalloc.get_traced_memory()
        finally:
            tracemalloc.stop()
        elapsed = time.perf_counter() - t0
        _accounted(lk)
        assert lk.packets_in <= n_bytes // 65536 + 2  # garbage is not read as packets
    return peak, elapsed


@pytest.mark.slow
@pytest.mark.parametrize("chunk", [1024, 60_000])  # serial reads, whole UDP datagrams
def test_a_megabyte_of_garbage_keeps_memory_flat(chunk):
    small_peak, small_s = _garbage_peak(125_000, chunk)
    big_peak, big_s = _garbage_peak(1_000_000, chunk)
    # 8x the input: the peak is what one chunk and one parser state take, it must not grow with it
    assert big_peak < 2 * small_peak + 64_000, (small_peak, big_peak)
    assert big_peak < 4 * chunk + 200_000
    assert big_s < 8 * small_s * 2.0 + 1.0  # linear in the input (2x margin for a shared machine)


def _feed_seconds(link_cls, data: bytes, chunk: int = 4096) -> float:
    with link_cls("udpin:127.0.0.1:0") as lk:
        t0 = time.perf_counter()
        for i in range(0, len(data), chunk):
            lk.feed(data[i:i + chunk])
            _drain(lk)
        return time.perf_counter() - t0


def test_garbage_costs_less_than_good_packets():
    """Regression: each false start marker (1 byte in 128 of random garbage) made the link copy
    the whole unparsed buffer to rescan it, and pymavlink walked the bytes before the next marker
    one Python step at a time: per byte, garbage cost 0.57-0.95x as much as good packets (measured
    in four runs), where the link's own work should be small. Now it steps back in place and
    skips to the next marker with one regex search: 0.17-0.18x. Both are timed in the same run,
    so a loaded machine does not decide the ratio; 0.35 sits between them."""
    garbage = random.Random(1).randbytes(200_000)
    good = b"".join(_packets(3 * 2000))
    good = good * (len(garbage) // len(good) + 1)
    ratio = (_feed_seconds(Link, garbage) / len(garbage)) / (_feed_seconds(Link, good) / len(good))
    assert ratio < 0.35, ratio


# -- hostile peers: a second sender on a udpin link (issue 15) -------------------------------------------

@settings(max_examples=60, deadline=timedelta(seconds=30))
@given(plan=st.lists(st.tuples(st.sampled_from(["a", "b"]),
                               st.one_of(st.binary(min_size=1, max_size=300).filter(lambda b: not set(b) & {0xFD, 0xFE}),
                                         st.integers(0, 5))),
                     min_size=1, max_size=12))
def test_a_udpin_link_reads_and_answers_only_its_peer(plan):
    """Two senders, a and b, each sending junk (no start marker, so it can never pose as a packet)
    or good packets, in any order. The first to send a good packet becomes the peer; from then on
    only its packets are delivered, in order; every other datagram is counted as foreign, before
    the lock too (it proved nothing); and what the link sends reaches the peer alone."""
    good = _packets(6, seed=3)
    with Link("udpin:127.0.0.1:0") as server, \
            socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as a, socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as b:
        socks = {"a": a, "b": b}
        for s in socks.values():
            s.bind(("127.0.0.1", 0))
            s.setblocking(False)
        peer, expected, foreign = None, [], 0
        for who, what in plan:
            data = good[what] if isinstance(what, int) else what
            socks[who].sendto(data, server.local_address)
            if peer is None and isinstance(what, int):
                peer = who
            if who == peer and isinstance(what, int):
                expected.append(data)
            elif who != peer or peer is None:
                foreign += 1
        got, deadline = [], time.monotonic() + 3.0
        while time.monotonic() < deadline and len(got) < len(expected):
            m = server.recv(0.05)
            if m is not None:
                got.append(bytes(m.get_msgbuf()))
        assert server.recv(0.05) is None
        assert got == expected
        assert server.stats()["foreign_datagrams"] == foreign
        assert server.has_peer == (peer is not None)
        server.send(mavlink.MAVLink_heartbeat_message(12, 0, 0, 0, 0, 3))
        for who, s in socks.items():
            try:
                answered = s.recv(65535)
            except BlockingIOError:
                answered = None
            assert (answered is not None) == (who == peer), who
