"""Recordings in (spec/recording.md section 1): .tlog or dataflash .bin -> a frozen `Recording`.

A `.tlog` is a sequence of [8-byte big-endian microsecond timestamp][MAVLink 1 or 2 packet].
Its framing is scanned by a compiled pass (`_scan_tlog`) that checks every packet's CRC with
the dialect's CRC_EXTRA (the same check pymavlink's parser makes), so a damaged file is read as
far as it is sound and every byte that is not part of a good packet is counted:
- a packet whose CRC fails is counted in `bad_crc_packets` (and its bytes in `skipped_bytes`);
- bytes between packets that frame as nothing (garbage, a torn write, a damaged length or start
  marker) are skipped until the next byte position holding a packet with a good CRC: framing
  and CRC decide, the tlog timestamp (which no CRC protects) is only a plausibility check, so a
  packet whose own bytes are intact is read whatever happened before it;
- a truncated last packet is counted in `truncated_bytes`.
Payloads of the messages the diagnosis needs are then decoded in bulk with numpy (the
dialect's own struct layout, MAVLink 2 zero-truncation undone), so a 10-minute 100 Hz log
reads in about a second.

Dataflash `.bin` logs are read with pymavlink's DFReader (IMU, BARO instance 1 = the depth
sensor, RCOU, ATT, ESC); the bytes its parser skips are counted as well.

Streams are aligned on vehicle time (the messages' own `time_usec` / `time_boot_ms`, in
seconds since boot; SERVO_OUTPUT_RAW's uint32 microseconds and every uint32 `time_boot_ms`
(49.7 days) unwrapped, and the servo stream put on the clock of the other streams through the
logger's offset from them where it is in the log, so a jump of vehicle time is followed). Within a stream, dropped and counted: a sample with a NaN, inf or physically
impossible value (`out_of_range`), an impossible time or one out of line with its neighbours, a
flipped bit (`bad_time`), a time that does not increase (`non_monotonic`). Gaps longer than five
nominal periods are listed; a stop over `SEGMENT_GAP_S` splits the recording into `segments()`,
so work on it needs memory by the data, never by its time span.
ArduSub units: SCALED_IMU / SCALED_IMU2 / RAW_IMU carry accel in mG and gyro in mrad/s
(ArduPilot GCS_Common send_scaled_imu / send_raw_imu); SCALED_PRESSURE2 press_abs in hPa.
"""

from __future__ import annotations

import contextlib
import math
import os
import struct
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
from numba import njit
from onboard.files import read_bounded

G_MSS = 9.80665  # ArduPilot GRAVITY_MSS, the mG scale of SCALED_IMU / RAW_IMU
SEGMENT_GAP_S = 1.0  # a stop longer than this in a core stream splits the recording (segments())
MAX_RECORDING_BYTES = 16_000_000_000  # a day of 100 Hz telemetry is ~1.5 GB
MAX_TIME_S = 1e10  # vehicle time beyond 317 years (boot or UNIX time) is impossible: a damaged stamp
# Physically possible sample values; beyond them (or NaN / inf) a sample is dropped and counted.
ACCEL_MAX_M_S2 = 1000.0  # about 100 g: every IMU saturates well below
GYRO_MAX_RAD_S = 100.0  # about 5700 deg/s: every IMU saturates well below (ArduPilot: 2000 deg/s)
PRESS_RANGE_PA = (1.0, 1.2e8)  # vacuum to 12,000 m of water (the deepest ocean)
ANGLE_MAX_RAD = 4 * np.pi
# Propeller speed: no thruster's motor turns 200,000 rpm (a T200 tops at ~3,800). Records whose
# type id a flipped bit turned into ESC's decoded as 11 million rpm (issue 15 re-run, 2 % flips).
ESC_RPM_MAX = 200_000.0
POS_MAX_M = 1e6


class RecordingError(ValueError):
    """A file that cannot be read as a recording; the message names the file and the problem."""


# ------------------------------------------------------------------------------------------------
# Domain types


def _frozen(a) -> np.ndarray:
    a = np.ascontiguousarray(a, dtype=float)
    a.setflags(write=False)
    return a


@dataclass(frozen=True)
class ImuStream:
    time_s: np.ndarray
    accel_frd_m_s2: np.ndarray  # (N, 3) specific force
    gyro_frd_rad_s: np.ndarray  # (N, 3)
    message: str  # which MAVLink / dataflash message it came from


@dataclass(frozen=True)
class PressureStream:
    time_s: np.ndarray
    press_abs_pa: np.ndarray
    message: str


@dataclass(frozen=True)
class ServoStream:
    time_s: np.ndarray
    pwm_us: np.ndarray  # (N, 16): channel c is column c - 1; 0 where not sent


@dataclass(frozen=True)
class AttitudeStream:
    time_s: np.ndarray
    euler_rad: np.ndarray  # (N, 3) roll, pitch, yaw
    rates_rad_s: np.ndarray  # (N, 3)


@dataclass(frozen=True)
class EscStream:
    time_s: np.ndarray
    rpm: np.ndarray  # (N, 4)


@dataclass(frozen=True)
class MocapStream:
    time_s: np.ndarray
    quat_wxyz: np.ndarray  # (N, 4) body to NED
    pos_ned_m: np.ndarray  # (N, 3)


@dataclass(frozen=True)
class Skipped:
    """What was not used, counted: nothing is dropped silently (spec/recording.md section 1)."""

    bad_crc_packets: int = 0
    skipped_bytes: int = 0  # garbage between packets + bad-CRC packets + a truncated tail
    truncated_bytes: int = 0  # of those, the torn packet at the end of the file
    unknown_packets: int = 0  # good framing, message id not in the dialect (CRC not checkable)
    non_monotonic: dict = field(default_factory=dict)  # stream -> samples dropped
    gaps: tuple = ()  # (stream, t0_s, t1_s) where a stream stops for > 5 periods
    bad_records: int = 0  # dataflash: damaged FMT records + records of a used type lacking a column or with a non-number
    out_of_range: dict = field(default_factory=dict)  # stream -> samples with a NaN, inf or impossible value
    bad_time: dict = field(default_factory=dict)  # stream -> samples at an impossible or out-of-line time


@dataclass(frozen=True)
class Recording:
    source: str
    format: str  # "tlog" or "dataflash"
    messages: dict  # message type -> count of good packets (from the vehicle)
    skipped: Skipped
    imu: ImuStream | None
    pressure: PressureStream | None
    servo: ServoStream | None
    attitude: AttitudeStream | None = None
    esc: EscStream | None = None
    mocap: MocapStream | None = None
    vehicle_id: tuple = (1, 1)  # (system, component) whose messages were used
    parameters: dict = field(default_factory=dict)  # the autopilot's parameters in the log, last value each
    parameters_changed: tuple = ()  # names whose value changed during the log (the last one is kept)
    parameters_dropped: int = 0  # rows left out: names beyond MAX_PARAMETERS, rows beyond MAX_PARAMETER_ROWS

    @property
    def streams(self) -> dict:
        names = ("imu", "pressure", "servo", "attitude", "esc", "mocap")
        return {n: getattr(self, n) for n in names if getattr(self, n) is not None}

    @property
    def t_start_s(self) -> float:
        return min((float(s.time_s[0]) for s in self.streams.values() if len(s.time_s)), default=0.0)

    @property
    def t_end_s(self) -> float:
        return max((float(s.time_s[-1]) for s in self.streams.values() if len(s.time_s)), default=0.0)

    @property
    def duration_s(self) -> float:
        return self.t_end_s - self.t_start_s

    def between(self, t0_s: float, t1_s: float) -> "Recording":
        """The same recording with every stream cut to t0_s <= t < t1_s (vehicle time)."""
        import dataclasses

        def cut(stream):  # times are strictly increasing: a slice, not a mask over the stream
            i0, i1 = np.searchsorted(stream.time_s, [t0_s, t1_s], side="left")
            return dataclasses.replace(stream, **{
                f.name: _frozen(getattr(stream, f.name)[i0:max(i0, i1)]) for f in dataclasses.fields(stream)
                if isinstance(getattr(stream, f.name), np.ndarray)})

        return dataclasses.replace(self, **{n: cut(s) for n, s in self.streams.items()})

    def summary(self) -> dict:
        """The `recording` block of the diagnosis report (spec/recording.md section 2)."""
        s = self.skipped
        return {
            "source": self.source,
            "format": self.format,
            "duration_s": round(self.duration_s, 3),
            "messages": dict(sorted(self.messages.items())),
            "skipped_bytes": s.skipped_bytes,
            "bad_crc_packets": s.bad_crc_packets,
            "truncated_bytes": s.truncated_bytes,
            "unknown_packets": s.unknown_packets,
            "non_monotonic": dict(s.non_monotonic),
            "bad_records": s.bad_records,
            "out_of_range": dict(s.out_of_range),
            "bad_time": dict(s.bad_time),
            "gaps": [{"stream": g[0], "t0": round(g[1], 3), "t1": round(g[2], 3)} for g in s.gaps],
            "segments": [[round(a, 3), round(b, 3)] for a, b in self.segment_bounds()],
        }

    def segment_bounds(self, max_gap_s: float = SEGMENT_GAP_S) -> list:
        """[(t0, t1)] of the stretches between gaps: a gap is a stop longer than max_gap_s in the
        IMU, pressure or servo stream (any of them). Work on a recording with a long gap goes
        segment by segment (`segments()`), so its memory follows the data, not the time span."""
        if not self.streams:
            return []
        cuts = []
        for name in ("imu", "pressure", "servo"):
            s = getattr(self, name)
            if s is not None and len(s.time_s) > 1:
                dt = np.diff(s.time_s)
                for i in np.nonzero(dt > max_gap_s)[0]:
                    cuts.append((float(s.time_s[i]), float(s.time_s[i + 1])))
        cuts.sort()
        out, t0 = [], self.t_start_s
        end = self.t_end_s
        for a, b in cuts:  # a stop in one stream is a stop of the recording's usable part
            if a > t0:
                out.append((t0, a))
            t0 = max(t0, b)
        out.append((t0, end))
        return [(a, b) for a, b in out if b >= a]

    def segments(self, max_gap_s: float = SEGMENT_GAP_S) -> list:
        """The recording cut at its gaps (`segment_bounds`): one Recording per stretch."""
        bounds = self.segment_bounds(max_gap_s)
        return [self.between(a, np.nextafter(b, np.inf)) for a, b in bounds]


