"""Vehicle files: TOML in, frozen, validated parameter objects out (spec/vehicle-model.md).

Field names are the vehicle-file keys themselves, so a fitted value keyed `hydro.added_mass`
can be pasted back into the file; the units of every key are those of the spec and of the
reference file `onboard/data/asr4.toml`, and each field's metadata says them.

Every key is checked: an unknown or missing key, a wrong length, a negative mass, a NaN or an
angle limit over pi raises `VehicleFileError` naming the file, the key and what was expected.

One section is optional: `[envelope]`, the setpoints the robot accepts from the ground
(`onboard.envelope` checks SET_POSITION_TARGET_LOCAL_NED and MANUAL_CONTROL against it). Each of
its keys may be left out and then takes the default below, chosen for the 0.32 m ASR-IV sphere;
a key that is present is checked like any other:

    max_depth_m         m below the surface   2.0  (above the 1.2 m pool of seed 003, with margin)
    min_depth_m         m below the surface   0.0  (the surface: no depth setpoint above the water)
    max_speed_m_s       m/s, horizontal       1.0  (seed 000: "the largest velocity of ASR-IV (1 m/s)")
    max_heave_speed_m_s m/s, vertical         0.5  (twice the controller's 0.25 m/s reference limit)
    max_yaw_rate_rad_s  rad/s                 1.0  (above the controller's 0.8 rad/s reference limit)
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .files import read_text_bounded

try:  # Python 3.11+
    import tomllib
except ModuleNotFoundError:  # pragma: no cover - Python 3.10
    import tomli as tomllib

DEFAULT_VEHICLE = Path(__file__).parent / "data" / "asr4.toml"
MAX_NAME = 64  # characters of a vehicle name
MAX_FILE_BYTES = 1_000_000  # a vehicle file is a few kB: larger (or a device, a pipe) is refused unread
MAX_PROBLEMS_SHOWN = 20  # an error lists this many problems and counts the rest

EFFECT_IDS = (
    "thrust_inflow",
    "motor_lag",
    "servo_lag",
    "azimuth_transient",
    "surface_proximity",
    "wall_proximity",
    "current",
)


class VehicleFileError(ValueError):
    """A vehicle file that cannot be used; the message names the file, key and expectation."""


# --- key declarations --------------------------------------------------------------------------
# A field's metadata says what the key must hold: `n` (vector length, None for a scalar),
# `check` (one of the CHECKS below), `unit` (for messages and docs).

def _key(unit: str, check: str = "finite", n: int | None = None, default: Any = dataclasses.MISSING,
         lo: float | None = None, hi: float | None = None, hint: str = "", per: str = "unit",
         rows: bool = False):
    """`lo`..`hi`: the plausible range of the key (of each element of a vector), in `unit`;
    `hint` is said when a value is out of it (the usual slip: grams for kg, rpm for rev/s).
    `n = -1`: a list of any length, "one per `per`"; `rows`: a list of such lists."""
    return field(default=default, metadata={"unit": unit, "check": check, "n": n, "per": per, "rows": rows,
                                            "range": (lo, hi, hint) if lo is not None else None})


CHECKS = {
    "finite": (lambda v: True, "a finite number"),
    "positive": (lambda v: v > 0, "a finite number > 0"),
    "nonneg": (lambda v: v >= 0, "a finite number >= 0"),
    "angle": (lambda v: 0 < v <= math.pi, "an angle in radians, 0 < value <= pi"),
    "pwm": (lambda v: 500 <= v <= 2500, "a PWM width in microseconds (500..2500)"),
    "channel": (lambda v: 1 <= v <= 16 and float(v).is_integer(), "a channel number 1..16"),
}


@dataclass(frozen=True)
class Environment:
    rho: float = _key("kg/m^3", "positive", lo=500.0, hi=2000.0, hint="g/cm^3?")
    g: float = _key("m/s^2", "positive", lo=1.0, hi=30.0)
    p_atm: float = _key("Pa", "positive", lo=1e4, hi=2e5, hint="hPa or kPa?")
    surface_depth: float = _key("m", lo=-100.0, hi=100.0)
    floor_depth: float = _key("m", lo=-100.0, hi=12000.0)
    current: tuple = _key("m/s NED", "finite", 3, lo=-10.0, hi=10.0)


@dataclass(frozen=True)
class Body:
    mass: float = _key("kg", "positive", lo=0.1, hi=1000.0, hint="grams?")
    volume: float = _key("m^3", "positive", lo=1e-5, hi=2.0, hint="litres?")
    radius: float = _key("m", "positive", lo=0.01, hi=5.0, hint="cm or mm?")
    inertia: tuple = _key("kg m^2 (Ixx, Iyy, Izz about the CG)", "positive", 3, lo=1e-6, hi=1e4, hint="g cm^2?")
    cg: tuple = _key("m body FRD", "finite", 3, lo=-5.0, hi=5.0, hint="cm or mm?")
    cb: tuple = _key("m body FRD", "finite", 3, lo=-5.0, hi=5.0, hint="cm or mm?")


@dataclass(frozen=True)
class Hydro:
    added_mass: tuple = _key("kg, kg m^2 [surge..yaw]", "nonneg", 6, lo=0.0, hi=1e4)
    linear_damping: tuple = _key("N s/m, N m s/rad [surge..yaw]", "nonneg", 6, lo=0.0, hi=1e5)
    quadratic_damping: tuple = _key("N s^2/m^2, N m s^2/rad^2 [surge..yaw]", "nonneg", 6, lo=0.0, hi=1e5)


@dataclass(frozen=True)
class Thruster:
    diameter: float = _key("m", "positive", lo=1e-3, hi=2.0, hint="mm?")
    kt: tuple = _key("K(J) coefficients [kt0, kt1, kt2]", "finite", 3, lo=-10.0, hi=10.0)
    j_range: tuple = _key("advance ratio [min, max]", "finite", 2, lo=-10.0, hi=10.0)
    n_max: float = _key("rev/s", "positive", lo=0.1, hi=2000.0, hint="rpm? expected rev/s")
    motor_time_constant: float = _key("s", "positive", lo=1e-4, hi=10.0, hint="ms?")


@dataclass(frozen=True)
class Servo:
    angle_limit: float = _key("rad", "angle")
    rate_limit: float = _key("rad/s", "positive", lo=0.01, hi=100.0, hint="deg/s?")
    time_constant: float = _key("s", "positive", lo=1e-4, hi=10.0, hint="ms?")


@dataclass(frozen=True)
class Unit:
    position: tuple = _key("m body FRD", "finite", 3, lo=-5.0, hi=5.0, hint="cm or mm?")
    neutral: tuple = _key("unit vector body FRD", "finite", 3)


@dataclass(frozen=True)
class FixedUnit:
    """[[fixed]]: a fixed two-way thruster (spec 3.1): where it is and which way positive thrust
    pushes the vehicle (a unit vector, body FRD)."""

    position: tuple = _key("m body FRD", "finite", 3, lo=-5.0, hi=5.0, hint="cm or mm?")
    direction: tuple = _key("unit vector body FRD", "finite", 3)


@dataclass(frozen=True)
class FixedThruster:
    """[fixed_thruster]: the thrust curve and motor lag shared by every [[fixed]] thruster.

    Either a table (`table_pwm` increasing, `table_thrust` one row of newtons per entry of
    `table_voltages`, `voltage` the supply: columns interpolated linearly between voltages) or
    coefficients (`dead_band`, `forward`, `reverse`: outside the dead band, with s the fraction
    of the way from its edge to the end of `pwm_range`, T = c1 s + c2 s^2 forward and
    -(c1 s + c2 s^2) in reverse). `time_constant`: first-order lag of the thrust (`motor_lag`).
    """

    time_constant: float = _key("s", "positive", lo=1e-4, hi=10.0, hint="ms?")
    pwm_range: tuple = _key("us [low, high]", "pwm", 2)
    voltage: float | None = _key("V", "positive", default=None, lo=1.0, hi=1000.0)
    table_voltages: tuple | None = _key("V", "positive", -1, default=None, lo=1.0, hi=1000.0,
                                        per="row of table_thrust")
    table_pwm: tuple | None = _key("us, increasing", "pwm", -1, default=None, per="table point")
    table_thrust: tuple | None = _key("N", "finite", -1, default=None, lo=-1e5, hi=1e5,
                                      per="table point", rows=True)
    dead_band: tuple | None = _key("us [low, high]", "pwm", 2, default=None)
    forward: tuple | None = _key("N [c1, c2]", "finite", 2, default=None, lo=-1e5, hi=1e5)
    reverse: tuple | None = _key("N [c1, c2]", "finite", 2, default=None, lo=-1e5, hi=1e5)

    @property
    def kind(self) -> str:
        return "table" if self.table_pwm is not None else "coefficients"


@dataclass(frozen=True)
class Pwm:
    """[pwm]: which channel drives what. A vehicle without jets leaves the jet keys out; one
    without fixed thrusters leaves `fixed_channels` out. `jet_neutral` (optional): the width at
    which a one-way jet stops, for an autopilot whose motor outputs are two-way with 1500 us as
    neutral (ArduSub): jet_neutral..jet_range[1] -> 0..n_max, below it 0. Absent: jet_range[0]."""

    jet_channels: tuple = _key("channel numbers, one per unit", "channel", -1, default=())
    azimuth_channels: tuple = _key("channel numbers, one per unit", "channel", -1, default=())
    elevation_channels: tuple = _key("channel numbers, one per unit", "channel", -1, default=())
    jet_range: tuple = _key("us [low, high]", "pwm", 2, default=(1100.0, 1900.0))
    servo_range: tuple = _key("us [low, high]", "pwm", 2, default=(1100.0, 1900.0))
    jet_neutral: float | None = _key("us", "pwm", default=None)
    fixed_channels: tuple = _key("channel numbers, one per [[fixed]] thruster", "channel", -1, default=(),
                                 per="[[fixed]] thruster")


@dataclass(frozen=True)
class Sensors:
    imu_rate: float = _key("Hz", "positive", lo=1.0, hi=4000.0)
    gyro_noise: float = _key("rad/s", "nonneg", lo=0.0, hi=1.0, hint="deg/s?")
    accel_noise: float = _key("m/s^2", "nonneg", lo=0.0, hi=10.0)
    pressure_rate: float = _key("Hz", "positive", lo=0.1, hi=1000.0)
    pressure_noise: float = _key("Pa", "nonneg", lo=0.0, hi=1e4)
    attitude_rate: float = _key("Hz", "positive", lo=0.1, hi=1000.0)
    attitude_noise: float = _key("rad", "nonneg", lo=0.0, hi=1.0, hint="degrees?")
    gyro_bias: tuple = _key("rad/s", "finite", 3, lo=-1.0, hi=1.0, hint="deg/s?")
    accel_bias: tuple = _key("m/s^2", "finite", 3, lo=-10.0, hi=10.0)
    delay: float = _key("s", "nonneg", lo=0.0, hi=2.0, hint="ms?")


@dataclass(frozen=True)
class Envelope:
    """[envelope] (optional, every key defaulted): what a ground setpoint may ask (onboard.envelope)."""

    max_depth_m: float = _key("m below the surface", "positive", default=2.0, lo=0.0, hi=12000.0)
    min_depth_m: float = _key("m below the surface", "finite", default=0.0, lo=-100.0, hi=12000.0)
    max_speed_m_s: float = _key("m/s, horizontal", "positive", default=1.0, lo=0.0, hi=20.0)
    max_heave_speed_m_s: float = _key("m/s", "positive", default=0.5, lo=0.0, hi=20.0)
    max_yaw_rate_rad_s: float = _key("rad/s", "positive", default=1.0, lo=0.0, hi=20.0, hint="deg/s?")


@dataclass(frozen=True)
class Effect:
    enabled: bool = _key("", "bool")


@dataclass(frozen=True)
class AzimuthTransient:
    enabled: bool = _key("", "bool")
    gain_per_newton: float = _key("1/N", "nonneg", lo=0.0, hi=1.0)
    f1x: tuple = _key("seed 004 eq. 5 [K, a, b, c, d, e, g]", "finite", 7, lo=-1e7, hi=1e7)
    f1y: tuple = _key("seed 004 eq. 5 [K, a, b, c, d, e, g]", "finite", 7, lo=-1e7, hi=1e7)
    m1z: tuple = _key("seed 004 eq. 6 [K, a, b, c, d]", "finite", 5, lo=-1e7, hi=1e7)
    f2x: tuple = _key("seed 004 eq. 5 [K, a, b, c, d, e, g]", "finite", 7, lo=-1e7, hi=1e7)
    f2z: tuple = _key("seed 004 eq. 5 [K, a, b, c, d, e, g]", "finite", 7, lo=-1e7, hi=1e7)


@dataclass(frozen=True)
class WallProximity:
    enabled: bool = _key("", "bool")
    k_wall: float = _key("dimensionless", "nonneg", lo=0.0, hi=100.0)


@dataclass(frozen=True)
class Effects:
    thrust_inflow: Effect
    motor_lag: Effect
    servo_lag: Effect
    azimuth_transient: AzimuthTransient
    surface_proximity: Effect
    wall_proximity: WallProximity
    current: Effect

    def on(self, effect_id: str) -> bool:
        return getattr(self, effect_id).enabled


@dataclass(frozen=True)
class Vehicle:
    name: str
    environment: Environment
    body: Body
    hydro: Hydro
    thruster: Thruster
    servo: Servo
    units: tuple  # of Unit
    pwm: Pwm
    sensors: Sensors
    effects: Effects
    source: str = "<memory>"
    envelope: Envelope = Envelope()  # optional [envelope]: absent, every key takes its default
    fixed: tuple = ()  # of FixedUnit: [[fixed]] two-way thrusters (spec 3.1), after the jets
    fixed_thruster: FixedThruster | None = None  # [fixed_thruster], present when `fixed` is

    @property
    def n_units(self) -> int:
        """Every actuator unit: the vectored jets ([[unit]]) first, then the fixed thrusters."""
        return len(self.units) + len(self.fixed)

    @property
    def n_jets(self) -> int:
        return len(self.units)

    @property
    def unit_kinds(self) -> tuple:
        """"jet" or "fixed" for every unit, in command order."""
        return ("jet",) * len(self.units) + ("fixed",) * len(self.fixed)

    @property
    def unit_positions(self) -> tuple:
        """r_i of every unit (jets, then fixed thrusters), body FRD."""
        return tuple(u.position for u in self.units) + tuple(f.position for f in self.fixed)

    def get(self, key: str) -> Any:
        """Value of a dotted vehicle-file key, e.g. `hydro.added_mass`."""
        obj: Any = self
        for part in key.split("."):
            obj = getattr(obj, "units" if part == "unit" else part)
        return obj

    def with_values(self, values: dict[str, Any]) -> "Vehicle":
        """A new vehicle with dotted keys replaced (validated like a file), e.g. a fitted fragment."""
        out = self
        for key, value in values.items():
            out = _replace_path(out, key.split("."), value, key)
        err = _Errors(out.source)  # cross-key rules too (unit neutral, channel counts, ranges)
        _check_consistency(out, err)
        err.raise_if_any()
        return out

    def with_effects(self, **enabled: bool) -> "Vehicle":
        """A new vehicle with effects switched on or off by id."""
        return self.with_values({f"effects.{k}.enabled": bool(v) for k, v in enabled.items()})


SECTIONS = {
    "environment": Environment,
    "body": Body,
    "hydro": Hydro,
    "thruster": Thruster,
    "servo": Servo,
    "pwm": Pwm,
    "sensors": Sensors,
    "envelope": Envelope,
}
OPTIONAL_SECTIONS = frozenset({"envelope"})  # may be left out; their keys have defaults
# A vehicle with only fixed thrusters has no jets and no joints: [thruster] and [servo] may be
# left out and then hold these stand-ins, which no term reads (no unit is a jet).
NO_JETS = {
    "thruster": {"diameter": 0.1, "kt": [0.0, 0.0, 0.0], "j_range": [0.0, 1.0], "n_max": 1.0,
                 "motor_time_constant": 0.1},
    "servo": {"angle_limit": 1.0, "rate_limit": 1.0, "time_constant": 0.1},
}
EFFECT_CLASSES = {
    eid: {"azimuth_transient": AzimuthTransient, "wall_proximity": WallProximity}.get(eid, Effect)
    for eid in EFFECT_IDS
}


# --- loading -----------------------------------------------------------------------------------

def load_vehicle(path: str | Path | None = None) -> Vehicle:
    """Load and validate a vehicle TOML (default: the reference vehicle asr4). A bare name that
    is no file here but a packaged vehicle (`bluerov2_heavy`, `asr4`) loads that one."""
    path = Path(path) if path is not None else DEFAULT_VEHICLE
    packaged = DEFAULT_VEHICLE.parent / f"{path.name}.toml"
    if not path.exists() and path.parent == Path(".") and not path.suffix and packaged.is_file():
        path = packaged
    try:
        text = read_text_bounded(path, MAX_FILE_BYTES)  # a byte-order mark (Windows editors) is not content
    except (OSError, UnicodeDecodeError) as exc:  # not UTF-8 text: a clear error, not a traceback
        raise VehicleFileError(f"{path}: cannot read vehicle file: {getattr(exc, 'strerror', None) or exc}") from exc
    return parse_vehicle(text, source=str(path))


def require_jets(v: Vehicle, command: str) -> Vehicle:
    """`v` if its actuators are vectored jets only; else a one-line VehicleFileError saying who flies
    it instead. The onboard loop is written for one kind of actuator: its allocator plans jet forces
    inside each joint's travel window, its transient compensation cancels the forces of moving
    joints, its monitor judges each jet by its speed model. A vehicle of fixed thrusters only is
    flown by its autopilot; one that mixes both kinds is simulated (`jetloop sim`, `jetloop hil`)
    but not flown onboard (README, "Mixed vehicles")."""
    if not v.n_jets:
        raise VehicleFileError(
            f"{v.source}: {v.name} has fixed thrusters only: `jetloop {command}` runs the onboard loop, which "
            "flies vectored water-jets; fly it with its autopilot (ArduSub SITL: jetloop hil --json-sitl)")
    if v.fixed:
        raise VehicleFileError(
            f"{v.source}: {v.name} mixes {v.n_jets} vectored jets with {len(v.fixed)} fixed thrusters: `jetloop "
            f"{command}` runs the onboard loop, which flies one kind of actuator (jets or, through an autopilot, "
            "fixed thrusters); a mixed vehicle can be simulated (jetloop sim, jetloop hil) but not flown onboard")
    return v


def parse_vehicle(text: str, source: str = "<string>") -> Vehicle:
    """Parse vehicle TOML text; every error names `source`, the key and what was expected."""
    try:
        doc = tomllib.loads(text.removeprefix("\ufeff"))
    except tomllib.TOMLDecodeError as exc:
        raise VehicleFileError(f"{source}: not valid TOML: {exc}") from exc
    except RecursionError:  # thousands of nested brackets: tomllib recurses
        raise VehicleFileError(f"{source}: not a vehicle file: arrays or tables nested too deeply") from None
    return vehicle_from_dict(doc, source)


def vehicle_from_dict(doc: dict, source: str = "<dict>") -> Vehicle:
    err = _Errors(source)
    top = {"name", "unit", "fixed", "fixed_thruster", "effects", *SECTIONS}
    for key in doc:
        if key not in top:
            err.unknown(key, sorted(top))
    name = doc.get("name")
    if not isinstance(name, str) or not name or not name.isprintable() or len(name) > MAX_NAME:
        # printed on terminals and in reports: a control character (an escape sequence) is refused
        err.add("name", f"a non-empty string of at most {MAX_NAME} printable characters", name)
    raw_units = doc.get("unit")
    raw_fixed = doc.get("fixed")
    jetless = raw_units is None and raw_fixed is not None
    sections = {}
    for sec, cls in SECTIONS.items():
        absent = {} if sec in OPTIONAL_SECTIONS else NO_JETS.get(sec) if jetless else None
        sections[sec] = _build(cls, doc.get(sec, absent), sec, err)
    units = []
    if not jetless and (not isinstance(raw_units, list) or not raw_units):
        err.add("unit", "one or more [[unit]] (vectored jet) or [[fixed]] (fixed thruster) tables", raw_units)
    elif not jetless:
        for i, raw in enumerate(raw_units):
            units.append(_build(Unit, raw, f"unit[{i}]", err))
    fixed = []
    fixed_thruster = None
    if raw_fixed is not None:
        if not isinstance(raw_fixed, list) or not raw_fixed:
            err.add("fixed", "one or more [[fixed]] tables", raw_fixed)
        else:
            for i, raw in enumerate(raw_fixed):
                fixed.append(_build(FixedUnit, raw, f"fixed[{i}]", err))
        fixed_thruster = _build(FixedThruster, doc.get("fixed_thruster"), "fixed_thruster", err)
    elif "fixed_thruster" in doc:
        err.add("fixed_thruster", "[[fixed]] thrusters for it to describe (or no [fixed_thruster])",
                doc.get("fixed_thruster"))
    raw_effects = doc.get("effects")
    effects = {}
    if not isinstance(raw_effects, dict):
        err.add("effects", "an [effects.*] table for each effect id: " + ", ".join(EFFECT_IDS), raw_effects)
    else:
        for key in raw_effects:
            if key not in EFFECT_CLASSES:
                err.unknown(f"effects.{key}", list(EFFECT_IDS))
        for eid, cls in EFFECT_CLASSES.items():
            effects[eid] = _build(cls, raw_effects.get(eid), f"effects.{eid}", err)
    err.raise_if_any()
    vehicle = Vehicle(
        name=name, units=tuple(units), effects=Effects(**effects), source=source,
        fixed=tuple(fixed), fixed_thruster=fixed_thruster, **sections
    )
    _check_consistency(vehicle, err)
    err.raise_if_any()
    return vehicle


def _build(cls, raw, where: str, err: "_Errors"):
    if not isinstance(raw, dict):
        err.add(where, f"a table with keys {', '.join(f.name for f in dataclasses.fields(cls))}", raw)
        return None
    names = {f.name for f in dataclasses.fields(cls)}
    for key in raw:
        if key not in names:
            err.unknown(f"{where}.{key}", sorted(names))
    values = {}
    for f in dataclasses.fields(cls):
        key = f"{where}.{f.name}"
        if f.name not in raw and f.default is not dataclasses.MISSING:
            values[f.name] = f.default  # an optional key ([envelope]) left out
            continue
        if f.name not in raw:
            err.add(key, f"{_expect(f)} ({f.metadata['unit']})".replace(" ()", ""), None, missing=True)
            continue
        ok, value = _coerce(raw[f.name], f)
        if not ok:
            err.add(key, _expect(f), raw[f.name])
        values[f.name] = value
    return cls(**values) if len(values) == len(names) else None


def _expect(f) -> str:
    check, n = f.metadata["check"], f.metadata["n"]
    if check == "bool":
        return "true or false"
    what = CHECKS[check][1]
    if n is None:
        return what
    if f.metadata.get("rows"):  # "each" before the check's words: "a channel number 1..16s" read badly
        return f"a list of lists of values, each {what}, a list per {f.metadata['per']}"
    if n == -1:
        return f"a list of values, each {what}, one per {f.metadata.get('per', 'unit')}"
    return f"a list of {n} values, each {what}"


def _coerce(value, f):
    check, n = f.metadata["check"], f.metadata["n"]
    if check == "bool":
        return isinstance(value, bool), value
    if n is None:
        ok = _number_ok(value, check)
        return ok, float(value) if ok else value
    if f.metadata.get("rows"):
        if not isinstance(value, list) or not value or not all(
                isinstance(r, list) and r and all(_number_ok(v, check) for v in r) for r in value):
            return False, value
        return True, tuple(tuple(float(v) for v in r) for r in value)
    if not isinstance(value, list) or (n != -1 and len(value) != n) or not value:
        return False, value
    if not all(_number_ok(v, check) for v in value):
        return False, value
    return True, tuple(int(v) if check == "channel" else float(v) for v in value)


def _number_ok(v, check) -> bool:
    if isinstance(v, bool) or not isinstance(v, (int, float)):
        return False
    if isinstance(v, int) and not -2 ** 1023 < v < 2 ** 1023:  # a 400-digit integer: no float holds it
        return False
    return math.isfinite(v) and CHECKS[check][0](v)


def _check_ranges(v: Vehicle, err: "_Errors") -> None:
    """Every key within its plausible range (field metadata `range`), the units in the message."""
    def walk(obj, where):
        for f in dataclasses.fields(obj):
            rng = f.metadata.get("range")
            value = getattr(obj, f.name)
            if rng is None or value is None:
                continue
            lo, hi, hint = rng
            values = value if isinstance(value, tuple) else (value,)
            if values and isinstance(values[0], tuple):  # a table: rows of values
                values = tuple(x for row in values for x in row)
            bad = [x for x in values if not lo <= x <= hi]
            if bad:
                full = f.metadata["unit"]
                compound = any(c in full for c in "[(,")  # e.g. "kg, kg m^2 [surge..yaw]"
                unit = "" if compound or full == "dimensionless" else " " + full.split(" ")[0]
                span = f"{lo:g}-{hi:g}" if lo >= 0 else f"{lo:g} to {hi:g}"
                err.lines.append(f"{where}{f.name} {bad[0]:.6g}{unit}: expected {span}{unit}"
                                 f"{' for each element' if isinstance(value, tuple) else ''}"
                                 f"{f' ({full})' if compound else ''}{'; ' + hint if hint else ''}")

    for sec in SECTIONS:
        walk(getattr(v, sec), f"{sec}.")
    for i, u in enumerate(v.units):
        walk(u, f"unit[{i}].")
    for i, u in enumerate(v.fixed):
        walk(u, f"fixed[{i}].")
    if v.fixed_thruster is not None:
        walk(v.fixed_thruster, "fixed_thruster.")
    for eid in EFFECT_IDS:
        walk(getattr(v.effects, eid), f"effects.{eid}.")


def _check_full_rank(v: Vehicle, err: "_Errors") -> None:
    """The units together must be able to push and turn the body about every axis: the wrench
    map B = [f_i; r_i x f_i] over every unit's force (spec 3) has rank 6, which needs at least
    three units not on one line. (All units at one point gave a LinAlgError in the allocation.)"""
    import numpy as np

    pos = np.array(v.unit_positions, float)
    r = pos - pos.mean(axis=0)
    scale = max(float(np.abs(r).max()), 1e-12)
    blocks = []
    for i, ri in enumerate(r / scale):  # moments in units of the layout's size: a scale-free test
        skew = np.array([[0, -ri[2], ri[1]], [ri[2], 0, -ri[0]], [-ri[1], ri[0], 0]])
        block = np.vstack([np.eye(3), skew])
        if i >= v.n_jets:  # a fixed thruster pushes along its direction only (spec 3.1)
            block = block @ np.asarray(v.fixed[i - v.n_jets].direction, float)[:, None]
        blocks.append(block)
    sv = np.linalg.svd(np.hstack(blocks), compute_uv=False)
    if len(sv) < 6 or sv[5] < 1e-3 * sv[0] or float(np.abs(r).max()) < 1e-3:
        what = "units" if not v.fixed else "units and fixed thrusters"
        err.lines.append(
            f"unit: the {what} cannot produce every force and moment (their wrench map has rank < 6): "
            "give at least three units at positions not on one line, at least 1 mm apart"
            + ("; fixed thrusters must push along at least six independent force-moment directions" if v.fixed else ""))


BUOYANCY_RATIO = (0.5, 2.0)  # rho V / m of a vehicle that dives and surfaces on its thrusters
HULL_FILL = (0.01, 20.0)  # V / (4/3 pi radius^3): the displaced volume against the sphere of the
# file's radius (asr4's floodable hull 0.39, bluerov2_heavy's sphere of its volume 1.0). A hostile
# user's find (2026-12-02): radius 5 m or 1 cm with asr4's 6.65 litres passed, and the surface
# crossing (spec: s = h^2 (3R - h) / 4R^3) of a 5 m sphere at 0.4 m depth is half out of the water


MIN_JET_THRUST_N = 1e-3  # a jet's thrust at full speed below this is a jet that pushes nothing


def _check_plausible(v: Vehicle, err: "_Errors") -> None:
    """What each key's range cannot see (issue 15, second pass: thrust coefficients of zero, or a
    1000 kg vehicle of the stock 6.65 litres, passed): buoyancy against weight rho V / m within
    `BUOYANCY_RATIO`, the volume against the sphere of the radius within `HULL_FILL`, and the
    jets' thrust coefficient K(J) (seed 000 eq. 15) positive over the advance ratios of the fit
    (`j_range`; a fixed-thruster vehicle's stand-in has no jets)."""
    ratio = v.environment.rho * v.body.volume / v.body.mass
    if not BUOYANCY_RATIO[0] <= ratio <= BUOYANCY_RATIO[1]:
        err.lines.append(f"body.mass {v.body.mass:g} kg with body.volume {v.body.volume:g} m^3: buoyancy/weight "
                         f"rho V / m {ratio:.3g}: expected {BUOYANCY_RATIO[0]:g}-{BUOYANCY_RATIO[1]:g} "
                         "(near neutral); grams? litres?")
    fill = v.body.volume / (4.0 / 3.0 * math.pi * v.body.radius ** 3)
    if not HULL_FILL[0] <= fill <= HULL_FILL[1]:
        err.lines.append(f"body.radius {v.body.radius:g} m with body.volume {v.body.volume:g} m^3: the volume fills "
                         f"{fill:.3g} of the radius' sphere ({'over' if fill > HULL_FILL[1] else 'under'} the limit): expected {HULL_FILL[0]:g}-{HULL_FILL[1]:g} "
                         "(the hull sphere's radius); a length? cm?")
    if v.n_jets:
        k0, k1, k2 = v.thruster.kt
        lo, hi = v.thruster.j_range
        js = [lo, hi] + ([-k1 / (2 * k2)] if k2 > 0 and lo < -k1 / (2 * k2) < hi else [])
        j = min(js, key=lambda x: k0 + k1 * x + k2 * x * x)
        k = k0 + k1 * j + k2 * j * j
        t = v.environment.rho * v.thruster.n_max ** 2 * v.thruster.diameter ** 4 * k  # seed 000 eq. 15
        if not k > 0:
            err.lines.append(f"thruster.kt [{k0:g}, {k1:g}, {k2:g}]: K(J) {k:.3g} at J = {j:.3g}: expected "
                             f"K(J) > 0 over j_range [{lo:g}, {hi:g}] (a jet that pushes nothing, or backwards)")
        elif not t >= MIN_JET_THRUST_N:  # positive but nothing: 1e-300 squared is 0 in the allocation's weights
            err.lines.append(f"thruster.kt [{k0:g}, {k1:g}, {k2:g}]: a jet's thrust at n_max is {t:.3g} N at J = "
                             f"{j:.3g}: expected at least {MIN_JET_THRUST_N:g} N (a jet that pushes nothing)")


def _transient_stable(row: str, coeffs) -> bool:
    """Whether a seed-004 row's denominator (onboard.model.transfer_function) has every pole in
    the left half plane. Force rows, eq. 5, (s^2 + c s + d)(s^2 + e s + g): c, d, e, g > 0.
    Moment row, eq. 6, s^4 + a s^3 + b s^2 + c s + d: Routh-Hurwitz for a quartic, a, b, c,
    d > 0, a b > c and a b c > c^2 + a^2 d."""
    if row == "m1z":
        _, a, b, c, d = coeffs
        return a > 0 and b > 0 and c > 0 and d > 0 and a * b > c and a * b * c > c * c + a * a * d
    _, _, _, c, d, e, g = coeffs
    return c > 0 and d > 0 and e > 0 and g > 0


def _check_transients(v: Vehicle, err: "_Errors") -> None:
    """With the azimuth transient on, its five rows must be stable transfer functions (seed 004's
    are): a zero or unstable denominator passed every range and then made the onboard loop die on
    a LinAlgError or an unstable yaw-preview plan (issue 15, adversarial re-run), and the plant
    diverge (the transient of a joint that stopped rotating grew for ever)."""
    at = v.effects.azimuth_transient
    if not at.enabled or not v.n_jets:
        return
    for row in ("f1x", "f1y", "m1z", "f2x", "f2z"):
        coeffs = getattr(at, row)
        if not _transient_stable(row, coeffs):
            err.lines.append(f"effects.azimuth_transient.{row} [{', '.join(f'{x:g}' for x in coeffs)}]: "
                             "a pole with Re >= 0: expected a stable transient (seed 004), or enabled = false")


def _check_consistency(v: Vehicle, err: "_Errors") -> None:
    _check_ranges(v, err)
    if not err.lines:
        _check_full_rank(v, err)
        _check_plausible(v, err)
        _check_transients(v, err)
    n = v.n_jets
    for key in ("jet_channels", "azimuth_channels", "elevation_channels"):
        if len(getattr(v.pwm, key)) != n:
            err.add(f"pwm.{key}", f"{n} channels, one per [[unit]]", list(getattr(v.pwm, key)))
    if len(v.pwm.fixed_channels) != len(v.fixed):
        err.add("pwm.fixed_channels", f"{len(v.fixed)} channels, one per [[fixed]] thruster",
                list(v.pwm.fixed_channels))
    first_use: dict[int, str] = {}  # a channel drives one joint or jet: name where it repeats
    for key in ("jet_channels", "azimuth_channels", "elevation_channels", "fixed_channels"):
        for c in getattr(v.pwm, key):
            if c in first_use:
                err.add(f"pwm.{key}", f"each channel used once (channel {c} is already in "
                        f"{first_use[c]})", list(getattr(v.pwm, key)))
            first_use.setdefault(c, f"pwm.{key}")
    for key in ("jet_range", "servo_range"):
        lo, hi = getattr(v.pwm, key)
        if not lo < hi:
            err.add(f"pwm.{key}", "[low, high] with low < high", [lo, hi])
    if v.pwm.jet_neutral is not None and not v.pwm.jet_range[0] <= v.pwm.jet_neutral < v.pwm.jet_range[1]:
        err.add("pwm.jet_neutral", f"a width in jet_range [{v.pwm.jet_range[0]:g}, {v.pwm.jet_range[1]:g})",
                v.pwm.jet_neutral)
    for i, f in enumerate(v.fixed):
        norm = math.sqrt(sum(c * c for c in f.direction))
        if abs(norm - 1.0) > 1e-3:
            err.add(f"fixed[{i}].direction", "a unit vector (norm 1 within 1e-3)", list(f.direction))
    if v.fixed_thruster is not None:
        _check_fixed_thruster(v.fixed_thruster, err)
    lo, hi = v.thruster.j_range
    if not lo < hi:
        err.add("thruster.j_range", "[min, max] with min < max", [lo, hi])
    for i, u in enumerate(v.units):
        norm = math.sqrt(sum(c * c for c in u.neutral))
        if abs(norm - 1.0) > 1e-3:
            err.add(f"unit[{i}].neutral", "a unit vector (norm 1 within 1e-3)", list(u.neutral))
        elif abs(u.neutral[2]) > 1e-3:
            err.add(f"unit[{i}].neutral", "a horizontal vector (z component 0)", list(u.neutral))
    if v.envelope.min_depth_m >= v.envelope.max_depth_m:
        err.add("envelope.min_depth_m", f"a depth above max_depth_m ({v.envelope.max_depth_m:g} m)",
                v.envelope.min_depth_m)
    if v.environment.floor_depth <= v.environment.surface_depth:
        err.add("environment.floor_depth", "a NED z below surface_depth", v.environment.floor_depth)


def _check_fixed_thruster(ft: FixedThruster, err: "_Errors") -> None:
    """One curve, complete and usable: a table (increasing PWM, a row per voltage, the supply
    within the table's voltages) or coefficients (dead band inside the PWM range)."""
    w = "fixed_thruster"
    table = [k for k in ("table_pwm", "table_thrust", "table_voltages", "voltage") if getattr(ft, k) is not None]
    coef = [k for k in ("dead_band", "forward", "reverse") if getattr(ft, k) is not None]
    lo, hi = ft.pwm_range
    if not lo < hi:
        err.add(f"{w}.pwm_range", "[low, high] with low < high", [lo, hi])
    if table and coef:
        err.lines.append(f"{w}: a table ({', '.join(table)}) or coefficients ({', '.join(coef)}), not both")
        return
    if not table and not coef:
        err.lines.append(f"{w}: a thrust curve: table_pwm, table_thrust, table_voltages and voltage, "
                         "or dead_band, forward and reverse")
        return
    if table:
        missing = [k for k in ("table_pwm", "table_thrust", "table_voltages", "voltage") if k not in table]
        if missing:
            err.lines.append(f"{w}: a table needs {', '.join(missing)} too")
            return
        pwm = ft.table_pwm
        if len(pwm) < 2 or any(b <= a for a, b in zip(pwm, pwm[1:])):
            err.add(f"{w}.table_pwm", "at least two widths, strictly increasing", list(pwm))
        if len(ft.table_thrust) != len(ft.table_voltages):
            err.add(f"{w}.table_thrust", f"{len(ft.table_voltages)} rows, one per table_voltages entry",
                    f"{len(ft.table_thrust)} rows")
        for j, row in enumerate(ft.table_thrust):
            if len(row) != len(pwm):
                err.add(f"{w}.table_thrust[{j}]", f"{len(pwm)} values, one per table_pwm entry",
                        f"{len(row)} values")
        vs = ft.table_voltages
        if any(b <= a for a, b in zip(vs, vs[1:])):
            err.add(f"{w}.table_voltages", "strictly increasing", list(vs))
        elif not min(vs) <= ft.voltage <= max(vs):
            err.add(f"{w}.voltage", f"a supply within the table's {min(vs):g}-{max(vs):g} V", ft.voltage)
        if not (pwm[0] <= lo and pwm[-1] >= hi):
            err.add(f"{w}.pwm_range", f"within the table's {pwm[0]:g}-{pwm[-1]:g} us", [lo, hi])
    else:
        missing = [k for k in ("dead_band", "forward", "reverse") if k not in coef]
        if missing:
            err.lines.append(f"{w}: coefficients need {', '.join(missing)} too")
            return
        a, b = ft.dead_band
        if not lo < a <= b < hi:
            err.add(f"{w}.dead_band", f"[low, high] with {lo:g} < low <= high < {hi:g} (inside pwm_range)", [a, b])


def _echo(value, limit: int = 80) -> str:
    """repr of a value as an error message shows it: at most `limit` characters (a 3-million
    element array made an 18 MB message), control characters escaped."""
    if isinstance(value, (list, tuple)) and len(value) > 8:
        text = "[" + ", ".join(_echo(v, 20) for v in value[:4]) + f", ... ({len(value)} values)]"
    elif isinstance(value, int) and not isinstance(value, bool) and abs(value) >= 10 ** 30:
        text = f"an integer of {len(str(abs(value)))} digits"
    else:
        text = repr(value)
    return text if len(text) <= limit else text[:limit - 4] + " ..."


class _Errors:
    def __init__(self, source: str):
        self.source = source
        self.lines: list[str] = []

    def add(self, key: str, expected: str, got: Any, missing: bool = False) -> None:
        if missing:
            self.lines.append(f"{key}: missing; expected {expected}")
        else:
            self.lines.append(f"{key}: expected {expected}, got {_echo(got)}")

    def unknown(self, key: str, allowed: list) -> None:
        key = key if key.isprintable() and len(key) <= 80 else _echo(key)
        self.lines.append(f"{key}: unknown key; allowed here: {', '.join(allowed)}")

    def raise_if_any(self) -> None:
        """One problem: one line (what a command prints before exiting 2); several: a header
        line, then one line per problem, every problem at once."""
        self.lines = list(dict.fromkeys(self.lines))  # a channel repeated thrice was one problem said thrice
        if len(self.lines) == 1:
            raise VehicleFileError(f"{self.source}: invalid vehicle file: {self.lines[0]}")
        if self.lines:
            head = f"{self.source}: invalid vehicle file ({len(self.lines)} problems)"
            shown = self.lines[:MAX_PROBLEMS_SHOWN]
            more = len(self.lines) - len(shown)
            tail = [f"... and {more} more"] if more else []
            raise VehicleFileError(head + "\n  " + "\n  ".join(shown + tail))


def _replace_path(obj, parts: list[str], value, full_key: str):
    name = "units" if parts[0] == "unit" else parts[0]
    if name.startswith("unit[") and isinstance(obj, Vehicle):
        idx = int(name[5:-1])
        units = list(obj.units)
        units[idx] = _replace_path(units[idx], parts[1:], value, full_key)
        return dataclasses.replace(obj, units=tuple(units))
    if not dataclasses.is_dataclass(obj) or name not in {f.name for f in dataclasses.fields(obj)}:
        raise VehicleFileError(f"{getattr(obj, 'source', '<vehicle>')}: {_echo(full_key)}: unknown key")
    if len(parts) > 1:
        new = _replace_path(getattr(obj, name), parts[1:], value, full_key)
        return dataclasses.replace(obj, **{name: new})
    f = next(f for f in dataclasses.fields(obj) if f.name == name)
    if "check" in f.metadata:
        ok, coerced = _coerce(_plain(value), f)
        if not ok:
            raise VehicleFileError(f"{full_key}: expected {_expect(f)}, got {_echo(_plain(value))}")
        value = coerced
    return dataclasses.replace(obj, **{name: value})


def _plain(value):
    """numpy arrays and scalars -> Python lists and numbers, so they validate like TOML values."""
    if hasattr(value, "tolist"):
        return value.tolist()
    if isinstance(value, (tuple, list)):
        return [_plain(x) for x in value]
    return value


def fragment_toml(values: dict[str, Any]) -> str:
    """A vehicle-file fragment (TOML) for dotted keys, e.g. fitted parameters to paste back
    (floats to 6 significant digits: a fit is not known better)."""
    tables: dict[str, list[str]] = {}
    unit_lines = []
    for key, value in values.items():
        if key.startswith("unit["):
            # TOML cannot address one [[unit]] table by index: say which one to edit
            unit_lines.append(f"# {key} = {_toml_value(value, 6)}   (edit [[unit]] number {int(key[5:key.index(']')]) + 1})")
            continue
        table, _, leaf = key.rpartition(".")
        tables.setdefault(table, []).append(f"{leaf} = {_toml_value(value, 6)}")
    out = "\n".join(f"[{t}]\n" + "\n".join(lines) + "\n" for t, lines in tables.items())
    return out + ("\n".join(unit_lines) + "\n" if unit_lines else "")


def _toml_value(v, digits: int | None = None) -> str:
    """A value as TOML. Floats exact by default (Python's repr: the shortest text that reads back
    to the same double; `inf`/`nan` are TOML too), so a vehicle written out loads back equal;
    `digits` rounds them to that many significant digits (a fitted value shown to a person)."""
    if hasattr(v, "tolist"):
        v = v.tolist()
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_toml_value(x, digits) for x in v) + "]"
    if isinstance(v, float):
        return repr(float(f"{v:.{digits}g}")) if digits is not None else repr(float(v))
    return repr(v)
