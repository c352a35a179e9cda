"""The robot's ground-facing MAVLink microservices over real loopback UDP (onboard.microservices,
onboard.params): a pymavlink ground station (system 255) talks to a real-time onboard loop running
in a thread, as QGroundControl, MAVProxy and MAVSDK do (their own runs: test_gcs_clients.py)."""

from __future__ import annotations

import threading
import time

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink

from onboard import params as P
from onboard.link import Link
from onboard.loop import LoopConfig, OnboardLoop, WallClock
from onboard.signing import enable_signing
from onboard.vehicle import load_vehicle

KEY = bytes(range(32))


class Station:
    """A ground station on a udpin link, with the robot's loop running in a thread."""

    def __init__(self, config=LoopConfig(), main=None):
        self.gcs = Link("udpin:127.0.0.1:0", source_system=255, source_component=190)
        self.main = main or Link("udpin:127.0.0.1:0", 1, 191)  # nobody speaks there: no sensors
        self.ground = Link(f"udpout:127.0.0.1:{self.gcs.local_address[1]}", 1, 191)
        self.loop = OnboardLoop(load_vehicle(), self.main, WallClock(), config, ground=self.ground)
        self.stop_event = threading.Event()
        self.thread = threading.Thread(target=self.loop.run, kwargs=dict(stop=self.stop_event.is_set), daemon=True)
        self.thread.start()
        self.wait("HEARTBEAT")  # the ground link's first datagram makes the loop our peer

    def send(self, msg) -> None:
        self.gcs.send(msg)

    def wait(self, name: str, cond=lambda m: True, timeout_s: float = 3.0):
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            m = self.gcs.recv(0.05)
            if m is not None and m.get_type() == name and cond(m):
                return m
        raise AssertionError(f"no {name} within {timeout_s} s")

    def collect(self, name: str, seconds: float) -> list:
        out, deadline = [], time.monotonic() + seconds
        while time.monotonic() < deadline:
            m = self.gcs.recv(0.05)
            if m is not None and m.get_type() == name:
                out.append(m)
        return out

    def ack(self, command: int, timeout_s: float = 3.0):
        return self.wait("COMMAND_ACK", lambda m: m.command == command, timeout_s)

    def close(self) -> None:
        self.stop_event.set()
        self.thread.join(5)
        for lk in (self.gcs, self.main, self.ground):
            lk.close()


@pytest.fixture
def station(tmp_path):
    s = Station(LoopConfig(parameter_file=str(tmp_path / "asr4.params")))
    yield s
    s.close()


def _name(m) -> str:
    return m.param_id if isinstance(m.param_id, str) else m.param_id.decode()


# -- identity --------------------------------------------------------------------------------------

def test_the_controller_is_component_1_a_submarine_that_qgroundcontrol_would_add(station):
    hb = station.wait("HEARTBEAT")
    assert (hb.get_srcSystem(), hb.get_srcComponent()) == (1, 1)
    assert hb.type == mavlink.MAV_TYPE_SUBMARINE and hb.autopilot == mavlink.MAV_AUTOPILOT_GENERIC
    assert hb.base_mode & mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED and hb.custom_mode == 4  # guided
    assert hb.base_mode & mavlink.MAV_MODE_FLAG_GUIDED_ENABLED


def test_beside_an_ardupilot_heartbeat_the_loop_becomes_its_companion_191():
    main = Link("udpin:127.0.0.1:0", 1, 191)
    autopilot = Link(f"udpout:127.0.0.1:{main.local_address[1]}", 1, 1)
    s = Station(main=main)
    try:
        assert s.wait("HEARTBEAT").get_srcComponent() == 1
        autopilot.send(mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_SUBMARINE, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                                         0, 19, mavlink.MAV_STATE_STANDBY, 3))
        text = s.wait("STATUSTEXT")
        assert "companion of autopilot 1:1" in (text.text if isinstance(text.text, str) else text.text.decode())
        hb = s.wait("HEARTBEAT", lambda m: m.get_srcComponent() == 191, timeout_s=3.0)
        assert hb.type == mavlink.MAV_TYPE_ONBOARD_CONTROLLER and hb.autopilot == mavlink.MAV_AUTOPILOT_INVALID
        # parameters addressed to the autopilot's component 1 are the autopilot's to answer
        s.send(mavlink.MAVLink_param_request_list_message(1, 1))
        assert not s.collect("PARAM_VALUE", 1.0)
    finally:
        s.close()
        autopilot.close()