# ------------------------------------------------------------------------------------------------
# Entry point


def read_recording(path) -> Recording:
    """Read a `.tlog` or dataflash `.bin` recording; raises `RecordingError` with the reason."""
    path = Path(path)
    try:
        data = read_bounded(path, MAX_RECORDING_BYTES)  # a regular file: never a device read whole
    except OSError as exc:
        raise RecordingError(f"{path}: cannot read recording: {exc.strerror or exc}") from exc
    if not data:
        raise RecordingError(f"{path}: empty file, expected a .tlog or dataflash .bin recording")
    if data[:2] == b"\xa3\x95" or path.suffix.lower() == ".bin":
        return _read_dataflash(path, data)
    return _read_tlog(path, data)


# ------------------------------------------------------------------------------------------------
# .tlog: compiled framing scan


def _dialect():
    from pymavlink.dialects.v20 import ardupilotmega  # explicit dialect, never from the environment

    return ardupilotmega


def _crc_table():
    d = _dialect()
    ids = np.array(sorted(d.mavlink_map), dtype=np.int64)
    extra = np.array([d.mavlink_map[i].crc_extra for i in ids], dtype=np.int64)
    return ids, extra


@njit(cache=True)
def _x25(buf, start, stop, extra):
    """CRC-16/MCRF4XX over buf[start:stop] then the CRC_EXTRA byte (MAVLink checksum.h)."""
    crc = 0xFFFF
    for i in range(start, stop + 1):
        b = buf[i] if i < stop else extra
        tmp = (b ^ (crc & 0xFF)) & 0xFF
        tmp = (tmp ^ (tmp << 4)) & 0xFF
        crc = ((crc >> 8) ^ (tmp << 8) ^ (tmp << 3) ^ (tmp >> 4)) & 0xFFFF
    return crc


@njit(cache=True)
def _frame(buf, p, ids, extra):
    """Packet at p (after its timestamp): (status, length, msgid, sys, comp, payload_off, plen).

    status 0 good, 1 bad CRC, 2 unknown id, 3 not a packet, 4 truncated.
    """
    n = buf.shape[0]
    if p >= n:
        return 4, 0, 0, 0, 0, 0, 0
    magic = buf[p]
    if magic == 0xFD:
        if p + 10 > n:
            return 4, n - p, 0, 0, 0, 0, 0
        plen = buf[p + 1]
        sig = 13 if (buf[p + 2] & 1) else 0
        if buf[p + 2] & 0xFE:  # unknown incompatibility flag: not a packet we can trust
            return 3, 0, 0, 0, 0, 0, 0
        total = 10 + plen + 2 + sig
        msgid = buf[p + 7] | (buf[p + 8] << 8) | (buf[p + 9] << 16)
        sysid, compid, hdr = buf[p + 5], buf[p + 6], 10
    elif magic == 0xFE:
        if p + 6 > n:
            return 4, n - p, 0, 0, 0, 0, 0
        plen = buf[p + 1]
        total = 6 + plen + 2
        sig = 0
        msgid = buf[p + 5]
        sysid, compid, hdr = buf[p + 3], buf[p + 4], 6
    else:
        return 3, 0, 0, 0, 0, 0, 0
    if p + total > n:
        return 4, n - p, msgid, sysid, compid, 0, 0
    k = np.searchsorted(ids, msgid)
    if k >= ids.shape[0] or ids[k] != msgid:
        return 2, total, msgid, sysid, compid, p + hdr, plen
    crc = buf[p + hdr + plen] | (buf[p + hdr + plen + 1] << 8)
    if _x25(buf, p + 1, p + hdr + plen, extra[k]) != crc:
        return 1, total, msgid, sysid, compid, p + hdr, plen
    return 0, total, msgid, sysid, compid, p + hdr, plen


@njit(cache=True)
def _timestamp(buf, p):
    t = np.uint64(0)
    for i in range(8):
        t = (t << np.uint64(8)) | np.uint64(buf[p + i])
    return t


@njit(cache=True)
def _ts_plausible(ts, last_ts):
    """A tlog stamp within [last - 1 min, last + 1 h] of the last trusted one (none before the
    first). A longer real jump of the logger's clock is taken when two packets agree on it."""
    if last_ts == np.uint64(0):
        return False
    lo = last_ts - np.uint64(60_000_000) if last_ts > np.uint64(60_000_000) else np.uint64(0)
    return lo <= ts <= last_ts + np.uint64(3600_000_000)


@njit(cache=True)
def _resync_ok(buf, q, last_ts, ids, extra):
    """A resync point: at q+8 a packet whose framing and CRC are good. The tlog stamp at q, which
    no CRC protects, is only a plausibility check for a MAVLink 1 packet (CRC-16 over a short
    header is found by chance in about one 0xFE byte in 80,000 of garbage): such a packet is
    taken if its stamp is near the last trusted one or the next packet frames well after it."""
    n = buf.shape[0]
    if q + 8 >= n:
        return False
    m = buf[q + 8]
    if m != 0xFD and m != 0xFE:
        return False
    st, total, msgid, sysid, compid, poff, plen = _frame(buf, q + 8, ids, extra)
    if st != 0:
        return False
    if m == 0xFD or _ts_plausible(_timestamp(buf, q), last_ts):
        return True
    nxt = q + 8 + total
    if nxt == n:
        return True
    if nxt + 8 >= n:
        return False
    st2 = _frame(buf, nxt + 8, ids, extra)[0]
    return st2 == 0 or st2 == 2


@njit(cache=True)
def _scan_tlog(buf, ids, extra):
    """Walk [ts][packet]...; returns per-packet arrays and the skip counters (see module doc).

    Resynchronisation is on MAVLink framing and CRC: after anything that is not a good packet
    where one was expected (garbage, a bad CRC, a damaged length or start marker), the next
    byte position holding a packet with a good CRC is where reading resumes, so a packet whose
    own bytes are intact is never lost to damage before it. The tlog stamp is a plausibility
    check only: a stamp out of line with the last trusted one (a flipped bit) is not trusted
    for resynchronisation; two consecutive packets agreeing on a time (the first two, or a real
    jump of the logger's clock) make it the trusted one. The stamps returned are the raw ones
    (`_clean_stamps` mends them).
    """
    n = buf.shape[0]
    cap = n // 16 + 16
    off = np.empty(cap, np.int64)
    plen_a = np.empty(cap, np.int64)
    mid = np.empty(cap, np.int64)
    src = np.empty(cap, np.int64)
    tsa = np.empty(cap, np.uint64)
    m = 0
    bad_crc = 0
    unknown = 0
    skipped = 0
    truncated = 0
    last_ts = np.uint64(0)
    cand = np.uint64(0)  # an untrusted stamp; trusted when the next packet agrees with it
    p = 0
    while p < n:
        if p + 8 > n:
            truncated += n - p
            skipped += n - p
            break
        st, total, msgid, sysid, compid, poff, plen = _frame(buf, p + 8, ids, extra)
        if st == 2:  # good framing, unknown id: taken if what follows frames (its length is sound)
            nxt = p + 8 + total
            if nxt + 8 < n:
                st2 = _frame(buf, nxt + 8, ids, extra)[0]
                if st2 != 0 and st2 != 2 and st2 != 4:
                    st = 3
        if st == 1:
            # a bad CRC: a good packet starting inside its span wins (its length byte may be
            # the damage); else, if its length leads to a packet, skip it as one bad packet
            bad_crc += 1
            nxt = p + 8 + total
            q = p + 1
            while q < nxt and not _resync_ok(buf, q, last_ts, ids, extra):
                q += 1
            if q == nxt and (nxt == n or (nxt + 8 < n and _frame(buf, nxt + 8, ids, extra)[0] != 3)):
                skipped += 8 + total
                p = nxt
                continue
            if q < nxt:
                skipped += q - p
                p = q
                continue
            st = 3  # its length leads nowhere: resynchronise from there
        if st == 3 or st == 4:
            q = p + 1
            while q < n and not _resync_ok(buf, q, last_ts, ids, extra):
                q += 1
            if q >= n:
                if st == 4 and _plausible_tail(buf, p, last_ts):
                    truncated += n - p
                skipped += n - p
                break
            skipped += q - p
            p = q
            continue
        if st == 2:
            unknown += 1
            p += 8 + total
            continue
        ts = _timestamp(buf, p)
        if _ts_plausible(ts, last_ts):
            last_ts = ts
            cand = np.uint64(0)
        elif _ts_plausible(ts, cand):
            last_ts = ts  # two packets in a row agree: the first stamp, or a real jump of the clock
            cand = np.uint64(0)
        else:
            cand = ts  # not trusted until the next packet agrees (stamps are cleaned after the scan)
        off[m] = poff
        plen_a[m] = plen
        mid[m] = msgid
        src[m] = sysid * 256 + compid
        tsa[m] = ts
        m += 1
        p += 8 + total
    return off[:m], plen_a[:m], mid[:m], src[:m], tsa[:m], bad_crc, unknown, skipped, truncated


