"""MAVLink 2 signing: keys, signing what we send, and the onboard check on commands (pure).

MAVLink 2 signing (https://mavlink.io/en/guide/message_signing.html): a 32-byte secret key;
each signed packet carries link id, a 48-bit timestamp (10 us since 2015-01-01) and the first
6 bytes of sha256(key + packet). `load_key` reads a key file (32 raw bytes or 64 hex digits),
`enable_signing` sets a pymavlink parser up to sign what it sends (`refresh_timestamp` keeps its
timestamp on the clock), and `SigningState.check` is the robot's check: with a key, a command
(anything that moves or reconfigures the vehicle) is accepted only with a good signature and a
timestamp newer than the last one of its stream. These are pymavlink's `check_signature` rules,
with one change: the signature is checked first, because pymavlink stores a packet's timestamp
before comparing the hash, so one forged packet stamped in the future would lock the real
sender's stream out.
It lives in `onboard` because the robot must carry it; the ground station imports it.

`CommandGate` is everything the robot checks before a ground message may act, in this order:
1. signing (when a key is set): unsigned -> `unsigned`; a signature that is not sha256(key +
   packet) (wrong key, or any byte altered: link id, timestamp, payload) -> `bad_signature`,
   and such a packet changes no state; a timestamp not newer than its stream's last one, or a
   new stream stamped more than 60 s behind the robot's clock -> `replayed` (the spec's rule,
   https://mavlink.io/en/guide/message_signing.html, as pymavlink and the C library apply it);
   a 17th stream (link id, system, component) -> `too_many_streams` (the C library's
   MAVLINK_MAX_SIGNING_STREAMS = 16), so a key holder cycling link ids cannot grow the table.
2. foreign system: a command or setpoint whose source system is not one of `ground_systems`
   (ArduPilot's SYSID_MYGCS, default 255 as QGroundControl and MAVProxy use; enforced like
   SYSID_ENFORCE=1), or addressed (target_system) to another vehicle -> `foreign`, ignored as
   ArduPilot ignores messages for another system. A message built in this process (no wire
   bytes: the HIL demo's and the benches' in-process calls) has no source to check.
3. parameters and envelope (onboard.envelope): arm/mode with bad parameters -> MAV_RESULT_DENIED
   (`commands_denied`); a setpoint outside the vehicle's [envelope] -> STATUSTEXT "setpoint
   refused: ..." (`setpoints_refused`), the previous setpoint stays.
Rejections 1-2 are silent on the link (nothing is sent to an unknown or unproven sender);
every one is counted in `SecurityCounts`, which the loop reports in telemetry and its summary.

Sensor data and actuator feedback (`SENSOR_MESSAGES`: IMU, pressure, attitude, the SYSTEM_TIME
frame marker, ESC rpm, joint angles) move the vehicle's clock, its estimate and its failsafe as
surely as a command does (issue 15: one unsigned HIGHRES_IMU from system 99, stamped 11 days
ahead, sent to the ground port of a signed robot tripped its IMU failsafe for good). So:
- with a key, every message that reaches the gate from a wire must be signed with it (the
  autopilot or plant signs too: `jetloop hil --key`, or ArduPilot's signing on that port);
  RADIO_STATUS alone is exempt, as ArduPilot exempts it;
- sensor data is accepted only on the main link (the ground link never carries it) and only from
  the autopilot: the (system, component) configured (`autopilot=`), else the first one seen
  sending sensor data from an autopilot's component (1, `AUTOPILOT_COMPONENTS`) on the main
  link; a ground system (`ground_systems`)
  never becomes it, and what comes before the election from anyone else (a companion's
  SYSTEM_TIME from 1:191) is refused, not elected.
  Anything else is `sensors_refused`, silently.
"""

from __future__ import annotations

import hashlib
import hmac
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

from pymavlink.dialects.v20 import ardupilotmega as mavlink
from onboard.files import read_bounded

