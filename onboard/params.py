"""The robot's tunables as MAVLink parameters: one table for the loop, the ground station and the file.

`PARAMS` is the only description of a parameter: its MAVLink name (at most 16 characters, the
PARAM_VALUE.param_id limit), units, the range a set must fall in, where its default comes from and
what it changes in the running loop. The parameter protocol (onboard.microservices) and the
parameter file both read it, so a name or range cannot differ between them.

What is a parameter: what an operator tunes (controller bandwidths and limits, allocation weights,
the IMU failsafe timeout, telemetry stream rates). What is not: the physics the model needs fixed
(mass, geometry, thrust coefficients: the vehicle file), and anything that would need the loop
rebuilt (control rate, allocator kind). Every value travels as MAV_PARAM_TYPE_REAL32, so the
bytewise and C-cast encodings of the parameter protocol are the same bytes.

The parameter file (`Parameters.save` / `load`): one `NAME VALUE` per line, `#` comments, the
format MAVProxy's `param load` / `param save` read and write. Only values that differ from their
default are written, so a default improved in code reaches a robot whose operator never set it.
A bad file (unknown name, a value that is not a number or out of range) is a `ParameterFileError`
naming the file, the line and what was expected.
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass, replace
from pathlib import Path

from .files import read_text_bounded

NAME_MAX = 16  # PARAM_VALUE.param_id: char[16], no terminator when all 16 are used
MAX_FILE_BYTES = 1 << 20
SAVE_PERIOD_S = 1.0  # the parameter file is rewritten at most this often (Parameters.flush)


class ParameterFileError(ValueError):
    """A parameter file that cannot be used; the message names the file, the line and the problem."""


@dataclass(frozen=True)
class ParamSpec:
    name: str  # MAVLink param_id, <= 16 characters, upper case
    group: str  # "controller" (control.Gains), "allocation" (allocation.AllocationConfig),
    #             "failsafe" (failsafe.FailsafeState), "streams" (the ground telemetry rates, Hz)
    field: str  # the attribute in its group (a Gains field, axis_weights[i] as "axis_weights.i", ...)
    lo: float
    hi: float
    units: str
    doc: str

    def __post_init__(self):
        if not (0 < len(self.name) <= NAME_MAX and self.name.isascii() and self.name == self.name.upper()):
            raise ValueError(f"parameter name {self.name!r}: expected 1-{NAME_MAX} upper-case ASCII characters")


AXES = ("SURGE", "SWAY", "HEAVE", "ROLL", "PITCH", "YAW")

PARAMS: tuple[ParamSpec, ...] = (
    ParamSpec("CTL_DEPTH_BW", "controller", "depth_bandwidth_rad_s", 0.1, 6.0, "rad/s", "depth loop bandwidth"),
    ParamSpec("CTL_ATT_BW", "controller", "attitude_bandwidth_rad_s", 0.2, 10.0, "rad/s", "roll/pitch loop bandwidth"),
    ParamSpec("CTL_YAW_BW", "controller", "yaw_bandwidth_rad_s", 0.2, 6.0, "rad/s", "yaw loop bandwidth"),
    ParamSpec("CTL_VEL_BW", "controller", "velocity_bandwidth_rad_s", 0.1, 6.0, "rad/s", "surge/sway loop bandwidth"),
    ParamSpec("CTL_DAMPING", "controller", "damping_ratio", 0.3, 2.0, "", "damping ratio of the position/attitude loops"),
    ParamSpec("CTL_INT_SHARE", "controller", "integral_share", 0.01, 1.0, "", "share of an axis the integrator may use"),
    ParamSpec("CTL_DEPTH_REF", "controller", "depth_reference_rad_s", 0.1, 6.0, "rad/s", "depth setpoint prefilter"),
    ParamSpec("CTL_YAW_REF", "controller", "yaw_reference_rad_s", 0.1, 6.0, "rad/s", "yaw setpoint prefilter"),
    ParamSpec("CTL_VEL_REF", "controller", "velocity_reference_s", 0.05, 5.0, "s", "velocity setpoint time constant"),
    ParamSpec("CTL_DEPTH_RATE", "controller", "max_depth_rate_m_s", 0.02, 1.0, "m/s", "reference heave speed limit"),
    ParamSpec("CTL_YAW_RATE", "controller", "max_yaw_rate_rad_s", 0.05, 3.0, "rad/s", "reference yaw rate limit"),
    ParamSpec("MAN_SPEED", "controller", "manual_speed_m_s", 0.01, 1.5, "m/s", "full-stick surge/sway speed"),
    ParamSpec("MAN_HEAVE", "controller", "manual_heave_m_s", 0.01, 1.0, "m/s", "full-stick heave speed"),
    ParamSpec("MAN_YAW_RATE", "controller", "manual_yaw_rate_rad_s", 0.05, 3.0, "rad/s", "full-stick yaw rate"),
    *(ParamSpec(f"ALLOC_W_{a}", "allocation", f"axis_weights.{i}", 0.0, 1000.0, "",
                f"allocation importance of {a.lower()}") for i, a in enumerate(AXES)),
    ParamSpec("ALLOC_EFFORT", "allocation", "effort_weight", 0.0, 10.0, "", "allocation weight on thrust effort"),
    ParamSpec("ALLOC_CHANGE", "allocation", "change_weight", 0.0, 100.0, "", "allocation weight on command change"),
    ParamSpec("FS_IMU_TIMEOUT", "failsafe", "imu_timeout_s", 0.05, 5.0, "s", "no IMU this long: failsafe"),
    ParamSpec("SR_ATTITUDE", "streams", "ATTITUDE", 0.0, 100.0, "Hz", "ATTITUDE rate to the ground"),
    ParamSpec("SR_NAMED_VALUE", "streams", "NAMED_VALUE_FLOAT", 0.0, 100.0, "Hz", "NAMED_VALUE_FLOAT rate"),
    ParamSpec("SR_WRENCH", "streams", "DEBUG_FLOAT_ARRAY", 0.0, 100.0, "Hz", "DEBUG_FLOAT_ARRAY wrench rate"),
    ParamSpec("SR_SERVO", "streams", "SERVO_OUTPUT_RAW", 0.0, 1000.0, "Hz", "SERVO_OUTPUT_RAW rate to the ground"),
)
BY_NAME = {p.name: p for p in PARAMS}
assert len(BY_NAME) == len(PARAMS), "duplicate parameter name"


def _get(obj, field: str) -> float:
    name, _, index = field.partition(".")
    v = getattr(obj, name)
    return float(v[int(index)] if index else v)


def defaults(gains, allocation_config, imu_timeout_s: float, stream_hz: dict) -> dict:
    """Each parameter's default, from the objects the loop is built with (control.Gains,
    allocation.AllocationConfig, the failsafe timeout, the default stream rates by message name)."""
    out = {}
    for p in PARAMS:
        if p.group == "controller":
            out[p.name] = _get(gains, p.field)
        elif p.group == "allocation":
            out[p.name] = _get(allocation_config, p.field)
        elif p.group == "failsafe":
            out[p.name] = float(imu_timeout_s)
        else:
            out[p.name] = float(stream_hz.get(p.field, 0.0))
    return out


def check(name: str, value) -> str | None:
    """Why `value` cannot be `name` (unknown, not finite, out of range), else None."""
    spec = BY_NAME.get(name)
    if spec is None:
        return f"unknown parameter {name!r}"
    try:
        v = float(value)
    except (TypeError, ValueError):
        return f"{name}: expected a number, got {value!r}"
    if not math.isfinite(v):
        return f"{name}: expected a finite number, got {v}"
    if not spec.lo <= v <= spec.hi:
        unit = f" {spec.units}" if spec.units else ""
        return f"{name} {v:g}{unit}: expected {spec.lo:g}-{spec.hi:g}{unit}"
    return None


def with_values(obj, group: str, values: dict):
    """A copy of a frozen config object (Gains or AllocationConfig) with the group's values set."""
    fields: dict = {}
    weights = None
    for p in PARAMS:
        if p.group != group or p.name not in values:
            continue
        name, _, index = p.field.partition(".")
        if index:
            weights = list(getattr(obj, name)) if weights is None else weights
            weights[int(index)] = float(values[p.name])
            fields[name] = tuple(weights)
        else:
            fields[name] = float(values[p.name])
    return replace(obj, **fields) if fields else obj