@njit(cache=True)
def _plausible_tail(buf, p, last_ts):
    """A torn packet at the end only if its timestamp is plausible; else it is garbage."""
    if last_ts == np.uint64(0):
        return True
    return _ts_plausible(_timestamp(buf, p), last_ts)


# Bulk payload decoding with the dialect's own struct layout.

_STRUCT_TO_NP = {"Q": "<u8", "q": "<i8", "I": "<u4", "i": "<i4", "H": "<u2", "h": "<i2",
                 "B": "u1", "b": "i1", "f": "<f4", "d": "<f8", "c": "S1", "s": "S1"}


def _payload_dtype(cls) -> tuple[np.dtype, int]:
    fmt = cls.unpacker.format.lstrip("<")
    items = []
    i = 0
    while i < len(fmt):
        j = i
        while fmt[j].isdigit():
            j += 1
        count = int(fmt[i:j]) if j > i else 1
        items.append((fmt[j], count))
        i = j + 1
    fields = []
    names = list(cls.ordered_fieldnames)
    for name, (code, count) in zip(names, items):
        base = _STRUCT_TO_NP[code]
        fields.append((name, base, (count,)) if count > 1 and code not in "cs" else
                      (name, f"S{count}" if code in "cs" else base))
    dt = np.dtype(fields)
    return dt, struct.calcsize("<" + cls.unpacker.format.lstrip("<"))


def _decode_bulk(buf: np.ndarray, offsets, lengths, cls) -> np.ndarray:
    """Structured array of the payloads at `offsets` (MAVLink 2 trailing-zero truncation undone)."""
    dt, full = _payload_dtype(cls)
    n = len(offsets)
    raw = np.zeros((n, full), dtype=np.uint8)
    cols = np.arange(full)
    idx = offsets[:, None] + cols[None, :]
    mask = cols[None, :] < np.minimum(lengths, full)[:, None]
    raw[mask] = buf[idx[mask]]
    return raw.view(dt).reshape(n)


def scan_packets(data: bytes):
    """The good packets of .tlog bytes, for readers of what read_recording does not keep:
    (buf, payload offsets, payload lengths, message ids, sys*256+comp, log stamps in us)."""
    buf = np.frombuffer(data, dtype=np.uint8)
    off, plen, mid, src, ts, *_ = _scan_tlog(buf, *_crc_table())
    return buf, off, plen, mid, src, _clean_stamps(ts)


def _clean_stamps(ts: np.ndarray) -> np.ndarray:
    """tlog stamps (us) with the damaged ones mended: a run of at most 4 packets whose stamps
    jump away (> 1 min) from the stamps before it while the stamps after it carry on from those
    before (a flipped bit, which no CRC sees) takes the stamp of the packet before it (after
    it, at the start of the file). A real jump of the logger's clock goes on after the jump and
    is kept."""
    ts = np.asarray(ts, dtype=np.uint64)
    n = len(ts)
    if n < 2:
        return ts
    t = ts.astype(np.float64) / 1e6
    brk = np.nonzero(np.abs(np.diff(t)) > 60.0)[0]
    if not len(brk):
        return ts
    starts = np.concatenate([[0], brk + 1])
    ends = np.concatenate([brk + 1, [n]])
    lens = ends - starts
    first, last = t[starts], t[ends - 1]
    runs = len(starts)

    def in_line(x, ref):  # a stamp that can follow `ref`: at most 1 min back, 1 h ahead
        return -60.0 <= x - ref <= 3600.0

    bad = np.zeros(runs, dtype=bool)
    prev_end = None  # the last stamp of the last run kept
    for r in range(runs):
        if lens[r] <= 4:
            if prev_end is not None:
                if not in_line(first[r], prev_end):
                    nxt = r + 1  # the next run that vouches for the past: long, or in line with it
                    while nxt < min(runs, r + 64) and lens[nxt] <= 4 and not in_line(first[nxt], prev_end):
                        nxt += 1
                    # a real jump goes on: some run up to that one carries on from this one
                    goes_on = any(abs(first[j] - last[r]) <= 60.0 for j in range(r + 1, min(nxt + 1, runs)))
                    bad[r] = not goes_on and (nxt == runs or in_line(first[nxt], prev_end))
            elif r + 1 < runs:  # at the start: the next run, if longer, says what the time is
                bad[r] = lens[r + 1] > lens[r]
        if not bad[r]:
            prev_end = last[r]
    if not bad.any():
        return ts
    mask = np.repeat(bad, lens)
    good = np.nonzero(~mask)[0]
    if not len(good):
        return ts
    out = ts.copy()
    pick = np.searchsorted(good, np.nonzero(mask)[0], side="right") - 1
    out[mask] = ts[good[np.maximum(pick, 0)]]
    return out


def decode_message(buf, off, plen, mid, name: str):
    """The packets of message NAME in a scan_packets() result, decoded in bulk, and their mask;
    None for the array when there are none."""
    d = _dialect()
    ident = getattr(d, f"MAVLINK_MSG_ID_{name}")
    sel = mid == ident
    if not sel.any():
        return None, sel
    return _decode_bulk(buf, off[sel], plen[sel], d.mavlink_map[ident]), sel


WANTED = ("HEARTBEAT", "HIGHRES_IMU", "SCALED_IMU", "SCALED_IMU2", "RAW_IMU", "SCALED_PRESSURE2",
          "SERVO_OUTPUT_RAW", "ATTITUDE", "ESC_STATUS", "ESC_TELEMETRY_1_TO_4", "ATT_POS_MOCAP")
MAX_PARAMETERS = 20000  # ArduSub has about 1000; a hostile log cannot grow the dict past this
MAX_PARAMETER_ROWS = 100_000  # PARAM_VALUE packets decoded (the last ones): memory by a bound, not the file


def _parameters(pairs) -> tuple[dict, tuple, int]:
    """({name: value}, changed, dropped) of (name, value) pairs in log order, the last value of
    each name kept: names of 1-16 printable ASCII characters, finite values, at most
    MAX_PARAMETERS names; `changed` the names whose value changed during the log (at most 1000),
    `dropped` the rows of names that did not fit."""
    out: dict = {}
    changed: dict = {}
    dropped = 0
    for name, value in pairs:
        if isinstance(name, bytes):
            name = name.split(b"\0", 1)[0].decode("ascii", "replace")
        try:
            value = float(value)
        except (TypeError, ValueError):
            continue
        if not (0 < len(name) <= 16 and name.isascii() and name.isprintable() and math.isfinite(value)):
            continue
        if name in out:
            if out[name] != value and len(changed) < 1000:
                changed[name] = True
            out[name] = value
        elif len(out) < MAX_PARAMETERS:
            out[name] = value
        else:
            dropped += 1
    return out, tuple(sorted(changed)), dropped


def _log_clock_reference(decoded, ts, use, mid, name_to_id):
    """(logger time, logger - vehicle time) of every sample of the streams whose vehicle time does
    not wrap within hours, sorted by logger time, or None: the offset where in the log it held."""
    t_logs, diffs = [], []
    for name, clock, scale in (("HIGHRES_IMU", "time_usec", 1e-6), ("SCALED_PRESSURE2", "time_boot_ms", 1e-3),
                               ("ATTITUDE", "time_boot_ms", 1e-3), ("SCALED_IMU2", "time_boot_ms", 1e-3)):
        if name in decoded and len(decoded[name]):
            t_log = ts[use & (mid == name_to_id[name])].astype(np.float64) / 1e6
            raw = decoded[name][clock]
            t_vehicle = (_unwrap_ms(raw) if clock == "time_boot_ms" else np.asarray(raw, np.float64)) * scale
            t_logs.append(t_log)
            diffs.append(t_log - t_vehicle)
    if not t_logs:
        return None
    t_log, diff = np.concatenate(t_logs), np.concatenate(diffs)
    order = np.argsort(t_log, kind="stable")
    return t_log[order], diff[order]


