"""Campaign spec files: TOML in, a frozen `Campaign` with its list of tasks out; errors name the key.

A spec names its `kind` and the sweep of that kind (ground/campaign/examples/ has one of each):

    kind = "missions" | "prove" | "diagnose"
    vehicle = "PATH"          # optional: the vehicle file (default the reference vehicle asr4)
    seed = 0                  # optional: the Monte Carlo draws' seed

    [missions]                # the lock-step closed loop over a sweep (cartesian product)
    mission = "turn"          # demo | hold | turn (hil.demo's missions)
    duration_s = 12.0         # hold and turn only
    draws = 4                 # perturbed vehicles (hil.batch.perturbed_values); 0: the vehicle as is
    allocators = ["qp", "baseline"]
    seeds = [0, 1]            # plant noise seeds
    compensation = true
    flight = "inprocess"      # inprocess (bench_onboard's loop) | loopback (jetloop demo's, over UDP)
    [missions.perturb]        # dotted vehicle key -> relative 1-sigma
    [missions.faults]         # fault name -> the flags of `jetloop demo` (hil.faults), e.g.
    "jet 3 weak" = { weak-jet = ["3:0.5@4"] }
    [missions.fail]           # a task beyond these is listed as a failure case
    depth_max_m = 0.25
    yaw_rms_deg = 10.0

    [prove]                   # the diagnosis benchmark (ground.prove.family_case), one case a task
    split = "dev"             # dev | eval
    first = 0
    cases = 30                # or indices = [6, 14]
    max_duration_s = 600      # leave out cases whose flight is longer
    draws = 8                 # null draws per diagnosis (default: diagnose's own)

    [diagnose]                # every recording a glob matches, one task each
    recordings = "pool-week/**/*.tlog"   # relative to the spec file
    draws = 8

Every task carries everything it needs (the vehicle file's text, the drawn values, the fault
flags, a recording's path and content hash), and its id is the hash of that: the same task in
another run, on another machine, has the same id, which is what resuming reads (content
addressing). Paths are made absolute relative to the spec file.
"""

from __future__ import annotations

import argparse
import glob as globlib
import hashlib
import json
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

KINDS = ("missions", "prove", "diagnose")
MISSIONS = ("demo", "hold", "turn")
FLIGHTS = ("inprocess", "loopback")
ALLOCATORS = ("qp", "baseline")
MAX_SPEC_BYTES = 1_000_000
MAX_TASKS = 1_000_000
MAX_PROBLEMS_SHOWN = 20
MAX_RECORDING_BYTES = 4_000_000_000  # hashed in 1 MB blocks, never read whole here


class CampaignSpecError(ValueError):
    """A spec that cannot be run; the message names the file, the key and what was expected."""


@dataclass(frozen=True)
class Task:
    """One unit of work: `inputs` is all it needs; `id` is the hash of kind and inputs."""

    kind: str
    label: str
    inputs: dict
    id: str = ""
    cost: float = 1.0  # a guess of its relative cost (not in the id): the longest go first on a cluster

    def __post_init__(self):
        if not self.id:
            object.__setattr__(self, "id", task_id(self.kind, self.inputs))


@dataclass(frozen=True)
class Campaign:
    kind: str
    source: str  # the spec file
    tasks: tuple  # Task
    settings: dict = field(default_factory=dict)  # the kind's section as read (for the report)
    skipped: int = 0  # tasks the spec's filters left out (prove: max_duration_s)


ADDRESS_EXCLUDES = ("recording",)  # where a file is, not what it holds (its sha256 is in the address)


def task_id(kind: str, inputs: dict) -> str:
    """sha256 of the canonical JSON of (kind, inputs), 16 hex digits: the task's address. A
    recording's path is left out (its content hash is in): a moved pool week resumes."""
    inputs = {k: v for k, v in inputs.items() if k not in ADDRESS_EXCLUDES}
    text = json.dumps({"kind": kind, "inputs": inputs}, sort_keys=True, separators=(",", ":"), allow_nan=False)
    return hashlib.sha256(text.encode()).hexdigest()[:16]


# ------------------------------------------------------------------------------------------------
# Errors in the vehicle-file style: one problem one line; several a header and a line each


def _echo(value, limit: int = 60) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[:limit - 4] + " ..."


