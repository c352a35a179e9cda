"""`jetloop identify`: each method reads its CSV, writes JSON, a vehicle fragment and a PNG."""

from __future__ import annotations

import json

try:
    import tomllib
except ModuleNotFoundError:  # pragma: no cover
    import tomli as tomllib

import numpy as np
import pytest

from ground.cli import main
from ground.identify.cli import _PENDULUM_EXAMPLE

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def flatten(doc: dict, prefix: str = "") -> dict:
    out = {}
    for k, v in doc.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(flatten(v, key + "."))
        else:
            out[key] = v
    return out


def outputs(tmp_path, name):
    return [f"--json={tmp_path / (name + '.json')}", f"--fragment={tmp_path / (name + '.toml')}",
            f"--plot={tmp_path / (name + '.png')}"]


def read_outputs(tmp_path, name, vehicle):
    res = json.loads((tmp_path / f"{name}.json").read_text())
    frag = flatten(tomllib.loads((tmp_path / f"{name}.toml").read_text()))
    assert (tmp_path / f"{name}.png").read_bytes()[:8] == PNG_MAGIC
    assert frag.keys() == res["fragment"].keys()
    vehicle.with_values(frag)  # the fragment is a valid set of vehicle keys
    return res, frag


def test_thrust_command(tmp_path, vehicle, capsys):
    data = tmp_path / "thrust.csv"
    assert main(["identify", "thrust", "--make-example", str(data)]) == 0
    assert main(["identify", "thrust", str(data), *outputs(tmp_path, "thrust")]) == 0
    res, frag = read_outputs(tmp_path, "thrust", vehicle)
    assert frag["thruster.kt"] == pytest.approx(res["kt"], rel=1e-5)
    assert res["kt"] == pytest.approx(vehicle.thruster.kt, rel=0.15)
    groups = {(round(g["v"], 2), round(np.degrees(g["angle"]))) for g in res["residuals"]}
    assert {(0.1, 0), (0.22, 0), (0.35, 0), (0.22, 10), (0.22, 30), (0.22, 50)} <= groups
    assert "residuals per condition" in capsys.readouterr().out


def test_free_decay_command_on_the_hil_spring_rig(tmp_path, vehicle):
    trace = tmp_path / "heave.csv"
    assert main(["identify", "free-decay", "--make-example", str(trace), "--spring", "400"]) == 0
    assert main(["identify", "free-decay", str(trace), "--spring", "400", *outputs(tmp_path, "fd")]) == 0
    res, frag = read_outputs(tmp_path, "fd", vehicle)
    for key in ("omega_n", "zeta", "added_mass", "cm", "cd"):
        assert np.isfinite(res[key])
    # omega_n^2 = K / (m + m'), the heave added mass of the vehicle file
    heave_added = vehicle.hydro.added_mass[2]
    assert res["omega_n"] == pytest.approx(np.sqrt(400 / (vehicle.body.mass + heave_added)), rel=0.005)
    assert res["cm"] == pytest.approx(res["added_mass"] / (vehicle.environment.rho * vehicle.body.volume))
    assert frag["hydro.added_mass"][2] == pytest.approx(heave_added, rel=0.01)
    assert frag["hydro.added_mass"][:2] == pytest.approx(list(vehicle.hydro.added_mass[:2]))


def test_pendulum_command(tmp_path, vehicle):
    trace = tmp_path / "pend.csv"
    assert main(["identify", "pendulum", "--make-example", str(trace)]) == 0
    assert main(["identify", "pendulum", str(trace), "--mass", "0.146", "--volume", "1.07597e-4",
                 "--length", "0.5", "--area", "0.0045", *outputs(tmp_path, "pend")]) == 0
    res, _ = read_outputs(tmp_path, "pend", vehicle)
    assert res["a1"] < 0 and res["a2"] > 0
    assert res["chin"]["added_mass"] == pytest.approx(_PENDULUM_EXAMPLE["added_mass"], rel=0.02)
    assert np.isfinite(res["added_mass"]) and np.isfinite(res["cd"])