def test_a_companion_leaves_commands_addressed_to_the_autopilot_to_the_autopilot():
    """Beside a real autopilot (companion, 191) a command for component 1 is the autopilot's: not
    carried out, not acked from 191 (before the fix the loop armed, changed mode and answered
    AUTOPILOT_VERSION for the autopilot, and acked them all); addressed to 191 or broadcast (0) it
    is the loop's, as before."""
    main = Link("udpin:127.0.0.1:0", 1, 191)
    autopilot = Link(f"udpout:127.0.0.1:{main.local_address[1]}", 1, 1)
    s = Station(main=main)
    cl, ci = mavlink.MAVLink_command_long_message, mavlink.MAVLink_command_int_message
    try:
        autopilot.send(mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_SUBMARINE, mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA,
                                                         0, 19, mavlink.MAV_STATE_STANDBY, 3))
        s.wait("HEARTBEAT", lambda m: m.get_srcComponent() == 191, timeout_s=3.0)
        mode = s.loop.mode
        s.send(cl(1, 1, mavlink.MAV_CMD_DO_SET_MODE, 0, 1, 2, 0, 0, 0, 0, 0))
        s.send(ci(1, 1, 0, mavlink.MAV_CMD_DO_SET_MODE, 0, 0, 1, 19, 0, 0, 0, 0, 0))
        s.send(cl(1, 1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0))
        s.send(cl(1, 1, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 0.5, 0, 0, 0, 0, 0, 0))  # the gate's DENIED too
        s.send(cl(1, 1, mavlink.MAV_CMD_REQUEST_MESSAGE, 0, mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION, 0, 0, 0, 0, 0, 0))
        s.send(cl(1, 1, mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES, 0, 1, 0, 0, 0, 0, 0, 0))
        heard, deadline = [], time.monotonic() + 1.5
        while time.monotonic() < deadline:
            m = s.gcs.recv(0.05)
            if m is not None and m.get_type() in ("COMMAND_ACK", "AUTOPILOT_VERSION"):
                heard.append(m)
        assert not heard
        assert s.loop.mode == mode and not s.loop.armed and s.loop.stats.arm_refusals == 0
        # addressed to the companion, or to every component: the loop's, answered as before
        s.send(cl(1, 191, mavlink.MAV_CMD_DO_SET_MODE, 0, 1, 2, 0, 0, 0, 0, 0))
        assert s.ack(mavlink.MAV_CMD_DO_SET_MODE).result == mavlink.MAV_RESULT_ACCEPTED
        assert s.loop.mode == 2
        s.send(ci(1, 0, 0, mavlink.MAV_CMD_DO_SET_MODE, 0, 0, 1, 19, 0, 0, 0, 0, 0))
        assert s.ack(mavlink.MAV_CMD_DO_SET_MODE).result == mavlink.MAV_RESULT_ACCEPTED
        s.send(cl(1, 0, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0))
        assert s.ack(mavlink.MAV_CMD_COMPONENT_ARM_DISARM).result == mavlink.MAV_RESULT_TEMPORARILY_REJECTED  # no IMU
        s.send(cl(1, 191, mavlink.MAV_CMD_REQUEST_MESSAGE, 0, mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION, 0, 0, 0, 0, 0, 0))
        assert s.wait("AUTOPILOT_VERSION")
    finally:
        s.close()
        autopilot.close()


# -- parameters ------------------------------------------------------------------------------------

def test_param_request_list_gives_every_parameter_once_with_index_and_count(station):
    station.send(mavlink.MAVLink_param_request_list_message(1, 0))
    got = station.collect("PARAM_VALUE", 1.5)
    assert len(got) == len(P.PARAMS)
    assert sorted(m.param_index for m in got) == list(range(len(P.PARAMS)))
    assert {m.param_count for m in got} == {len(P.PARAMS)}
    assert all(m.param_type == mavlink.MAV_PARAM_TYPE_REAL32 and len(_name(m)) <= 16 for m in got)
    by = {_name(m): m.param_value for m in got}
    assert by["CTL_DEPTH_BW"] == pytest.approx(1.2) and by["FS_IMU_TIMEOUT"] == pytest.approx(0.3)
    assert by["ALLOC_W_HEAVE"] == pytest.approx(10.0) and by["SR_ATTITUDE"] == pytest.approx(10.0)


def test_param_read_by_name_and_by_index(station):
    station.send(mavlink.MAVLink_param_request_read_message(1, 1, b"CTL_YAW_BW", -1))
    m = station.wait("PARAM_VALUE")
    assert _name(m) == "CTL_YAW_BW" and m.param_index == P.Parameters(
        {p.name: 0.0 for p in P.PARAMS}).index("CTL_YAW_BW")
    station.send(mavlink.MAVLink_param_request_read_message(1, 1, b"", 0))
    assert _name(station.wait("PARAM_VALUE")) == P.PARAMS[0].name


