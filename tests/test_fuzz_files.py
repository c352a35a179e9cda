"""Fuzzing the files and text the package reads (issue 7 part 2): vehicle TOML (onboard.vehicle),
the commands CSV of `jetloop sim` (hil.sim.parse_commands, as onboard/data/demo_commands.csv),
the operator's command lines and stream rates of `jetloop ground` (ground.commands), signing key
files (onboard.signing.load_key) and the CSV tables of `jetloop identify` (read_columns).

Property for each reader: it returns a valid object or raises its documented error type
(VehicleFileError, CommandsFileError, CommandError, SigningError, InputError) with a message that
names the source; never another exception. A vehicle that loads has only finite numbers.
"""

from __future__ import annotations

import copy
import math
from datetime import timedelta

import pytest
from hypothesis import HealthCheck, example, given, settings
from hypothesis import strategies as st

from ground.commands import CommandError, parse_command, parse_rates
from ground.identify.cli import InputError, read_columns
from hil.sim import DEMO_COMMANDS, CommandsFileError, parse_commands
from onboard.signing import SigningError, load_key
from onboard.vehicle import DEFAULT_VEHICLE, Vehicle, VehicleFileError, parse_vehicle, tomllib, vehicle_from_dict

FUZZ = settings(max_examples=80, deadline=timedelta(seconds=30),
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.function_scoped_fixture])
REFERENCE_TEXT = DEFAULT_VEHICLE.read_text(encoding="utf-8")
REFERENCE = tomllib.loads(REFERENCE_TEXT)

HOSTILE_VALUES = st.one_of(
    st.sampled_from([math.nan, math.inf, -math.inf, 1e308, -1e308, 0, -1, 2 ** 63, -(2 ** 63), True, "", "1.0",
                     "m/s", [], {}, [[1.0]], [math.nan] * 3, 10 ** 400, -(10 ** 400), [10 ** 400] * 3,
                     "asr4\x1b[2J", 1e300, 1e-300]),
    st.floats(), st.integers(), st.text(max_size=12),
    st.lists(st.floats(), max_size=5),
    st.integers(0, 100_000).map(lambda n: [0.5] * n),  # huge arrays
    st.dictionaries(st.text(max_size=6), st.floats(), max_size=3),
)


def _leaves(doc, path=()):
    if isinstance(doc, dict):
        for k, v in doc.items():
            yield from _leaves(v, path + (k,))
    elif isinstance(doc, list) and doc and isinstance(doc[0], dict):
        for i, v in enumerate(doc):
            yield from _leaves(v, path + (i,))
    else:
        yield path


LEAVES = list(_leaves(REFERENCE))


def _set(doc, path, value, delete=False):
    for p in path[:-1]:
        doc = doc[p]
    if delete:
        doc.pop(path[-1], None) if isinstance(doc, dict) else None
    else:
        doc[path[-1]] = value


def _assert_finite_vehicle(v: Vehicle) -> None:
    """Only finite numbers, each within its key's plausible range, and an allocation that builds
    (issue 15 item 10: absurd-but-parsable files crashed or hung the commands later)."""
    import dataclasses

    from onboard.allocation import QpAllocator
    from onboard.vehicle import _check_consistency, _Errors

    err = _Errors("check")
    _check_consistency(v, err)
    assert not err.lines, err.lines
    assert QpAllocator(v, 0.01) is not None

    def walk(x):
        if dataclasses.is_dataclass(x):
            for f in dataclasses.fields(x):
                walk(getattr(x, f.name))
        elif isinstance(x, (list, tuple)):
            for y in x:
                walk(y)
        elif isinstance(x, float):
            assert math.isfinite(x)

    walk(v)


@FUZZ
@given(edits=st.lists(st.tuples(st.sampled_from(LEAVES), HOSTILE_VALUES, st.booleans()), min_size=1, max_size=4),
       extra=st.one_of(st.none(), st.tuples(st.sampled_from(["", "body", "thruster", "unit"]), st.text(min_size=1, max_size=8))))
@example(edits=[(LEAVES[0], math.nan, False)], extra=None)
@example(edits=[(("body", "mass"), 10 ** 400, False)], extra=None)  # regression: OverflowError traceback
def test_vehicle_with_wrong_keys_types_values_is_refused_with_the_key(edits, extra):
    doc = copy.deepcopy(REFERENCE)
    for path, value, delete in edits:
        _set(doc, path, value, delete)
    if extra is not None:
        section, key = extra
        target = doc if not section else doc.get(section)
        if isinstance(target, list) and target:
            target = target[0]
        if isinstance(target, dict):
            target[key] = 1.0
    try:
        v = vehicle_from_dict(doc, "fuzz.toml")
    except VehicleFileError as exc:
        assert str(exc).startswith("fuzz.toml: invalid vehicle file")
        return
    _assert_finite_vehicle(v)