def test_tables_command(tmp_path, vehicle):
    prefix = tmp_path / "tab"
    assert main(["identify", "tables", "--make-example", str(prefix)]) == 0
    assert main(["identify", "tables", "--added-mass", f"{prefix}_added_mass.csv", "--damping",
                 f"{prefix}_damping.csv", *outputs(tmp_path, "tab")]) == 0
    res, frag = read_outputs(tmp_path, "tab", vehicle)
    # the example: 3 attitudes x 3 DOFs of added mass lines; damping surge at 5 attitudes, heave and yaw at 1
    assert len(res["added_mass_lines"]) == 3 * 3 and len(res["damping_curves"]) == 5 + 1 + 1
    # the example's level lines reach the vehicle's added mass at full depth (within its 1 % noise)
    assert frag["hydro.added_mass"][2] == pytest.approx(vehicle.hydro.added_mass[2], rel=0.03)
    assert frag["hydro.quadratic_damping"][0] == pytest.approx(vehicle.hydro.quadratic_damping[0], rel=0.05)


def test_azimuth_command(tmp_path, vehicle):
    design = tmp_path / "design.csv"
    args = ["identify", "azimuth", "--rows", "f1y,m1z", "--samples", "9000", "--rate", "200",
            "--export-design", str(design), "--save-rig", str(tmp_path / "rig"), *outputs(tmp_path, "az")]
    assert main(args) == 0
    res, frag = read_outputs(tmp_path, "az", vehicle)
    assert set(res["rows"]) == {"f1y", "m1z"}
    assert res["design"]["band_hz"] == pytest.approx(10.0)
    for row in ("f1y", "m1z"):
        assert res["rows"][row]["correlation"] >= res["rows"][row]["seed004_correlation_75pwm"]
        assert frag[f"effects.azimuth_transient.{row}"] == pytest.approx(
            getattr(vehicle.effects.azimuth_transient, row), rel=0.05)
    assert design.read_text().splitlines()[2] == "t,rate,angle"
    # the saved rig record reads back as a real rig's would
    T = res["thrust"]["azimuth"]
    assert main(["identify", "azimuth", "--rows", "m1z", "--samples", "9000", "--rate", "200",
                 "--rig-azimuth", str(tmp_path / "rig_azimuth.csv"), "--thrust", str(T),
                 f"--json={tmp_path / 'az2.json'}"]) == 0
    res2 = json.loads((tmp_path / "az2.json").read_text())
    assert res2["rows"]["m1z"]["coeffs"] == pytest.approx(res["rows"]["m1z"]["coeffs"], rel=1e-3)


@pytest.mark.parametrize("argv, message", [
    (["thrust", "{missing}"], "cannot read"),
    (["thrust", "{badcols}"], "missing column(s) angle,thrust"),
    (["thrust", "{badnum}"], ":3: column 'v': expected a number"),
    (["free-decay", "{trace}"], "missing --spring"),
    (["pendulum", "{trace}", "--mass", "1"], "missing --volume, --length, --area"),
    (["tables"], "give --added-mass CSV, --damping CSV or both"),
    (["azimuth", "--rows", "f9q"], "--rows: unknown row"),
    (["azimuth", "--rig-azimuth", "{trace}"], "--thrust must be"),
])
def test_bad_input_gets_a_clear_error(tmp_path, capsys, argv, message):
    files = {
        "missing": tmp_path / "nope.csv",
        "badcols": tmp_path / "badcols.csv",
        "badnum": tmp_path / "badnum.csv",
        "trace": tmp_path / "trace.csv",
    }
    files["badcols"].write_text("n,v\n1,2\n")
    files["badnum"].write_text("n,v,angle,thrust\n10,0.1,0,1\n10,fast,0,1\n")
    files["trace"].write_text("t,y\n" + "\n".join(f"{i * 0.01},{np.sin(i * 0.1)}" for i in range(100)))
    argv = [a.format(**{k: str(v) for k, v in files.items()}) for a in argv]
    assert main(["identify", *argv]) == 2
    err = capsys.readouterr().err
    assert f"jetloop identify {argv[0]}: error:" in err
    assert message in err
    assert "Traceback" not in err