SIGNING_EPOCH_UNIX_S = 1_420_070_400  # 2015-01-01T00:00:00Z, MAVLink 2 signing time origin
SIGNED_FLAG = 0x01  # MAVLINK_IFLAG_SIGNED, incompat_flags bit 0
KEY_BYTES = 32
SIGNATURE_BYTES = 13  # link id (1) + timestamp (6, little-endian) + sha256 prefix (6)
NEW_STREAM_MAX_AGE = 6_000_000  # 60 s in 10 us units: a new stream may lag the robot's clock this much
MAX_STREAMS = 16  # MAVLINK_MAX_SIGNING_STREAMS of the MAVLink C library (mavlink_types.h)
GCS_SYSTEMS = (255,)  # QGroundControl's and MAVProxy's default system id (ArduPilot SYSID_MYGCS)
REFUSAL_TEXT_PERIOD_S = 0.2  # at most one "setpoint refused"/"command denied" text per period
# Messages that move or reconfigure the vehicle: refused unsigned when signing is on.
COMMAND_MESSAGES = frozenset({
    "COMMAND_LONG", "COMMAND_INT", "SET_POSITION_TARGET_LOCAL_NED", "SET_POSITION_TARGET_GLOBAL_INT",
    "SET_ATTITUDE_TARGET", "MANUAL_CONTROL", "SET_MODE", "RC_CHANNELS_OVERRIDE", "PARAM_SET",
    "SETUP_SIGNING", "MISSION_ITEM", "MISSION_ITEM_INT", "MISSION_COUNT", "MISSION_CLEAR_ALL",
    "REQUEST_DATA_STREAM",
})


# Sensor data and actuator feedback the onboard loop reads: accepted from the autopilot on the main link only.
SENSOR_MESSAGES = frozenset({
    "HIGHRES_IMU", "SCALED_IMU", "SCALED_IMU2", "SCALED_IMU3", "RAW_IMU", "SCALED_PRESSURE",
    "SCALED_PRESSURE2", "ATTITUDE", "SYSTEM_TIME", "ESC_TELEMETRY_1_TO_4", "ESC_TELEMETRY_5_TO_8",
    "ESC_TELEMETRY_9_TO_12", "ACTUATOR_OUTPUT_STATUS",
})
# Who may be elected the autopilot (issue 15, second pass): an autopilot's component. A companion's
# SYSTEM_TIME (1:191), ESC telemetry or a joint-angle report first on the link made its sender "the
# autopilot" for good, and the real autopilot's samples were refused from then on.
AUTOPILOT_COMPONENTS = frozenset({mavlink.MAV_COMP_ID_AUTOPILOT1})  # 1: ArduPilot's, PX4's and the HIL plant's
UNSIGNED_EXEMPT = frozenset({"RADIO_STATUS"})  # what a signed channel still takes unsigned (as ArduPilot)


class SigningError(ValueError):
    """A key file or key that cannot be used; the message says what was expected."""


def load_key(path) -> bytes:
    """A 32-byte signing key from a file: 32 raw bytes, or 64 hex digits (whitespace ignored)."""
    path = Path(path)
    try:
        data = read_bounded(path, 4096)  # 32 bytes or 64 hex digits; never a device read whole
    except OSError as exc:
        raise SigningError(f"key file {path}: cannot read: {exc.strerror or exc}") from exc
    if len(data) == KEY_BYTES:
        return data
    text = data.decode("ascii", "replace").strip()
    if len(text) == 2 * KEY_BYTES:
        try:
            return bytes.fromhex(text)
        except ValueError:
            pass
    raise SigningError(f"key file {path}: expected {KEY_BYTES} raw bytes or {2 * KEY_BYTES} hex digits, "
                       f"got {len(data)} bytes")


def signing_timestamp(unix_s: float) -> int:
    """MAVLink 2 signing time: units of 10 us since 2015-01-01."""
    return int((unix_s - SIGNING_EPOCH_UNIX_S) * 100_000)


