"""The MAVLink microservices a ground station expects of a vehicle: identity, parameters, commands, mission.

What QGroundControl, MAVProxy and MAVSDK do on connect, and what the robot answers (the loop hands
each such message here; onboard.loop keeps only the flying):

- **Identity** (`Identity`). QGroundControl makes a vehicle only of a HEARTBEAT from component 1
  (MAV_COMP_ID_AUTOPILOT1) whose type is not GCS / ONBOARD_CONTROLLER / GIMBAL / ADSB
  (MultiVehicleManager::_vehicleHeartbeatInfo); MAVSDK looks for an autopilot the same way. So when
  the loop is the vehicle's controller (role "vehicle": a HIL plant, or a sensor board that is no
  flight stack) it speaks to the ground as component 1, MAV_TYPE_SUBMARINE. When its sensors come
  from a real flight stack on the main link (a HEARTBEAT there whose autopilot field names one:
  ArduPilot, PX4, ...; role "companion") it speaks as component 191 (MAV_COMP_ID_ONBOARD_COMPUTER),
  MAV_TYPE_ONBOARD_CONTROLLER, and leaves parameters, mission and identity to the autopilot. On the
  main link beside a plant or an autopilot (which own component 1 there) it is always 191.
- **Parameters** (onboard.params is the table): PARAM_REQUEST_LIST -> every PARAM_VALUE with its
  index and the count; PARAM_REQUEST_READ by name or index; PARAM_SET -> the value takes effect at
  the next control step, is written to the parameter file (at most once a second, and when the loop
  stops) and echoed in PARAM_VALUE; a value out of
  range is refused, the old value echoed and a STATUSTEXT says why. PARAM_SET is a command
  (onboard.signing.COMMAND_MESSAGES): with signing on, unsigned ones are refused by the gate.
- **Commands**: every COMMAND_LONG and COMMAND_INT gets a COMMAND_ACK (a companion's: those
  addressed to 191 or 0, `for_another_component`) (the loop's `_on_command`;
  COMMAND_INT is read as the same command). Here: MAV_CMD_REQUEST_MESSAGE (AUTOPILOT_VERSION,
  HEARTBEAT, SYS_STATUS, SYSTEM_TIME, ATTITUDE, LOCAL_POSITION_NED, MESSAGE_INTERVAL: the ones the
  robot can fill truthfully; any other DENIED), REQUEST_AUTOPILOT_CAPABILITIES, GET_MESSAGE_INTERVAL.
  The message goes out after its ACK. REQUEST_MESSAGE(AVAILABLE_MODES, 435) answers the standard
  modes protocol with each mode's number and name (QGroundControl names a generic vehicle's modes
  from it). REQUEST_PROTOCOL_VERSION is UNSUPPORTED: the dialect the robot
  carries (pymavlink's ardupilotmega) has no PROTOCOL_VERSION message.
- **Modes**: SET_MODE (legacy message) is read as MAV_CMD_DO_SET_MODE; HEARTBEAT.base_mode carries
  the standard flags of each mode (stabilize, guided, manual input) beside the custom number.
- **Time**: SYSTEM_TIME at 1 Hz to the ground; TIMESYNC requests answered (tc1 = our monotonic ns);
  PING requests answered.
- **Mission**: the robot holds no mission items: MISSION_REQUEST_LIST of any type -> MISSION_COUNT 0;
  an upload of items -> MISSION_ACK NO_SPACE (fence, rally: UNSUPPORTED); an empty upload or
  MISSION_CLEAR_ALL -> ACCEPTED; a request for an item -> INVALID_SEQUENCE.
- **MAVFTP**: the robot serves no files (no FTP capability bit); every FILE_TRANSFER_PROTOCOL
  request is answered NAK UnknownCommand at once, so a ground station that tries MAVFTP first
  (MAVProxy fetches parameters that way) falls back without waiting for a timeout.
- **Streams**: REQUEST_DATA_STREAM (MAVProxy's and older ground stations' way) sets the rates of the
  streams it names, as SET_MESSAGE_INTERVAL does.
"""