def test_free_decay_reads_a_tlog_recording(tmp_path, vehicle):
    rec = tmp_path / "heave.tlog"
    csv_path = tmp_path / "heave.csv"
    assert main(["identify", "free-decay", "--make-example", str(rec)]) == 0
    assert main(["identify", "free-decay", "--make-example", str(csv_path)]) == 0
    for src, name in ((rec, "a"), (csv_path, "b")):
        assert main(["identify", "free-decay", str(src), "--spring", "400", "--t0", "0.5",
                     f"--json={tmp_path / (name + '.json')}"]) == 0
    a = json.loads((tmp_path / "a.json").read_text())
    b = json.loads((tmp_path / "b.json").read_text())
    # the recording's SCALED_PRESSURE2 (hPa, float32) carries the same trace as the CSV
    assert a["omega_n"] == pytest.approx(b["omega_n"], rel=1e-4)
    assert a["chin"]["added_mass"] == pytest.approx(4.1, rel=0.01)


def test_free_decay_on_a_recording_with_a_gap_is_refused_with_the_gap(tmp_path, capsys):
    """Issue 15 items 5 and 9: a pressure stream that stops for 2000 s was resampled across the
    gap (filled by interpolation, memory by the time span, 419 TiB on a bit-flipped .bin):
    the gap is named and the user picks the stretch with --t0/--t1, which then fits."""
    from ground.identify import free_decay as fd
    from ground.identify.cli import _write_tlog_depth

    t, y = fd.synthesize_linear_decay(6.0, 0.05, 0.05, 20.0, 50.0)
    t = np.where(t >= 10.0, t + 2000.0, t)
    path = tmp_path / "gap.tlog"
    _write_tlog_depth(path, t, 101325.0 + 1000.0 * 9.81 * (0.5 + y))
    assert main(["identify", "free-decay", str(path), "--spring", "400"]) == 2
    err = capsys.readouterr().err
    assert "a gap in the recording" in err and "after t = 9.98 s" in err and "Traceback" not in err
    assert main(["identify", "free-decay", str(path), "--spring", "400", "--t1", "9.99",
                 f"--json={tmp_path / 'a.json'}"]) == 0


def test_resampling_a_trace_never_allocates_by_its_time_span():
    """A 1e9 s jump in a slightly irregular trace asked numpy for 10^11 samples (MemoryError)."""
    from ground.identify import free_decay as fd

    t = np.arange(200) * 0.01 + np.r_[np.zeros(100), np.full(100, 1e9)]
    t[5] += 1e-4  # irregular: resampled
    with pytest.raises(ValueError, match="a gap in the recording"):
        fd.uniform(t, np.sin(t))


@pytest.mark.parametrize("argv, message", [
    (["--samples", "10000000000"], "--samples 10000000000: expected an even number 16-1000000"),
    (["--samples", "1e10"], "--samples 1e10: expected an even number 16-1000000"),
    (["--noise", "nan"], "--noise nan N: expected 0-1000 N"),
    (["--noise", "-1"], "--noise -1 N: expected 0-1000 N"),
    (["--rate", "10"], "--rate 10 Hz: expected 50-20000 Hz"),
    (["--rate", "1e-300"], "--rate 1e-300 Hz: expected 50-20000 Hz"),
    (["--rate", "1e300"], "--rate 1e+300 Hz: expected 50-20000 Hz"),
    (["--peak-rate", "1e308"], "--peak-rate 1e+308 rad/s: expected 0.01-10 rad/s"),
    (["--a", "1e9"], "--a 1e+09: expected 1-"),
    (["--b", "0"], "--b 0: expected 1-"),
], ids=lambda x: x if isinstance(x, str) else " ".join(x))
def test_azimuth_arguments_out_of_range_get_one_line_and_exit_2(capsys, argv, message):
    """Issue 15, second pass: --samples 1e10 ended in a MemoryError traceback (149 GiB), --noise nan
    was accepted and produced NaN-free nonsense, --rate 10 gave scipy's "Initial guess is outside of
    provided bounds" (the simulated rig at 10 Hz diverges), --rate 1e300 an IndexError traceback.
    Each is refused before any work, in one line, with the range and its unit."""
    assert main(["identify", "azimuth", *argv]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("jetloop identify azimuth: error: "), err
    assert message in err[0], err