def _local_offset(t_log_s, ref, window: int = 9):
    """For each logger time, the logger - vehicle offset of the reference samples around it in the
    log (the median of the `window` nearest in logger time: a flipped bit is outvoted), so a
    stretch after a jump of the vehicle's time that the logger's clock did not make (or made
    differently) is placed by its own neighbours, not by the whole log's median (issue 15, second
    pass: a servo stream stayed 1e5 s off the IMU). None without a reference."""
    if ref is None:
        return None
    r_log, r_off = ref
    n = len(r_off)
    w = min(window, n)
    if w < n:
        med = np.median(np.lib.stride_tricks.sliding_window_view(r_off, w), axis=1)  # n - w + 1 windows
        i = np.clip(np.searchsorted(r_log, np.asarray(t_log_s, float)) - w // 2, 0, n - w)
        return med[i]
    return np.full(len(t_log_s), float(np.median(r_off)))


def _read_tlog(path: Path, data: bytes) -> Recording:
    d = _dialect()
    buf = np.frombuffer(data, dtype=np.uint8)
    ids, extra = _crc_table()
    off, plen, mid, src, ts, bad_crc, unknown, skipped, truncated = _scan_tlog(buf, ids, extra)
    ts = _clean_stamps(ts)
    if len(off) == 0:
        raise RecordingError(
            f"{path}: no MAVLink packet with a good CRC found; expected a .tlog "
            "([8-byte timestamp][MAVLink packet]...) or a dataflash .bin")
    name_to_id = {cls.msgname: i for i, cls in d.mavlink_map.items()}
    vehicle = _vehicle_source(buf, off, plen, mid, src, d)
    use = src == vehicle[0] * 256 + vehicle[1]
    counts = {}
    decoded = {}
    for name in set(d.mavlink_map[i].msgname for i in np.unique(mid[use])):
        sel = use & (mid == name_to_id[name])
        counts[name] = int(sel.sum())
        if name in WANTED and name != "HEARTBEAT":
            decoded[name] = _decode_bulk(buf, off[sel], plen[sel], d.mavlink_map[name_to_id[name]])
    tally = _Tally()
    imu = _imu_from_tlog(decoded, tally)
    reference = _log_clock_reference(decoded, ts, use, mid, name_to_id)
    pressure = None
    if "SCALED_PRESSURE2" in decoded:
        a = decoded["SCALED_PRESSURE2"]
        p_pa = np.asarray(a["press_abs"], float) * 100.0
        t, keep = _monotonic(_unwrap_ms(a["time_boot_ms"]) / 1e3, "pressure", tally, _press_valid(p_pa))
        pressure = PressureStream(_frozen(t), _frozen(p_pa[keep]), "SCALED_PRESSURE2")
    attitude = None
    if "ATTITUDE" in decoded:
        a = decoded["ATTITUDE"]
        e = np.column_stack([a["roll"], a["pitch"], a["yaw"]]).astype(float)
        r = np.column_stack([a["rollspeed"], a["pitchspeed"], a["yawspeed"]]).astype(float)
        t, keep = _monotonic(_unwrap_ms(a["time_boot_ms"]) / 1e3, "attitude", tally, _attitude_valid(e, r))
        attitude = AttitudeStream(_frozen(t), _frozen(e[keep]), _frozen(r[keep]))
    servo = None
    if "SERVO_OUTPUT_RAW" in decoded:
        t_log = ts[use & (mid == name_to_id["SERVO_OUTPUT_RAW"])].astype(np.float64) / 1e6
        ref = [s.time_s for s in (imu, pressure, attitude) if s is not None and len(s.time_s)]
        span = (min(float(x[0]) for x in ref), max(float(x[-1]) for x in ref)) if ref else None
        servo = _servo_from_tlog(decoded["SERVO_OUTPUT_RAW"], t_log, _local_offset(t_log, reference), span, tally)
    esc = None
    if "ESC_STATUS" in decoded:
        a = decoded["ESC_STATUS"]
        a = a[a["index"] == 0]  # units 1-4
        rpm = np.asarray(a["rpm"], float)
        t, keep = _monotonic(_unwrap_us(a["time_usec"]) / 1e6, "esc", tally, _finite_within(ESC_RPM_MAX, rpm))
        esc = EscStream(_frozen(t), _frozen(rpm[keep]))
    if esc is None and "ESC_TELEMETRY_1_TO_4" in decoded:
        # ESC_TELEMETRY carries no time of its own (it is how ArduSub and our codec send rpm):
        # place it on vehicle time through the logger clock's offset from a stream that has one
        sel = use & (mid == name_to_id["ESC_TELEMETRY_1_TO_4"])
        t_log = ts[sel].astype(np.float64) / 1e6
        if reference is not None:
            t, keep = _monotonic(t_log - _local_offset(t_log, reference), "esc", tally)
            esc = EscStream(_frozen(t), _frozen(np.asarray(decoded["ESC_TELEMETRY_1_TO_4"]["rpm"], float)[keep]))
    mocap = None
    if "ATT_POS_MOCAP" in decoded:
        a = decoded["ATT_POS_MOCAP"]
        q = np.asarray(a["q"], float)
        pos = np.column_stack([a["x"], a["y"], a["z"]]).astype(float)
        with np.errstate(invalid="ignore", over="ignore"):
            qn = np.sqrt((q * q).sum(axis=1))
            valid = _finite_within(2.0, q) & (np.abs(qn - 1.0) < 0.1) & _finite_within(POS_MAX_M, pos)
        t, keep = _monotonic(_unwrap_us(a["time_usec"]) / 1e6, "mocap", tally, valid)
        mocap = MocapStream(_frozen(t), _frozen(q[keep]), _frozen(pos[keep]))
    imu, pressure, servo, attitude, esc, mocap = _trim_tails((imu, pressure, servo, attitude, esc, mocap), tally)
    skipped_info = Skipped(int(bad_crc), int(skipped), int(truncated), int(unknown), tally.nonmono,
                           tuple(tally.gaps), 0, tally.out_of_range, tally.bad_time)
    params, changed, dropped = {}, (), 0
    if "PARAM_VALUE" in counts:
        sel = np.flatnonzero(use & (mid == name_to_id["PARAM_VALUE"]))[-MAX_PARAMETER_ROWS:]
        a = _decode_bulk(buf, off[sel], plen[sel], d.mavlink_map[name_to_id["PARAM_VALUE"]])
        params, changed, dropped = _parameters(zip(a["param_id"], a["param_value"]))
        dropped += max(counts["PARAM_VALUE"] - MAX_PARAMETER_ROWS, 0)
    return Recording(str(path), "tlog", counts, skipped_info, imu, pressure, servo, attitude, esc,
                     mocap, vehicle, params, changed, dropped)


def _vehicle_source(buf, off, plen, mid, src, d) -> tuple:
    """(system, component) of the vehicle: the first HEARTBEAT of an autopilot, else (1, 1)."""
    hb = np.nonzero(mid == 0)[0]
    if len(hb):
        a = _decode_bulk(buf, off[hb], plen[hb], d.mavlink_map[0])
        ok = a["autopilot"] != 8  # MAV_AUTOPILOT_INVALID: a GCS or companion, not the vehicle
        sub = ok & (a["type"] == 12)  # MAV_TYPE_SUBMARINE
        pick = np.nonzero(sub)[0] if sub.any() else np.nonzero(ok)[0]
        if len(pick):
            s = int(src[hb[pick[0]]])
            return (s // 256, s % 256)
    return (1, 1)


def _unwrap_us(t_us) -> np.ndarray:
    """Microsecond clocks sent as uint32 (SERVO_OUTPUT_RAW) wrap every 71.6 min: unwrap them.
    A wrap is a step back of more than 2^31 us; a uint64 clock is only converted."""
    raw = np.asarray(t_us)
    t = raw.astype(np.float64)
    if raw.dtype == np.uint32 and t.size > 1:
        jumps = np.diff(t) < -2.0 ** 31
        t = t + np.concatenate([[0.0], np.cumsum(jumps) * 2.0 ** 32])
    return t


WRAP_S = 2.0 ** 32 / 1e6  # a uint32 microsecond clock's period: 4294.967296 s (71.6 min)


def _unwrap_ms(t_ms) -> np.ndarray:
    """time_boot_ms is uint32 milliseconds: it wraps after 49.7 days up. Unwrapped within the log
    as `_unwrap_us` does (a step back of more than 2^31 ms is a wrap), in ms as float."""
    t = np.asarray(t_ms).astype(np.float64)
    if t.size > 1:
        jumps = np.diff(t) < -2.0 ** 31
        if jumps.any():
            t = t + np.concatenate([[0.0], np.cumsum(jumps) * 2.0 ** 32])
    return t


def _align_wrapped(t_s, t_log_s, offset_s, span=None):
    """A uint32-us stream whose whole wraps before the log began, or during a gap in it, are
    unknown (a vehicle up for more than 71.6 min, a log that stops for hours): each stretch
    between jumps gets the whole periods that put it on the vehicle clock of the other streams,
    through the logger clock (`offset_s`, logger - vehicle, from a stream that does not wrap; one
    per sample, where the log held it, or one for the whole log).
    The stretch must land within `span` (first, last vehicle time of the streams that do not
    wrap) when there is one: if the logger's stamps there are damaged, the one whole number of
    periods that puts it inside the span is taken, or none. Without a reference, or where the
    logger clock disagrees by more than a quarter period, a stretch is left as it is."""
    if (offset_s is None and span is None) or not len(t_s):
        return t_s
    t = np.array(t_s, dtype=float)
    behind = (np.asarray(t_log_s, float) - (offset_s if offset_s is not None else np.nan)) - t
    jumps = np.abs(np.diff(t)) > 1.0  # the stream's own clock (CRC-protected), not the logger's stamps
    cuts = np.concatenate([[0], np.nonzero(jumps)[0] + 1, [len(t)]])
    margin = 60.0

    def inside(k, a, b):
        return span is None or (t[a] + k * WRAP_S >= span[0] - margin and t[b - 1] + k * WRAP_S <= span[1] + margin)

    for a, b in zip(cuts[:-1], cuts[1:]):
        if not np.isfinite(t[a]) or not np.isfinite(t[b - 1]):
            continue
        piece = behind[a:b]
        piece = piece[np.isfinite(piece)]
        k = None
        if len(piece):  # the whole number of periods most samples agree on (damaged stamps outvoted)
            ks = np.round(piece / WRAP_S)
            near = np.abs(piece - ks * WRAP_S) <= WRAP_S / 4
            if near.any():
                vals, counts = np.unique(ks[near], return_counts=True)
                if counts.max() * 2 > len(piece):
                    k = int(vals[np.argmax(counts)])
            if k is not None and not inside(k, a, b):
                k = None
        if k is None and span is not None:  # the logger cannot tell: the span may
            k_lo = math.ceil((span[0] - margin - t[a]) / WRAP_S)
            k_hi = math.floor((span[1] + margin - t[b - 1]) / WRAP_S)
            k = k_lo if k_lo == k_hi else None
        if k and t[a] + k * WRAP_S >= 0:
            t[a:b] += k * WRAP_S
    return t


class _Tally:
    """The per-stream counts of samples not used (Skipped's dicts) and the gaps."""

    def __init__(self):
        self.nonmono: dict = {}
        self.out_of_range: dict = {}
        self.bad_time: dict = {}
        self.gaps: list = []

    @staticmethod
    def add(d: dict, stream: str, n) -> None:
        if int(n):
            d[stream] = d.get(stream, 0) + int(n)


def _out_of_line(t: np.ndarray, rounds: int = 8) -> np.ndarray:
    """Samples whose time is out of line with the stream: a run of at most 4 samples that jumps
    ahead of the samples after it while those follow on from the samples before it (a flipped
    bit in a stamp). A real gap never goes back, so it is kept; a sample going back is left to
    the monotonic check. Judged again without what was found (at most `rounds` times): a run
    judged against one that was itself out of line was kept (issue 15, second pass: the first
    IMU stamp of small.BIN flipped to 1339 s hid the next flipped one, 1.4e8 s, and every later
    sample was dropped as going back)."""
    out = np.zeros(len(t), dtype=bool)
    for _ in range(rounds):
        idx = np.nonzero(~out)[0]
        more = _out_of_line_once(np.asarray(t)[idx])
        if not more.any():
            break
        out[idx[more]] = True
    return out


def _out_of_line_once(t: np.ndarray) -> np.ndarray:
    n = len(t)
    out = np.zeros(n, dtype=bool)
    if n < 2:
        return out
    d = np.diff(t)
    pos = d[d > 0]
    period = float(np.median(pos)) if len(pos) else 0.0
    brk = np.nonzero(np.abs(d) > max(20.0 * period, 1e-3))[0]
    if not len(brk):
        return out
    starts = np.concatenate([[0], brk + 1])
    ends = np.concatenate([brk + 1, [n]])
    first, last, lens = t[starts], t[ends - 1], ends - starts
    runs = np.arange(len(starts))
    long_ = lens > 4
    # judged against the nearest long runs around it (several flipped stamps in a row are
    # several short runs), or the nearest runs where there is no long one
    nxt_long = np.minimum.accumulate(np.where(long_, runs, len(starts))[::-1])[::-1]
    nxt_long = np.append(nxt_long[1:], len(starts))
    prv_long = np.maximum.accumulate(np.where(long_, runs, -1))
    prv_long = np.insert(prv_long[:-1], 0, -1)
    nxt = np.where(nxt_long < len(starts), nxt_long, np.minimum(runs + 1, len(starts)))
    prv = np.where(prv_long >= 0, prv_long, np.where(runs > 0, 0, -1))  # no long run before: the first
    nxt_first = np.append(first, np.inf)[nxt]
    prev_last = np.where(prv >= 0, last[np.maximum(prv, 0)], -np.inf)
    bad = ~long_ & (last > nxt_first) & (prev_last < nxt_first)
    return np.repeat(bad, lens)


def _monotonic(t, stream: str, tally: "_Tally", valid=None):
    """The samples to keep and their times. Dropped and counted: an impossible time (NaN, < 0,
    > MAX_TIME_S) or one out of line with its neighbours (`bad_time`); a value that is NaN, inf
    or physically impossible, `valid` False (`out_of_range`); a time that does not increase
    (`non_monotonic`). Gaps > 5 median periods are listed."""
    t = np.asarray(t, dtype=float)
    ok = np.isfinite(t) & (t >= 0) & (t <= MAX_TIME_S)
    bad_time = int(len(t) - ok.sum())
    if valid is not None:
        valid = np.asarray(valid, dtype=bool)
        tally.add(tally.out_of_range, stream, (ok & ~valid).sum())
        ok &= valid
    idx = np.nonzero(ok)[0]
    line = _out_of_line(t[idx])
    bad_time += int(line.sum())
    tally.add(tally.bad_time, stream, bad_time)
    idx = idx[~line]
    tt = t[idx]
    mono = np.zeros(len(tt), dtype=bool)
    if len(tt):
        running = np.maximum.accumulate(tt)
        mono[0] = True
        mono[1:] = tt[1:] > running[:-1]
    tally.add(tally.nonmono, stream, len(tt) - mono.sum())
    keep = np.zeros(len(t), dtype=bool)
    keep[idx[mono]] = True
    tk = t[keep]
    if len(tk) > 2:
        dt = np.diff(tk)
        period = float(np.median(dt))
        for i in np.nonzero(dt > 5 * period + 1e-9)[0]:
            tally.gaps.append((stream, float(tk[i]), float(tk[i + 1])))
    return tk, keep


STREAM_NAMES = ("imu", "pressure", "servo", "attitude", "esc", "mocap")


def _core(t: np.ndarray) -> tuple:
    """(i0, i1): a stream without up to 4 samples at each end that stand apart (> 1 s) from the
    rest: t[i0:i1] is what the other streams' ends are judged against."""
    i0, i1 = 0, len(t)
    gaps = np.nonzero(np.diff(t) > 1.0)[0]
    for g in gaps[:4]:  # leading runs, while at most 4 samples in all
        if g + 1 > 4:
            break
        i0 = g + 1
    for g in gaps[::-1][:4]:  # trailing runs
        if len(t) - (g + 1) > 4:
            break
        i1 = g + 1
    return (i0, i1) if i1 - i0 >= 5 else (0, len(t))


def _trim_tails(streams: tuple, tally: _Tally, ref: tuple | None = None) -> tuple:
    """At most 4 samples at a stream's start or end lying more than 1 s outside the time span of
    every other stream (a flipped bit in the last stamps: nothing after them says they are out of
    line) are dropped and counted in `bad_time`; the gaps to them go too. A stream left with no
    sample (every one NaN, say) is None, as one that was never sent. `ref`, the span of the
    log's own clock (every dataflash record), stands in for the others when a stream is alone."""
    import dataclasses

    out = [s if s is not None and len(s.time_s) else None for s in streams]
    named = [(n, s) for n, s in zip(STREAM_NAMES, out) if s is not None]
    if len(named) + (ref is not None) < 2:
        return tuple(out)
    cores = {n: _core(s.time_s) for n, s in named}
    spans = {n: (float(s.time_s[cores[n][0]]), float(s.time_s[cores[n][1] - 1])) for n, s in named}
    if ref is not None and len(named) == 1:  # the log's clock, only where no other stream can say
        spans["log"] = ref
    for name, s in named:
        lo = min(c[0] for m, c in spans.items() if m != name)
        hi = max(c[1] for m, c in spans.items() if m != name)
        t = s.time_s
        c0, c1 = cores[name]  # of the samples apart at the ends, those outside the others' span
        i0 = min(c0, int(np.searchsorted(t, lo - 1.0, side="left")))
        i1 = max(c1, int(np.searchsorted(t, hi + 1.0, side="right")))
        if len(t) <= 4 and (t[-1] < lo - 1.0 or t[0] > hi + 1.0):
            i0 = i1 = len(t)  # a few samples, all away from everything else: a damaged record or two
        if (i0, i1) == (0, len(t)):
            continue
        if i1 <= i0:
            tally.add(tally.bad_time, name, len(t))
            tally.gaps[:] = [g for g in tally.gaps if g[0] != name]
            out[STREAM_NAMES.index(name)] = None
            continue
        tally.add(tally.bad_time, name, i0 + len(t) - i1)
        t0, t1 = float(t[i0]), float(t[i1 - 1])
        tally.gaps[:] = [g for g in tally.gaps if g[0] != name or (g[1] >= t0 and g[2] <= t1)]
        out[STREAM_NAMES.index(name)] = dataclasses.replace(s, **{
            f.name: _frozen(getattr(s, f.name)[i0:i1]) for f in dataclasses.fields(s)
            if isinstance(getattr(s, f.name), np.ndarray)})
    return tuple(out)


def _finite_within(limit, *cols) -> np.ndarray:
    """True where every column is finite and within +-limit."""
    ok = np.ones(len(cols[0]) if len(cols) else 0, dtype=bool)
    for c in cols:
        c = np.asarray(c, dtype=float)
        with np.errstate(invalid="ignore"):
            ok &= np.isfinite(c).all(axis=-1) if c.ndim > 1 else np.isfinite(c)
            ok &= (np.abs(c) <= limit).all(axis=-1) if c.ndim > 1 else (np.abs(c) <= limit)
    return ok


def _imu_valid(acc, gyr) -> np.ndarray:
    return _finite_within(ACCEL_MAX_M_S2, acc) & _finite_within(GYRO_MAX_RAD_S, gyr)


def _press_valid(p) -> np.ndarray:
    p = np.asarray(p, dtype=float)
    with np.errstate(invalid="ignore"):
        return np.isfinite(p) & (p >= PRESS_RANGE_PA[0]) & (p <= PRESS_RANGE_PA[1])


def _attitude_valid(e, r) -> np.ndarray:
    return _finite_within(ANGLE_MAX_RAD, e) & _finite_within(GYRO_MAX_RAD_S, r)


def _imu_from_tlog(decoded: dict, tally: _Tally) -> ImuStream | None:
    if "HIGHRES_IMU" in decoded:
        a = decoded["HIGHRES_IMU"]
        a = a[a["id"] == 0] if "id" in a.dtype.names and (a["id"] == 0).any() else a
        acc = np.column_stack([a["xacc"], a["yacc"], a["zacc"]]).astype(float)
        gyr = np.column_stack([a["xgyro"], a["ygyro"], a["zgyro"]]).astype(float)
        t, keep = _monotonic(_unwrap_us(a["time_usec"]) / 1e6, "imu", tally, _imu_valid(acc, gyr))
        return ImuStream(_frozen(t), _frozen(acc[keep]), _frozen(gyr[keep]), "HIGHRES_IMU")
    # ArduSub sends RAW_IMU and SCALED_IMU for the primary IMU and SCALED_IMU2 for the second;
    # an IMU that is not fitted is sent as all zeros and is passed over.
    for name, tkey in (("RAW_IMU", "time_usec"), ("SCALED_IMU", "time_boot_ms"), ("SCALED_IMU2", "time_boot_ms")):
        if name in decoded and any(np.any(decoded[name][k] != 0) for k in ("xacc", "yacc", "zacc")):
            a = decoded[name]
            scale_t = 1e-3 if tkey == "time_boot_ms" else 1e-6
            t_raw = (_unwrap_ms(a[tkey]) if tkey == "time_boot_ms" else _unwrap_us(a[tkey])) * scale_t
            # mG -> m/s^2, mrad/s -> rad/s (ArduPilot GCS_Common)
            acc = np.column_stack([a["xacc"], a["yacc"], a["zacc"]]).astype(float) * G_MSS / 1000.0
            gyr = np.column_stack([a["xgyro"], a["ygyro"], a["zgyro"]]).astype(float) / 1000.0
            t, keep = _monotonic(t_raw, "imu", tally, _imu_valid(acc, gyr))
            return ImuStream(_frozen(t), _frozen(acc[keep]), _frozen(gyr[keep]), name)
    return None


def _servo_from_tlog(a, t_log_s, offset_s, span, tally: _Tally) -> ServoStream:
    # port 0 carries channels 1-16 (9-16 in the MAVLink 2 extension fields); other ports are
    # further banks of 8 that ArduSub does not use.
    if (a["port"] == 0).any():
        t_log_s = t_log_s[a["port"] == 0]
        if offset_s is not None and np.ndim(offset_s):
            offset_s = offset_s[a["port"] == 0]
        a = a[a["port"] == 0]
    # time_usec is uint32: unwrapped within the log, then put on the other streams' clock
    t = _align_wrapped(_unwrap_us(a["time_usec"]) / 1e6, t_log_s, offset_s, span)
    t, keep = _monotonic(t, "servo", tally)
    pwm = np.column_stack([a[f"servo{c}_raw"] for c in range(1, 17)]).astype(float)[keep]
    return ServoStream(_frozen(t), _frozen(pwm))


# ------------------------------------------------------------------------------------------------
# Dataflash .bin (pymavlink DFReader)


def _read_dataflash(path: Path, data: bytes) -> Recording:
    # DFReader (and its compiled indexer, which writes to the file descriptors themselves) prints
    # a line for every byte it cannot frame ("bad header ..."): a damaged 8 MB log flooded the
    # terminal with millions of lines and took minutes under a capturing caller (found by
    # fuzzing). What it skips is counted here (skipped_bytes), so its prints go nowhere.
    with _quiet():
        return _read_dataflash_quietly(path, data)


@contextlib.contextmanager
def _quiet():
    """stdout and stderr to /dev/null, at the file descriptors (for compiled code) and in sys."""
    import sys

    for stream in (sys.stdout, sys.stderr):
        if stream is not None:
            stream.flush()
    saved = [os.dup(1), os.dup(2)]
    try:
        with open(os.devnull, "w") as null, contextlib.redirect_stdout(null), contextlib.redirect_stderr(null):
            os.dup2(null.fileno(), 1)
            os.dup2(null.fileno(), 2)
            yield
    finally:
        os.dup2(saved[0], 1)
        os.dup2(saved[1], 2)
        for fd in saved:
            os.close(fd)


def _damaged_fmts(data: bytes) -> list:
    """Offsets of FMT records (0xA3 0x95 0x80, 89 bytes) DFReader cannot use, left unframed so
    that it reads the rest (their type's records are skipped, counted): a format character it has
    no type for; a column count other than the format's length (DFReader indexes one by the
    other: IndexError); a length byte other than the format's size; a type id that an FMT of
    another name claims too, unless its length is the one the type's records frame by (a type id
    flipped into MULT's redefined MULT, and DFReader died reading the unit tables). Each of these,
    one flipped bit in any FMT record (UNIT's or GPS's as well as a stream's), made DFReader refuse
    the whole log (issue 15, adversarial re-run: 16 of 1,824 one-bit flips sampled over all 152 FMT
    records of small.BIN's first 80 kB)."""
    from pymavlink.DFReader import FORMAT_TO_STRUCT

    ok = set(FORMAT_TO_STRUCT)
    out = []
    by_type: dict = {}
    i = data.find(b"\xa3\x95\x80")
    while 0 <= i <= len(data) - 89:
        fmt = data[i + 9:i + 25].split(b"\0", 1)[0].decode("latin-1")
        cols = data[i + 25:i + 89].split(b"\0", 1)[0]
        if (any(c not in ok for c in fmt) or len(cols.split(b",")) != len(fmt)
                or _fmt_size(fmt) != data[i + 4]):
            out.append(i)
        else:
            by_type.setdefault(data[i + 3], []).append(i)
        i = data.find(b"\xa3\x95\x80", i + 3)
    clashes = {t: at for t, at in by_type.items() if t != 0x80 and len({data[j + 5:j + 9] for j in at}) > 1}
    if clashes:
        arr = np.frombuffer(data, np.uint8)
        heads_at = np.nonzero((arr[:-2] == 0xA3) & (arr[1:-1] == 0x95))[0]
        for t, at in clashes.items():
            share = {j: _framing(arr, heads_at, t, data[j + 4]) for j in at}
            best = max(share.values())
            keep = next(j for j in at if share[j] == best)  # the first of the best
            out.extend(j for j in at if data[j + 5:j + 9] != data[keep + 5:keep + 9])
    return sorted(out)


# The streams read from a dataflash log, and the columns each needs (_read_dataflash_file).
DF_NEEDED = {"IMU": ("TimeUS", "I", "AccX", "AccY", "AccZ", "GyrX", "GyrY", "GyrZ"),
             "BARO": ("TimeUS", "I", "Press"), "RCOU": ("TimeUS",) + tuple(f"C{c}" for c in range(1, 15)),
             "ATT": ("TimeUS", "Roll", "Pitch", "Yaw"), "ESC": ("TimeUS", "Instance", "RPM")}
FMT_HEADER = b"\xa3\x95\x80"

# ArduPilot's own definitions (name, format, columns) of the streams read, as its logger writes
# them into every log's FMT records: an FMT of one of these names whose length, format and
# columns are one bit from exactly one of these is mended to it (_repair_fmts). The record alone
# cannot tell a format character flipped into another of the same size (`f` into `n`, the length
# agrees with both) or a column flipped into its neighbour's name (`GyrX` into `GyrY`).
#   IMU:  libraries/AP_InertialSensor/LogStructure.h, LOG_STRUCTURE_FROM_INERTIALSENSOR (4.1 on);
#         before 4.1, libraries/AP_Logger/LogStructure.h (DataFlash/LogStructure.h) LOG_IMU_MSG
#   BARO: libraries/AP_Baro/LogStructure.h, LOG_STRUCTURE_FROM_BARO
#   RCOU: libraries/AP_Logger/LogStructure.h, LOG_RCOUT_MSG
#   ATT:  libraries/AP_AHRS/LogStructure.h, LOG_ATTITUDE_MSG (AP_Logger/LogStructure.h before)
#   ESC:  libraries/AP_ESC_Telem/LogStructure.h, LOG_STRUCTURE_FROM_ESC_TELEM (with RXErr; with
#         RawRPM later); ArduSub V4.1.0 wrote it without RXErr (shared/data/ardusub/small.BIN)
DF_KNOWN = {
    "IMU": (("QBffffffIIfBBHH", "TimeUS,I,GyrX,GyrY,GyrZ,AccX,AccY,AccZ,EG,EA,T,GH,AH,GHz,AHz"),
            ("QffffffIIfBBHH", "TimeUS,GyrX,GyrY,GyrZ,AccX,AccY,AccZ,EG,EA,T,GH,AH,GHz,AHz"),
            ("QffffffIIfBB", "TimeUS,GyrX,GyrY,GyrZ,AccX,AccY,AccZ,ErrG,ErrA,Temp,GyHlt,AcHlt")),
    "BARO": (("QBffcfIffB", "TimeUS,I,Alt,Press,Temp,CRt,SMS,Offset,GndTemp,Health"),),
    "RCOU": (("QHHHHHHHHHHHHHH", "TimeUS,C1,C2,C3,C4,C5,C6,C7,C8,C9,C10,C11,C12,C13,C14"),),
    "ATT": (("QccccCCCCB", "TimeUS,DesRoll,Roll,DesPitch,Pitch,DesYaw,Yaw,ErrRP,ErrYaw,AEKF"),),
    # DFReader reads these itself (units and multipliers): libraries/AP_Logger/LogStructure.h,
    # LOG_UNIT_MSG, LOG_FORMAT_UNITS_MSG, LOG_MULT_MSG
    "UNIT": (("QbZ", "TimeUS,Id,Label"),),
    "FMTU": (("QBNN", "TimeUS,FmtType,UnitIds,MultIds"),),
    "MULT": (("Qbd", "TimeUS,Id,Mult"),),
    "ESC": (("QBeffcfcf", "TimeUS,Instance,RPM,Volt,Curr,Temp,CTot,MotTemp,Err"),
            ("QBeffcfcff", "TimeUS,Instance,RPM,Volt,Curr,Temp,CTot,MotTemp,Err,RXErr"),
            ("QBffffcfcf", "TimeUS,Instance,RPM,RawRPM,Volt,Curr,Temp,CTot,MotTemp,Err")),
}


# The FMT record of FMT itself, the same in every dataflash log (libraries/AP_Logger/
# LogStructure.h, LOG_FORMAT_MSG: "FMT", "BBnNZ", "Type,Length,Name,Format,Columns", 89 bytes).
# DFReader reads every later FMT record with what this record says: one flipped bit in it
# ('l' of Columns into ',') lost every stream of small.BIN, and at 2 % byte flips a damaged one
# lost whole logs.
FMT_OF_FMT = (FMT_HEADER + bytes([0x80, 89]) + b"FMT\0" + b"BBnNZ".ljust(16, b"\0")
              + b"Type,Length,Name,Format,Columns".ljust(64, b"\0"))


# How many flipped bits a damaged FMT record of a known stream may hold and still be mended to the
# nearest known definition. The definitions of one stream in different firmware (DF_KNOWN) are at
# least 26 bits apart (ESC with and without RXErr; IMU's are 92 or more), so a record within 8
# bits of one is at least 18 from any other. One bit covers a single flip; at 2 % of a log's
# bytes flipped, small.BIN's IMU record took 5 (seed 17), and the whole IMU stream was lost.
MAX_KNOWN_BITS = 8


def _known_fmt(name: str, record: bytes) -> bytes | None:
    """The length, format and columns fields (record[4], [9:25], [25:89]) of the known
    definition of NAME (DF_KNOWN) nearest this FMT record's, within MAX_KNOWN_BITS bits and
    nearer than any other; None when the record is one exactly, or none (or two) is near."""
    have = record[4:5] + record[9:89]
    near = []
    for fmt, cols in DF_KNOWN.get(name, ()):
        want = bytes([_fmt_size(fmt)]) + fmt.encode().ljust(16, b"\0") + cols.encode().ljust(64, b"\0")
        bits = sum(bin(a ^ b).count("1") for a, b in zip(have, want))
        if bits == 0:
            return None
        if bits <= MAX_KNOWN_BITS:
            near.append((bits, want))
    near.sort(key=lambda x: x[0])
    if not near or (len(near) > 1 and near[1][0] == near[0][0]):
        return None
    return near[0][1]


def _one_bit(a: bytes, b: bytes) -> bool:
    return len(a) == len(b) and sum(bin(x ^ y).count("1") for x, y in zip(a, b)) == 1


def _fmt_size(fmt: str) -> int | None:
    """Bytes of a record of this format string (header included), or None if a character is unknown."""
    from pymavlink.DFReader import FORMAT_TO_STRUCT

    try:
        return 3 + struct.calcsize("<" + "".join(FORMAT_TO_STRUCT[c][0] for c in fmt))
    except (KeyError, struct.error):
        return None


def _framing(arr: np.ndarray, heads_at: np.ndarray, t: int, length: int) -> float:
    """The share of the records headed A3 95 t that another record header follows at +length."""
    p = heads_at[arr[heads_at + 2] == t]
    p = p[p + length + 1 < len(arr)]
    if not len(p) or length < 3:
        return 0.0
    return float(np.mean((arr[p + length] == 0xA3) & (arr[p + length + 1] == 0x95)))


def _repair_fmts(data: bytes) -> tuple:
    """A dataflash log with its FMT records mended where one flipped bit shows (issue 15, second
    pass: one flipped bit in the IMU's FMT record lost the IMU stream in 495 of its 712 bits).
    An FMT record is redundant in itself: its length byte is its format's size, it has one column
    per format character, its name and columns are ASCII words, and its type id heads the
    records that follow. So, for the streams read (`DF_NEEDED`): a header one bit from 0xA3 0x95
    0x80 before an otherwise whole FMT record; a name one bit from a wanted name no other FMT
    has; a length byte that disagrees with its format (or a format character one bit from the one
    that agrees with the length); a column name one bit from a needed one that is missing, or a
    character one bit from the comma that gives one column per format character; a type id no
    record uses, one bit from a type that heads records and has no FMT. Returns (bytes, repaired)."""
    buf = bytearray(data)
    n = len(buf)
    arr = np.frombuffer(bytes(buf), np.uint8)
    if n < 89:
        return bytes(buf), 0
    # candidate FMT records: a header within one bit of 0xA3 0x95 0x80
    h0, h1, h2 = arr[:-2] == 0xA3, arr[1:-1] == 0x95, arr[2:] == 0x80
    close = (h0.astype(np.int8) + h1 + h2) >= 2
    starts = [int(i) for i in np.nonzero(close[: n - 88])[0] if _one_bit(bytes(buf[i:i + 3]), FMT_HEADER)
              or bytes(buf[i:i + 3]) == FMT_HEADER]
    # record headers per type id (A3 95 t), to tell a type id in use from a flipped one
    heads_at = np.nonzero(h0 & h1)[0]
    heads = np.bincount(arr[heads_at + 2], minlength=256)
    fmts = {}
    for i in starts:
        name = bytes(buf[i + 5:i + 9]).split(b"\0", 1)[0]
        fmt = bytes(buf[i + 9:i + 25]).split(b"\0", 1)[0]
        cols = bytes(buf[i + 25:i + 89]).split(b"\0", 1)[0]
        exact = bytes(buf[i:i + 3]) == FMT_HEADER
        whole = (name.isalnum() and name.isupper() or name.isdigit()) and fmt and cols and \
            _fmt_size(fmt.decode("latin-1")) == buf[i + 4] and len(cols.split(b",")) == len(fmt)
        if exact or whole:  # a header flip is believed only before an otherwise whole record
            fmts[i] = (exact, name, fmt, cols)
    names = {v[1] for v in fmts.values()}
    types = {int(buf[i + 3]) for i in fmts}
    repaired = 0
    for i, (exact, name, fmt, cols) in fmts.items():
        before = bytes(buf[i:i + 89])
        fmt_name = bytes(buf[i + 5:i + 9])
        if buf[i + 3] == 0x80 and (fmt_name == b"FMT\0" or _one_bit(fmt_name, b"FMT\0")):
            # FMT's own record: a constant of the format, whatever its damage (another type's
            # record whose type id flipped into 0x80 keeps its own name, and is left alone)
            buf[i:i + 89] = FMT_OF_FMT
            repaired += bytes(buf[i:i + 89]) != before
            continue
        if not exact:
            buf[i:i + 3] = FMT_HEADER
        wanted = [w for w in DF_KNOWN if w.encode() not in names and _one_bit(name.ljust(4, b"\0"), w.encode().ljust(4, b"\0"))]
        if len(wanted) == 1:
            name = wanted[0].encode()
            buf[i + 5:i + 9] = name.ljust(4, b"\0")
        if name.decode("latin-1") not in DF_KNOWN:
            buf[i:i + 89] = before  # only what is read is mended (a mended MULT made DFReader fail on its records)
            continue
        known = _known_fmt(name.decode("latin-1"), bytes(buf[i:i + 89]))
        if known is not None:  # a few bits from ArduPilot's own definition: that is the record
            buf[i + 4] = known[0]
            buf[i + 9:i + 89] = known[1:]
            repaired += 1
            continue
        f = fmt.decode("latin-1")
        size = _fmt_size(f)
        if size != buf[i + 4]:  # the length byte or a format character flipped: the records frame by the true length
            t = int(buf[i + 3])
            fixes = [(k, bit) for k in range(len(f)) for bit in range(8)
                     if _fmt_size(f[:k] + chr(ord(f[k]) ^ (1 << bit)) + f[k + 1:]) == buf[i + 4]]
            by_length = _framing(arr, heads_at, t, int(buf[i + 4]))
            by_format = _framing(arr, heads_at, t, size) if size is not None else 0.0
            if size is not None and len(cols.split(b",")) == len(f) and by_format > max(by_length, 0.5):
                buf[i + 4] = size  # the length byte flipped
            elif len(fixes) == 1 and by_length > 0.5:
                k, bit = fixes[0]
                buf[i + 9 + k] ^= 1 << bit
                f = f[:k] + chr(ord(f[k]) ^ (1 << bit)) + f[k + 1:]
        need = DF_NEEDED.get(name.decode("latin-1"))
        if need is not None:
            c = cols.decode("latin-1")
            parts = c.split(",")
            if len(parts) != len(f):  # a comma flipped (or flipped into one)
                cands = [k for k in range(len(c)) for bit in range(8)
                         if len((c[:k] + chr(ord(c[k]) ^ (1 << bit)) + c[k + 1:]).split(",")) == len(f)
                         and all(p.isidentifier() for p in (c[:k] + chr(ord(c[k]) ^ (1 << bit)) + c[k + 1:]).split(","))]
                if len(set(cands)) == 1:
                    k = cands[0]
                    c = c[:k] + "," + c[k + 1:] if c[k] != "," else c
                    if c[k] == ",":
                        buf[i + 25 + k] = ord(",")
                    parts = c.split(",")
            missing = [x for x in need if x not in parts]
            for j, p in enumerate(parts):
                if p in need:
                    continue  # a whole needed column is never the one that flipped
                fix = [x for x in missing if _one_bit(p.encode("latin-1"), x.encode())]
                if len(fix) == 1:
                    at = i + 25 + sum(len(q) + 1 for q in parts[:j])
                    buf[at:at + len(p)] = fix[0].encode()
                    missing.remove(fix[0])
        repaired += bytes(buf[i:i + 89]) != before
    claims = np.bincount([int(buf[i + 3]) for i in fmts], minlength=256)
    # a flipped type id: records of a type no FMT describes, and one FMT (of a type no record
    # uses, one bit away) whose length frames them
    for o in np.nonzero(heads)[0]:
        if int(o) in types:
            continue
        cands = [i for i in fmts if bytes(buf[i + 5:i + 9]).split(b"\0", 1)[0].decode("latin-1") in DF_NEEDED
                 and (heads[buf[i + 3]] == 0 or claims[buf[i + 3]] > 1)  # unused, or another FMT's type
                 and _one_bit(bytes([buf[i + 3]]), bytes([int(o)]))
                 and _framing(arr, heads_at, int(o), int(buf[i + 4])) > 0.5]
        if len(cands) == 1:
            buf[cands[0] + 3] = int(o)
            types.add(int(o))
            repaired += 1
    return bytes(buf), repaired


def _read_dataflash_quietly(path: Path, data: bytes) -> Recording:
    import tempfile

    from pymavlink import DFReader

    mended, repaired = _repair_fmts(data)
    damaged = _damaged_fmts(mended)
    read_path = str(path)
    tmp = None
    if damaged or repaired:  # read a copy: FMT records mended, those still damaged not framed (skipped)
        fixed = bytearray(mended)
        for i in damaged:
            fixed[i + 2] = 0x00
        tmp = tempfile.NamedTemporaryFile(suffix=".bin", delete=False)
        tmp.write(fixed)
        tmp.close()
        read_path = tmp.name
    try:
        try:
            return _read_dataflash_file(path, read_path, data, len(damaged) + repaired)
        except RecordingError:
            if not repaired:
                raise
            # a mended record the log's other damage makes unreadable: as without the mending
            fixed = bytearray(data)
            for i in _damaged_fmts(data):
                fixed[i + 2] = 0x00
            Path(tmp.name).write_bytes(bytes(fixed))
            return _read_dataflash_file(path, read_path, data, len(_damaged_fmts(data)))
    finally:
        if tmp is not None:
            os.unlink(tmp.name)


def _read_dataflash_file(path: Path, read_path: str, data: bytes, bad_fmts: int) -> Recording:
    from pymavlink import DFReader

    try:
        log = DFReader.DFReader_binary(read_path, zero_time_base=False)
    except Exception as exc:  # DFReader raises bare exceptions on unusable headers
        raise RecordingError(f"{path}: not a readable dataflash log: {exc}") from exc
    rows: dict = {"IMU": [], "BARO": [], "RCOU": [], "ATT": [], "ESC": [], "PARM": []}
    log_times: list = []  # TimeUS of every record of every type: the log's own clock, for _trim_tails
    bad_decode = 0  # records DFReader framed but could not decode: counted in bad_records
    counts: dict = {}
    used_bytes = 0
    while True:
        try:
            m = log.recv_msg()
        except Exception:  # a torn last record
            break
        if m is None:
            break
        name = m.get_type()
        counts[name] = counts.get(name, 0) + 1
        fmt = getattr(m, "fmt", None)
        used_bytes += getattr(fmt, "len", 0) or 0
        try:  # a record DFReader framed but cannot decode (its FMT damaged past what is mended)
            if name in rows:
                rows[name].append(m.to_dict())
            t_us = getattr(m, "TimeUS", None)
        except (IndexError, KeyError, ValueError, TypeError, struct.error):
            bad_decode += 1
            continue
        if isinstance(t_us, (int, float)) and not isinstance(t_us, bool):
            log_times.append(t_us)
    tally = _Tally()
    bad = [bad_fmts + bad_decode]  # damaged FMT records, undecodable records, then records of a used type that cannot be read
    imu = pressure = servo = attitude = esc = None
    # A damaged FMT record can rename a type's columns or change their types: a record without
    # the columns a stream needs, or with a value that is not a number, is counted, not used.
    imu_rows = _df_columns(rows["IMU"], ("TimeUS", "AccX", "AccY", "AccZ", "GyrX", "GyrY", "GyrZ"), bad, "I")
    imu_rows = imu_rows[imu_rows[:, -1] == 0] if len(imu_rows) else imu_rows
    if len(imu_rows):
        t, keep = _monotonic(imu_rows[:, 0] / 1e6, "imu", tally, _imu_valid(imu_rows[:, 1:4], imu_rows[:, 4:7]))
        imu = ImuStream(_frozen(t), _frozen(imu_rows[keep, 1:4]), _frozen(imu_rows[keep, 4:7]), "IMU")
    baro_rows = _df_columns(rows["BARO"], ("TimeUS", "Press"), bad, "I")
    baro = baro_rows[baro_rows[:, -1] == 1] if len(baro_rows) else baro_rows
    if not len(baro) and len(baro_rows):
        baro = baro_rows[baro_rows[:, -1] == 0]
    if len(baro):  # ArduSub: instance 1 is the external depth sensor
        t, keep = _monotonic(baro[:, 0] / 1e6, "pressure", tally, _press_valid(baro[:, 1]))
        pressure = PressureStream(_frozen(t), _frozen(baro[keep, 1]), "BARO")
    rcou = _df_columns(rows["RCOU"], ("TimeUS",), bad, *(f"C{c}" for c in range(1, 17)))
    if len(rcou):
        t, keep = _monotonic(rcou[:, 0] / 1e6, "servo", tally, np.isfinite(rcou[:, 1:17]).all(axis=1))
        servo = ServoStream(_frozen(t), _frozen(rcou[keep, 1:17]))
    att = _df_columns(rows["ATT"], ("TimeUS", "Roll", "Pitch", "Yaw"), bad)
    if len(att):
        t, keep = _monotonic(att[:, 0] / 1e6, "attitude", tally,
                             _finite_within(np.degrees(ANGLE_MAX_RAD), att[:, 1:4]))
        e = np.radians(att[keep, 1:4])
        e[:, 2] = (e[:, 2] + np.pi) % (2 * np.pi) - np.pi
        rates = np.zeros_like(e)
        if len(t) > 1:
            rates = np.gradient(np.unwrap(e, axis=0), t, axis=0)
        attitude = AttitudeStream(_frozen(t), _frozen(e), _frozen(rates))
    esc_rows = _df_columns(rows["ESC"], ("TimeUS", "RPM"), bad, "Instance")
    esc_rows = esc_rows[np.isin(esc_rows[:, -1], (0, 1, 2, 3))] if len(esc_rows) else esc_rows
    if len(esc_rows):
        times = np.unique(esc_rows[:, 0])  # sorted; NaN times (if any) each their own row, then dropped
        rpm = np.zeros((len(times), 4))
        rpm[np.searchsorted(times, esc_rows[:, 0]), esc_rows[:, -1].astype(int)] = esc_rows[:, 1]
        t, keep = _monotonic(times / 1e6, "esc", tally, _finite_within(ESC_RPM_MAX, rpm))
        esc = EscStream(_frozen(t), _frozen(rpm[keep]))
    if not counts:
        raise RecordingError(f"{path}: no dataflash records found")
    skipped_bytes = max(int(len(data) - used_bytes), 0)
    ref = None
    if len(log_times) >= 20:  # the span most records of every type agree on (damaged stamps outvoted)
        p5, p95 = np.percentile(np.asarray(log_times, float) / 1e6, [5, 95])
        ref = (float(p5 - 0.1 * (p95 - p5)), float(p95 + 0.1 * (p95 - p5)))
    imu, pressure, servo, attitude, esc = _trim_tails((imu, pressure, servo, attitude, esc), tally, ref)
    skipped_info = Skipped(0, skipped_bytes, 0, 0, tally.nonmono, tuple(tally.gaps), bad[0],
                           tally.out_of_range, tally.bad_time)
    params, changed, dropped = _parameters((r.get("Name"), r.get("Value")) for r in rows["PARM"][-MAX_PARAMETER_ROWS:]
                                           if isinstance(r.get("Name"), str))
    return Recording(str(path), "dataflash", counts, skipped_info, imu, pressure, servo, attitude, esc,
                     parameters=params, parameters_changed=changed,
                     parameters_dropped=dropped + max(len(rows["PARM"]) - MAX_PARAMETER_ROWS, 0))


def _df_columns(rows: list, need: tuple, bad: list, *optional: str) -> np.ndarray:
    """Rows (dicts of DFReader records) as a float array of the `need` columns then the
    `optional` ones (0 when absent, as ArduPilot omits unused RCOU channels and instance 0); a
    record missing a needed column or holding a non-number anywhere used counts in bad[0]."""
    out = []
    for r in rows:
        vals = [r.get(c) for c in need] + [r.get(c, 0) for c in optional]
        if all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in vals):
            out.append(vals)
        else:
            bad[0] += 1
    return np.array(out, dtype=float).reshape(len(out), len(need) + len(optional))
