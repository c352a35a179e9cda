"""QGroundControl's connect sequence replayed against the robot (QGC cannot be installed here).

Written from QGroundControl's public source (github.com/mavlink/qgroundcontrol):
- MultiVehicleManager::_vehicleHeartbeatInfo: a vehicle is created only from a HEARTBEAT of
  component MAV_COMP_ID_AUTOPILOT1 (1), system id not 0, type not GCS / ONBOARD_CONTROLLER /
  GIMBAL / ADSB; QGC then sends its own HEARTBEAT (MAV_TYPE_GCS, MAV_AUTOPILOT_INVALID) at 1 Hz.
- InitialConnectStateMachine, in order: REQUEST_MESSAGE(AUTOPILOT_VERSION) to component 1 (the
  capabilities decide what follows; a failure means "MAVLink 2 only"), the standard modes request
  (REQUEST_MESSAGE AVAILABLE_MODES, id 435) and component information (REQUEST_MESSAGE
  COMPONENT_METADATA 397, then COMPONENT_INFORMATION 395): any answer but silence lets it go on;
  ParameterManager::refreshAllParameters: PARAM_REQUEST_LIST to MAV_COMP_ID_ALL, PARAM_VALUEs
  counted by param_count / param_index, missing indices asked again by PARAM_REQUEST_READ; the
  mission (MISSION_REQUEST_LIST, type mission); geofence and rally points only when the
  capability bits MISSION_FENCE / MISSION_RALLY are set.
- Vehicle::sendMavCommand: a command unanswered is sent again and finally reported as failed, so
  every command needs its COMMAND_ACK.
"""

from __future__ import annotations

import select
import socket
import struct
import time
from collections import deque

import pytest
from pymavlink.dialects.v20 import ardupilotmega as mavlink
from pymavlink.generator.mavcrc import x25crc

from conftest import free_udp_port
from gcs_rig import Robot
from onboard import params as P
from onboard.loop import LoopConfig

NOT_VEHICLES = (mavlink.MAV_TYPE_GCS, mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_TYPE_GIMBAL, mavlink.MAV_TYPE_ADSB)
ACK_TIMEOUT_S = 1.0  # well inside QGC's command retry interval


AVAILABLE_MODES_CRC_EXTRA = 134  # MAVLINK_MSG_ID_AVAILABLE_MODES_CRC of MAVLink's generated C header


def available_modes(msg):
    """(number_modes, mode_index, standard_mode, custom_mode, name) of an AVAILABLE_MODES packet that
    pymavlink 2.4.50 cannot decode, after checking its CRC with the message's published CRC extra."""
    buf = bytes(msg.get_msgbuf())
    n = buf[1]
    crc = x25crc(buf[1:10 + n])
    crc.accumulate([AVAILABLE_MODES_CRC_EXTRA])
    assert crc.crc == struct.unpack("<H", buf[10 + n:12 + n])[0], "AVAILABLE_MODES CRC"
    custom, _props, number, index, standard, name = struct.unpack("<IIBBB35s", buf[10:10 + n].ljust(46, b"\0"))
    return number, index, standard, custom, name.split(b"\0")[0].decode()


class Qgc:
    """QGC's side: a UDP port the vehicle sends to, and a MAVLink parser that keeps messages it has
    no definition for (as QGC's newer dialect has AVAILABLE_MODES)."""

    def __init__(self, port: int):
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", port))
        self.mav = mavlink.MAVLink(None, srcSystem=255, srcComponent=190)
        self.mav.robust_parsing = True
        self.peer = None
        self.queue: deque = deque()
        self._next_beat = 0.0

    def send(self, msg) -> None:
        self.sock.sendto(msg.pack(self.mav), self.peer)

    def recv(self, timeout_s: float):
        if time.monotonic() >= self._next_beat and self.peer is not None:  # QGC's 1 Hz GCS heartbeat
            self._next_beat = time.monotonic() + 1.0
            self.send(mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID,
                                                        mavlink.MAV_MODE_MANUAL_ARMED, 0, mavlink.MAV_STATE_ACTIVE, 3))
        if not self.queue and select.select([self.sock], [], [], timeout_s)[0]:
            data, self.peer = self.sock.recvfrom(65535)
            self.queue.extend(m for m in (self.mav.parse_buffer(data) or []) if m.get_type() != "BAD_DATA")
        return self.queue.popleft() if self.queue else None

    def close(self) -> None:
        self.sock.close()

    def wait(self, pred, timeout_s: float):
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            m = self.recv(0.05)
            if m is not None and pred(m):
                return m
        return None

    def request_message(self, msg_id: int):
        """Vehicle::requestMessage: COMMAND_LONG REQUEST_MESSAGE to component 1; (result, message)."""
        self.send(mavlink.MAVLink_command_long_message(1, 1, mavlink.MAV_CMD_REQUEST_MESSAGE, 0,
                                                       msg_id, 0, 0, 0, 0, 0, 0))
        ack = self.wait(lambda m: m.get_type() == "COMMAND_ACK" and m.command == mavlink.MAV_CMD_REQUEST_MESSAGE,
                        ACK_TIMEOUT_S)
        assert ack is not None, f"REQUEST_MESSAGE {msg_id} never acked: QGC would retry, then stall this step"
        if ack.result != mavlink.MAV_RESULT_ACCEPTED:
            return ack.result, None
        msg = self.wait(lambda m: m.get_msgId() == msg_id, 2.0)
        return ack.result, msg