def test_param_set_takes_effect_live_persists_and_the_next_start_uses_it(station, tmp_path):
    loop = station.loop
    station.send(mavlink.MAVLink_param_set_message(1, 1, b"CTL_DEPTH_BW", 2.0, mavlink.MAV_PARAM_TYPE_REAL32))
    m = station.wait("PARAM_VALUE", lambda m: _name(m) == "CTL_DEPTH_BW")
    assert m.param_value == pytest.approx(2.0)
    assert loop.controller.gains.depth_bandwidth_rad_s == pytest.approx(2.0)  # the controller flies it now
    station.send(mavlink.MAVLink_param_set_message(1, 1, b"ALLOC_W_YAW", 3.0, mavlink.MAV_PARAM_TYPE_REAL32))
    station.wait("PARAM_VALUE", lambda m: _name(m) == "ALLOC_W_YAW")
    assert loop.allocator.config.axis_weights[5] == 3.0
    station.send(mavlink.MAVLink_param_set_message(1, 1, b"SR_ATTITUDE", 2.0, mavlink.MAV_PARAM_TYPE_REAL32))
    station.wait("PARAM_VALUE", lambda m: _name(m) == "SR_ATTITUDE")
    att = station.collect("ATTITUDE", 2.0)
    assert 2 <= len(att) <= 6, len(att)  # 2 Hz, not the default 10 Hz
    text = (tmp_path / "asr4.params").read_text()
    assert "CTL_DEPTH_BW 2\n" in text and "ALLOC_W_YAW 3\n" in text and "CTL_ATT_BW" not in text  # only the changed
    again = OnboardLoop(load_vehicle(), Link("udpin:127.0.0.1:0"), WallClock(),
                        LoopConfig(parameter_file=str(tmp_path / "asr4.params")), warm_up=False)
    assert again.controller.gains.depth_bandwidth_rad_s == pytest.approx(2.0)
    assert again.allocator.config.axis_weights[5] == 3.0
    again.link.close()


def test_out_of_range_set_is_refused_with_the_old_value_echoed_and_a_reason(station, tmp_path):
    station.send(mavlink.MAVLink_param_set_message(1, 1, b"CTL_DEPTH_BW", 50.0, mavlink.MAV_PARAM_TYPE_REAL32))
    m = station.wait("PARAM_VALUE", lambda m: _name(m) == "CTL_DEPTH_BW")
    assert m.param_value == pytest.approx(1.2)
    text = station.wait("STATUSTEXT")
    assert "CTL_DEPTH_BW 50 rad/s: expected 0.1-6 rad/s" in (text.text if isinstance(text.text, str) else text.text.decode())
    assert station.loop.controller.gains.depth_bandwidth_rad_s == pytest.approx(1.2)
    assert not (tmp_path / "asr4.params").exists()


def test_all_allocation_weights_zero_is_refused_by_the_allocator_not_applied(station):
    for axis in P.AXES[:-1]:
        station.send(mavlink.MAVLink_param_set_message(1, 1, f"ALLOC_W_{axis}".encode(), 0.0, 9))
        station.wait("PARAM_VALUE", lambda m, a=axis: _name(m) == f"ALLOC_W_{a}")
    station.send(mavlink.MAVLink_param_set_message(1, 1, b"ALLOC_W_YAW", 0.0, 9))
    m = station.wait("PARAM_VALUE", lambda m: _name(m) == "ALLOC_W_YAW")
    assert m.param_value == 1.0 and station.loop.allocator.config.axis_weights[5] == 1.0


def test_unsigned_param_set_is_refused_when_signing_is_on(tmp_path):
    s = Station(LoopConfig(signing_key=KEY, parameter_file=str(tmp_path / "p.params")))
    try:
        s.send(mavlink.MAVLink_param_set_message(1, 1, b"CTL_DEPTH_BW", 2.0, 9))
        assert not s.collect("PARAM_VALUE", 1.0)
        assert s.loop.controller.gains.depth_bandwidth_rad_s == pytest.approx(1.2)
        assert s.loop.stats.security.unsigned >= 1
        enable_signing(s.gcs.mav, KEY)
        s.send(mavlink.MAVLink_param_set_message(1, 1, b"CTL_DEPTH_BW", 2.0, 9))
        assert s.wait("PARAM_VALUE").param_value == pytest.approx(2.0)
    finally:
        s.close()


def test_a_bad_parameter_file_is_one_line_naming_file_line_and_range(tmp_path):
    f = tmp_path / "v.params"
    f.write_text("# ok\nCTL_DEPTH_BW 1.5\nCTL_DEPHT_BW 1.0\n")
    with pytest.raises(P.ParameterFileError, match=r"v.params:3: unknown parameter 'CTL_DEPHT_BW'"):
        P.load(f)
    f.write_text("FS_IMU_TIMEOUT nan\n")
    with pytest.raises(P.ParameterFileError, match=r"v.params:1: FS_IMU_TIMEOUT: expected a finite number"):
        P.load(f)


def test_every_parameter_default_lies_in_its_range_and_names_fit_16_characters():
    loop = OnboardLoop(load_vehicle(), Link("udpin:127.0.0.1:0"), WallClock(), warm_up=False)
    try:
        for spec in P.PARAMS:
            v = loop.services.params.defaults[spec.name]
            assert spec.lo <= v <= spec.hi, spec
            assert len(spec.name) <= 16
    finally:
        loop.link.close()