NUMERIC_LEAVES = [p for p in LEAVES if isinstance(p[-1], str) and p[0] != "name"]


@FUZZ
@given(edits=st.lists(st.tuples(st.sampled_from(NUMERIC_LEAVES),
                                st.sampled_from([0.0, -1.0, 1e-300, 1e-6, 1e-3, 1e3, 1e6, 1e300])),
                      min_size=1, max_size=4))
@example(edits=[(("body", "mass"), 1e3)])  # grams for kg
@example(edits=[(("sensors", "imu_rate"), 1e-6)])
def test_vehicle_with_values_off_by_units_is_refused_or_plausible(edits):
    """Issue 15 item 10: a number scaled as a unit slip would (kg/g, s/ms, rev/s/rpm, 1e300):
    refused with the key's plausible range, or a vehicle whose allocation builds."""
    doc = copy.deepcopy(REFERENCE)
    for path, factor in edits:
        node = doc
        for p in path[:-1]:
            node = node[p]
        old = node[path[-1]]
        if isinstance(old, bool):
            continue
        node[path[-1]] = [x * factor for x in old] if isinstance(old, list) else old * factor
    try:
        v = vehicle_from_dict(doc, "units.toml")
    except VehicleFileError as exc:
        assert str(exc).startswith("units.toml") and len(str(exc)) < 2000
        return
    _assert_finite_vehicle(v)


TEXT_EDIT = st.tuples(st.floats(0, 1), st.integers(0, 40), st.text(max_size=12))


@FUZZ
@given(edits=st.lists(TEXT_EDIT, min_size=1, max_size=6))
@example(edits=[(0.0, 10 ** 6, "")])  # an empty file
@example(edits=[(0.5, 0, "\x00\ud7ff")])
def test_vehicle_text_mutations_are_refused_with_the_file_name(edits):
    text = REFERENCE_TEXT
    for at, cut, insert in edits:
        i = int(at * len(text))
        text = text[:i] + insert + text[i + cut:]
    try:
        v = parse_vehicle(text, source="mutated.toml")
    except VehicleFileError as exc:
        assert str(exc).startswith("mutated.toml")
        return
    _assert_finite_vehicle(v)


# -- commands CSV (jetloop sim) ------------------------------------------------------------------

DEMO_TEXT = DEMO_COMMANDS.read_text(encoding="utf-8")
CELL = st.one_of(st.sampled_from(["nan", "inf", "-1", "1e308", "", "1500", "1100", "2000", "0", "0x10", "1_500", " ",
                                  "1_0", "\u0661\u0665\u0660\u0660", "infinity", "1" * 5000]),
                 st.text(max_size=6))


@FUZZ
@given(edits=st.lists(TEXT_EDIT, max_size=6), cells=st.lists(st.tuples(st.floats(0, 1), CELL), max_size=6))
@example(edits=[], cells=[(0.99, "1e308")])  # a run of 1e308 s: refused or left to the run's own limits
def test_commands_csv_is_parsed_or_refused_with_the_line(edits, cells):
    text = DEMO_TEXT
    for at, cut, insert in edits:
        i = int(at * len(text))
        text = text[:i] + insert + text[i + cut:]
    lines = text.splitlines()
    for at, cell in cells:  # replace one field of one data row
        rows = [i for i, ln in enumerate(lines) if ln and not ln.startswith("#") and "," in ln]
        if rows:
            r = rows[int(at * (len(rows) - 1))]
            parts = lines[r].split(",")
            parts[int(at * (len(parts) - 1))] = cell
            lines[r] = ",".join(parts)
    try:
        sched = parse_commands("\n".join(lines), "cmds.csv")
    except CommandsFileError as exc:
        assert str(exc).startswith("cmds.csv")
        return
    assert all(math.isfinite(t) and t >= 0 for t in sched.times_s)
    assert list(sched.times_s) == sorted(set(sched.times_s))