from __future__ import annotations

import math
import struct
import time
import zlib

from pymavlink.dialects.v20 import ardupilotmega as mavlink

from . import params as P

MAV_COMP_ID_AUTOPILOT1 = mavlink.MAV_COMP_ID_AUTOPILOT1  # 1
MAV_COMP_ID_ONBOARD_COMPUTER = mavlink.MAV_COMP_ID_ONBOARD_COMPUTER  # 191
NOT_A_FLIGHT_STACK = (mavlink.MAV_AUTOPILOT_GENERIC, mavlink.MAV_AUTOPILOT_INVALID)
VERSION = (0, 1, 0)  # pyproject's version: AUTOPILOT_VERSION.flight_sw_version

# What AUTOPILOT_VERSION claims: only what this module and the loop really do
CAPABILITIES = (mavlink.MAV_PROTOCOL_CAPABILITY_MAVLINK2
                | mavlink.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST  # every value REAL32: both encodings agree
                | mavlink.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
                | mavlink.MAV_PROTOCOL_CAPABILITY_MISSION_INT  # MISSION_REQUEST_INT answered (empty mission)
                | mavlink.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED)

MODE_FLAGS = {  # HEARTBEAT.base_mode flags of each mode (onboard.loop.MODES numbers)
    0: mavlink.MAV_MODE_FLAG_STABILIZE_ENABLED | mavlink.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED,  # stabilize
    2: mavlink.MAV_MODE_FLAG_STABILIZE_ENABLED | mavlink.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED,  # depth_hold
    4: mavlink.MAV_MODE_FLAG_STABILIZE_ENABLED | mavlink.MAV_MODE_FLAG_GUIDED_ENABLED,  # guided
    19: mavlink.MAV_MODE_FLAG_MANUAL_INPUT_ENABLED,  # manual
}

# REQUEST_DATA_STREAM stream id -> the telemetry messages it sets (ArduPilot's grouping)
DATA_STREAMS = {
    mavlink.MAV_DATA_STREAM_ALL: ("ATTITUDE", "NAMED_VALUE_FLOAT", "DEBUG_FLOAT_ARRAY", "SERVO_OUTPUT_RAW"),
    mavlink.MAV_DATA_STREAM_EXTRA1: ("ATTITUDE",),
    mavlink.MAV_DATA_STREAM_POSITION: ("LOCAL_POSITION_NED",),
    mavlink.MAV_DATA_STREAM_RC_CHANNELS: ("SERVO_OUTPUT_RAW",),
    mavlink.MAV_DATA_STREAM_EXTRA3: ("NAMED_VALUE_FLOAT", "DEBUG_FLOAT_ARRAY"),
}

MODE_NAMES = {0: "Stabilize", 2: "Depth Hold", 4: "Guided", 19: "Manual"}  # AVAILABLE_MODES.mode_name


class AvailableModes(mavlink.MAVLink_message):
    """AVAILABLE_MODES (id 435, MAVLink's standard modes protocol): one mode's number and name, so a
    ground station that knows no ArduSub numbering (QGroundControl's generic vehicle) can name the
    modes and offer them. pymavlink 2.4.50's dialects lack it; the layout and CRC extra (134) are
    those of MAVLink's generated C header (mavlink_msg_available_modes.h)."""

    id = 435
    msgname = "AVAILABLE_MODES"
    crc_extra = 134
    unpacker = struct.Struct("<IIBBB35s")  # custom_mode, properties, number_modes, mode_index, standard_mode, mode_name

    def __init__(self, number_modes: int, mode_index: int, custom_mode: int, name: str):
        mavlink.MAVLink_message.__init__(self, self.id, self.msgname)
        self._fieldnames = ["number_modes", "mode_index", "standard_mode", "custom_mode", "properties", "mode_name"]
        self.number_modes, self.mode_index, self.standard_mode = number_modes, mode_index, 0  # non-standard
        self.custom_mode, self.properties, self.mode_name = custom_mode, 0, name

    def pack(self, mav, force_mavlink1: bool = False) -> bytes:
        return self._pack(mav, self.crc_extra, self.unpacker.pack(
            self.custom_mode, self.properties, self.number_modes, self.mode_index, self.standard_mode,
            self.mode_name.encode()), force_mavlink1=force_mavlink1)