def enable_signing(mav, key: bytes, link_id: int = 0, unix_s: float | None = None,
                   accept_unsigned_incoming: bool = True) -> None:
    """Sign everything `mav` (a pymavlink MAVLink object, e.g. Link.mav) packs from now on.

    Incoming unsigned packets stay readable when `accept_unsigned_incoming` (the ground reads an
    unsigned vehicle's telemetry); pymavlink checks the signature of signed ones.
    """
    if len(key) != KEY_BYTES:
        raise SigningError(f"signing key: expected {KEY_BYTES} bytes, got {len(key)}")
    s = mav.signing
    s.secret_key = bytes(key)
    s.link_id = int(link_id)
    s.timestamp = signing_timestamp(time.time() if unix_s is None else unix_s)
    s.sign_outgoing = True
    s.allow_unsigned_callback = (lambda _mav, _msg_id: True) if accept_unsigned_incoming else None


def refresh_timestamp(mav, unix_s: float | None = None) -> None:
    """Bring a signing sender's timestamp up to its clock (never back). pymavlink only adds 1
    (10 us) per packet sent, so a ground that sends one heartbeat a second falls ~1 s behind
    real time every second, and after a minute a robot that restarts (new stream) would refuse
    it as a replay; the spec wants the timestamp to follow the clock. Call before each send."""
    s = mav.signing
    s.timestamp = max(s.timestamp, signing_timestamp(time.time() if unix_s is None else unix_s))


def is_signed(msg) -> bool:
    buf = msg.get_msgbuf()
    return len(buf) > 2 and buf[0] == 0xFD and bool(buf[2] & SIGNED_FLAG)



def signature_fields(buf: bytes) -> tuple[int, int] | None:
    """(link_id, timestamp) of a signed MAVLink 2 packet, None if it carries no signature."""
    if len(buf) < 12 + SIGNATURE_BYTES or buf[0] != 0xFD or not buf[2] & SIGNED_FLAG:
        return None
    return buf[-13], int.from_bytes(buf[-12:-6], "little")


def signature_ok(buf: bytes, key: bytes) -> bool:
    """The packet's 6 signature bytes are the first 6 of sha256(key + everything before them)."""
    return hmac.compare_digest(hashlib.sha256(bytes(key) + bytes(buf[:-6])).digest()[:6], bytes(buf[-6:]))


@dataclass
class SecurityCounts:
    """What the robot refused, by reason (and what signing accepted): the loop's telemetry and summary."""

    accepted: int = 0  # signed packets (commands, and with a key every packet) that passed the signature and timestamp checks
    unsigned: int = 0
    bad_signature: int = 0
    replayed: int = 0
    too_many_streams: int = 0
    foreign: int = 0
    setpoints_refused: int = 0
    commands_denied: int = 0
    sensors_refused: int = 0  # sensor data from the ground link, or from anyone but the autopilot

    def summary(self) -> dict:
        return {"sig_accepted": self.accepted, "sig_unsigned": self.unsigned, "sig_bad": self.bad_signature,
                "sig_replayed": self.replayed, "sig_too_many_streams": self.too_many_streams,
                "foreign_commands": self.foreign, "setpoints_refused": self.setpoints_refused,
                "commands_denied": self.commands_denied, "sensors_refused": self.sensors_refused}

    def telemetry(self) -> dict:
        """NAMED_VALUE_FLOAT names (<= 10 characters) -> value, for the counters that are not zero
        (a quiet link costs no telemetry bandwidth; a counter appears with its first event)."""
        named = {"sig_ok": self.accepted, "sig_unsig": self.unsigned, "sig_bad": self.bad_signature,
                 "sig_replay": self.replayed, "sig_strm": self.too_many_streams, "foreign": self.foreign,
                 "sp_refused": self.setpoints_refused, "cmd_denied": self.commands_denied,
                 "sens_ref": self.sensors_refused}
        return {k: float(v) for k, v in named.items() if v}


