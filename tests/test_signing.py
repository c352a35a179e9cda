"""MAVLink 2 signing: key files, the ground signs what it sends, the onboard check refuses unsigned,
forged and replayed commands when signing is on and lets telemetry and everything through when off."""

from __future__ import annotations

import hashlib
import time

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from ground.commands import arm
from onboard.signing import (SigningError, SigningState, accept_command, enable_signing, is_signed,
                             load_key, signing_timestamp)
from ground.ground_cli import GroundSession
from onboard.link import Link
from conftest import free_udp_port

KEY = hashlib.sha256(b"jetloop test passphrase").digest()  # MAVProxy's `signing setup` derivation


def _parse(data: bytes):
    return mavlink.MAVLink(None).parse_char(data)


def _signed(msg, key=KEY, unix_s=None, link_id=0, src=255, comp=190):
    mav = mavlink.MAVLink(None, src, comp)
    enable_signing(mav, key, link_id=link_id, unix_s=unix_s)
    return _parse(msg.pack(mav))


def test_key_file_forms_and_errors(tmp_path):
    raw = tmp_path / "raw.key"
    raw.write_bytes(KEY)
    hexf = tmp_path / "hex.key"
    hexf.write_text(KEY.hex() + "\n")
    short = tmp_path / "short.key"
    short.write_bytes(b"123")
    assert load_key(raw) == KEY and load_key(hexf) == KEY
    with pytest.raises(SigningError, match=r"short.key: expected 32 raw bytes or 64 hex digits, got 3 bytes"):
        load_key(short)
    with pytest.raises(SigningError, match="cannot read"):
        load_key(tmp_path / "missing.key")


def test_signature_is_sha256_of_key_and_packet_with_the_2015_timestamp():
    unix_s = 1_700_000_000.0
    m = _signed(arm(True), unix_s=unix_s)
    buf = bytes(m.get_msgbuf())
    assert is_signed(m) and buf[2] & 1
    ts = int.from_bytes(buf[-12:-6], "little")
    # 10 us units since 2015-01-01 (1420070400): (1.7e9 - 1420070400) * 1e5 for the first packet
    assert ts == (1_700_000_000 - 1_420_070_400) * 100_000
    assert buf[-6:] == hashlib.sha256(KEY + buf[:-6]).digest()[:6]


def test_onboard_check_with_signing_on():
    state = SigningState(KEY)
    good = _signed(arm(True))
    assert accept_command(good, state)
    assert not accept_command(good, state)  # the same packet again: a replay (timestamp not newer)
    unsigned = _parse(arm(True).pack(mavlink.MAVLink(None, 255, 190)))
    assert not accept_command(unsigned, state)
    forged = _signed(arm(True), key=bytes(32))
    assert not accept_command(forged, state)
    telemetry = _parse(mavlink.MAVLink_attitude_message(0, 0, 0, 0, 0, 0, 0).pack(mavlink.MAVLink(None, 1, 1)))
    assert accept_command(telemetry, state)  # not a command: signing does not gate sensor data
    assert (state.accepted, state.rejected_unsigned, state.rejected_bad, state.rejected_replay) == (1, 1, 1, 1)
    # a forged packet stamped far in the future must not lock the real sender out
    future = _signed(arm(True), key=bytes(32), unix_s=time.time() + 3600)
    assert not accept_command(future, state)
    assert accept_command(_signed(arm(False)), state)


def test_signing_off_accepts_everything():
    unsigned = _parse(arm(True).pack(mavlink.MAVLink(None, 255, 190)))
    assert accept_command(unsigned, None)
    assert accept_command(unsigned, SigningState(None))
    with pytest.raises(SigningError, match="expected 32 bytes"):
        SigningState(b"short")


def _command_seen_by_vehicle(key_ground):
    """A vehicle link (udpin) and a ground session (udpout) with or without the key; returns
    whether the vehicle's check accepts the ground's arm command."""
    port = free_udp_port()
    vehicle = Link(f"udpin:127.0.0.1:{port}")
    ground = GroundSession(f"udpout:127.0.0.1:{port}", key=key_ground)
    state = SigningState(KEY)
    try:
        ground.send(arm(True))
        deadline = time.monotonic() + 2.0
        while time.monotonic() < deadline:
            m = vehicle.recv(0.05)
            if m is not None and m.get_type() == "COMMAND_LONG":
                return accept_command(m, state), is_signed(m)
    finally:
        vehicle.close()
        ground.close()
    raise AssertionError("command never arrived")