@pytest.mark.parametrize("cell", ["1_0", "\u0661", "\uff11", "infinity"])
def test_commands_csv_reads_only_plain_decimal_numbers(cell, tmp_path):
    """Issue 15 item 11: Python's float() read `1_0` as t = 10 s (and Arabic-Indic or full-width
    digits as numbers): a commands CSV cell is a plain decimal number or refused with its line;
    identify's CSV tables read numbers the same way."""
    head = DEMO_TEXT.splitlines()
    rows = [i for i, ln in enumerate(head) if ln and not ln.startswith("#") and "," in ln]
    parts = head[rows[2]].split(",")
    parts[0] = cell
    head[rows[2]] = ",".join(parts)
    with pytest.raises(CommandsFileError, match=f"^cmds.csv:{rows[2] + 1}: column t: '{cell}' is not a number"):
        parse_commands("\n".join(head), "cmds.csv")
    csv_path = tmp_path / "t.csv"
    csv_path.write_text(f"t,y\n0,1\n{cell},2\n", encoding="utf-8")
    with pytest.raises(InputError, match=f"column 't': expected a number, got '{cell}'"):
        read_columns(str(csv_path), ("t", "y"))


# -- operator command lines and rates (jetloop ground) ---------------------------------------------

WORDS = st.sampled_from(["arm", "disarm", "mode", "depth", "yaw", "velocity", "manual", "rate", "guided", "manual",
                         "nan", "inf", "-inf", "1e400", "-1", "0", "1000", "1e9", "ATTITUDE", "HEARTBEAT", "99999",
                         "yaw", "=", ",", ""])


@FUZZ
@given(words=st.lists(st.one_of(WORDS, st.text(max_size=8)), max_size=6))
@example(words=["manual", "1e9", "0", "0", "0"])  # out of MANUAL_CONTROL's int16 range
@example(words=["depth", "nan"])
@example(words=["depth", "7" * 117])  # regression (atheris): 7.7e117 m did not pack as float32
@example(words=["rate", "ATTITUDE", "1e-300"])  # regression: an interval of 1e306 us did not pack
@example(words=["rate", "9" * 40, "10"])  # regression: a message id of 1e40 did not pack
@example(words=["rate", "\u00b2", "10"])  # regression: a Unicode digit passed isdigit() and int() raised
def test_operator_command_lines(words):
    line = " ".join(words)
    try:
        msgs = parse_command(line)
    except CommandError as exc:
        assert str(exc)
        return
    from pymavlink.dialects.v20 import ardupilotmega as mavlink

    mav = mavlink.MAVLink(None)
    for m in msgs:
        m.pack(mav)  # whatever parses can go on the wire


@FUZZ
@given(text=st.one_of(st.text(max_size=40), st.lists(st.tuples(WORDS, WORDS), max_size=4).map(
    lambda kv: ",".join(f"{k}={v}" for k, v in kv))))
def test_stream_rates(text):
    try:
        rates = parse_rates(text)
    except CommandError as exc:
        assert str(exc)
        return
    assert all(math.isfinite(hz) and hz >= 0 for hz in rates.values())


# -- key files and identification CSVs -----------------------------------------------------------

@FUZZ
@given(data=st.one_of(st.binary(max_size=80), st.text(alphabet="0123456789abcdefABCDEF \n", max_size=80).map(str.encode)))
@example(data=bytes(32))
@example(data=b"zz" * 32)
def test_key_file(tmp_path, data):
    path = tmp_path / "key"
    path.write_bytes(data)
    try:
        key = load_key(path)
    except SigningError as exc:
        assert str(path) in str(exc)
        return
    assert len(key) == 32


@FUZZ
@given(text=st.one_of(st.text(max_size=200),
                      st.lists(st.lists(st.one_of(CELL, st.sampled_from(["n", "v", "angle", "thrust", "# c"])),
                                        min_size=1, max_size=5), max_size=6).map(
                          lambda rows: "\n".join(",".join(r) for r in rows))))
@example(text="n,v,angle,thrust\n")
@example(text="n,v,angle,thrust\n1,2,3,nan\n")
def test_identification_csv(tmp_path, text):
    path = tmp_path / "data.csv"
    path.write_text(text, encoding="utf-8")
    try:
        cols = read_columns(str(path), ("n", "v", "angle", "thrust"))
    except InputError as exc:
        assert str(path) in str(exc) or "no input" in str(exc)
        return
    assert all(len(c) == len(cols["n"]) > 0 for c in cols.values())


@pytest.mark.parametrize("bad", [b"\xff\xfe\x00", "é".encode("latin-1")])
def test_undecodable_files_are_refused_with_the_reader_error(tmp_path, bad):
    from hil.sim import read_commands
    from onboard.vehicle import load_vehicle

    p = tmp_path / "bad"
    p.write_bytes(bad)
    with pytest.raises(VehicleFileError, match=str(p)):
        load_vehicle(p)
    with pytest.raises(CommandsFileError, match=str(p)):
        read_commands(p, load_vehicle())
    with pytest.raises(InputError, match=str(p)):
        read_columns(str(p), ("n",))