# -- commands, modes, time, mission ----------------------------------------------------------------

def test_every_command_long_and_command_int_is_acked(station):
    station.send(mavlink.MAVLink_command_long_message(1, 1, mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, 0, 0, 0, 0, 0))
    assert station.ack(mavlink.MAV_CMD_NAV_TAKEOFF).result == mavlink.MAV_RESULT_UNSUPPORTED
    station.send(mavlink.MAVLink_command_int_message(1, 1, 0, mavlink.MAV_CMD_DO_REPOSITION, 0, 0, 0, 0, 0, 0, 0, 0, 0))
    assert station.ack(mavlink.MAV_CMD_DO_REPOSITION).result == mavlink.MAV_RESULT_UNSUPPORTED
    # arming with no IMU: refused for now, said so
    station.send(mavlink.MAVLink_command_int_message(1, 1, 0, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 0,
                                                     1, 0, 0, 0, 0, 0, 0))
    assert station.ack(mavlink.MAV_CMD_COMPONENT_ARM_DISARM).result == mavlink.MAV_RESULT_TEMPORARILY_REJECTED
    station.send(mavlink.MAVLink_command_int_message(1, 1, 0, mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 0,
                                                     0.5, 0, 0, 0, 0, 0, 0))
    assert station.ack(mavlink.MAV_CMD_COMPONENT_ARM_DISARM).result == mavlink.MAV_RESULT_DENIED


def test_modes_by_do_set_mode_and_by_set_mode_show_in_the_heartbeat(station):
    station.send(mavlink.MAVLink_command_long_message(1, 1, mavlink.MAV_CMD_DO_SET_MODE, 0, 1, 2, 0, 0, 0, 0, 0))
    assert station.ack(mavlink.MAV_CMD_DO_SET_MODE).result == mavlink.MAV_RESULT_ACCEPTED
    hb = station.wait("HEARTBEAT", lambda m: m.custom_mode == 2, timeout_s=2.5)
    assert hb.base_mode & mavlink.MAV_MODE_FLAG_STABILIZE_ENABLED
    station.send(mavlink.MAVLink_set_mode_message(1, mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, 19))
    assert station.ack(mavlink.MAV_CMD_DO_SET_MODE).result == mavlink.MAV_RESULT_ACCEPTED
    assert station.wait("HEARTBEAT", lambda m: m.custom_mode == 19, timeout_s=2.5)
    station.send(mavlink.MAVLink_command_long_message(1, 1, mavlink.MAV_CMD_DO_SET_MODE, 0, 1, 7, 0, 0, 0, 0, 0))
    assert station.ack(mavlink.MAV_CMD_DO_SET_MODE).result == mavlink.MAV_RESULT_DENIED  # no such mode


def test_request_message_autopilot_version_acks_then_sends_the_true_capabilities(station):
    station.send(mavlink.MAVLink_command_long_message(1, 1, mavlink.MAV_CMD_REQUEST_MESSAGE, 0,
                                                      mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION, 0, 0, 0, 0, 0, 0))
    seen = []
    deadline = time.monotonic() + 3
    while time.monotonic() < deadline and len(seen) < 2:
        m = station.gcs.recv(0.05)
        if m is not None and (m.get_type() == "AUTOPILOT_VERSION" or
                              (m.get_type() == "COMMAND_ACK" and m.command == mavlink.MAV_CMD_REQUEST_MESSAGE)):
            seen.append(m)
    assert [m.get_type() for m in seen] == ["COMMAND_ACK", "AUTOPILOT_VERSION"]
    assert seen[0].result == mavlink.MAV_RESULT_ACCEPTED
    caps = seen[1].capabilities
    assert caps & mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2 and caps & mavlink.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
    assert caps & mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST
    for absent in ("FTP", "MISSION_FENCE", "MISSION_RALLY", "TERRAIN", "SET_ATTITUDE_TARGET", "FLIGHT_TERMINATION"):
        assert not caps & getattr(mavlink, f"MAV_PROTOCOL_CAPABILITY_{absent}"), absent
    assert seen[1].flight_sw_version >> 16 == 0x0001  # 0.1.x
    station.send(mavlink.MAVLink_command_long_message(1, 1, mavlink.MAV_CMD_REQUEST_MESSAGE, 0,
                                                      mavlink.MAVLINK_MSG_ID_GPS_RAW_INT, 0, 0, 0, 0, 0, 0))
    assert station.ack(mavlink.MAV_CMD_REQUEST_MESSAGE).result == mavlink.MAV_RESULT_DENIED  # no GNSS to report
    # every message the robot can fill is acked (SYS_STATUS raised inside the request: no ACK at all,
    # found by a hostile sweep of REQUEST_MESSAGE over ids 0-300)
    for mid in (mavlink.MAVLINK_MSG_ID_SYS_STATUS, mavlink.MAVLINK_MSG_ID_HEARTBEAT, mavlink.MAVLINK_MSG_ID_SYSTEM_TIME):
        station.send(mavlink.MAVLink_command_long_message(1, 1, mavlink.MAV_CMD_REQUEST_MESSAGE, 0, mid, 0, 0, 0, 0, 0, 0))
        assert station.ack(mavlink.MAV_CMD_REQUEST_MESSAGE).result == mavlink.MAV_RESULT_ACCEPTED, mid


