"""Ground commands as standard MAVLink, MAVLink 2 signing, and the onboard side's checks (pure).

Commands (the onboard loop's own builders, onboard/loop.py, so both sides agree on the fields):
- arm / disarm: COMMAND_LONG MAV_CMD_COMPONENT_ARM_DISARM (param1 1 / 0)
- mode: COMMAND_LONG MAV_CMD_DO_SET_MODE (param1 MAV_MODE_FLAG_CUSTOM_MODE_ENABLED, param2 mode)
- depth / yaw setpoint: SET_POSITION_TARGET_LOCAL_NED in MAV_FRAME_LOCAL_NED (z = depth, yaw)
- velocity setpoint: SET_POSITION_TARGET_LOCAL_NED in MAV_FRAME_BODY_FRD (vx, vy)
- joystick: MANUAL_CONTROL (x, y, r in +-1000; z 0..1000 with 500 neutral, as ArduSub)
- stream rates: COMMAND_LONG MAV_CMD_SET_MESSAGE_INTERVAL (param1 message id, param2 interval
  in us; -1 stops the stream, 0 restores the default) - MAVLink common.xml.

`parse_command("depth 1.5")` turns an operator's line into messages (`COMMAND_HELP` lists them).

Signing (MAVLink 2, https://mavlink.io/en/guide/message_signing.html): a 32-byte secret key;
each signed packet carries link id, a 48-bit timestamp (10 us since 2015-01-01) and the first
6 bytes of sha256(key + packet). `load_key` reads a key file (32 raw bytes or 64 hex digits),
`enable_signing` sets a pymavlink parser up to sign what it sends, and `SigningState` +
`accept_command(msg, state)` is the onboard side's check: with a key, a command (anything that
moves or reconfigures the vehicle) is accepted only with a good signature and a timestamp newer
than the last one of its stream (pymavlink's `check_signature`, replay protection included).
`StreamRates` is the onboard side of SET_MESSAGE_INTERVAL: which telemetry message is due when.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path

from pymavlink.dialects.v20 import ardupilotmega as mavlink

SIGNING_EPOCH_UNIX_S = 1_420_070_400  # 2015-01-01T00:00:00Z, MAVLink 2 signing time origin
SIGNED_FLAG = 0x01  # MAVLINK_IFLAG_SIGNED, incompat_flags bit 0
KEY_BYTES = 32
# Messages that move or reconfigure the vehicle: refused unsigned when signing is on.
COMMAND_MESSAGES = frozenset({
    "COMMAND_LONG", "COMMAND_INT", "SET_POSITION_TARGET_LOCAL_NED", "SET_POSITION_TARGET_GLOBAL_INT",
    "SET_ATTITUDE_TARGET", "MANUAL_CONTROL", "SET_MODE", "RC_CHANNELS_OVERRIDE", "PARAM_SET",
    "SETUP_SIGNING", "MISSION_ITEM", "MISSION_ITEM_INT",
})
COMMAND_HELP = ("arm | disarm | mode NAME | depth M [yaw DEG] | yaw DEG | velocity U [V] | "
                "manual X Y Z R | rate MESSAGE HZ")


class CommandError(ValueError):
    """An operator command or key file that cannot be used; the message says what was expected."""


# ------------------------------------------------------------------------------------------------
# Command builders


def arm(armed: bool = True):
    from onboard.loop import arm_command

    return arm_command(armed)


def set_mode(name: str):
    from onboard.loop import MODES, mode_command

    if name not in MODES:
        raise CommandError(f"mode {name!r}: expected one of {', '.join(sorted(MODES))}")
    return mode_command(name)


def depth_yaw(depth_m: float | None = None, yaw_rad: float | None = None):
    from onboard.loop import depth_yaw_target

    for label, v in (("depth", depth_m), ("yaw", yaw_rad)):
        if v is not None and not math.isfinite(v):
            raise CommandError(f"{label} setpoint {v!r}: expected a finite number")
    return depth_yaw_target(depth_m, yaw_rad)


def velocity(u_m_s: float, v_m_s: float = 0.0):
    from onboard.loop import body_velocity_target

    if not (math.isfinite(u_m_s) and math.isfinite(v_m_s)):
        raise CommandError(f"velocity ({u_m_s!r}, {v_m_s!r}): expected finite numbers in m/s")
    return body_velocity_target(u_m_s, v_m_s)


def manual(x: int, y: int, z: int, r: int, target_system: int = 1):
    """MANUAL_CONTROL; axes clipped to their ranges (x, y, r: -1000..1000; z: 0..1000)."""
    c = lambda a, lo, hi: int(max(lo, min(hi, round(a))))  # noqa: E731
    return mavlink.MAVLink_manual_control_message(target_system, c(x, -1000, 1000), c(y, -1000, 1000),
                                                   c(z, 0, 1000), c(r, -1000, 1000), 0)


def message_interval(message: str | int, rate_hz: float, target_system: int = 1, target_component: int = 1):
    """COMMAND_LONG MAV_CMD_SET_MESSAGE_INTERVAL: rate_hz > 0 sets, 0 stops (-1), < 0 default (0)."""
    msg_id = message_id(message)
    if not math.isfinite(rate_hz):
        raise CommandError(f"rate for {message}: expected a number of Hz, got {rate_hz!r}")
    interval_us = 1e6 / rate_hz if rate_hz > 0 else (-1.0 if rate_hz == 0 else 0.0)
    return mavlink.MAVLink_command_long_message(target_system, target_component,
                                                mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, 0,
                                                float(msg_id), float(interval_us), 0, 0, 0, 0, 0)


def message_id(message: str | int) -> int:
    if isinstance(message, int) or str(message).isdigit():
        return int(message)
    name = str(message).upper()
    ident = getattr(mavlink, f"MAVLINK_MSG_ID_{name}", None)
    if ident is None:
        raise CommandError(f"message {message!r}: not a MAVLink message name (e.g. ATTITUDE)")
    return int(ident)


def parse_rates(text: str) -> dict:
    """'ATTITUDE=10,NAMED_VALUE_FLOAT=5' -> {'ATTITUDE': 10.0, ...} (names checked)."""
    out = {}
    for item in filter(None, (s.strip() for s in str(text).split(","))):
        name, sep, value = item.partition("=")
        try:
            hz = float(value)
        except ValueError:
            hz = math.nan
        if not sep or not math.isfinite(hz) or hz < 0:
            raise CommandError(f"rate {item!r}: expected MESSAGE=HZ (HZ >= 0), e.g. ATTITUDE=10")
        message_id(name)
        out[name.strip().upper()] = hz
    return out


def parse_command(line: str) -> list:
    """One operator line -> the messages to send; CommandError naming the expected form."""
    words = str(line).split()
    if not words:
        raise CommandError(f"empty command: expected {COMMAND_HELP}")
    verb, args = words[0].lower(), words[1:]

    def nums(n_min, n_max):
        if not n_min <= len(args) <= n_max:
            raise CommandError(f"{line!r}: expected {COMMAND_HELP}")
        try:
            return [float(a) for a in args]
        except ValueError:
            raise CommandError(f"{line!r}: arguments must be numbers; expected {COMMAND_HELP}") from None

    if verb in ("arm", "disarm") and not args:
        return [arm(verb == "arm")]
    if verb == "mode" and len(args) == 1:
        return [set_mode(args[0].lower())]
    if verb == "depth":
        if len(args) == 3 and args[1].lower() == "yaw":
            args = [args[0], args[2]]
        v = nums(1, 2)
        return [depth_yaw(v[0], math.radians(v[1]) if len(v) > 1 else None)]
    if verb == "yaw":
        return [depth_yaw(None, math.radians(nums(1, 1)[0]))]
    if verb == "velocity":
        v = nums(1, 2)
        return [velocity(v[0], v[1] if len(v) > 1 else 0.0)]
    if verb == "manual":
        return [manual(*nums(4, 4))]
    if verb == "rate" and len(args) == 2:
        try:
            hz = float(args[1])
        except ValueError:
            raise CommandError(f"{line!r}: expected rate MESSAGE HZ") from None
        return [message_interval(args[0], hz)]
    raise CommandError(f"{line!r}: expected {COMMAND_HELP}")


# ------------------------------------------------------------------------------------------------
# Signing


def load_key(path) -> bytes:
    """A 32-byte signing key from a file: 32 raw bytes, or 64 hex digits (whitespace ignored)."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise CommandError(f"key file {path}: cannot read: {exc.strerror or exc}") from exc
    if len(data) == KEY_BYTES:
        return data
    text = data.decode("ascii", "replace").strip()
    if len(text) == 2 * KEY_BYTES:
        try:
            return bytes.fromhex(text)
        except ValueError:
            pass
    raise CommandError(f"key file {path}: expected {KEY_BYTES} raw bytes or {2 * KEY_BYTES} hex digits, "
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
        raise CommandError(f"signing key: expected {KEY_BYTES} bytes, got {len(key)}")
    s = mav.signing
    s.secret_key = bytes(key)
    s.link_id = int(link_id)
    s.timestamp = signing_timestamp(time.time() if unix_s is None else unix_s)
    s.sign_outgoing = True
    s.allow_unsigned_callback = (lambda _mav, _msg_id: True) if accept_unsigned_incoming else None


def is_signed(msg) -> bool:
    buf = msg.get_msgbuf()
    return len(buf) > 2 and buf[0] == 0xFD and bool(buf[2] & SIGNED_FLAG)


@dataclass
class SigningState:
    """The onboard side's signing state: the key (None: signing off) and the per-stream
    timestamps, kept in a pymavlink MAVLink object whose `check_signature` does the check."""

    key: bytes | None = None
    accepted: int = 0
    rejected_unsigned: int = 0
    rejected_bad: int = 0

    def __post_init__(self):
        self._mav = None
        if self.key is not None:
            if len(self.key) != KEY_BYTES:
                raise CommandError(f"signing key: expected {KEY_BYTES} bytes, got {len(self.key)}")
            self._mav = mavlink.MAVLink(None)
            self._mav.signing.secret_key = bytes(self.key)
            self._mav.signing.timestamp = signing_timestamp(time.time())

    @property
    def on(self) -> bool:
        return self.key is not None


def accept_command(msg, signing_state: SigningState | None) -> bool:
    """Onboard: may this message act? True for non-commands and when signing is off; with signing
    on, a command needs a good signature with a fresh timestamp (replays are refused)."""
    if signing_state is None or not signing_state.on or msg.get_type() not in COMMAND_MESSAGES:
        return True
    if not is_signed(msg):
        signing_state.rejected_unsigned += 1
        return False
    mav = signing_state._mav
    buf = bytearray(msg.get_msgbuf())
    stream = (buf[-13], msg.get_srcSystem(), msg.get_srcComponent())
    before = mav.signing.stream_timestamps.get(stream)
    if mav.check_signature(buf, msg.get_srcSystem(), msg.get_srcComponent()):
        signing_state.accepted += 1
        return True
    # pymavlink records the timestamp before comparing the hash: a forged packet must not move
    # the stream on (it would lock out the real sender), so restore it
    if before is None:
        mav.signing.stream_timestamps.pop(stream, None)
    else:
        mav.signing.stream_timestamps[stream] = before
    signing_state.rejected_bad += 1
    return False


# ------------------------------------------------------------------------------------------------
# Stream rates, onboard side


class StreamRates:
    """Which telemetry message is due: defaults per message name, changed by SET_MESSAGE_INTERVAL.

    `handle(msg)` takes a COMMAND_LONG and returns a MAV_RESULT (None if it is not one);
    `due(name, t_s)` is True when `name` should be sent at time t_s (and books it).
    """

    def __init__(self, default_hz: dict):
        self.default_hz = {k.upper(): float(v) for k, v in default_hz.items()}
        self.rate_hz = dict(self.default_hz)
        self._next: dict = {}
        self._names = {}

    def handle(self, msg):
        if msg.get_type() != "COMMAND_LONG" or int(msg.command) != mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
            return None
        cls = mavlink.mavlink_map.get(int(round(msg.param1)))
        if cls is None or not math.isfinite(msg.param2):
            return mavlink.MAV_RESULT_DENIED
        name, interval = cls.msgname, float(msg.param2)
        if interval < 0:
            self.rate_hz[name] = 0.0
        elif interval == 0:
            self.rate_hz[name] = self.default_hz.get(name, 0.0)
        else:
            self.rate_hz[name] = 1e6 / interval
        self._next.pop(name, None)
        return mavlink.MAV_RESULT_ACCEPTED

    def due(self, name: str, t_s: float) -> bool:
        hz = self.rate_hz.get(name, self.default_hz.get(name, 0.0))
        if hz <= 0:
            return False
        nxt = self._next.get(name, -math.inf)
        if t_s + 1e-9 < nxt:
            return False
        # next slot on the rate's grid (no drift), or from now when a slot was missed
        self._next[name] = max(nxt + 1.0 / hz, t_s + 0.5 / hz) if math.isfinite(nxt) else t_s + 1.0 / hz
        return True