class _Problems:
    def __init__(self, source: str):
        self.source = source
        self.lines: list[str] = []

    def add(self, key: str, expected: str, got=None, missing: bool = False) -> None:
        self.lines.append(f"{key}: missing; expected {expected}" if missing
                          else f"{key}: expected {expected}, got {_echo(got)}")

    def unknown(self, key: str, allowed) -> None:
        key = key if key.isprintable() and len(key) <= 60 else _echo(key)
        self.lines.append(f"{key}: unknown key; allowed here: {', '.join(allowed)}")

    def text(self, line: str) -> None:
        self.lines.append(line)

    def raise_if_any(self) -> None:
        if len(self.lines) == 1:
            raise CampaignSpecError(f"{self.source}: invalid campaign spec: {self.lines[0]}")
        if self.lines:
            shown = self.lines[:MAX_PROBLEMS_SHOWN]
            more = len(self.lines) - len(shown)
            raise CampaignSpecError(f"{self.source}: invalid campaign spec ({len(self.lines)} problems)\n  "
                                    + "\n  ".join(shown + ([f"... and {more} more"] if more else [])))


def _k(where: str, key: str) -> str:
    return f"{where}.{key}" if where else key


def _int(p: _Problems, sec: dict, where: str, key: str, default, lo: int, hi: int = 10**9):
    v = sec.get(key, default)
    if isinstance(v, bool) or not isinstance(v, int) or not lo <= v <= hi:
        p.add(_k(where, key), f"a whole number {lo}..{hi}", v)
        return default
    return v


def _float(p: _Problems, sec: dict, where: str, key: str, default, lo: float, hi: float):
    v = sec.get(key, default)
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not (math.isfinite(v) and lo <= v <= hi):
        p.add(_k(where, key), f"a number {lo:g}..{hi:g}", v)
        return default
    return float(v)


def _choice_list(p: _Problems, sec: dict, where: str, key: str, default, allowed):
    v = sec.get(key, default)
    if isinstance(v, str):
        v = [v]
    if not isinstance(v, list) or not v or any(x not in allowed for x in v) or len(set(v)) != len(v):
        p.add(_k(where, key), f"a list of distinct values from {', '.join(allowed)}", v)
        return list(default)
    return v


def _unknown(p: _Problems, sec: dict, where: str, allowed) -> None:
    for k in sec:
        if k not in allowed:
            p.unknown(f"{where}.{k}" if where else k, sorted(allowed))


# ------------------------------------------------------------------------------------------------
# Loading


def load_spec(path) -> Campaign:
    """Read and check a spec file; CampaignSpecError (file, key, expectation) otherwise."""
    from onboard.files import read_text_bounded

    path = Path(path)
    try:
        text = read_text_bounded(path, MAX_SPEC_BYTES)
    except (OSError, UnicodeDecodeError) as exc:
        raise CampaignSpecError(f"{path}: cannot read campaign spec: {getattr(exc, 'strerror', None) or exc}") from None
    return parse_spec(text, path)


def parse_spec(text: str, path) -> Campaign:
    path = Path(path)
    source = str(path)
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise CampaignSpecError(f"{source}: not valid TOML: {exc}") from None
    except RecursionError:
        raise CampaignSpecError(f"{source}: not a campaign spec: arrays or tables nested too deeply") from None
    p = _Problems(source)
    base = path.resolve().parent
    kind = doc.get("kind")
    if kind not in KINDS:
        p.add("kind", f"one of {', '.join(KINDS)}", kind, missing="kind" not in doc)
        p.raise_if_any()
    _unknown(p, doc, "", {"kind", "vehicle", "seed", kind})
    seed = _int(p, doc, "", "seed", 0, 0, 2**32 - 1)
    vehicle_text, vehicle = _vehicle(p, doc.get("vehicle"), base, "vehicle")
    sec = doc.get(kind, {})
    if not isinstance(sec, dict):
        p.add(kind, f"a [{kind}] table", sec)
        p.raise_if_any()
    if kind in ("missions", "prove") and not p.lines:  # both fly the vehicle's jets (the loop, the pilot)
        from onboard.vehicle import VehicleFileError, require_jets

        try:
            require_jets(vehicle, f"campaign ({kind})")
        except VehicleFileError as exc:
            p.text(f"vehicle: {exc}")
            p.raise_if_any()
    if kind == "missions":
        tasks, skipped = _missions(p, sec, seed, vehicle_text, vehicle), 0
    elif kind == "prove":
        tasks, skipped = _prove(p, sec, vehicle_text)
    else:
        tasks, skipped = _diagnose(p, sec, base, vehicle_text, vehicle), 0
    p.raise_if_any()
    if not tasks:
        raise CampaignSpecError(f"{source}: invalid campaign spec: [{kind}]: the sweep has no task")
    ids = [t.id for t in tasks]
    if len(set(ids)) != len(ids):  # e.g. the same recording twice under two names
        seen, dup = set(), None
        for t in tasks:
            if t.id in seen:
                dup = t
                break
            seen.add(t.id)
        raise CampaignSpecError(f"{source}: invalid campaign spec: [{kind}]: task {dup.label!r} appears twice")
    return Campaign(kind, source, tuple(tasks), dict(sec), skipped)