MESSAGES = frozenset({
    "HEARTBEAT", "PARAM_REQUEST_LIST", "PARAM_REQUEST_READ", "PARAM_SET", "COMMAND_INT", "SET_MODE",
    "TIMESYNC", "PING", "REQUEST_DATA_STREAM", "AUTOPILOT_VERSION_REQUEST", "MISSION_REQUEST_LIST",
    "MISSION_REQUEST", "MISSION_REQUEST_INT", "MISSION_COUNT", "MISSION_CLEAR_ALL", "MISSION_ITEM",
    "MISSION_ITEM_INT", "FILE_TRANSFER_PROTOCOL",
})
FTP_NAK, FTP_ERR_UNKNOWN_COMMAND = 129, 7  # MAVLink FTP opcode NAK, error UnknownCommand
FTP_FIRST_REPLY = 128  # opcodes from 128 (ACK, NAK) are replies: never answered (two robots would ping-pong)
INT32_MAX = 2**31 - 1


class Identity:
    """Who the loop is to the ground: role "vehicle" (component 1, MAV_TYPE_SUBMARINE) or
    "companion" (component 191, MAV_TYPE_ONBOARD_CONTROLLER). `setting` "auto" decides on the
    main link's HEARTBEATs: one from a flight stack (autopilot field other than GENERIC/INVALID)
    makes the loop its companion, for good."""

    def __init__(self, setting: str = "auto"):
        if setting not in ("auto", "vehicle", "companion"):
            raise ValueError(f"identity: expected 'auto', 'vehicle' or 'companion', got {setting!r}")
        self.setting = setting
        self.role = "companion" if setting == "companion" else "vehicle"
        self.autopilot = None  # (system, component, MAV_AUTOPILOT) of the flight stack seen
        self.component1_taken = False  # a plant or autopilot speaks as our system's component 1 on the main link

    @property
    def component(self) -> int:
        """The component id the ground hears the loop as."""
        return MAV_COMP_ID_AUTOPILOT1 if self.role == "vehicle" else MAV_COMP_ID_ONBOARD_COMPUTER

    def observe_heartbeat(self, m, own_system: int = 1) -> bool:
        """A HEARTBEAT from the main link; True when it changed the role or the main link's owner."""
        if (m.get_srcSystem(), m.get_srcComponent()) == (own_system, MAV_COMP_ID_AUTOPILOT1) \
                and int(m.type) != mavlink.MAV_TYPE_GCS and not self.component1_taken:
            self.component1_taken = True
            self.observe_heartbeat(m, own_system)
            return True
        if self.setting != "auto" or self.role == "companion" or int(m.autopilot) in NOT_A_FLIGHT_STACK:
            return False
        if int(m.type) in (mavlink.MAV_TYPE_GCS, mavlink.MAV_TYPE_ONBOARD_CONTROLLER):
            return False
        self.role = "companion"
        self.autopilot = (m.get_srcSystem(), m.get_srcComponent(), int(m.autopilot))
        return True


def command_int_as_long(m):
    """COMMAND_INT read as the COMMAND_LONG of the same command (x, y as param5, param6), keeping
    the sender's header so its ACK goes back to it."""
    cl = mavlink.MAVLink_command_long_message(m.target_system, m.target_component, m.command, 0,
                                              m.param1, m.param2, m.param3, m.param4, float(m.x), float(m.y), m.z)
    cl._header = m._header
    return cl


