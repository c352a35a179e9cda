"""Fuzzing the ground station's ingest (issue 7 part 2): ground.station.Station, ground.view's
renderers and ground.recorder.Recorder fed hostile telemetry of every type the station reads,
received through a real onboard.link.Link (so each example is a packet a vehicle could send).

Properties: update() never raises; snapshot(), render_text() and render_rich() build from any
state; a message a handler cannot read leaves an event that says so; the recorder writes every
packet and the recording reads back with each of them and nothing skipped.
"""

from __future__ import annotations

import io
import math
from datetime import timedelta

from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from ground.recorder import Recorder
from ground.recording import read_recording
from ground.station import Station
from ground.view import render_rich, render_text
from onboard.link import Link
from test_fuzz_messages import hostile_any, pack

READ = ("HEARTBEAT", "ATTITUDE", "NAMED_VALUE_FLOAT", "DEBUG_FLOAT_ARRAY", "SERVO_OUTPUT_RAW", "SCALED_PRESSURE2",
        "LOCAL_POSITION_NED", "VFR_HUD", "SYS_STATUS", "COMMAND_ACK", "STATUSTEXT")
FUZZ = settings(max_examples=60, deadline=timedelta(seconds=30),
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
NAMES = st.sampled_from([b"depth", b"depth_sp", b"yaw_sp", b"u_sp", b"u_est", b"alloc_err", b"alloc_fb", b"qp_us",
                         b"step_ms", b"step_p99", b"failsafe", b"armed", b"est_rej", b"in_rej", b"link_bad"])


def _received(packets: list[bytes]) -> list:
    """The packets through a Link's parser, as the ground station's loop gets them."""
    with Link("udpin:127.0.0.1:0") as lk:
        lk.feed(b"".join(packets), datagram=True)
        out = []
        while lk._ready:
            out.append(lk._ready.popleft())
        return out


def _ingest(vehicle, msgs, system: int, ticks=(0.5, 3.0, 10.0)):
    st_ = Station(vehicle)
    packets = [pack(m, system=system, component=1, seq=i) for i, m in enumerate(msgs)]
    received = _received(packets)
    assert len(received) == len(packets)  # hostile values, but well-formed packets
    for i, m in enumerate(received):
        st_.update(m, now_s=0.01 * i)
    st_.link_counters(garbage_bytes=7, bad_packets=1, now_s=0.2)
    for t in ticks:
        st_.tick(t)
        snap = st_.snapshot(t)
        text = render_text(snap)
        assert "[link]" in text
        from rich.console import Console

        Console(file=io.StringIO(), width=120).print(render_rich(snap))
    return st_, received


@FUZZ
@given(msgs=st.lists(hostile_any(READ), min_size=1, max_size=12), system=st.sampled_from([1, 2, 255]))
@example(msgs=[mavlink.MAVLink_servo_output_raw_message(0, 0, *([65535] * 8))], system=1)
@example(msgs=[mavlink.MAVLink_attitude_message(2 ** 32 - 1, math.nan, math.inf, -math.inf, 0, 0, 0)], system=1)
def test_station_and_view_take_any_telemetry(vehicle, msgs, system):
    station, received = _ingest(vehicle, msgs, system)
    assert station.packets == len(received)
    unreadable = [e for _, e in station.events if "could not be read" in e]
    assert len(unreadable) <= len(received)  # each one named, never an exception


@FUZZ
@given(values=st.lists(st.tuples(NAMES, st.floats(width=32)), min_size=1, max_size=20))
def test_named_values_of_any_float_render(vehicle, values):
    msgs = [mavlink.MAVLink_named_value_float_message(i, name, v) for i, (name, v) in enumerate(values)]
    station, _ = _ingest(vehicle, msgs, 1)
    for name, v in values:  # the last value of each name is kept, whatever it is
        last = [x for n, x in values if n == name][-1]
        got = station.values[name.decode()]
        assert (math.isnan(got) and math.isnan(last)) or got == last


@settings(max_examples=20, deadline=timedelta(seconds=30),
          suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
@given(msgs=st.lists(hostile_any(READ), min_size=1, max_size=30))
def test_recorder_keeps_every_hostile_packet(tmp_path_factory, msgs):
    directory = tmp_path_factory.mktemp("rec")
    packets = [pack(m, system=1, component=1, seq=i) for i, m in enumerate(msgs)]
    with Recorder(directory, prefix="fuzz") as rec:
        for m in _received(packets):
            rec.record_message(m)
    files = sorted(directory.glob("fuzz*.tlog"))
    assert len(files) == 1
    r = read_recording(files[0])
    assert sum(r.messages.values()) + r.skipped.unknown_packets <= len(packets)
    assert r.skipped.skipped_bytes == 0 and r.skipped.bad_crc_packets == 0
    assert files[0].stat().st_size == sum(8 + len(p) for p in packets)