def test_timesync_ping_and_system_time(station):
    station.send(mavlink.MAVLink_timesync_message(0, 123456789))
    ts = station.wait("TIMESYNC")
    assert ts.ts1 == 123456789 and ts.tc1 > 0
    station.send(mavlink.MAVLink_ping_message(42, 7, 0, 0))
    p = station.wait("PING")
    assert (p.time_usec, p.seq, p.target_system, p.target_component) == (42, 7, 255, 190)
    st = station.collect("SYSTEM_TIME", 2.2)
    assert len(st) >= 2 and abs(st[-1].time_unix_usec / 1e6 - time.time()) < 5


def test_mission_protocol_holds_an_empty_mission(station):
    for mtype in (mavlink.MAV_MISSION_TYPE_MISSION, mavlink.MAV_MISSION_TYPE_FENCE, mavlink.MAV_MISSION_TYPE_RALLY):
        station.send(mavlink.MAVLink_mission_request_list_message(1, 1, mtype))
        c = station.wait("MISSION_COUNT", lambda m, t=mtype: m.mission_type == t)
        assert c.count == 0 and (c.target_system, c.target_component) == (255, 190)
    station.send(mavlink.MAVLink_mission_count_message(1, 1, 3, 0))
    assert station.wait("MISSION_ACK").type == mavlink.MAV_MISSION_NO_SPACE
    station.send(mavlink.MAVLink_mission_clear_all_message(1, 1, 0))
    assert station.wait("MISSION_ACK").type == mavlink.MAV_MISSION_ACCEPTED
    station.send(mavlink.MAVLink_mission_request_int_message(1, 1, 0, 0))
    assert station.wait("MISSION_ACK").type == mavlink.MAV_MISSION_INVALID_SEQUENCE


def test_sys_status_claims_only_what_the_robot_has_and_no_fence_breach(station):
    s = station.wait("SYS_STATUS")
    S = mavlink
    has = (S.MAV_SYS_STATUS_SENSOR_3D_GYRO | S.MAV_SYS_STATUS_SENSOR_3D_ACCEL | S.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE
           | S.MAV_SYS_STATUS_AHRS | S.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS)
    assert s.onboard_control_sensors_present == has and s.onboard_control_sensors_enabled == has
    assert s.onboard_control_sensors_health & S.MAV_SYS_STATUS_GEOFENCE  # no fence, so never breached
    assert not s.onboard_control_sensors_health & S.MAV_SYS_STATUS_SENSOR_3D_GYRO  # no IMU heard: not healthy
    assert not s.onboard_control_sensors_health & S.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE


def test_available_modes_one_by_index_or_denied_for_an_index_that_does_not_exist(station):
    before = station.gcs.unknown_packets  # pymavlink 2.4.50 has no AVAILABLE_MODES: counted unknown here
    station.send(mavlink.MAVLink_command_long_message(1, 1, mavlink.MAV_CMD_REQUEST_MESSAGE, 0, 435, 2, 0, 0, 0, 0, 0))
    assert station.ack(mavlink.MAV_CMD_REQUEST_MESSAGE).result == mavlink.MAV_RESULT_ACCEPTED
    station.collect("HEARTBEAT", 0.5)
    assert station.gcs.unknown_packets == before + 1
    station.send(mavlink.MAVLink_command_long_message(1, 1, mavlink.MAV_CMD_REQUEST_MESSAGE, 0, 435, 9, 0, 0, 0, 0, 0))
    assert station.ack(mavlink.MAV_CMD_REQUEST_MESSAGE).result == mavlink.MAV_RESULT_DENIED


def test_mavftp_requests_get_an_immediate_nak_not_silence(station):
    import struct

    req = struct.pack("<HBBBBBBI", 5, 0, 4, 0, 0, 0, 0, 0) + b"@PARAM/param.pck"  # OpenFileRO
    station.send(mavlink.MAVLink_file_transfer_protocol_message(0, 1, 1, list(req.ljust(251, b"\0"))))
    m = station.wait("FILE_TRANSFER_PROTOCOL")
    seq, session, opcode, size, req_opcode = struct.unpack_from("<HBBBB", bytes(m.payload))
    assert (m.target_system, m.target_component) == (255, 190)
    assert (seq, opcode, size, req_opcode, m.payload[12]) == (6, 129, 1, 4, 7)  # NAK, UnknownCommand


