"""MAVLink 2 signing: keys, signing what we send, and the onboard check on commands (pure).

MAVLink 2 signing (https://mavlink.io/en/guide/message_signing.html): a 32-byte secret key;
each signed packet carries link id, a 48-bit timestamp (10 us since 2015-01-01) and the first
6 bytes of sha256(key + packet). `load_key` reads a key file (32 raw bytes or 64 hex digits),
`enable_signing` sets a pymavlink parser up to sign what it sends, and `SigningState` +
`accept_command(msg, state)` is the robot's check: with a key, a command (anything that moves or
reconfigures the vehicle) is accepted only with a good signature and a timestamp newer than the
last one of its stream (pymavlink's `check_signature`, replay protection included).
It lives in `onboard` because the robot must carry it; the ground station imports it.
"""

from __future__ import annotations

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


class SigningError(ValueError):
    """A key file or key that cannot be used; the message says what was expected."""


def load_key(path) -> bytes:
    """A 32-byte signing key from a file: 32 raw bytes, or 64 hex digits (whitespace ignored)."""
    path = Path(path)
    try:
        data = path.read_bytes()
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
                raise SigningError(f"signing key: expected {KEY_BYTES} bytes, got {len(self.key)}")
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
