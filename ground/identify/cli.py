"""`jetloop identify METHOD`: the seed papers' identification methods on a user's measurements.

Each method reads measurements (CSV), fits with the pure functions of this package, prints a
summary, and writes what the user asks for: `--json OUT.json` (results plus the fragment),
`--fragment OUT.toml` (vehicle-file keys to paste back), `--plot OUT.png` (matplotlib, Agg).
`--make-example PATH` writes a synthetic measurement file of the method's format instead, from
the vehicle model (the HIL plant where a rig exists), so every command can be tried at once.

    thrust      DATA.csv (n,v,angle,thrust)              seed 000 sec. 5-6: K(J), residuals per condition
    free-decay  TRACE.csv (t,y) --mass --spring ...      seed 001 sec. 3.2: omega_n, zeta, m', C_m, C_D, K_L, K_Q
    pendulum    TRACE.csv (t,theta) --mass --volume ...  seed 001 sec. 3.3: a1, a2, m', C_D, K_L, K_Q
    tables      --added-mass AM.csv --damping D.csv      seed 003 sec. 3.2: M_A(depth) lines, damping polynomials
    azimuth     [--rig-azimuth R.csv ...]                seed 004 sec. 3-4: pseudo-impulse, compression, eq. 5/6 fits
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import re
import sys
from pathlib import Path

import numpy as np

from onboard.files import read_text_bounded
from onboard.vehicle import VehicleFileError, fragment_toml, load_vehicle

from .tables import DOFS

METHODS = ("thrust", "free-decay", "pendulum", "tables", "azimuth")
AXES = ("surge", "sway", "heave")


MAX_CSV_BYTES = 512_000_000  # as a commands CSV (hil.sim): a day of samples at 1 kHz is ~100 MB


class InputError(ValueError):
    """Bad input: the message names the file or flag, the place and what was expected."""


# ------------------------------------------------------------------------------------------------
# Arguments

def configure(parser: argparse.ArgumentParser) -> None:
    parser.description = (
        "Identify model parameters with the seed papers' methods; each method writes JSON, "
        "a vehicle-file fragment and a plot."
    )
    sub = parser.add_subparsers(dest="method", metavar="METHOD")
    sub.required = True

    p = sub.add_parser("thrust", help="K(J) of the water-jet from thrust measurements (seed 000)",
                       description="Fit K(J) = kt0 + kt1 J + kt2 J^2 (seed 000 eq. 13-15) to thrust "
                       "measurements; residuals per flow speed and angle as in section 6.3.")
    p.add_argument("data", nargs="?", help="CSV with columns n,v,angle,thrust (rev/s, m/s, rad, N)")
    p.add_argument("--rho", type=float, help="water density kg/m^3 (default: the vehicle's)")
    p.add_argument("--diameter", type=float, help="propeller diameter D in m (default: the vehicle's)")
    _common(p)

    p = sub.add_parser("free-decay", help="spring free decay: omega_n, zeta, added mass, C_D (seed 001)",
                       description="Spring-rig free decay (seed 001 eq. 6-9) and Chin's K_L/K_Q fit of eq. 6.")
    p.add_argument("data", nargs="?", help="CSV with columns t,y (s, m), or a .tlog / .bin recording "
                   "(y = depth from its pressure sensor)")
    p.add_argument("--mass", type=float, help="body mass m in kg (default: the vehicle's)")
    p.add_argument("--spring", type=float, default=None, help="spring constant K in N/m (required to fit)")
    p.add_argument("--volume", type=float, help="displaced volume V in m^3 (default: the vehicle's)")
    p.add_argument("--length", type=float, help="reference length D in m (default: the vehicle's diameter)")
    p.add_argument("--rho", type=float, help="water density kg/m^3 (default: the vehicle's)")
    p.add_argument("--zeta-structural", type=float, default=0.0,
                   help="damping ratio of the rig itself, zeta_s of eq. 8 (default 0)")
    p.add_argument("--axis", choices=AXES, default="heave", help="axis the trace moves along (fragment index)")
    _window(p)
    _common(p)

    p = sub.add_parser("pendulum", help="pendulum free decay: a1, a2, added mass, C_D (seed 001)",
                       description="Pendulum free decay (seed 001 eq. 10-16) and Chin's K_L/K_Q form.")
    p.add_argument("data", nargs="?", help="CSV with columns t,theta (s, rad), or a .tlog / .bin "
                   "recording (theta = its ATTITUDE roll or pitch, see --angle)")
    p.add_argument("--angle", choices=("roll", "pitch"), default="pitch",
                   help="attitude angle of a recording that is the swing angle (default pitch)")
    p.add_argument("--mass", type=float, help="body mass m in kg (required to fit)")
    p.add_argument("--volume", type=float, help="body volume V in m^3 (required to fit)")
    p.add_argument("--length", type=float, help="pendulum length r in m (required to fit)")
    p.add_argument("--area", type=float, help="wetted (cross-section) area A_wet in m^2 (required to fit)")
    p.add_argument("--rho", type=float, help="water density kg/m^3 (default: the vehicle's)")
    p.add_argument("--g", type=float, help="gravity m/s^2 (default: the vehicle's)")
    p.add_argument("--axis", choices=AXES, default="surge", help="axis the body swings along (fragment index)")
    _window(p)
    _common(p)

    p = sub.add_parser("tables", help="added mass vs depth and damping vs speed tables (seed 003)",
                       description="First-order added-mass lines over depth per attitude and second-order "
                       "damping polynomials over speed (seed 003 Figures 5, 8, 9) into vehicle keys.")
    p.add_argument("--added-mass", metavar="CSV", help="CSV with columns attitude,depth,dof,added_mass "
                   "(rad, m, surge|sway|heave|roll|pitch|yaw, kg or kg m^2)")
    p.add_argument("--damping", metavar="CSV", help="CSV with columns attitude,dof,speed,force "
                   "(rad, dof name, m/s or rad/s, N or N m)")
    p.add_argument("--full-depth", type=float, help="water-entry depth where the body is fully "
                   "submerged, m (default: the vehicle's 2 * radius)")
    p.add_argument("--attitude", type=float, default=0.0, help="attitude (rad) whose fits become the "
                   "vehicle keys (default 0, level)")
    _common(p)

    p = sub.add_parser("azimuth", help="azimuth transients by signal compression (seed 004)",
                       description="Design the pseudo-impulse joint rate (eq. 1-3), run it on the vehicle "
                       "model clamped on a rig (or read a real rig's record), compress, draw the Bode "
                       "magnitude and fit eq. 5/6 rows by maximising the correlation number.")
    p.add_argument("--rig-azimuth", metavar="CSV", help="a real rig record of an azimuth run: columns "
                   "t,alpha_rate,beta_rate,axial_loss,lateral_alpha,lateral_beta,moment")
    p.add_argument("--rig-elevation", metavar="CSV", help="the same for an elevation run")
    p.add_argument("--thrust", type=float, help="the unit's steady thrust T in N during a real rig run "
                   "(needed with --rig-*: K = measured gain / (gain_per_newton T))")
    p.add_argument("--rows", default=",".join(("f1x", "f1y", "m1z", "f2x", "f2z")),
                   help="rows to fit, comma-separated (default all five)")
    p.add_argument("--unit", type=int, default=0, help="unit on the simulated rig (default 0)")
    p.add_argument("--jet", type=float, default=0.75, help="propeller speed on the simulated rig as a "
                   "fraction of n_max (default 0.75, seed 004's 75 %% PWM)")
    p.add_argument("--samples", default="18000", help="pseudo-impulse length N (default 18000)")
    p.add_argument("--rate", type=float, default=400.0, help="sample rate Hz (default 400; band = a rate / N)")
    p.add_argument("--a", type=float, default=450.0, help="power-spectrum parameter a of eq. 1 (default 450)")
    p.add_argument("--b", type=float, default=2100.0, help="expansion parameter b of eq. 3 (default 2100)")
    p.add_argument("--peak-rate", type=float, default=1.0, help="peak joint rate rad/s (default 1)")
    p.add_argument("--noise", type=float, default=0.0, help="force-sensor noise N on the simulated rig "
                   "(the moment gets a fifth of it in N m)")
    p.add_argument("--export-design", metavar="CSV", help="write the designed profile t,rate,angle "
                   "(s, rad/s, rad) for a real rig")
    p.add_argument("--design-plot", metavar="PNG", help="plot the design as seed 004 Figure 6")
    p.add_argument("--save-rig", metavar="PREFIX", help="write the simulated rig records as "
                   "PREFIX_azimuth.csv and PREFIX_elevation.csv")
    _common(p, example=False)


def _window(p) -> None:
    p.add_argument("--t0", type=float, help="use the trace from this time on (s), e.g. the release")
    p.add_argument("--t1", type=float, help="use the trace up to this time (s)")


def _common(p, example: bool = True) -> None:
    p.add_argument("--vehicle", help="vehicle TOML (default: the reference vehicle asr4)")
    p.add_argument("--json", metavar="OUT.json", help="write the results and the fragment as JSON")
    p.add_argument("--fragment", metavar="OUT.toml", help="write the fitted vehicle-file keys as TOML")
    p.add_argument("--plot", metavar="OUT.png", help="draw the fit (PNG)")
    if example:
        p.add_argument("--make-example", metavar="PATH", help="write a synthetic measurement file of this "
                       "method's format (from the vehicle model) and stop")
    p.add_argument("--seed", type=int, default=0, help="random seed of synthetic data (default 0)")


def run(args) -> int:
    handler = {
        "thrust": _thrust, "free-decay": _free_decay, "pendulum": _pendulum,
        "tables": _tables, "azimuth": _azimuth,
    }[args.method]
    try:
        vehicle = load_vehicle(args.vehicle)
        return handler(args, vehicle)
    except (InputError, VehicleFileError, ValueError, OSError) as exc:  # RecordingError is a ValueError
        msg = str(exc) if not isinstance(exc, OSError) else f"{getattr(exc, 'filename', '') or ''}: {exc.strerror or exc}"
        print(f"jetloop identify {args.method}: error: {msg}", file=sys.stderr)
        return 2


# ------------------------------------------------------------------------------------------------
# CSV in and out

_PLAIN_NUMBER = re.compile(r"[+-]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)(?:[eE][+-]?[0-9]+)?|[+-]?(?:nan|inf)", re.I)


def read_columns(path: str, numeric: tuple, text: tuple = ()) -> dict:
    """Columns of a CSV with a header line ('#' lines and blank lines skipped), checked."""
    if path is None:
        raise InputError("no input file given")
    p = Path(path)
    try:
        # a regular file, bounded (`identify thrust /dev/zero` read until memory ran out, a FIFO
        # blocked: issue 15 re-run); a byte-order mark (spreadsheet exports) is not content
        raw = read_text_bounded(p, MAX_CSV_BYTES)
    except (OSError, UnicodeDecodeError) as exc:  # not UTF-8 text: a clear error, not a traceback
        raise InputError(f"{path}: cannot read: {getattr(exc, 'strerror', None) or exc}") from exc
    rows = [(i + 1, r) for i, r in enumerate(csv.reader(raw.splitlines()))
            if r and not r[0].lstrip().startswith("#") and any(c.strip() for c in r)]
    if not rows:
        raise InputError(f"{path}: empty; expected a header line with columns {','.join(numeric + text)}")
    header = [c.strip().lower() for c in rows[0][1]]
    missing = [c for c in numeric + text if c not in header]
    if missing:
        raise InputError(f"{path}:{rows[0][0]}: missing column(s) {','.join(missing)}; expected a header "
                         f"with {','.join(numeric + text)}, got {','.join(header)}")
    out = {c: [] for c in numeric + text}
    for line, r in rows[1:]:
        if len(r) < len(header):
            raise InputError(f"{path}:{line}: {len(r)} fields, expected {len(header)} ({','.join(header)})")
        for c in numeric:
            s = r[header.index(c)].strip()
            try:  # a plain decimal number: float() also reads "1_0" as 10 and Arabic-Indic digits
                v = float(s) if _PLAIN_NUMBER.fullmatch(s) else float("invalid")
            except ValueError:
                shown = repr(s) if len(s) <= 40 else repr(s[:36]) + "..."
                raise InputError(f"{path}:{line}: column '{c}': expected a number, got {shown}") from None
            if not math.isfinite(v):
                raise InputError(f"{path}:{line}: column '{c}': expected a finite number, got {s!r}")
            out[c].append(v)
        for c in text:
            out[c].append(r[header.index(c)].strip().lower())
    if len(rows) < 2:
        raise InputError(f"{path}: a header but no data rows")
    return {c: (np.array(v) if c in numeric else np.array(v, dtype=object)) for c, v in out.items()}


def write_columns(path: str, columns: dict, comment: str = "") -> None:
    names = list(columns)
    n = len(next(iter(columns.values())))
    with open(path, "w", newline="", encoding="utf-8") as f:
        if comment:
            for line in comment.splitlines():
                f.write(f"# {line}\n")
        w = csv.writer(f)
        w.writerow(names)
        for i in range(n):
            w.writerow([_fmt(columns[c][i]) for c in names])


def _fmt(v):
    return v if isinstance(v, str) else f"{float(v):.10g}"


def _emit(args, results: dict, fragment: dict, summary: list) -> int:
    """Print the summary and fragment; write JSON / TOML where asked."""
    results = dict(results)
    results["fragment"] = {k: _plain(v) for k, v in fragment.items()}
    text = fragment_toml(fragment) if fragment else ""
    print("\n".join(summary))
    if text:
        print("\nvehicle-file fragment:\n" + text.rstrip())
    if args.json:
        Path(args.json).write_text(json.dumps(_plain(results), indent=2) + "\n", encoding="utf-8")
        print(f"wrote {args.json}")
    if args.fragment:
        Path(args.fragment).write_text(text, encoding="utf-8")
        print(f"wrote {args.fragment}")
    return 0


def _plain(v):
    if isinstance(v, dict):
        return {str(k): _plain(x) for k, x in v.items()}
    if isinstance(v, (list, tuple)):
        return [_plain(x) for x in v]
    if isinstance(v, np.ndarray):
        return _plain(v.tolist())
    if isinstance(v, (np.floating, float)):
        return float(v)
    if isinstance(v, (np.integer,)):
        return int(v)
    return v


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path):
    """Lay out, write (110 dpi) and close a figure of one of the plots below."""
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    _pyplot().close(fig)


def _need(args, *names):
    missing = [f"--{n.replace('_', '-')}" for n in names if getattr(args, n) is None]
    if missing:
        raise InputError(f"missing {', '.join(missing)} (needed to fit)")


AZ_SAMPLES = (16, 1_000_000)  # the pseudo-impulse length N (16 MB per complex array at the top)
AZ_RATE_HZ = (50.0, 20_000.0)  # below 50 Hz the simulated rig's fixed step diverges (10 Hz: NaN)
AZ_PEAK_RATE_RAD_S = (0.01, 10.0)
AZ_NOISE_N = (0.0, 1000.0)


def _whole(text) -> int | None:
    """An integer given as digits or as a whole float ("18000", "1.8e4"), or None."""
    try:
        v = float(text)
    except (TypeError, ValueError):
        return None
    return int(v) if math.isfinite(v) and v == int(v) and abs(v) < 2 ** 53 else None


def _within(name: str, value, lo: float, hi: float, unit: str = "", why: str = "") -> float:
    """One line naming the flag, its value with the unit, the range and why (NaN fails every test)."""
    if value is None or not (lo <= value <= hi):
        u = f" {unit}" if unit else ""
        shown = f"{value:g}" if isinstance(value, (int, float)) else repr(value)
        raise InputError(f"{name} {shown}{u}: expected {lo:g}-{hi:g}{u}" + (f" ({why})" if why else ""))
    return float(value)


def _positive(name: str, value) -> float:
    if value is None or not (math.isfinite(value) and value > 0):
        raise InputError(f"{name} must be a finite number > 0, got {value!r}")
    return float(value)


# ------------------------------------------------------------------------------------------------
# thrust

def _no_jets(vehicle, method: str) -> None:
    """The seed methods of jets (000: K(J); 004: azimuth transients) need a vectored water-jet."""
    if not vehicle.n_jets:
        raise InputError(f"{vehicle.name} has no vectored water-jets: `identify {method}` fits a jet's "
                         f"{'K(J) of seed 000' if method == 'thrust' else 'azimuth transients of seed 004'}; "
                         "its fixed thrusters' curve is the [fixed_thruster] table of the vehicle file")


def _thrust(args, vehicle) -> int:
    _no_jets(vehicle, "thrust")
    from . import thrust as th

    rho = _positive("--rho", args.rho if args.rho is not None else vehicle.environment.rho)
    D = _positive("--diameter", args.diameter if args.diameter is not None else vehicle.thruster.diameter)
    if args.make_example:
        # seed 000 Figure 9 grid (J over 0..0.54) plus the section 6.3 verification conditions
        grid = [(v, 0.0) for v in np.linspace(0.0, 1.0, 6)]
        n1, v1, a1, t1 = th.synthesize_thrust_data(vehicle.thruster.kt, rho, D, grid,
                                                   np.array([3000, 3500, 4000, 4500, 5000]) / 60.0,
                                                   noise_rel=0.01, noise_abs_n=0.0, seed=args.seed)
        n2, v2, a2, t2 = th.synthesize_thrust_data(vehicle.thruster.kt, rho, D, th.seed000_conditions(),
                                                   np.linspace(2000, 4900, 15) / 60.0,
                                                   noise_rel=0.03, noise_abs_n=0.0, seed=args.seed + 1)
        cols = {"n": np.concatenate([n1, n2]), "v": np.concatenate([v1, v2]),
                "angle": np.concatenate([a1, a2]), "thrust": np.concatenate([t1, t2])}
        write_columns(args.make_example, cols,
                      f"synthetic thrust data from seed 000 eq. 15 with kt = {list(vehicle.thruster.kt)}, "
                      f"D = {D} m, rho = {rho}\nn rev/s, v m/s, angle rad, thrust N")
        print(f"wrote {args.make_example}: {cols['n'].size} thrust measurements")
        return 0
    d = read_columns(args.data, ("n", "v", "angle", "thrust"))
    if np.any(d["n"] <= 0):
        line = int(np.argmax(d["n"] <= 0))
        raise InputError(f"{args.data}: data row {line + 1}: n must be > 0 rev/s, got {d['n'][line]}")
    fit = th.fit_thrust(d["n"], d["v"], d["angle"], d["thrust"], rho, D)
    groups = [{"v": g.v_m_s, "angle": g.angle_rad, "n_points": g.n_points, "max_residual": g.max_residual_n,
               "mean_residual": g.mean_residual_n, "max_at_n": g.max_at_n_rev_s, "max_relative": g.max_relative}
              for g in fit.groups]
    results = {"kt": list(fit.kt), "kt_std": list(fit.kt_std), "rmse": fit.rmse_n, "r2": fit.r2,
               "j_range": [fit.j_min, fit.j_max], "residuals": groups, "rho": rho, "diameter": D}
    summary = [
        f"thrust model (seed 000 eq. 15), {d['n'].size} points, J in [{fit.j_min:.3f}, {fit.j_max:.3f}]",
        "  K(J) = {:.6g} {:+.6g} J {:+.6g} J^2".format(*fit.kt),
        "  1-sigma: " + ", ".join(f"{s:.3g}" for s in fit.kt_std) + f"   rmse {fit.rmse_n:.4f} N, R^2 {fit.r2:.5f}",
        "  residuals per condition (seed 000 sec. 6.3):",
        "    v m/s  angle deg   n   max N   at rpm   max %   mean N",
    ]
    for g in fit.groups:
        summary.append(f"    {g.v_m_s:5.2f}  {math.degrees(g.angle_rad):8.1f}  {g.n_points:3d}  {g.max_residual_n:6.3f}"
                       f"  {60 * g.max_at_n_rev_s:7.0f}  {100 * g.max_relative:6.1f}  {g.mean_residual_n:7.3f}")
    if args.plot:
        _plot_thrust(args.plot, d, fit, rho, D)
        summary.append(f"wrote {args.plot}")
    return _emit(args, results, {"thruster.kt": list(fit.kt)}, summary)


def _plot_thrust(path, d, fit, rho, D):
    from . import thrust as th

    plt = _pyplot()
    fig, (ax1, ax2) = plt.subplots(1, 2, figsize=(11, 4.2))
    J = th.advance_ratio(d["n"], d["v"], d["angle"], D)
    kt = th.thrust_coefficient(d["n"], d["thrust"], rho, D)
    ax1.plot(J, kt, "k.", ms=4, label="measured K_T (eq. 13)")
    jj = np.linspace(min(0.0, J.min()), J.max(), 200)
    ax1.plot(jj, fit.kt[0] + fit.kt[1] * jj + fit.kt[2] * jj ** 2, "r-", label="fit (eq. 14)")
    ax1.set_xlabel("advance ratio J = V cos(theta) / (n D)")
    ax1.set_ylabel("K_T")
    ax1.set_title("Thrust coefficient (seed 000 Fig. 21)")
    ax1.legend()
    ax1.grid(alpha=0.3)
    big = [g for g in fit.groups if g.n_points >= 10] or list(fit.groups)
    for g in big:
        sel = (np.abs(d["v"] - g.v_m_s) < 1e-6) & (np.abs(d["angle"] - g.angle_rad) < 1e-6)
        order = np.argsort(d["n"][sel])
        line, = ax2.plot(60 * d["n"][sel][order], np.abs(fit.residual_n[sel][order]), "o-", ms=3,
                         label=f"{g.v_m_s:.2f} m/s, {math.degrees(g.angle_rad):.0f} deg")
        ax2.axhline(g.max_residual_n, color=line.get_color(), ls="--", lw=0.8)
    ax2.set_xlabel("propeller speed (rpm)")
    ax2.set_ylabel("|residual| (N)")
    ax2.set_title("Residuals per condition, dashed: max (Figs. 24, 26)")
    ax2.legend(fontsize=7, ncol=2)
    ax2.grid(alpha=0.3)
    _save(fig, path)


# ------------------------------------------------------------------------------------------------
# free decay (spring)

def _trace(args, vehicle, name: str) -> dict:
    """{"t", name} from a CSV, or from a recording: depth (pressure) for y, roll / pitch for theta."""
    path = args.data
    if path is None:
        raise InputError("no input file given (or use --make-example PATH)")
    if Path(path).suffix.lower() in (".tlog", ".bin"):
        from ground.recording import read_recording

        rec = read_recording(path)
        if name == "y":
            if rec.pressure is None or len(rec.pressure.time_s) == 0:
                raise InputError(f"{path}: no pressure stream (SCALED_PRESSURE2 / BARO) to read depth from")
            e = vehicle.environment
            t = np.asarray(rec.pressure.time_s, float)
            y = (np.asarray(rec.pressure.press_abs_pa, float) - e.p_atm) / (e.rho * e.g)
        else:
            if rec.attitude is None or len(rec.attitude.time_s) == 0:
                raise InputError(f"{path}: no ATTITUDE stream to read the swing angle from")
            t = np.asarray(rec.attitude.time_s, float)
            y = np.asarray(rec.attitude.euler_rad, float)[:, 0 if args.angle == "roll" else 1]
        d = {"t": t, name: y}
    else:
        d = read_columns(path, ("t", name))
    sel = np.ones(d["t"].size, bool)
    if args.t0 is not None:
        sel &= d["t"] >= args.t0
    if args.t1 is not None:
        sel &= d["t"] <= args.t1
    if sel.sum() < 20:
        raise InputError(f"{path}: {int(sel.sum())} samples in the --t0/--t1 window; a free decay needs at least 20")
    return {k: v[sel] for k, v in d.items()}


def _write_tlog_depth(path, t, press_pa) -> None:
    """A minimal recording of the pressure stream (HEARTBEAT + SCALED_PRESSURE2)."""
    from hil.tlog import FIXED_EPOCH_US, TlogWriter
    from onboard import mavlink_codec as codec
    from onboard.sensors import PressureSample

    with TlogWriter(path) as w:
        next_hb = 0.0
        for ti, p in zip(t, press_pa):
            if ti >= next_hb:
                w.write(codec.heartbeat(), FIXED_EPOCH_US + int(round(ti * 1e6)))
                next_hb += 1.0
            w.write(codec.encode_pressure(PressureSample(float(ti), float(p))), FIXED_EPOCH_US + int(round(ti * 1e6)))


def _hydro_fragment(vehicle, axis: str, added=None, k_l=None, k_q=None) -> dict:
    i = AXES.index(axis)
    out = {}
    for key, val in (("hydro.added_mass", added), ("hydro.linear_damping", k_l),
                     ("hydro.quadratic_damping", k_q)):
        if val is not None:
            row = list(vehicle.get(key))
            row[i] = max(float(val), 0.0)
            out[key] = row
    return out


def _free_decay(args, vehicle) -> int:
    from . import free_decay as fd

    rho = _positive("--rho", args.rho if args.rho is not None else vehicle.environment.rho)
    if args.make_example:
        t, y, K, press = _hil_spring_trace(vehicle, args.spring if args.spring is not None else 400.0, args.seed)
        if Path(args.make_example).suffix.lower() == ".tlog":
            _write_tlog_depth(args.make_example, t, press)
        else:
            write_columns(args.make_example, {"t": t, "y": y},
                          f"HIL plant heave free decay on a spring rig K = {K} N/m (vehicle {vehicle.name}, "
                          "surface and wall proximity off), depth from the pressure sensor\nt s, y m")
        print(f"wrote {args.make_example}: {t.size} samples; fit with --spring {K}")
        return 0
    _need(args, "spring")
    mass = _positive("--mass", args.mass if args.mass is not None else vehicle.body.mass)
    volume = _positive("--volume", args.volume if args.volume is not None else vehicle.body.volume)
    length = _positive("--length", args.length if args.length is not None else 2 * vehicle.body.radius)
    K = _positive("--spring", args.spring)
    d = _trace(args, vehicle, "y")
    f = fd.spring_free_decay(d["t"], d["y"], mass, K, volume, length, rho, args.zeta_structural)
    results = {
        "omega_n": f.omega_n_rad_s, "zeta": f.zeta, "added_mass": f.added_mass_kg, "cm": f.cm, "cd": f.cd,
        "omega_n_log_decrement": f.omega_n_log_decrement_rad_s, "zeta_log_decrement": f.zeta_log_decrement,
        "amplitude": f.amplitude_m, "equilibrium": f.equilibrium_m,
        "chin": {"added_mass": f.chin_added_mass_kg, "cm": f.chin_cm, "k_l": f.k_l_n_s_m,
                 "k_q": f.k_q_n_s2_m2, "cd": f.chin_cd, "rmse": f.chin_rmse_m},
        "inputs": {"mass": mass, "spring": K, "volume": volume, "length": length, "rho": rho,
                   "zeta_structural": args.zeta_structural, "axis": args.axis},
    }
    summary = [
        f"spring free decay (seed 001 eq. 6-9), {d['t'].size} samples, m = {mass} kg, K = {K} N/m",
        f"  least squares : omega_n {f.omega_n_rad_s:.4f} rad/s, zeta {f.zeta:.4f}",
        f"  log decrement : omega_n {f.omega_n_log_decrement_rad_s:.4f} rad/s, zeta {f.zeta_log_decrement:.4f}",
        f"  added mass (eq. 7) {f.added_mass_kg:.4f} kg, C_m {f.cm:.4f}, C_D (eq. 9, A = {1000 * f.amplitude_m:.1f} mm) {f.cd:.4f}",
        f"  eq. 6 fitted (Chin): added mass {f.chin_added_mass_kg:.4f} kg, C_m {f.chin_cm:.4f}, "
        f"K_L {f.k_l_n_s_m:.4f} N s/m, K_Q {f.k_q_n_s2_m2:.4f} N s^2/m^2, C_D {f.chin_cd:.4f}, rmse {1000 * f.chin_rmse_m:.2f} mm",
    ]
    if args.plot:
        _plot_spring(args.plot, d, f, mass, K)
        summary.append(f"wrote {args.plot}")
    frag = _hydro_fragment(vehicle, args.axis, f.chin_added_mass_kg, f.k_l_n_s_m, f.k_q_n_s2_m2)
    return _emit(args, results, frag, summary)


def _hil_spring_trace(vehicle, K: float, seed: int, amplitude: float = 0.05, duration: float = 20.0):
    """Heave free decay of the HIL plant on a spring rig, read through its pressure sensor."""
    from hil.plant import Plant
    from onboard.sensors import depth_from_pressure

    K = _positive("--spring", K)
    v = vehicle.with_effects(surface_proximity=False, wall_proximity=False)
    plant = Plant(v, dt_s=0.002, seed=seed, depth_m=0.5, rig_stiffness=[0.0, 0.0, K], noise=True)
    plant.state[2] += amplitude
    s = plant.advance(duration)
    t = np.array([q.time_s for q in s.pressure])
    press = np.array([q.press_abs_pa for q in s.pressure])
    y = np.array([depth_from_pressure(q, v) for q in press])
    return t, y, K, press


def _plot_spring(path, d, f, mass, K):
    from . import free_decay as fd

    plt = _pyplot()
    t, y = d["t"], d["y"]
    tt = t - t[0]
    fig, ax = plt.subplots(figsize=(9, 4))
    ax.plot(t, y, "b-", lw=1, label="measured")
    wd = f.omega_n_rad_s * math.sqrt(max(1 - f.zeta ** 2, 0.0))
    ax.plot(t, f.equilibrium_m + f.sine_amplitude_m * np.exp(-f.zeta * f.omega_n_rad_s * tt)
            * np.cos(wd * tt + f.sine_phase_rad), "r--", lw=1,
            label=f"omega_n {f.omega_n_rad_s:.3f} rad/s, zeta {f.zeta:.3f}")
    m_tot = mass + f.chin_added_mass_kg
    dt = float(np.median(np.diff(t)))
    y_eq = f.equilibrium_m  # the Chin fit's own equilibrium is within noise of the sinusoid's
    sim = fd._oscillator(K * y_eq / m_tot, -K / m_tot, 0.0, f.k_l_n_s_m / m_tot,
                         f.k_q_n_s2_m2 / m_tot, f.chin_initial[0], f.chin_initial[1], t.size, dt, 4)
    ax.plot(t, sim, "g:", lw=1.2, label=f"eq. 6: m' {f.chin_added_mass_kg:.3f} kg, K_L {f.k_l_n_s_m:.2f}, K_Q {f.k_q_n_s2_m2:.2f}")
    ax.set_xlabel("t (s)")
    ax.set_ylabel("y (m)")
    ax.set_title(f"Spring free decay (seed 001 Fig. 7): added mass {f.added_mass_kg:.3f} kg, C_m {f.cm:.3f}")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    _save(fig, path)


# ------------------------------------------------------------------------------------------------
# pendulum

# Seed 001 Table 3 pendulum model (PVC, 22 % scale) and a plausible set of its coefficients.
_PENDULUM_EXAMPLE = {"mass": 0.146, "volume": 107597e-9, "length": 0.5, "area": 0.0045,
                     "added_mass": 0.089, "k_l": 0.05, "k_q": 0.6}


def _pendulum(args, vehicle) -> int:
    from . import free_decay as fd

    rho = _positive("--rho", args.rho if args.rho is not None else vehicle.environment.rho)
    g = _positive("--g", args.g if args.g is not None else vehicle.environment.g)
    if args.make_example:
        e = _PENDULUM_EXAMPLE
        t, th = fd.synthesize_pendulum(e["mass"], e["volume"], e["length"], e["added_mass"], e["k_l"], e["k_q"],
                                       math.radians(15.0), 20.0, 100.0, rho, g, noise_rad=0.002, seed=args.seed)
        write_columns(args.make_example, {"t": t, "theta": th},
                      "synthetic pendulum free decay, seed 001 Table 3 model: "
                      + ", ".join(f"{k} {v}" for k, v in e.items()) + "\nt s, theta rad")
        print(f"wrote {args.make_example}: {t.size} samples; fit with --mass {e['mass']} --volume {e['volume']:.6g} "
              f"--length {e['length']} --area {e['area']}")
        return 0
    _need(args, "mass", "volume", "length", "area")
    d = _trace(args, vehicle, "theta")
    f = fd.pendulum_free_decay(d["t"], d["theta"], args.mass, args.volume, args.length, args.area, rho, g)
    results = {
        "a1": f.a1, "a2": f.a2, "added_mass": f.added_mass_kg, "cm": f.cm, "cd": f.cd, "rmse": f.rmse_rad,
        "chin": {"a1": f.chin_a1, "al": f.chin_al, "aq": f.chin_aq, "added_mass": f.chin_added_mass_kg,
                 "k_l": f.k_l_n_s_m, "k_q": f.k_q_n_s2_m2, "cd": f.chin_cd, "rmse": f.chin_rmse_rad},
        "inputs": {"mass": args.mass, "volume": args.volume, "length": args.length, "area": args.area,
                   "rho": rho, "g": g, "axis": args.axis},
    }
    summary = [
        f"pendulum free decay (seed 001 eq. 10-16), {d['t'].size} samples",
        f"  eq. 14: a1 {f.a1:.5g} 1/s^2, a2 {f.a2:.5g} 1/rad (rmse {f.rmse_rad:.2e} rad)",
        f"  added mass (eq. 15) {f.added_mass_kg:.5g} kg, C_m {f.cm:.4f}, C_D (eq. 16) {f.cd:.4f}",
        f"  Chin: a1 {f.chin_a1:.5g}, aL {f.chin_al:.5g} 1/s, aQ {f.chin_aq:.5g} 1/rad, added mass "
        f"{f.chin_added_mass_kg:.5g} kg, K_L {f.k_l_n_s_m:.4g} N s/m, K_Q {f.k_q_n_s2_m2:.4g} N s^2/m^2, C_D {f.chin_cd:.4f}",
        "  (values of the body on the rod; scale a scale model's by similarity before using the fragment)",
    ]
    if args.plot:
        _plot_pendulum(args.plot, d, f)
        summary.append(f"wrote {args.plot}")
    frag = _hydro_fragment(vehicle, args.axis, f.chin_added_mass_kg, f.k_l_n_s_m, f.k_q_n_s2_m2)
    return _emit(args, results, frag, summary)


def _plot_pendulum(path, d, f):
    from . import free_decay as fd

    plt = _pyplot()
    t, th = d["t"], d["theta"]
    dt = float(np.median(np.diff(t)))
    fig, ax = plt.subplots(figsize=(9, 4))
    ax.plot(t, np.degrees(th), "b-", lw=1, label="measured")
    m = fd._oscillator(0.0, 0.0, f.a1, 0.0, f.a2, f.initial[0], f.initial[1], t.size, dt, 4)
    c = fd._oscillator(0.0, 0.0, f.chin_a1, f.chin_al, f.chin_aq, f.chin_initial[0], f.chin_initial[1], t.size, dt, 4)
    ax.plot(t, np.degrees(m), "r--", lw=1, label=f"eq. 14: a1 {f.a1:.3f}, a2 {f.a2:.3f}")
    ax.plot(t, np.degrees(c), "g:", lw=1.2, label=f"Chin: aL {f.chin_al:.3f}, aQ {f.chin_aq:.3f}")
    ax.set_xlabel("t (s)")
    ax.set_ylabel("theta (deg)")
    ax.set_title(f"Pendulum free decay (seed 001): added mass {f.added_mass_kg:.4f} kg, C_D {f.cd:.3f}")
    ax.legend(fontsize=8)
    ax.grid(alpha=0.3)
    _save(fig, path)


# ------------------------------------------------------------------------------------------------
# tables

def _tables(args, vehicle) -> int:
    from . import tables as tb

    if args.make_example:
        am, dp = _table_examples(vehicle, args.seed)
        base = str(args.make_example)
        write_columns(base + "_added_mass.csv", am, "synthetic added mass vs water-entry depth per pitch attitude "
                      "(seed 003 Fig. 5 shape)\nattitude rad, depth m, dof, added_mass kg or kg m^2")
        write_columns(base + "_damping.csv", dp, "synthetic damping vs speed per attitude (seed 003 Figs. 8-9 "
                      f"shape) from the vehicle {vehicle.name}'s D_l, D_q\nattitude rad, dof, speed m/s or rad/s, force N or N m")
        print(f"wrote {base}_added_mass.csv and {base}_damping.csv")
        return 0
    if not args.added_mass and not args.damping:
        raise InputError("give --added-mass CSV, --damping CSV or both")
    lines, curves, a, d = (), (), None, None
    if args.added_mass:
        a = read_columns(args.added_mass, ("attitude", "depth", "added_mass"), ("dof",))
        lines = tb.fit_added_mass_lines(a["attitude"], a["depth"], a["dof"], a["added_mass"])
    if args.damping:
        d = read_columns(args.damping, ("attitude", "speed", "force"), ("dof",))
        curves = tb.fit_damping(d["attitude"], d["dof"], d["speed"], d["force"])
    full = args.full_depth if args.full_depth is not None else 2 * vehicle.body.radius
    current = {k: vehicle.get(k) for k in ("hydro.added_mass", "hydro.linear_damping", "hydro.quadratic_damping")}
    frag = tb.vehicle_values(current, lines, curves, full, args.attitude)
    results = {
        "added_mass_lines": [ln.__dict__ for ln in lines],
        "damping_curves": [c.__dict__ for c in curves],
        "full_depth": full, "attitude": args.attitude,
    }
    summary = [f"tables (seed 003 sec. 3.2): {len(lines)} added-mass lines, {len(curves)} damping curves"]
    for ln in lines:
        summary.append(f"  M_A {ln.dof:5s} at {math.degrees(ln.attitude_rad):5.1f} deg: {ln.intercept:.4g} + "
                       f"{ln.slope:.4g} depth  (R^2 {ln.r2:.4f}, {ln.n_points} pts)")
    for c in curves:
        summary.append(f"  D   {c.dof:5s} at {math.degrees(c.attitude_rad):5.1f} deg: {c.c0:.4g} {c.c1:+.4g} v {c.c2:+.4g} v^2"
                       f"  (R^2 {c.r2:.4f}); D_l {c.linear:.4g}, D_q {c.quadratic:.4g} (R^2 {c.r2_origin:.4f})")
    if not frag:
        summary.append(f"  (no fit at attitude {args.attitude} rad: no vehicle keys)")
    if args.plot:
        _plot_tables(args.plot, lines, curves, full, a, d)
        summary.append(f"wrote {args.plot}")
    return _emit(args, results, frag, summary)


def _table_examples(vehicle, seed: int):
    """Added mass lines per attitude (slopes fall with pitch, as seed 003 Fig. 5) and damping curves."""
    rng = np.random.default_rng(seed)
    R2 = 2 * vehicle.body.radius
    ma = vehicle.hydro.added_mass
    am = {"attitude": [], "depth": [], "dof": [], "added_mass": []}
    for att_deg, shrink in ((0.0, 1.0), (15.0, 0.85), (30.0, 0.7)):
        for dof in ("surge", "heave", "pitch"):
            full = ma[DOFS.index(dof)] * shrink
            for depth in np.linspace(0.2 * R2, R2, 6):
                val = full * (0.1 + 0.9 * depth / R2) * (1 + 0.01 * rng.standard_normal())
                am["attitude"].append(math.radians(att_deg))
                am["depth"].append(depth)
                am["dof"].append(dof)
                am["added_mass"].append(val)
    dp = {"attitude": [], "dof": [], "speed": [], "force": []}
    for dof, speeds in (("surge", (0.2, 0.4, 0.6, 0.8, 1.0)), ("heave", (0.2, 0.4, 0.6, 0.8, 1.0)),
                        ("yaw", (1.0, 2.0, 3.0, 4.0, 5.0))):
        i = DOFS.index(dof)
        atts = (0.0, 10.0, 20.0, 30.0, 40.0) if dof == "surge" else (0.0,)
        for att_deg in atts:
            grow = 1 + 0.01 * att_deg
            for v in speeds:
                f = grow * (vehicle.hydro.linear_damping[i] * v + vehicle.hydro.quadratic_damping[i] * v * v)
                dp["attitude"].append(math.radians(att_deg))
                dp["dof"].append(dof)
                dp["speed"].append(v)
                dp["force"].append(f * (1 + 0.01 * rng.standard_normal()))
    return am, dp


def _plot_tables(path, lines, curves, full_depth, am=None, dp=None):
    plt = _pyplot()
    dofs_l = sorted({ln.dof for ln in lines}, key=lambda d: DOFS.index(d))
    dofs_c = sorted({c.dof for c in curves}, key=lambda d: DOFS.index(d))
    n = max(len(dofs_l) + len(dofs_c), 1)
    cols = min(n, 3)
    nrow = (n + cols - 1) // cols
    fig, axes = plt.subplots(nrow, cols, figsize=(4.2 * cols, 3.6 * nrow), squeeze=False)
    axes = axes.ravel()
    for ax in axes[n:]:
        ax.axis("off")
    for ax, dof in zip(axes, dofs_l):
        for ln in (x for x in lines if x.dof == dof):
            dd = np.linspace(ln.depth_min_m, max(ln.depth_max_m, full_depth), 50)
            line, = ax.plot(dd, ln.at(dd), "-", label=f"{math.degrees(ln.attitude_rad):.0f} deg: {ln.intercept:.3g}+{ln.slope:.3g} l")
            if am is not None:
                sel = (am["dof"] == dof) & (np.abs(am["attitude"] - ln.attitude_rad) < 1e-9)
                ax.plot(am["depth"][sel], am["added_mass"][sel], "o", ms=3, color=line.get_color())
        ax.axvline(full_depth, color="k", ls=":", lw=0.8)
        ax.set_xlabel("water-entry depth l (m)")
        ax.set_ylabel("added mass")
        ax.set_title(f"{dof} (seed 003 Fig. 5)")
        ax.legend(fontsize=7)
        ax.grid(alpha=0.3)
    for ax, dof in zip(axes[len(dofs_l):], dofs_c):
        for c in (x for x in curves if x.dof == dof):
            vv = np.linspace(0, c.speed_max, 50)
            line, = ax.plot(vv, c.c0 + c.c1 * vv + c.c2 * vv ** 2, "-", label=f"{math.degrees(c.attitude_rad):.0f} deg")
            if dp is not None:
                sel = (dp["dof"] == dof) & (np.abs(dp["attitude"] - c.attitude_rad) < 1e-9)
                ax.plot(dp["speed"][sel], dp["force"][sel], "o", ms=3, color=line.get_color())
        ax.set_xlabel("speed (m/s or rad/s)")
        ax.set_ylabel("damping force (N or N m)")
        ax.set_title(f"{dof} damping (seed 003 Figs. 8-9)")
        ax.legend(fontsize=7)
        ax.grid(alpha=0.3)
    _save(fig, path)


# ------------------------------------------------------------------------------------------------
# azimuth

_RIG_COLUMNS = ("t", "alpha_rate", "beta_rate", "axial_loss", "lateral_alpha", "lateral_beta", "moment")


def _azimuth(args, vehicle) -> int:
    _no_jets(vehicle, "azimuth")
    from . import azimuth as az

    rows = [r.strip() for r in args.rows.split(",") if r.strip()]
    bad = [r for r in rows if r not in az.ROWS]
    if bad or not rows:
        raise InputError(f"--rows: unknown row(s) {bad}; expected a comma-separated subset of {','.join(az.ROWS)}")
    # every number in a range before any work (issue 15, second pass: --samples 1e10 was a
    # MemoryError of 149 GiB, --noise nan was flown, --rate 10 diverged the simulated rig and
    # ended in scipy's "Initial guess is outside of provided bounds", --rate 1e300 an IndexError)
    n = _whole(args.samples)
    if n is None or not AZ_SAMPLES[0] <= n <= AZ_SAMPLES[1] or n % 2:
        raise InputError(f"--samples {args.samples}: expected an even number {AZ_SAMPLES[0]}-{AZ_SAMPLES[1]} "
                         f"(a 400 Hz rig record of at most {AZ_SAMPLES[1] / 400 / 60:.0f} min)")
    args.samples = n
    _within("--rate", args.rate, *AZ_RATE_HZ, "Hz", "a rig's force-sensor rate; seed 004: 400 Hz")
    _within("--a", args.a, 1.0, n / 2, "", "below N/2, so the band a * rate / N stays under the Nyquist frequency")
    _within("--b", args.b, 1.0, 1e7, "", "seed 004: 2100")
    _within("--peak-rate", args.peak_rate, *AZ_PEAK_RATE_RAD_S, "rad/s", "a joint's rate")
    _within("--noise", args.noise, *AZ_NOISE_N, "N", "the force sensor's noise")
    if not 0 < args.jet <= 1:
        raise InputError(f"--jet must be a fraction of n_max in (0, 1], got {args.jet}")
    if not 0 <= args.unit < vehicle.n_units:
        raise InputError(f"--unit must be 0..{vehicle.n_units - 1}, got {args.unit}")
    design = az.design_pseudo_impulse(args.samples, args.rate, args.a, args.b, args.peak_rate,
                                      vehicle.servo.angle_limit)
    summary = [f"pseudo-impulse (seed 004 eq. 1-3): N {design.n_samples}, {design.rate_hz:g} Hz, a {design.a:g}, "
               f"b {design.b:g}, band {design.band_hz:.2f} Hz, peak rate {np.max(np.abs(design.rate_rad_s)):.3f} rad/s, "
               f"angle {design.angle_rad.min():+.3f}..{design.angle_rad.max():+.3f} rad"]
    if args.export_design:
        write_columns(args.export_design, {"t": design.time_s, "rate": design.rate_rad_s, "angle": design.angle_rad},
                      "seed 004 pseudo-impulse joint-rate profile\nt s, rate rad/s, angle rad (command)")
        summary.append(f"wrote {args.export_design}")
    if args.design_plot:
        _plot_design(args.design_plot, design)
        summary.append(f"wrote {args.design_plot}")
    gain = vehicle.effects.azimuth_transient.gain_per_newton
    if gain <= 0:
        raise InputError(f"{vehicle.source}: effects.azimuth_transient.gain_per_newton is 0; K cannot be normalised")
    records = {}
    if args.rig_azimuth or args.rig_elevation:
        T = _positive("--thrust", args.thrust)
        for axis, path in (("azimuth", args.rig_azimuth), ("elevation", args.rig_elevation)):
            if path:
                c = read_columns(path, _RIG_COLUMNS)
                records[axis] = az.RigRecord(c["t"], c["alpha_rate"], c["beta_rate"], c["axial_loss"],
                                             c["lateral_alpha"], c["lateral_beta"], c["moment"], T, gain)
        source = "rig records " + ", ".join(p for p in (args.rig_azimuth, args.rig_elevation) if p)
    else:
        n = args.jet * vehicle.thruster.n_max
        for axis in sorted({az.ROW_AXIS[r] for r in rows}):
            records[axis] = az.simulate_fixed_rig(vehicle, design, axis, args.unit, n, noise_n=args.noise,
                                                  noise_nm=args.noise / 5, seed=args.seed + (axis == "elevation"))
        source = f"vehicle {vehicle.name} clamped on a rig, unit {args.unit}, n {n:.1f} rev/s"
        if args.save_rig:
            for axis, r in records.items():
                write_columns(f"{args.save_rig}_{axis}.csv", dict(zip(_RIG_COLUMNS, (
                    r.time_s, r.alpha_rate_rad_s, r.beta_rate_rad_s, r.axial_loss_n, r.lateral_alpha_n,
                    r.lateral_beta_n, r.reaction_moment_nm))), f"simulated rig record ({axis} run), T = {r.thrust_n:.6g} N")
                summary.append(f"wrote {args.save_rig}_{axis}.csv")
    summary.append(f"source: {source}")
    at = vehicle.effects.azimuth_transient
    fits, bodes, results_rows, frag = {}, {}, {}, {}
    for row in rows:
        rec = records.get(az.ROW_AXIS[row])
        if rec is None:
            raise InputError(f"row {row} needs a {az.ROW_AXIS[row]} run: give --rig-{az.ROW_AXIS[row]} CSV")
        u, y = az.row_signals(rec, row)
        rate = 1.0 / float(np.median(np.diff(rec.time_s)))
        bode = az.frequency_response(u, y, rate, design.band_hz)
        fit = az.fit_row(row, bode, getattr(at, row), gain * rec.thrust_n, seed=args.seed)
        fits[row], bodes[row] = fit, bode
        results_rows[row] = {"coeffs": list(fit.coeffs), "correlation": fit.correlation, "rms_db": fit.rms_db,
                             "measured_gain": fit.measured_gain, "prior": list(getattr(at, row)),
                             "seed004_correlation_75pwm": az.SEED004_CORRELATION_75[row]}
        frag[f"effects.azimuth_transient.{row}"] = list(fit.coeffs)
        summary.append(f"  {row}: [" + ", ".join(f"{c:.2f}" for c in fit.coeffs) + f"]  correlation {fit.correlation:.4f} "
                       f"(seed 004: {az.SEED004_CORRELATION_75[row]:.2f}), rms {fit.rms_db:.3f} dB")
        if fit.at_bound:
            summary.append(f"    warning: {row} {', '.join(fit.at_bound)} stopped at the bound (a factor 30 from the prior): "
                           f"the {design.band_hz:.3g} Hz band and this noise do not resolve it; keep the prior's value, "
                           "average repeated runs or widen the band")
        results_rows[row]["at_bound"] = list(fit.at_bound)
    results = {"design": {"samples": design.n_samples, "rate": design.rate_hz, "a": design.a, "b": design.b,
                          "q": design.q, "band_hz": design.band_hz},
               "thrust": {a: r.thrust_n for a, r in records.items()}, "gain_per_newton": gain,
               "rows": results_rows, "source": source}
    if args.plot:
        _plot_bode(args.plot, fits, bodes, at, {r: gain * records[az.ROW_AXIS[r]].thrust_n for r in rows})
        summary.append(f"wrote {args.plot}")
    return _emit(args, results, frag, summary)


def _plot_design(path, design):
    from . import azimuth as az

    plt = _pyplot()
    N = design.n_samples
    fig, axes = plt.subplots(1, 3, figsize=(13, 3.6))
    k = np.arange(N // 2)
    f = k * design.rate_hz / N
    axes[0].plot(f, az.power_spectrum(k, design.a, 1.0))
    axes[0].set_xlim(0, 2 * design.band_hz)
    axes[0].set_xlabel("frequency (Hz)")
    axes[0].set_ylabel("P(n) / Q")
    axes[0].set_title("(a) power spectrum, eq. 1")
    axes[1].plot(design.time_s, design.rate_rad_s, lw=0.6)
    axes[1].set_xlabel("t (s)")
    axes[1].set_ylabel("joint rate (rad/s)")
    axes[1].set_title("(b) pseudo-impulse, eq. 2-3")
    c = az.compress(design.rate_rad_s, N, design.b)
    tc = np.arange(N) / design.rate_hz
    tc = np.where(tc > tc[-1] / 2, tc - tc[-1] - 1 / design.rate_hz, tc)
    order = np.argsort(tc)
    axes[2].plot(tc[order], c[order], lw=0.8)
    axes[2].set_xlim(-1, 1)
    axes[2].set_xlabel("t (s)")
    axes[2].set_title("(c) compressed input: an impulse")
    for ax in axes:
        ax.grid(alpha=0.3)
    _save(fig, path)


def _plot_bode(path, fits, bodes, at, scale):
    from . import azimuth as az

    plt = _pyplot()
    rows = list(fits)
    fig, axes = plt.subplots(1, len(rows), figsize=(3.8 * len(rows), 3.6), squeeze=False)
    for ax, row in zip(axes[0], rows):
        b, f = bodes[row], fits[row]
        w = np.geomspace(b.raw_omega_rad_s[0], b.raw_omega_rad_s[-1], 300)
        ax.semilogx(b.raw_omega_rad_s, b.raw_magnitude_db, ".", color="0.6", ms=2, label="measured")
        ax.semilogx(w, az.magnitude_db(row, f.coeffs, w) + 20 * np.log10(scale[row]), "r-",
                    label=f"fit, corr {f.correlation:.3f}")
        ax.semilogx(w, az.magnitude_db(row, getattr(at, row), w) + 20 * np.log10(scale[row]), "b--", lw=0.8,
                    label="vehicle file")
        fig_no = {"f1x": "9a", "f1y": "9b", "m1z": "11", "f2x": "13a", "f2z": "13b"}[row]
        ax.set_title(f"{row} (seed 004 Fig. {fig_no})")
        ax.set_xlabel("omega (rad/s)")
        ax.set_ylabel("magnitude (dB)")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=7)
    _save(fig, path)