@dataclass
class SigningState:
    """The onboard side's signing state: the key (None: signing off), the last timestamp of each
    stream (link id, system, component) and the robot's own signing clock."""

    key: bytes | None = None
    counts: SecurityCounts = field(default_factory=SecurityCounts)
    clock: object = time.time  # unix seconds; the robot's time for judging a new stream's age

    def __post_init__(self):
        if self.key is not None and len(self.key) != KEY_BYTES:
            raise SigningError(f"signing key: expected {KEY_BYTES} bytes, got {len(self.key)}")
        self.streams: dict = {}
        self.newest = 0  # the newest timestamp accepted (10 us units since 2015)

    @property
    def on(self) -> bool:
        return self.key is not None

    # the counters under their earlier names
    accepted = property(lambda self: self.counts.accepted)
    rejected_unsigned = property(lambda self: self.counts.unsigned)
    rejected_bad = property(lambda self: self.counts.bad_signature)
    rejected_replay = property(lambda self: self.counts.replayed)

    def check(self, msg) -> str | None:
        """None if the signed packet may act, else why not ("unsigned", "bad_signature",
        "replayed", "too_many_streams"), counted. Only a packet with a good signature changes state."""
        c = self.counts
        buf = bytes(msg.get_msgbuf())
        fields = signature_fields(buf)
        if fields is None:
            c.unsigned += 1
            return "unsigned"
        if not signature_ok(buf, self.key):  # first: what is not proven changes nothing below
            c.bad_signature += 1
            return "bad_signature"
        link_id, ts = fields
        stream = (link_id, msg.get_srcSystem(), msg.get_srcComponent())
        last = self.streams.get(stream)
        if last is not None:
            if ts <= last:
                c.replayed += 1
                return "replayed"
        else:
            now = max(self.newest, signing_timestamp(self.clock()))
            if ts + NEW_STREAM_MAX_AGE < now:
                c.replayed += 1
                return "replayed"
            if len(self.streams) >= MAX_STREAMS:
                c.too_many_streams += 1
                return "too_many_streams"
        self.streams[stream] = ts
        self.newest = max(self.newest, ts)
        c.accepted += 1
        return None


def accept_command(msg, signing_state: SigningState | None) -> bool:
    """Onboard: may this message act, as far as signing goes? True for non-commands and when
    signing is off; with signing on, a command needs a good signature with a fresh timestamp."""
    if signing_state is None or not signing_state.on or msg.get_type() not in COMMAND_MESSAGES:
        return True
    return signing_state.check(msg) is None


def _target_system(msg) -> int:
    t = getattr(msg, "target_system", None)
    return int(getattr(msg, "target", 0) if t is None else t)


@dataclass(frozen=True)
class Verdict:
    accepted: bool
    reason: str = ""  # why not, for tests and logs ("" when accepted)
    replies: tuple = ()  # messages to send back (COMMAND_ACK, STATUSTEXT)


ACCEPT = Verdict(True)