def test_real_time_imu_stamps_on_another_clock_raise_no_imu_lost():
    """A real autopilot's stamps count from its own boot, not the loop's start: here the loop has
    run 10 s when the autopilot, booted 5 s ago, starts sending (`jetloop hil --realtime` starts its
    clock when the controller first speaks, after the loop's warm-up).
    Before the fix the monitor compared them with the loop clock and raised IMU_LOST at every tick
    (and cleared it at every sample): thousands of STATUSTEXTs in a ground station."""
    from onboard import mavlink_codec as codec
    from onboard.monitor import Fault
    from onboard.sensors import ImuSample

    link = Link("udpin:127.0.0.1:0")
    loop = OnboardLoop(load_vehicle(), link, WallClock(), warm_up=False)
    loop.clock._t0 -= 10.0  # the loop started 10 s ago
    try:
        for i in range(80):
            t = loop.clock.now()
            loop.handle(codec.encode_imu(ImuSample(t - 5.0, (0.001 * (i % 7), 0.0, -9.81), (0.0, 0.0, 0.0))))
            loop.step(t)
            time.sleep(0.01)
        assert not loop.monitor.faults_seen & Fault.IMU_LOST, loop.stats.fault_events
        assert not [e for e in loop.stats.fault_events if "IMU_LOST" in e[2]]
    finally:
        link.close()


def test_a_set_that_cannot_be_saved_flies_and_says_it_was_not_saved(tmp_path):
    s = Station(LoopConfig(parameter_file=str(tmp_path / "no-such-dir" / "v.params")))
    try:
        s.send(mavlink.MAVLink_param_set_message(1, 1, b"CTL_ATT_BW", 4.0, 9))
        assert s.wait("PARAM_VALUE").param_value == pytest.approx(4.0)
        text = s.wait("STATUSTEXT")
        assert (text.text if isinstance(text.text, str) else text.text.decode()).startswith(
            "CTL_ATT_BW not saved: No such file or directory")
        assert s.loop.controller.gains.attitude_bandwidth_rad_s == pytest.approx(4.0)
    finally:
        s.close()


def test_a_flood_of_param_sets_is_written_at_most_once_a_second_and_the_last_at_stop(tmp_path):
    """A PARAM_SET takes effect at once but the parameter file is rewritten at most once a second
    (the writes are the control loop's disk IO): before the fix each of the N sets rewrote it. The
    last value is in the file once the loop stops."""
    path = tmp_path / "asr4.params"
    s = Station(LoopConfig(parameter_file=str(path)))
    n = 150
    values = [2.0 + 4.0 * i / (n - 1) for i in range(n)]  # CTL_ATT_BW, in range, all different
    writes = []  # (mtime_ns, inode) of each version of the file seen while the sets go in
    try:
        t0 = time.monotonic()
        for i, v in enumerate(values):
            s.send(mavlink.MAVLink_param_set_message(1, 1, b"CTL_ATT_BW", v, 9))
            s.wait("PARAM_VALUE", lambda m: m.param_value == pytest.approx(v, rel=1e-6))  # one at a time
            st = path.stat() if path.exists() else None
            if st is not None and (st.st_mtime_ns, st.st_ino) not in writes:
                writes.append((st.st_mtime_ns, st.st_ino))
        elapsed = time.monotonic() - t0
        assert s.loop.controller.gains.attitude_bandwidth_rad_s == pytest.approx(values[-1], rel=1e-6)  # live
        assert len(writes) <= 2 + elapsed < n / 4, (len(writes), elapsed)  # seen on disk
        assert s.loop.services.params.writes <= 2 + elapsed, (s.loop.services.params.writes, elapsed)
    finally:
        s.close()
    assert P.load(path)["CTL_ATT_BW"] == pytest.approx(values[-1], rel=1e-6)  # written at stop


@pytest.mark.slow  # a jetloop process loads the compiled model
def test_jetloop_onboard_with_a_bad_parameter_file_exits_2_with_one_line(tmp_path):
    import subprocess
    import sys

    bad = tmp_path / "v.params"
    bad.write_text("CTL_DEPTH_BW 99\n")
    r = subprocess.run([sys.executable, "-m", "ground.cli", "onboard", "--link", "udpin:127.0.0.1:0",
                        "--params", str(bad), "--duration", "1"], capture_output=True, text=True, timeout=120)
    assert r.returncode == 2, r
    assert r.stderr.strip().splitlines() == [f"jetloop onboard: {bad}:1: CTL_DEPTH_BW 99 rad/s: expected 0.1-6 rad/s"]


# -- hostile or odd requests, in process (the loop's handle, the replies it sends) --------------------