def _vehicle(p: _Problems, value, base: Path, key: str):
    """(vehicle file text or None, Vehicle) of a `vehicle = PATH` key (None: the reference)."""
    from onboard.files import read_text_bounded
    from onboard.vehicle import MAX_FILE_BYTES, VehicleFileError, load_vehicle, parse_vehicle

    if value is None:
        return None, load_vehicle(None)
    if not isinstance(value, str) or not value:
        p.add(key, "the path of a vehicle TOML file", value)
        return None, load_vehicle(None)
    vpath = (base / value) if not Path(value).is_absolute() else Path(value)
    try:
        text = read_text_bounded(vpath, MAX_FILE_BYTES)
        return text, parse_vehicle(text, source=str(vpath))
    except (OSError, UnicodeDecodeError) as exc:
        p.add(key, "the path of a readable vehicle TOML file", f"{value} ({getattr(exc, 'strerror', None) or exc})")
    except VehicleFileError as exc:  # one problem one line; several: the vehicle's header, then each
        lines = str(exc).splitlines()
        p.text(f"{key}: {lines[0]}")
        for line in lines[1:]:
            p.text(f"{key}: {line.strip()}")
    return None, load_vehicle(None)


def _missions(p: _Problems, sec: dict, seed: int, vehicle_text, vehicle) -> list[Task]:
    from hil.batch import perturbed_values
    from hil.faults import FLAG_HELP, FaultPlanError, plan_from_args
    from onboard.vehicle import VehicleFileError

    w = "missions"
    allowed = {"mission", "duration_s", "draws", "allocators", "seeds", "compensation", "flight", "perturb",
               "faults", "fail"}
    _unknown(p, sec, w, allowed)
    mission = sec.get("mission", "turn")
    if mission not in MISSIONS:
        p.add(f"{w}.mission", f"one of {', '.join(MISSIONS)}", mission)
        mission = "turn"
    duration = None
    if mission == "demo":
        if "duration_s" in sec:
            p.add(f"{w}.duration_s", "no duration with mission = \"demo\" (its script is 32 s)", sec["duration_s"])
    else:
        duration = _float(p, sec, w, "duration_s", 20.0, 2.0, 3600.0)
        if mission == "turn" and duration is not None and duration <= 8.0:
            p.add(f"{w}.duration_s", "more than 8 s with mission = \"turn\" (it turns at 8 s)", duration)
    draws = _int(p, sec, w, "draws", 0, 0, 100_000)
    allocators = _choice_list(p, sec, w, "allocators", ["qp"], ALLOCATORS)
    seeds = sec.get("seeds", [0])
    if (not isinstance(seeds, list) or not seeds or len(set(map(repr, seeds))) != len(seeds)
            or any(isinstance(s, bool) or not isinstance(s, int) or not 0 <= s < 2**31 for s in seeds)):
        p.add(f"{w}.seeds", "a list of distinct whole numbers 0..2^31-1", seeds)
        seeds = [0]
    comp = sec.get("compensation", True)
    if not isinstance(comp, bool):
        p.add(f"{w}.compensation", "true or false", comp)
        comp = True
    flight = sec.get("flight", "inprocess")
    if flight not in FLIGHTS:
        p.add(f"{w}.flight", f"one of {', '.join(FLIGHTS)}", flight)
        flight = "inprocess"
    fail = sec.get("fail", {})
    if not isinstance(fail, dict):
        p.add(f"{w}.fail", "a table of thresholds", fail)
    else:
        _unknown(p, fail, f"{w}.fail", {"depth_max_m", "yaw_rms_deg"})
        _float(p, fail, f"{w}.fail", "depth_max_m", 0.25, 0.0, 100.0)
        _float(p, fail, f"{w}.fail", "yaw_rms_deg", 10.0, 0.0, 360.0)
    perturb = sec.get("perturb", {})
    if not isinstance(perturb, dict):
        p.add(f"{w}.perturb", "a table of dotted vehicle keys -> relative 1-sigma", perturb)
        perturb = {}
    flat_perturb = {}
    try:
        flat = _flatten(perturb)
    except ValueError as exc:
        p.add(f"{w}.perturb", "dotted vehicle keys (e.g. \"hydro.added_mass\")", str(exc))
        flat = {}
    for key, sigma in flat.items():
        if isinstance(sigma, bool) or not isinstance(sigma, (int, float)) or not (math.isfinite(sigma) and 0 <= sigma <= 1):
            p.add(f"{w}.perturb.{key}", "a relative 1-sigma 0..1", sigma)
        else:
            flat_perturb[key] = float(sigma)
    if draws and not flat_perturb and "perturb" not in sec:
        p.add(f"{w}.perturb", f"a [missions.perturb] table (draws = {draws} perturbed vehicles of what?)", None,
              missing=True)
    draw_values: list = [None]
    if draws and flat_perturb:
        try:
            values = perturbed_values(vehicle, flat_perturb, draws, seed)
            draw_values = []
            for i in range(draws):
                d = {k: (float(v[i, 0]) if not isinstance(vehicle.get(k), (tuple, list)) else [float(c) for c in v[i]])
                     for k, v in values.items()}
                vehicle.with_values(d)  # a draw the vehicle file would refuse is the spec's error
                draw_values.append(d)
        except (VehicleFileError, ValueError) as exc:
            msg = str(exc).splitlines()[0]
            p.text(f"{w}.perturb: {msg}" + (f" (draw {len(draw_values)}, seed {seed})" if "draw" not in msg else ""))
            draw_values = [None]
    faults = sec.get("faults", {"none": {}})
    if not isinstance(faults, dict) or not faults:
        p.add(f"{w}.faults", "a table: fault name -> {flag = value} (the flags of jetloop demo)", faults)
        faults = {"none": {}}
    fault_items = []
    link_flags = ("loss", "delay", "jitter", "duplicate", "reorder")
    for name, flags in faults.items():
        where = f"{w}.faults.{_key_text(name)}"
        if not isinstance(flags, dict):
            p.add(where, f"a table of fault flags ({', '.join(FLAG_HELP)})", flags)
            continue
        ok = True
        ns = argparse.Namespace()
        norm = {}
        for flag, value in flags.items():
            if flag not in FLAG_HELP:
                p.unknown(f"{where}.{_key_text(flag)}", list(FLAG_HELP))
                ok = False
                continue
            repeat = flag in ("dead-jet", "weak-jet", "stuck-joint", "imu-freeze", "imu-nan", "depth-jump")
            if repeat and isinstance(value, str):
                value = [value]
            if (repeat and not (isinstance(value, list) and all(isinstance(x, str) for x in value))) or \
                    (not repeat and not isinstance(value, str)):
                p.add(f"{where}.{flag}", f"{'a list of strings' if repeat else 'a string'} "
                      f"{FLAG_HELP[flag].partition(':')[0]}", value)
                ok = False
                continue
            setattr(ns, flag.replace("-", "_"), value)
            norm[flag] = value
            if flag in link_flags and flight == "inprocess":
                p.add(f"{where}.{flag}", "no link fault with flight = \"inprocess\" (there is no link: use "
                      "flight = \"loopback\")", value)
                ok = False
        if not ok:
            continue
        try:
            plan_from_args(ns, vehicle.n_units)
        except FaultPlanError as exc:
            p.text(f"{where}: {str(exc).lstrip('-')}")
            continue
        fault_items.append((str(name), {k: norm[k] for k in sorted(norm)}))
    tasks = []
    total = len(draw_values) * len(allocators) * len(fault_items) * len(seeds)
    if total > MAX_TASKS:
        p.add(w, f"at most {MAX_TASKS:,} tasks", f"{total:,} tasks")
        return []
    for di, dv in enumerate(draw_values):
        for alloc in allocators:
            for fname, flags in fault_items:
                for s in seeds:
                    inputs = {"mission": mission, "duration_s": duration, "allocator": alloc, "compensation": comp,
                              "flight": flight, "fault": fname, "fault_flags": flags, "seed": s,
                              "draw": di if dv is not None else -1, "vehicle_values": dv or {},
                              "vehicle_toml": vehicle_text}
                    label = f"{alloc} / {fname} / draw {inputs['draw']} / seed {s}"
                    tasks.append(Task("missions", label, inputs, cost=duration or 32.0))
    return tasks