def test_over_udp_signed_ground_is_obeyed_and_unsigned_refused():
    assert _command_seen_by_vehicle(KEY) == (True, True)
    assert _command_seen_by_vehicle(None) == (False, False)


def test_signing_timestamp_units():
    assert signing_timestamp(1_420_070_400.0) == 0
    assert signing_timestamp(1_420_070_401.0) == 100_000


def test_onboard_loop_with_a_key_obeys_only_signed_commands():
    from ground.commands import depth_yaw, message_interval
    from onboard.loop import LoopConfig, OnboardLoop, VehicleClock
    from onboard.vehicle import load_vehicle

    link = Link("udpout:127.0.0.1:9")
    try:
        loop = OnboardLoop(load_vehicle(), link, VehicleClock(), LoopConfig(signing_key=KEY))
        loop.handle(_parse(depth_yaw(2.0).pack(mavlink.MAVLink(None, 255, 190))))
        assert loop.setpoint.depth_m != 2.0  # unsigned: ignored
        loop.handle(_parse(message_interval("ATTITUDE", 2.0).pack(mavlink.MAVLink(None, 255, 190))))
        assert loop.rates.rate_hz["ATTITUDE"] == 10.0
        loop.handle(_signed(depth_yaw(2.0)))
        assert loop.setpoint.depth_m == 2.0
        loop.handle(_signed(message_interval("ATTITUDE", 2.0)))
        assert loop.rates.rate_hz["ATTITUDE"] == 2.0
        c = loop.gate.counts
        assert (c.unsigned, c.accepted) == (2, 2)
        assert loop.stats.summary()["sig_unsigned"] == 2
        # with a key, sensor data must be signed too (issue 15: one unsigned sample stamped far ahead
        # tripped a signed robot's failsafe)
        loop.handle(_parse(mavlink.MAVLink_scaled_pressure2_message(10, 1013.25, 0, 2000, 0).pack(mavlink.MAVLink(None, 1, 1))))
        assert len(loop._queue) == 0 and c.unsigned == 3
        loop.handle(_signed(mavlink.MAVLink_scaled_pressure2_message(10, 1013.25, 0, 2000, 0), src=1, comp=1))
        assert loop.stats.rejected_inputs == 0 and len(loop._queue) == 1
    finally:
        link.close()


@pytest.mark.slow
def test_jetloop_onboard_with_a_key_file_answers_only_signed_commands(tmp_path):
    """The robot's own process: `jetloop onboard --key` acknowledges an arm command signed with
    the key and ignores the same command unsigned; one sender does both, so the loop's replies
    always come back to it. A bad key file is refused before anything listens."""
    import subprocess
    import sys

    from ground.commands import arm

    bad = tmp_path / "bad.key"
    bad.write_bytes(b"abc")
    r = subprocess.run([sys.executable, "-m", "ground.cli", "onboard", "--link", "udpin:127.0.0.1:0",
                        "--key", str(bad)], capture_output=True, text=True, timeout=60)
    assert r.returncode == 2 and "bad.key: expected 32 raw bytes or 64 hex digits" in r.stderr

    keyfile = tmp_path / "robot.key"
    keyfile.write_text(KEY.hex())
    port = free_udp_port()
    proc = subprocess.Popen([sys.executable, "-m", "ground.cli", "onboard", "--link", f"udpin:127.0.0.1:{port}",
                             "--key", str(keyfile), "--realtime", "--duration", "90"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    link = Link(f"udpout:127.0.0.1:{port}")
    unsigned = arm(True).pack(mavlink.MAVLink(None, 255, 190))

    def acked(packet_of, seconds):
        deadline = time.monotonic() + seconds
        while time.monotonic() < deadline:
            link.write_raw(packet_of())
            m = link.recv(0.1)
            if m is not None and m.get_type() == "COMMAND_ACK":
                return True
        return False

    try:
        # signed: acknowledged (also proves the loop is up and replies to this one sender)
        assert acked(lambda: _signed(arm(True)).get_msgbuf(), 60.0)  # first start compiles the model
        end = time.monotonic() + 1.0
        while time.monotonic() < end:  # drain the acks of signed commands still in flight
            link.recv(0.1)
        assert not acked(lambda: unsigned, 1.5)  # the same command unsigned: ignored
        assert acked(lambda: _signed(arm(True)).get_msgbuf(), 5.0)  # and the loop is still there
    finally:
        link.close()
        proc.terminate()
        proc.wait(timeout=30)