class CommandGate:
    """Everything the robot checks before an inbound message acts (see the module docstring):
    `admit(msg, link) -> Verdict`, `link` "main" (the autopilot's or plant's) or "ground".
    With a key every message from a wire needs a good signature; sensor data must come from the
    autopilot on the main link; commands and setpoints go through the checks 1-3."""

    def __init__(self, key: bytes | None = None, ground_systems=GCS_SYSTEMS, own_system: int = 1,
                 envelope=None, counts: SecurityCounts | None = None, clock=time.monotonic,
                 signing_clock=time.time, autopilot: tuple | None = None):
        systems = tuple(ground_systems)
        if not systems or not all(isinstance(s, int) and 1 <= s <= 255 for s in systems):
            raise SigningError(f"ground_systems: expected system ids 1..255, got {ground_systems!r}")
        if autopilot is not None:
            ok = (isinstance(autopilot, tuple) and len(autopilot) == 2 and all(isinstance(x, int) for x in autopilot)
                  and 1 <= autopilot[0] <= 255 and 0 <= autopilot[1] <= 255)
            if not ok or autopilot[0] in systems:
                raise SigningError(f"autopilot: expected (system 1..255 not a ground system, component 0..255; "
                                   f"0: any), got {autopilot!r}")
        self.autopilot = autopilot  # (system, component) whose sensor data counts; None: the first seen
        if envelope is None:
            from .vehicle import Envelope

            envelope = Envelope()
        self.counts = counts if counts is not None else SecurityCounts()
        self.signing = SigningState(key, counts=self.counts, clock=signing_clock)
        self.ground_systems = frozenset(systems)
        self.own_system = int(own_system)
        self.envelope = envelope
        self.clock = clock
        self._next_text = -math.inf

    def admit(self, msg, link: str = "main") -> Verdict:
        name = msg.get_type()
        wire = len(msg.get_msgbuf()) > 0  # built in this process: no source system to check
        command = name in COMMAND_MESSAGES
        if self.signing.on and (command or (wire and name not in UNSIGNED_EXEMPT)):
            why = self.signing.check(msg)
            if why is not None:
                return Verdict(False, why)
        if name in SENSOR_MESSAGES:
            return self._sensor(msg, link) if wire else ACCEPT
        if not command:
            return ACCEPT
        if wire and msg.get_srcSystem() not in self.ground_systems:
            self.counts.foreign += 1
            return Verdict(False, f"foreign source system {msg.get_srcSystem()}")
        try:
            target = _target_system(msg)
        except (TypeError, ValueError, OverflowError):
            target = 0
        if target not in (0, self.own_system):
            self.counts.foreign += 1
            return Verdict(False, f"addressed to system {target}")
        from . import envelope as env

        try:
            if name == "COMMAND_LONG":
                why = env.command_violation(msg)
                if why is not None:
                    self.counts.commands_denied += 1
                    ack = mavlink.MAVLink_command_ack_message(int(msg.command), mavlink.MAV_RESULT_DENIED, 0, 0,
                                                              msg.get_srcSystem(), msg.get_srcComponent())
                    return Verdict(False, why, (ack,) + self.refusal_text(why))
            elif name == "SET_POSITION_TARGET_LOCAL_NED":
                why = env.position_target_violation(self.envelope, msg)
            elif name == "MANUAL_CONTROL":
                why = env.manual_violation(msg)
            else:
                why = None
        except (TypeError, ValueError, AttributeError, OverflowError):
            return ACCEPT  # malformed: the loop's decoder refuses and counts it (rejected_inputs)
        if why is not None:
            self.counts.setpoints_refused += 1
            return Verdict(False, why, self.refusal_text(why))
        return ACCEPT

    def _sensor(self, msg, link: str) -> Verdict:
        """Sensor data: from the autopilot on the main link, else refused (silently, counted)."""
        src = (msg.get_srcSystem(), msg.get_srcComponent())
        if link != "main":
            why = f"sensor data on the {link} link"
        elif src[0] in self.ground_systems or src[0] == 0:
            why = f"sensor data from ground system {src[0]}"
        elif self.autopilot is None:
            # the component decides, not the message: the HIL plant's lock-step frame marker
            # (SYSTEM_TIME from 1:1) may arrive first under reordering, and refusing it left the
            # plant waiting for its t = 0 command for good (test_monitor's faulty-link flight)
            if src[1] in AUTOPILOT_COMPONENTS:
                self.autopilot = src  # the first autopilot component sending sensor data on the main link
                return ACCEPT
            why = f"sensor data from {src[0]}:{src[1]} before an autopilot (component 1 sending sensor data)"
        elif src[0] == self.autopilot[0] and self.autopilot[1] in (0, src[1]):
            return ACCEPT
        else:
            why = f"sensor data from {src[0]}:{src[1]}, not the autopilot {self.autopilot[0]}:{self.autopilot[1]}"
        self.counts.sensors_refused += 1
        return Verdict(False, why)

    def refusal_text(self, why: str) -> tuple:
        """A STATUSTEXT warning saying why, at most one per REFUSAL_TEXT_PERIOD_S (a flood of bad
        setpoints must not become a flood of replies; the counters still count every one)."""
        now = self.clock()
        if now < self._next_text:
            return ()
        self._next_text = now + REFUSAL_TEXT_PERIOD_S
        return (mavlink.MAVLink_statustext_message(mavlink.MAV_SEVERITY_WARNING, why[:50].encode()),)