def _decoded(msg):
    """`msg` as the robot receives it from system 255 (packed and parsed, header and all)."""
    return mavlink.MAVLink(None, 1, 1).parse_char(msg.pack(mavlink.MAVLink(None, 255, 190)))


@pytest.fixture
def bare_loop():
    link = Link("udpin:127.0.0.1:0")
    loop = OnboardLoop(load_vehicle(), link, WallClock(), LoopConfig(), warm_up=False)
    sent = []
    link.send = sent.append  # the replies, in order
    yield loop, sent
    link.close()


def test_the_interval_of_a_very_slow_stream_is_reported_not_a_crash(bare_loop):
    """SET_MESSAGE_INTERVAL takes any float: 1e12 us is a rate of 1e-6 Hz, whose interval does not
    fit MESSAGE_INTERVAL's int32 (before the fix the pack raised struct.error out of the loop: two
    commands from any ground station ended `jetloop onboard`)."""
    loop, sent = bare_loop
    cmd = mavlink.MAVLink_command_long_message
    loop.handle(_decoded(cmd(1, 1, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0, 30, 1e12, 0, 0, 0, 0, 0)))
    sent.clear()
    loop.handle(_decoded(cmd(1, 1, mavlink.MAV_CMD_GET_MESSAGE_INTERVAL, 0, 30, 0, 0, 0, 0, 0, 0)))
    assert [m.get_type() for m in sent] == ["COMMAND_ACK", "MESSAGE_INTERVAL"]
    assert (sent[1].message_id, sent[1].interval_us) == (30, 2**31 - 1)


def test_request_message_interval_reports_the_message_named_in_param2(bare_loop):
    """MAVLink's MESSAGE_INTERVAL: requested with param1 244 and param2 the message id (before the
    fix the answer was about message 244 itself)."""
    loop, sent = bare_loop
    loop.handle(_decoded(mavlink.MAVLink_command_long_message(1, 1, mavlink.MAV_CMD_REQUEST_MESSAGE, 0,
                                                              mavlink.MAVLINK_MSG_ID_MESSAGE_INTERVAL,
                                                              mavlink.MAVLINK_MSG_ID_ATTITUDE, 0, 0, 0, 0, 0)))
    assert sent[0].result == mavlink.MAV_RESULT_ACCEPTED
    assert (sent[1].message_id, sent[1].interval_us) == (mavlink.MAVLINK_MSG_ID_ATTITUDE, 100_000)  # 10 Hz


def test_an_ftp_reply_is_not_answered(bare_loop):
    """Only requests get the NAK: a NAK (opcode 129) from another robot answered with a NAK would
    ping-pong between the two for ever."""
    import struct

    loop, sent = bare_loop
    nak = struct.pack("<HBBBBBBIB", 6, 0, 129, 1, 4, 0, 0, 0, 7)
    loop.handle(_decoded(mavlink.MAVLink_file_transfer_protocol_message(0, 1, 1, list(nak.ljust(251, b"\0")))))
    assert not [m for m in sent if m.get_type() == "FILE_TRANSFER_PROTOCOL"]


def test_a_parameter_file_whose_values_are_each_in_range_but_no_loop_together_is_one_error(tmp_path):
    """All six allocation weights 0 is each in ALLOC_W_*'s range, but no allocator: the start is a
    ParameterFileError naming the file (before the fix a ValueError traceback from the allocator)."""
    f = tmp_path / "v.params"
    f.write_text("".join(f"ALLOC_W_{a} 0\n" for a in P.AXES))
    link = Link("udpin:127.0.0.1:0")
    try:
        with pytest.raises(P.ParameterFileError, match=r"v.params: AllocationConfig.axis_weights: .*not all zero"):
            OnboardLoop(load_vehicle(), link, WallClock(), LoopConfig(parameter_file=str(f)), warm_up=False)
    finally:
        link.close()


def test_request_data_stream_capabilities_and_uploads_as_the_readme_says(bare_loop):
    """The README's table rows no other test reached: REQUEST_DATA_STREAM sets the streams it names,
    REQUEST_AUTOPILOT_CAPABILITIES sends AUTOPILOT_VERSION after its ACK, an uploaded item is
    NO_SPACE and a fence upload UNSUPPORTED."""
    loop, sent = bare_loop
    loop.handle(_decoded(mavlink.MAVLink_request_data_stream_message(1, 1, mavlink.MAV_DATA_STREAM_EXTRA1, 2, 1)))
    loop.handle(_decoded(mavlink.MAVLink_request_data_stream_message(1, 1, mavlink.MAV_DATA_STREAM_POSITION, 5, 1)))
    assert loop.rates.rate_hz["ATTITUDE"] == 2.0 and loop.rates.rate_hz["LOCAL_POSITION_NED"] == 5.0
    loop.handle(_decoded(mavlink.MAVLink_request_data_stream_message(1, 1, mavlink.MAV_DATA_STREAM_EXTRA1, 2, 0)))
    assert loop.rates.rate_hz["ATTITUDE"] == 0.0  # start_stop 0: stopped
    sent.clear()
    loop.handle(_decoded(mavlink.MAVLink_command_long_message(1, 1, mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES,
                                                              0, 1, 0, 0, 0, 0, 0, 0)))
    assert [m.get_type() for m in sent] == ["COMMAND_ACK", "AUTOPILOT_VERSION"]
    sent.clear()
    loop.handle(_decoded(mavlink.MAVLink_mission_item_int_message(1, 1, 0, 0, 16, 1, 1, 0, 0, 0, 0, 0, 0, 0, 0)))
    loop.handle(_decoded(mavlink.MAVLink_mission_count_message(1, 1, 2, mavlink.MAV_MISSION_TYPE_FENCE)))
    assert [(m.get_type(), m.type) for m in sent] == [("MISSION_ACK", mavlink.MAV_MISSION_NO_SPACE),
                                                      ("MISSION_ACK", mavlink.MAV_MISSION_UNSUPPORTED)]