def _key_text(name, limit: int = 60) -> str:
    name = str(name)
    text = name if name.replace("_", "").replace("-", "").isalnum() else json.dumps(name)
    return text if len(text) <= limit else text[:limit - 4] + " ..."


MAX_KEY_DEPTH = 8  # a vehicle key is a few levels deep ("hydro.added_mass"); TOML allows thousands


def _flatten(d: dict, prefix: str = "", depth: int = 0) -> dict:
    """{"a.b": v} of {"a": {"b": v}}; ValueError past MAX_KEY_DEPTH levels (not a RecursionError)."""
    if depth >= MAX_KEY_DEPTH:
        raise ValueError(f"{_key_text(prefix.rstrip('.'))}... is nested more than {MAX_KEY_DEPTH} levels deep")
    out = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(_flatten(v, key + ".", depth + 1))
        else:
            out[key] = v
    return out


def _prove(p: _Problems, sec: dict, vehicle_text):
    from ground.prove import SPLITS, family_case

    w = "prove"
    _unknown(p, sec, w, {"split", "first", "cases", "indices", "max_duration_s", "draws"})
    split = sec.get("split", "dev")
    if split not in SPLITS:
        p.add(f"{w}.split", f"one of {', '.join(sorted(SPLITS))}", split)
        return [], 0
    if "indices" in sec:
        if "first" in sec or "cases" in sec:
            p.add(f"{w}.indices", "either indices or first/cases, not both", sec["indices"])
        idx = sec["indices"]
        if (not isinstance(idx, list) or not idx or len(set(map(repr, idx))) != len(idx)
                or any(isinstance(i, bool) or not isinstance(i, int) or not 0 <= i < 10**6 for i in idx)):
            p.add(f"{w}.indices", "a list of distinct case numbers 0..999999", idx)
            return [], 0
    else:
        first = _int(p, sec, w, "first", 0, 0, 10**6)
        n = _int(p, sec, w, "cases", 30, 1, 10**5)
        idx = list(range(first, first + n))
    max_d = _float(p, sec, w, "max_duration_s", 600.0, 1.0, 1e6)
    draws = _int(p, sec, w, "draws", None, 1, 1000) if "draws" in sec else None
    tasks, skipped = [], 0
    for i in idx:
        case, flight, _ = family_case(split, i)
        if flight.duration_s > max_d:
            skipped += 1
            continue
        tasks.append(Task("prove", case.name, {"split": split, "index": i, "draws": draws,
                                               "vehicle_toml": vehicle_text}, cost=flight.duration_s))
    return tasks, skipped