@pytest.mark.slow
def test_qgroundcontrol_connect_sequence_completes(tmp_path):
    port = free_udp_port()
    qgc = Qgc(port)
    robot = Robot(port, LoopConfig(parameter_file=str(tmp_path / "asr4.params"))).start()
    try:
        # MultiVehicleManager: which heartbeat makes a vehicle
        hb = qgc.wait(lambda m: m.get_type() == "HEARTBEAT", 10.0)
        assert hb is not None
        assert hb.get_srcComponent() == mavlink.MAV_COMP_ID_AUTOPILOT1 and hb.get_srcSystem() != 0
        assert hb.type not in NOT_VEHICLES and hb.type == mavlink.MAV_TYPE_SUBMARINE
        assert hb.autopilot == mavlink.MAV_AUTOPILOT_GENERIC  # QGC's generic firmware plugin

        # 1. AUTOPILOT_VERSION
        result, av = qgc.request_message(mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION)
        assert result == mavlink.MAV_RESULT_ACCEPTED and av is not None
        caps = av.capabilities
        assert caps & mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2
        assert av.uid != 0 and av.flight_sw_version != 0  # QGC shows the version when it is not 0

        # 2. standard modes (StandardModes::request, param2 0: all): every mode with its name, the
        # last one's index equal to number_modes (QGC's "done")
        qgc.send(mavlink.MAVLink_command_long_message(1, 1, mavlink.MAV_CMD_REQUEST_MESSAGE, 0, 435, 0, 0, 0, 0, 0, 0))
        ack = qgc.wait(lambda m: m.get_type() == "COMMAND_ACK" and m.command == mavlink.MAV_CMD_REQUEST_MESSAGE,
                       ACK_TIMEOUT_S)
        assert ack is not None and ack.result == mavlink.MAV_RESULT_ACCEPTED
        modes = []
        while not modes or modes[-1][1] < modes[-1][0]:
            m = qgc.wait(lambda m: m.get_type() == "UNKNOWN_435", 2.0)  # pymavlink 2.4.50 has no definition
            assert m is not None, modes
            modes.append(available_modes(m))
        assert [(custom, name) for _, _, _, custom, name in modes] == [
            (0, "Stabilize"), (2, "Depth Hold"), (4, "Guided"), (19, "Manual")]
        assert [index for _, index, _, _, _ in modes] == [1, 2, 3, 4]
        # component information: refused at once, QGC moves on
        for msg_id in (397, 395):  # COMPONENT_METADATA, COMPONENT_INFORMATION
            result, _ = qgc.request_message(msg_id)
            assert result in (mavlink.MAV_RESULT_DENIED, mavlink.MAV_RESULT_UNSUPPORTED)

        # 3. parameters: list to every component, then fill the gaps by index as ParameterManager does
        qgc.send(mavlink.MAVLink_param_request_list_message(1, mavlink.MAV_COMP_ID_ALL))
        values: dict = {}
        count = None
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            m = qgc.wait(lambda m: m.get_type() == "PARAM_VALUE", 0.5)
            if m is None:
                missing = sorted(set(range(count or 0)) - set(values))
                if count is not None and not missing:
                    break
                for i in missing[:10]:
                    qgc.send(mavlink.MAVLink_param_request_read_message(1, 1, b"", i))
                continue
            assert m.get_srcComponent() == mavlink.MAV_COMP_ID_AUTOPILOT1  # QGC's default component
            count = m.param_count if count is None else count
            assert m.param_count == count and 0 <= m.param_index < count
            values[m.param_index] = m.param_id if isinstance(m.param_id, str) else m.param_id.decode()
            if len(values) == count:
                break
        assert count == len(P.PARAMS) and sorted(values) == list(range(count))
        assert len(set(values.values())) == count  # names unique, so QGC's fact map holds them all

        # 4. mission (MissionManager::loadFromVehicle)
        qgc.send(mavlink.MAVLink_mission_request_list_message(1, 1, mavlink.MAV_MISSION_TYPE_MISSION))
        mc = qgc.wait(lambda m: m.get_type() == "MISSION_COUNT", 2.0)
        assert mc is not None and mc.count == 0 and mc.mission_type == mavlink.MAV_MISSION_TYPE_MISSION
        # 5./6. geofence and rally: skipped by QGC, because the robot does not claim them
        assert not caps & mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_FENCE
        assert not caps & mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_RALLY

        # the operator's first actions, once SYS_STATUS says the IMU is healthy (QGC's "ready"):
        # arm, a mode, disarm; each acknowledged in time
        gyro = mavlink.MAV_SYS_STATUS_SENSOR_3D_GYRO
        assert qgc.wait(lambda m: m.get_type() == "SYS_STATUS" and m.onboard_control_sensors_health & gyro, 10.0)
        for cmd, p1, p2, want in ((mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1, 0, mavlink.MAV_RESULT_ACCEPTED),
                                  (mavlink.MAV_CMD_DO_SET_MODE, 1, 2, mavlink.MAV_RESULT_ACCEPTED),
                                  (mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 0, 0, mavlink.MAV_RESULT_ACCEPTED),
                                  (mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, mavlink.MAV_RESULT_UNSUPPORTED)):
            qgc.send(mavlink.MAVLink_command_long_message(1, 1, cmd, 0, p1, p2, 0, 0, 0, 0, 0))
            ack = qgc.wait(lambda m, c=cmd: m.get_type() == "COMMAND_ACK" and m.command == c, ACK_TIMEOUT_S)
            assert ack is not None, cmd
            if ack.result == mavlink.MAV_RESULT_TEMPORARILY_REJECTED:
                why = qgc.wait(lambda m: m.get_type() == "STATUSTEXT", 1.0)
                pytest.fail(f"command {cmd} rejected: {why.text if why is not None else '?'}; "
                            f"{robot.loop.fs_state}")
            assert ack.result == want, (cmd, ack.result)
        assert qgc.wait(lambda m: m.get_type() == "HEARTBEAT" and m.custom_mode == 2, 2.5) is not None
    finally:
        robot.stop()
        qgc.close()