def test_an_imu_timeout_not_above_the_stamp_skew_is_refused_live_and_from_the_file(bare_loop, tmp_path):
    """LoopConfig refuses max_stamp_skew_s >= imu_timeout_s (a stamp accepted ahead would starve
    the failsafe); FS_IMU_TIMEOUT's range (0.05-5 s) let a PARAM_SET or the parameter file undo it
    (before the fix 0.1 s was flown beside the 0.2 s skew)."""
    loop, sent = bare_loop
    loop.handle(_decoded(mavlink.MAVLink_param_set_message(1, 1, b"FS_IMU_TIMEOUT", 0.1, 9)))
    assert sent[0].get_type() == "PARAM_VALUE" and sent[0].param_value == pytest.approx(0.3)  # the old one echoed
    assert loop.fs_state.imu_timeout_s == pytest.approx(0.3) and loop.services.params.values["FS_IMU_TIMEOUT"] == 0.3
    text = "".join(m.text for m in sent if m.get_type() == "STATUSTEXT")
    assert text == "FS_IMU_TIMEOUT 0.1: expected > stamp skew 0.2 s", text  # STATUSTEXT holds 50
    loop.handle(_decoded(mavlink.MAVLink_param_set_message(1, 1, b"FS_IMU_TIMEOUT", 0.5, 9)))
    assert loop.fs_state.imu_timeout_s == pytest.approx(0.5)  # above the skew: flown
    f = tmp_path / "v.params"
    f.write_text("FS_IMU_TIMEOUT 0.1\n")
    link = Link("udpin:127.0.0.1:0")
    try:
        with pytest.raises(P.ParameterFileError, match=r"v.params: FS_IMU_TIMEOUT 0.1: expected > stamp skew 0.2 s"):
            OnboardLoop(load_vehicle(), link, WallClock(), LoopConfig(parameter_file=str(f)), warm_up=False)
    finally:
        link.close()


@pytest.mark.parametrize("message_id", [float("inf"), float("-inf"), float("nan")])
def test_set_message_interval_for_an_infinite_or_nan_message_id_is_acked_denied(bare_loop, message_id):
    """Every COMMAND_LONG gets a COMMAND_ACK (README): before the fix int(round(inf)) raised
    OverflowError (NaN: ValueError), counted as a rejected input and dropped with no ACK."""
    loop, sent = bare_loop
    before = loop.stats.rejected_inputs
    loop.handle(_decoded(mavlink.MAVLink_command_long_message(1, 1, mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                                                              message_id, 100_000, 0, 0, 0, 0, 0)))
    acks = [m for m in sent if m.get_type() == "COMMAND_ACK"]
    assert [(a.command, a.result) for a in acks] == [(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, mavlink.MAV_RESULT_DENIED)]
    assert loop.stats.rejected_inputs == before


def test_a_set_within_a_second_of_the_last_write_is_written_when_the_loop_stops(tmp_path):
    """The second of two quick sets waits (at most a second, the 1 Hz tick) and is written when the
    loop's run() returns; before the fix both were written at once."""
    path = tmp_path / "asr4.params"
    link = Link("udpin:127.0.0.1:0")
    try:
        loop = OnboardLoop(load_vehicle(), link, WallClock(), LoopConfig(parameter_file=str(path)), warm_up=False)
        for v in (4.0, 5.0):
            loop.handle(_decoded(mavlink.MAVLink_param_set_message(1, 1, b"CTL_ATT_BW", v, 9)))
        assert loop.controller.gains.attitude_bandwidth_rad_s == pytest.approx(5.0)  # in effect at once
        assert P.load(path)["CTL_ATT_BW"] == pytest.approx(4.0)  # the file: the first, written at once
        assert loop.run(stop=lambda: True) == "stopped"
        assert P.load(path)["CTL_ATT_BW"] == pytest.approx(5.0)
    finally:
        link.close()