def _diagnose(p: _Problems, sec: dict, base: Path, vehicle_text, vehicle) -> list[Task]:
    w = "diagnose"
    _unknown(p, sec, w, {"recordings", "draws"})
    pattern = sec.get("recordings")
    if not isinstance(pattern, str) or not pattern:
        p.add(f"{w}.recordings", "a glob of recordings, e.g. \"pool/**/*.tlog\" (relative to the spec file)",
              pattern, missing=pattern is None)
        return []
    draws = _int(p, sec, w, "draws", None, 1, 1000) if "draws" in sec else None
    full = pattern if Path(pattern).is_absolute() else str(base / pattern)
    paths = sorted(Path(x) for x in globlib.glob(full, recursive=True) if Path(x).is_file())
    if not paths:
        p.add(f"{w}.recordings", "a glob that matches at least one recording file", pattern)
        return []
    tasks, seen = [], set()
    for path in paths:
        try:
            digest = file_sha256(path)
        except OSError as exc:
            p.text(f"{w}.recordings: {path}: cannot read: {exc.strerror or exc}")
            continue
        try:
            name = str(path.resolve().relative_to(base))
        except ValueError:
            name = str(path.resolve())
        if digest in seen:  # the same recording twice (a copy): diagnosed once
            continue
        seen.add(digest)
        tasks.append(Task("diagnose", name, {"recording": str(path.resolve()), "sha256": digest, "draws": draws,
                                             "vehicle_toml": vehicle_text}, cost=float(path.stat().st_size)))
    return tasks


def file_sha256(path) -> str:
    import os
    import stat

    h = hashlib.sha256()
    with open(path, "rb") as f:
        st = os.fstat(f.fileno())
        if not stat.S_ISREG(st.st_mode):
            raise OSError(22, "not a regular file")
        if st.st_size > MAX_RECORDING_BYTES:
            raise OSError(27, f"larger than {MAX_RECORDING_BYTES:,} bytes")
        for block in iter(lambda: f.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()
