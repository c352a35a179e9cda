"""Hostile MAVLink messages for every reader in the package (issue 7 part 2), shared by the
fuzz tests of onboard, hil and ground: structurally valid packets of the types a reader reads, with
each field drawn from its wire type's hostile values (NaN, +-inf, +-3.4e38, denormals, integer
extremes, any bytes in a char array). Building them with pymavlink's own constructors and packing
them with its own packer makes every example a packet a real sender could put on the wire.
"""

from __future__ import annotations

import math

from hypothesis import strategies as st
from pymavlink.dialects.v20 import ardupilotmega as mavlink

FLOAT32_MAX = 3.4028234663852886e38
HOSTILE_FLOATS = (math.nan, math.inf, -math.inf, FLOAT32_MAX, -FLOAT32_MAX, 1e-45, -0.0, 0.0, 1.0, -1.0, 1e9)
INT_RANGES = {"int8_t": (-2 ** 7, 2 ** 7 - 1), "uint8_t": (0, 2 ** 8 - 1), "int16_t": (-2 ** 15, 2 ** 15 - 1),
              "uint16_t": (0, 2 ** 16 - 1), "int32_t": (-2 ** 31, 2 ** 31 - 1), "uint32_t": (0, 2 ** 32 - 1),
              "int64_t": (-2 ** 63, 2 ** 63 - 1), "uint64_t": (0, 2 ** 64 - 1)}


def _scalar(ftype: str):
    if ftype == "float":
        return st.one_of(st.sampled_from(HOSTILE_FLOATS), st.floats(width=32))
    if ftype == "double":
        return st.one_of(st.sampled_from(HOSTILE_FLOATS), st.floats())
    lo, hi = INT_RANGES[ftype.replace("_mavlink_version", "")]
    return st.one_of(st.sampled_from(sorted({lo, hi, 0, 1, max(lo, -1), hi // 2})), st.integers(lo, hi))


def _field(ftype: str, n: int):
    if ftype == "char":
        return st.binary(max_size=max(n, 1))
    if n:
        return st.lists(_scalar(ftype), min_size=n, max_size=n)
    return _scalar(ftype)


def hostile(name: str):
    """A strategy of NAME messages (pymavlink objects) with every field hostile."""
    cls = mavlink.mavlink_map[getattr(mavlink, f"MAVLINK_MSG_ID_{name}")]
    length = dict(zip(cls.ordered_fieldnames, cls.array_lengths))  # array_lengths is in wire order
    fields = [_field(t, length[f]) for f, t in zip(cls.fieldnames, cls.fieldtypes)]
    return st.tuples(*fields).map(lambda values: cls(*values))


def hostile_any(names):
    return st.one_of(*(hostile(n) for n in names))


def pack(msg, system: int = 1, component: int = 1, seq: int = 0) -> bytes:
    mav = mavlink.MAVLink(None, srcSystem=system, srcComponent=component)
    mav.seq = seq % 256
    return bytes(msg.pack(mav))


def decoded(packet: bytes):
    """The packet parsed back, as a receiver sees it (fields rounded to their wire types)."""
    mav = mavlink.MAVLink(None)
    mav.robust_parsing = True
    msgs = mav.parse_buffer(packet) or []
    assert len(msgs) == 1 and msgs[0].get_type() != "BAD_DATA", msgs
    return msgs[0]