def _text(v) -> str:
    return (v.decode("ascii", "replace") if isinstance(v, (bytes, bytearray)) else str(v)).split("\x00")[0]


class Microservices:
    """The ground-facing services of one OnboardLoop (see the module docstring)."""

    def __init__(self, loop):
        self.loop = loop
        cfg = loop.config
        self.identity = Identity(getattr(cfg, "identity", "auto"))
        from .control import Gains

        gains = getattr(loop.controller, "gains", Gains())
        self.params = P.Parameters(P.defaults(gains, loop.allocator.config, cfg.imu_timeout_s, loop.rates.default_hz),
                                   getattr(cfg, "parameter_file", None))
        self.uid = zlib.crc32(loop.vehicle.name.encode()) or 1  # AUTOPILOT_VERSION.uid: stable per vehicle
        self._after_ack: list = []
        try:  # each value of the file is in its range; together they must still make a loop
            self._apply(set(p.group for p in P.PARAMS if p.name in self.params.changed()))
        except (ValueError, TypeError) as exc:
            raise P.ParameterFileError(f"{self.params.path}: {str(exc)[:200]}") from exc
        self.apply_identity()

    # -- identity -------------------------------------------------------------------------------
    def apply_identity(self) -> None:
        """The ground link speaks as the identity's component; with no ground link the main link
        does, unless a plant or autopilot owns component 1 there (then 191, as before)."""
        loop = self.loop
        comp = self.identity.component
        if loop.ground is not None:
            _set_component(loop.ground, comp)
        elif self.identity.role == "companion" or self.identity.component1_taken:
            _set_component(loop.link, MAV_COMP_ID_ONBOARD_COMPUTER)
        else:
            _set_component(loop.link, comp)

    def heartbeat_fields(self, mode: int) -> tuple[int, int, int]:
        """(type, autopilot, extra base_mode flags) of the loop's own HEARTBEAT to the ground."""
        if self.identity.role == "companion":
            return mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID, 0
        return mavlink.MAV_TYPE_SUBMARINE, mavlink.MAV_AUTOPILOT_GENERIC, MODE_FLAGS.get(int(mode), 0)

    def _mine(self, m, link: str) -> bool:
        """Whether a request addressed (target_system, target_component) is the loop's to answer."""
        ts = getattr(m, "target_system", 0)
        tc = getattr(m, "target_component", 0)
        if ts not in (0, self.loop.gate.own_system):
            return False
        if tc == 0:
            return True
        if link == "ground" or self.loop.ground is None:
            return tc == self.identity.component
        return tc in (MAV_COMP_ID_ONBOARD_COMPUTER, MAV_COMP_ID_AUTOPILOT1) and self.identity.role == "vehicle"

    def for_another_component(self, m) -> bool:
        """A companion's (191 beside a real autopilot) commands are those addressed to it or to
        every component (0): one for the autopilot (1) or any other component is theirs, neither
        carried out nor acknowledged here."""
        if self.identity.role != "companion" or m.get_type() not in ("COMMAND_LONG", "COMMAND_INT"):
            return False
        return getattr(m, "target_component", 0) not in (0, MAV_COMP_ID_ONBOARD_COMPUTER)

    # -- messages -------------------------------------------------------------------------------
    def _out(self, link: str):
        lp = self.loop
        return lp.ground if (link == "ground" and lp.ground is not None) else lp.link

    def handle(self, m, link: str) -> None:
        name = m.get_type()
        out = self._out(link)
        if name == "HEARTBEAT":
            was = self.identity.role
            if link == "main" and self.identity.observe_heartbeat(m, self.loop.gate.own_system):
                self.apply_identity()
                a = self.identity.autopilot
                if self.identity.role != was:
                    self.loop._statustext(mavlink.MAV_SEVERITY_NOTICE,
                                          f"companion of autopilot {a[0]}:{a[1]}: component 191")
            return
        if name == "COMMAND_INT":
            from .envelope import command_violation

            cl = command_int_as_long(m)
            why = command_violation(cl)
            if why is not None:
                self.loop.stats.security.commands_denied += 1
                out.send(mavlink.MAVLink_command_ack_message(int(m.command), mavlink.MAV_RESULT_DENIED, 0, 0,
                                                             m.get_srcSystem(), m.get_srcComponent()))
                return
            self.loop._on_command(cl)
            return
        if name == "SET_MODE":
            if m.target_system not in (0, self.loop.gate.own_system):
                return
            cl = mavlink.MAVLink_command_long_message(m.target_system, 0, mavlink.MAV_CMD_DO_SET_MODE, 0,
                                                      float(m.base_mode | mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED),
                                                      float(m.custom_mode), 0, 0, 0, 0, 0)
            cl._header = m._header
            self.loop._on_command(cl)
            return
        if name == "TIMESYNC":
            if int(m.tc1) == 0:  # a request: tc1 our time, ts1 theirs echoed (MAVLink timesync)
                out.send(mavlink.MAVLink_timesync_message(time.monotonic_ns(), int(m.ts1)))
            return
        if name == "PING":
            if m.target_system == 0 and m.target_component == 0:  # a request, not an answer
                out.send(mavlink.MAVLink_ping_message(int(m.time_usec), int(m.seq), m.get_srcSystem(),
                                                      m.get_srcComponent()))
            return
        if not self._mine(m, link):
            return
        if name == "PARAM_REQUEST_LIST":
            for i in range(self.params.count):
                out.send(self._param_value(i))
        elif name == "PARAM_REQUEST_READ":
            i = int(m.param_index)
            if i < 0:
                pid = _text(m.param_id)
                i = self.params.index(pid) if pid in P.BY_NAME else -1
            if 0 <= i < self.params.count:
                out.send(self._param_value(i))
        elif name == "PARAM_SET":
            self._param_set(m, out)
        elif name == "AUTOPILOT_VERSION_REQUEST":
            out.send(self.autopilot_version())
        elif name == "REQUEST_DATA_STREAM":
            names = DATA_STREAMS.get(int(m.req_stream_id), ())
            hz = float(m.req_message_rate) if m.start_stop else 0.0
            for n in names:
                self.loop.rates.set_hz(n, hz)
        elif name.startswith("MISSION_"):
            self._mission(m, out)
        elif name == "FILE_TRANSFER_PROTOCOL":  # no file service: every request NAKed at once, so a
            req = bytes(m.payload[:12])        # ground station falls back (MAVProxy: PARAM_REQUEST_LIST)
            seq, session, opcode = struct.unpack_from("<HBB", req)
            if opcode >= FTP_FIRST_REPLY:
                return
            nak = struct.pack("<HBBBBBBIB", (seq + 1) & 0xFFFF, session, FTP_NAK, 1, opcode, 0, 0, 0,
                              FTP_ERR_UNKNOWN_COMMAND)
            out.send(mavlink.MAVLink_file_transfer_protocol_message(0, m.get_srcSystem(), m.get_srcComponent(),
                                                                    list(nak.ljust(251, b"\0"))))

    # -- parameters -----------------------------------------------------------------------------
    def _param_value(self, i: int):
        spec = P.PARAMS[i]
        return mavlink.MAVLink_param_value_message(spec.name.encode(), float(self.params.values[spec.name]),
                                                   mavlink.MAV_PARAM_TYPE_REAL32, self.params.count, i)

    def _param_set(self, m, out) -> None:
        name = _text(m.param_id)
        if name not in P.BY_NAME:
            for reply in self.loop.gate.refusal_text(f"param {name[:16]!r}: no such parameter"):
                out.send(reply)
            return
        old = self.params.values[name]
        why = P.check(name, m.param_value)
        if why is None:
            why = self._try_apply(name, float(m.param_value))
        if why is None:
            self.params.set(name, float(m.param_value))
        else:
            self.params.values[name] = old
        out.send(self._param_value(self.params.index(name)))  # the new value, or the old one echoed
        if why is None and self.params.last_save_error:  # flying with it; the next start will not have it
            out.send(mavlink.MAVLink_statustext_message(mavlink.MAV_SEVERITY_WARNING,
                                                        self.params.last_save_error[:50].encode()))
        if why is not None:  # and why
            self.loop.stats.security.commands_denied += 1
            for reply in self.loop.gate.refusal_text(why):  # STATUSTEXT holds 50 characters
                out.send(reply)

    def _try_apply(self, name: str, value: float) -> str | None:
        """Apply one new value to the running loop; why not (then nothing changed), else None."""
        old = self.params.values[name]
        self.params.values[name] = value
        try:
            self._apply({P.BY_NAME[name].group})
        except (ValueError, TypeError, AttributeError) as exc:
            self.params.values[name] = old
            self._apply({P.BY_NAME[name].group})
            return (str(exc) if str(exc).startswith(name) else f"{name}: {exc}")[:120]
        return None

    def _apply(self, groups: set) -> None:
        """Put the current values of these groups into the loop: controller gains (kept references
        and integrators), allocation weights (the allocator rebuilt with them), the IMU failsafe
        timeout, stream rates."""
        loop, values = self.loop, self.params.values
        if "controller" in groups:
            ctl = loop.controller
            if not hasattr(ctl, "set_gains"):
                raise ValueError("this controller takes no gains in flight")
            old = ctl.gains
            new = P.with_values(old, "controller", values)
            ctl.set_gains(new)
            yp = loop.yaw_preview
            if yp is not None and (new.yaw_bandwidth_rad_s, new.damping_ratio) != (old.yaw_bandwidth_rad_s, old.damping_ratio):
                loop.yaw_preview = type(yp)(loop.vehicle, loop.period_s, new.yaw_bandwidth_rad_s, new.damping_ratio)
        if "allocation" in groups:
            old = loop.allocator
            cfg = P.with_values(old.config, "allocation", values)
            if cfg != old.config:
                new = type(old)(loop.vehicle, loop.period_s, cfg)
                new.previous = old.previous
                new.set_health(old.efficiency, old.stuck_alpha_rad, old.stuck_beta_rad)
                loop.allocator = new
        if "failsafe" in groups:
            from dataclasses import replace

            t = values["FS_IMU_TIMEOUT"]
            skew = loop.config.max_stamp_skew_s
            if not t > skew:  # LoopConfig's rule: a stamp accepted ahead must not starve the failsafe
                raise ValueError(f"FS_IMU_TIMEOUT {t:g}: expected > stamp skew {skew:g} s")  # fits STATUSTEXT
            loop.fs_state = replace(loop.fs_state, imu_timeout_s=t)
            mon = loop.monitor
            if mon is not None and hasattr(mon.config, "imu_timeout_s"):
                mon.config = replace(mon.config, imu_timeout_s=t)
        if "streams" in groups:
            for p in P.PARAMS:
                if p.group == "streams":
                    loop.rates.set_hz(p.field, values[p.name], default=True)

    # -- commands -------------------------------------------------------------------------------
    def command(self, m) -> int:
        """MAV_RESULT of a COMMAND_LONG the loop itself does not fly; the message a request asks
        for is sent after the ACK (`after_ack`)."""
        cmd = int(m.command)
        if cmd == mavlink.MAV_CMD_REQUEST_MESSAGE:
            p1 = float(m.param1)
            if not (math.isfinite(p1) and p1.is_integer()):
                return mavlink.MAV_RESULT_DENIED
            if int(p1) == AvailableModes.id:
                modes = self.available_modes(m.param2)
                if not modes:
                    return mavlink.MAV_RESULT_DENIED
                self._after_ack.extend(modes)
                return mavlink.MAV_RESULT_ACCEPTED
            # MESSAGE_INTERVAL names the message it is about in param2 (MAVLink's MESSAGE_INTERVAL doc)
            msg = self.message(int(p1), m.param2 if int(p1) == mavlink.MAVLINK_MSG_ID_MESSAGE_INTERVAL else None)
            if msg is None:
                return mavlink.MAV_RESULT_DENIED
            self._after_ack.append(msg)
            return mavlink.MAV_RESULT_ACCEPTED
        if cmd == mavlink.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            self._after_ack.append(self.autopilot_version())
            return mavlink.MAV_RESULT_ACCEPTED
        if cmd == mavlink.MAV_CMD_GET_MESSAGE_INTERVAL:
            msg = self.message(mavlink.MAVLINK_MSG_ID_MESSAGE_INTERVAL, m.param1)
            if msg is None:
                return mavlink.MAV_RESULT_DENIED
            self._after_ack.append(msg)
            return mavlink.MAV_RESULT_ACCEPTED
        return mavlink.MAV_RESULT_UNSUPPORTED

    def after_ack(self, out) -> None:
        """Send what the command just acknowledged asked for."""
        msgs, self._after_ack = self._after_ack, []
        for msg in msgs:
            out.send(msg)

    def message(self, msg_id: int, about=None):
        """The message `msg_id` as the robot can fill it truthfully now, else None; `about`: for
        MESSAGE_INTERVAL, the id of the message whose interval it reports."""
        loop = self.loop
        now = loop.clock.now()
        t = now if math.isfinite(now) and now > 0 else 0.0
        ms = int(round(t * 1e3)) & 0xFFFFFFFF
        est = loop.estimator.estimate
        if msg_id == mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
            return self.autopilot_version()
        if msg_id == mavlink.MAVLINK_MSG_ID_HEARTBEAT:
            return loop._heartbeat()
        if msg_id == mavlink.MAVLINK_MSG_ID_SYS_STATUS:
            st = loop.stats.step_time_s
            return loop._sys_status(next(reversed(st), 0.0))  # the newest step (a Ring has no [-1])
        if msg_id == mavlink.MAVLINK_MSG_ID_SYSTEM_TIME:
            return self.system_time(t)
        if msg_id == mavlink.MAVLINK_MSG_ID_ATTITUDE:
            r, p, y = est.euler_rad
            wx, wy, wz = est.rates_rad_s
            return mavlink.MAVLink_attitude_message(ms, r, p, y, wx, wy, wz)
        if msg_id == mavlink.MAVLINK_MSG_ID_LOCAL_POSITION_NED:
            return self.local_position(t)
        if msg_id == mavlink.MAVLINK_MSG_ID_MESSAGE_INTERVAL and about is not None:
            about = float(about)
            cls = mavlink.mavlink_map.get(int(about)) if math.isfinite(about) and about.is_integer() else None
            if cls is None:
                return None
            hz = loop.rates.rate_hz.get(cls.msgname, loop.rates.default_hz.get(cls.msgname))
            if hz is None:
                return mavlink.MAVLink_message_interval_message(int(about), 0)  # not supported
            # interval_us is an int32: a rate set from a very long interval (SET_MESSAGE_INTERVAL takes
            # any float) is reported as the longest it can say, at least 1 us for a very high one
            us = min(max(round(1e6 / hz), 1), INT32_MAX) if hz > 0 else -1
            return mavlink.MAVLink_message_interval_message(int(about), us)
        return None

    @staticmethod
    def available_modes(which) -> list:
        """AVAILABLE_MODES of every mode (`which` 0) or of the mode with that index (1-based)."""
        modes = sorted(MODE_NAMES.items())
        n = len(modes)
        out = [AvailableModes(n, i, number, name) for i, (number, name) in enumerate(modes, 1)]
        try:
            k = int(which) if math.isfinite(float(which)) else -1
        except (TypeError, ValueError):
            k = -1
        return out if k == 0 else [a for a in out if a.mode_index == k]

    def autopilot_version(self):
        major, minor, patch = VERSION
        sw = (major << 24) | (minor << 16) | (patch << 8) | mavlink.FIRMWARE_VERSION_TYPE_DEV
        return mavlink.MAVLink_autopilot_version_message(CAPABILITIES, sw, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8,
                                                         0, 0, self.uid, [0] * 18)

    @staticmethod
    def system_time(t: float):
        return mavlink.MAVLink_system_time_message(int(time.time() * 1e6), int(round(t * 1e3)) & 0xFFFFFFFF)

    def local_position(self, t: float):
        """LOCAL_POSITION_NED: depth as z and the NED velocity from the estimate; x, y NaN (the
        robot has no horizontal position: no DVL, no GNSS under water)."""
        est = self.loop.estimator.estimate
        u, v, w = est.velocity_body_m_s
        yaw = est.euler_rad[2]
        c, s = math.cos(yaw), math.sin(yaw)
        nan = math.nan
        return mavlink.MAVLink_local_position_ned_message(int(round(t * 1e3)) & 0xFFFFFFFF, nan, nan,
                                                          float(est.depth_m), c * u - s * v, s * u + c * v, float(w))

    # -- telemetry ------------------------------------------------------------------------------
    def one_hz(self, out, t: float) -> None:
        """Sent with the HEARTBEAT: SYSTEM_TIME (to a ground station, never to a plant or autopilot)."""
        if out is not self.loop.link or not self.identity.component1_taken:
            out.send(self.system_time(t))
        self.save_params(out)

    def save_params(self, out=None, force: bool = False) -> None:
        """Write parameters set since the file was last written (at most once a second; `force`:
        now, as the loop stops); a failed write is said in a STATUSTEXT on `out`."""
        why = self.params.flush(force)
        if why and out is not None:  # flying with it; the next start will not have it
            out.send(mavlink.MAVLink_statustext_message(mavlink.MAV_SEVERITY_WARNING, why[:50].encode()))

    def streams(self, out, t: float) -> None:
        if self.loop.rates.due("LOCAL_POSITION_NED", t):
            out.send(self.local_position(t))

    # -- mission --------------------------------------------------------------------------------
    def _mission(self, m, out) -> None:
        name = m.get_type()
        mtype = int(getattr(m, "mission_type", 0) or 0)
        src = (m.get_srcSystem(), m.get_srcComponent())

        def ack(result):
            out.send(mavlink.MAVLink_mission_ack_message(src[0], src[1], result, mtype))

        if name == "MISSION_REQUEST_LIST":
            out.send(mavlink.MAVLink_mission_count_message(src[0], src[1], 0, mtype))
        elif name in ("MISSION_REQUEST", "MISSION_REQUEST_INT"):
            ack(mavlink.MAV_MISSION_INVALID_SEQUENCE)
        elif name == "MISSION_CLEAR_ALL":
            ack(mavlink.MAV_MISSION_ACCEPTED)
        elif name == "MISSION_COUNT":
            if int(m.count) == 0:
                ack(mavlink.MAV_MISSION_ACCEPTED)
            else:
                ack(mavlink.MAV_MISSION_NO_SPACE if mtype == mavlink.MAV_MISSION_TYPE_MISSION
                    else mavlink.MAV_MISSION_UNSUPPORTED)
        elif name in ("MISSION_ITEM", "MISSION_ITEM_INT"):
            ack(mavlink.MAV_MISSION_NO_SPACE)


def _set_component(link, component: int) -> None:
    mav = getattr(link, "mav", None)
    if mav is not None:
        mav.srcComponent = int(component)