class Parameters:
    """The current values, in the table's order (PARAM_VALUE.param_index is the position in
    PARAMS), their defaults, and the file they persist to (None: not persisted)."""

    def __init__(self, default_values: dict, path: str | Path | None = None):
        missing = [p.name for p in PARAMS if p.name not in default_values]
        if missing:
            raise ValueError(f"Parameters: no default for {', '.join(missing)}")
        self.defaults = {p.name: float(default_values[p.name]) for p in PARAMS}
        self.values = dict(self.defaults)
        self.path = Path(path) if path is not None else None
        self.save_errors = 0  # file writes that failed (the values still took effect)
        self.last_save_error: str | None = None  # of the write the last call made, None if none
        self.writes = 0  # file writes attempted
        self._unsaved: str | None = None  # the last name set and not yet written, if any
        self._next_write = -math.inf  # time.monotonic() before which the file is not rewritten
        if self.path is not None and self.path.exists():
            self.values.update(load(self.path))

    @property
    def count(self) -> int:
        return len(PARAMS)

    def index(self, name: str) -> int:
        return [p.name for p in PARAMS].index(name)

    def by_index(self, i: int) -> ParamSpec | None:
        return PARAMS[i] if 0 <= i < len(PARAMS) else None

    def changed(self) -> dict:
        """Values that differ from their defaults (what the file holds)."""
        return {k: v for k, v in self.values.items() if v != self.defaults[k]}

    def set(self, name: str, value: float) -> str | None:
        """Set and persist one value; why not (nothing changed), else None. The file is written at
        once if it was not in the last SAVE_PERIOD_S, else by a later `flush` (the loop's 1 Hz
        tick, and its stop): a flood of sets is not a file write each. A file that cannot be
        written leaves the value set and says so in `last_save_error`."""
        why = check(name, value)
        if why is not None:
            return why
        self.values[name] = float(value)
        self._unsaved = name
        self.flush()
        return None

    def flush(self, force: bool = False) -> str | None:
        """Write the values set since the last write, if any, and if the last write is
        SAVE_PERIOD_S old (`force`: now); why the write failed, else None."""
        self.last_save_error = None
        if self.path is None or self._unsaved is None:
            return None
        now = time.monotonic()
        if not force and now < self._next_write:
            return None
        name, self._unsaved = self._unsaved, None
        self._next_write = now + SAVE_PERIOD_S
        self.writes += 1
        try:
            save(self.path, self.changed())
        except OSError as exc:
            self.save_errors += 1
            self.last_save_error = f"{name} not saved: {exc.strerror or exc}"
        return self.last_save_error


def load(path: str | Path) -> dict:
    """{name: value} from a parameter file (`NAME VALUE` or `NAME,VALUE` per line, # comments)."""
    path = Path(path)
    try:
        text = read_text_bounded(path, MAX_FILE_BYTES)
    except (OSError, UnicodeDecodeError) as exc:
        raise ParameterFileError(f"{path}: cannot read parameter file: {getattr(exc, 'strerror', None) or exc}") from exc
    out = {}
    for n, line in enumerate(text.splitlines(), 1):
        line = line.split("#", 1)[0].strip()
        if not line:
            continue
        parts = line.replace(",", " ").split()
        if len(parts) != 2:
            raise ParameterFileError(f"{path}:{n}: expected NAME VALUE, got {line[:60]!r}")
        why = check(parts[0], parts[1])
        if why is not None:
            raise ParameterFileError(f"{path}:{n}: {why[:120]}")
        out[parts[0]] = float(parts[1])
    return out


def save(path: str | Path, values: dict) -> None:
    """Write `values` atomically (a temporary file renamed over the old one)."""
    path = Path(path)
    lines = ["# jetloop parameters (onboard/params.py): values that differ from the defaults",
             *(f"{name} {values[name]:.9g}" for name in (p.name for p in PARAMS) if name in values)]
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_text("\n".join(lines) + "\n")
    os.replace(tmp, path)


def default_path(vehicle_path: str | Path | None) -> Path:
    """The parameter file beside the vehicle file (`V.toml` -> `V.params`); for the packaged
    reference vehicle, `asr4.params` in the working directory (the package is not the user's)."""
    if vehicle_path is None:
        return Path("asr4.params")
    return Path(vehicle_path).with_suffix(".params")
