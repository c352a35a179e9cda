"""The diagnosis: replay, locate, name (fit every candidate, then pairs, then a sparse term), show.

`diagnose(recording, vehicle)` returns a frozen `Diagnosis` holding the report of
spec/recording.md section 2 (`report`) and the arrays the HTML report plots. Pure apart from
the optional `progress` callback (a function of one string) the console uses.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np
from scipy.signal import savgol_filter

from onboard import model
from onboard.vehicle import Vehicle

from . import locate, replay, sparse
from .candidates import (CHANNEL_AXIS, CHANNELS, CorrectedModel, Evaluator, Fit, SegmentedEvaluator,
                         candidates_for, chi2, combine, fit)

# Decision thresholds (held-out chi-square units, noise-normalised; see README "diagnose").
MIN_DELTA = 40.0  # a finding must lower the held-out chi-square by at least this ...
MIN_DELTA_PER_PARAM = 4.0  # ... plus this per fitted parameter
MIN_EXPLAINED = 0.15  # ... and remove at least this fraction of the held-out excess over noise
SECOND_MIN_GAIN = 0.15  # a second effect must add this fraction of the first one's improvement
UNKNOWN_IF_EXPLAINED_BELOW = 0.5
SHOOT_S = 2.0  # multiple-shooting window length for the held-out NRMSE
FIT_SEGMENTS = 4
Z_GATE = 2.5  # a finding's held-out improvement must exceed Z_GATE sd of the held-out chi-square

PHRASES = {
    "thrust_inflow": "grows with the inflow along the jets (advance ratio, seed 000)",
    "motor_lag": "leads the propeller-speed changes (a first-order motor lag)",
    "servo_lag": "appears while the joints slew (joint lag)",
    "azimuth_transient": "follows the joint rates through a band-pass (seed 004 transients)",
    "surface_proximity": "appears only near the free surface (buoyancy and added mass fall)",
    "wall_proximity": "appears near the floor with heave acceleration (gap effect)",
    "current": "follows heading like a steady water velocity",
    "added_mass": "follows the acceleration",
    "linear_damping": "follows the velocity",
    "quadratic_damping": "follows the velocity squared",
    "buoyancy": "is a steady vertical force",
    "restoring_moment": "follows roll and pitch (righting arm)",
    "imu_bias": "is a steady offset of the IMU against the attitude (and motion capture) and the dynamics",
    "sensor_delay": "lags the commands by a constant time",
    "thruster_fault": "follows one jet's thrust",
    "unknown": "has a shape no known effect gives",
}


@dataclass(frozen=True)
class Diagnosis:
    report: dict
    traj: replay.Trajectory = field(repr=False)
    residual0: np.ndarray = field(repr=False)  # (N, 12) nominal residual channels
    residual1: np.ndarray = field(repr=False)  # (N, 12) with the findings
    windows: list = field(repr=False)
    fits: list = field(repr=False)  # every single-candidate Fit, ranked
    shots: dict = field(repr=False)  # "starts", "length", "before", "after", "meas"
    mass_diag: np.ndarray = field(repr=False)


def _say(progress, msg):
    if progress is not None:
        progress(msg)


def significant(f: Fit, gate: float) -> bool:
    """Named only if it lowers the held-out chi-square by more than the gate (and a minimum per
    parameter), removes a fair share of the held-out excess, and wins on BIC in training."""
    return (f.delta_holdout > max(gate, MIN_DELTA + MIN_DELTA_PER_PARAM * f.candidate.n_params)
            and f.explained > MIN_EXPLAINED and f.bic < -10.0)


def diagnose(rec, vehicle: Vehicle, progress=None, max_fit_s: float = 120.0) -> Diagnosis:
    t_start = time.perf_counter()
    _say(progress, f"replaying {rec.duration_s:.1f} s through the nominal model '{vehicle.name}'")
    ev = Evaluator(rec, vehicle)
    traj = ev.traj0
    res0 = ev.residual(ev.base)
    _say(progress, "estimating the noise floor from the data")
    noise = locate.noise_realisation(ev, res0)
    split = locate.make_split(traj, noise)
    p0 = model.pack_params(vehicle)
    act0 = ev.actuators(traj, p0, ev.base)
    windows = locate.flag_windows(traj, res0, noise, split, vehicle, act0)
    _say(progress, f"{len(windows)} window(s) above the noise floor")
    # Long recordings: candidates are fitted and scored on at most `max_fit_s` seconds, in
    # FIT_SEGMENTS segments spread evenly over the recording (every regime stays represented).
    ev_fit, split_fit, res0_fit = ev, split, res0
    if rec.duration_s > max_fit_s:
        seg = max_fit_s / FIT_SEGMENTS
        t_a, t_b = traj.time_s[0], traj.time_s[-1]
        starts = np.linspace(t_a, t_b - seg, FIT_SEGMENTS)
        evs = [Evaluator(rec.between(s0, s0 + seg), vehicle) for s0 in starts]
        ev_fit = SegmentedEvaluator(evs)
        res0_fit = ev_fit.residual(ev_fit.base)
        noises = [locate.noise_realisation(e, e.residual(e.base)) for e in evs]
        split_fit = locate.make_split([e.traj0 for e in evs], noises)
        _say(progress, f"fitting on {FIT_SEGMENTS} segments of {seg:.0f} s spread over the recording")
    # --- name: every candidate alone
    cands = candidates_for(vehicle)
    fits: list[Fit] = []
    for i, c in enumerate(cands):
        t0 = time.perf_counter()
        f = fit(ev_fit, c, split_fit, res0_fit)
        fits.append(f)
        _say(progress, f"[{i + 1}/{len(cands)}] {c.effect:18s} held-out chi2 -{f.delta_holdout:9.1f}  "
                       f"explains {100 * f.explained:5.1f} %  ({time.perf_counter() - t0:.1f} s)")
    fits.sort(key=lambda f: -f.delta_holdout)
    n_h_fit = len(split_fit.holdout) * float(split_fit.neff[split_fit.active].sum())
    gate = Z_GATE * math.sqrt(2.0 * n_h_fit)
    chosen: list[Fit] = []
    best = fits[0]
    final = None
    if significant(best, gate):
        chosen.append(best)
        final = best
        # --- a second effect on top of the first
        others = [f for f in fits[1:4] if f.delta_holdout > 0]
        pair_best = None
        for other in others:
            pc = combine(best.candidate, other.candidate)
            pf = fit(ev_fit, pc, split_fit, res0_fit, x0=tuple(best.theta) + tuple(other.theta))
            _say(progress, f"pair {pc.effect:34s} held-out chi2 -{pf.delta_holdout:9.1f}")
            if pair_best is None or pf.delta_holdout > pair_best[0].delta_holdout:
                pair_best = (pf, other)
        if pair_best is not None:
            pf, other = pair_best
            gain = pf.delta_holdout - best.delta_holdout
            if (gain > max(gate, MIN_DELTA, SECOND_MIN_GAIN * best.delta_holdout)
                    and gain > MIN_DELTA_PER_PARAM * other.candidate.n_params):
                chosen = list(_split_pair(pf, best, other))
                final = pf
    # --- unknown: a sparse term when nothing known explains enough
    c0_h, _ = chi2(res0, split, split.holdout)
    n_h = len(split.holdout) * float(split.neff[split.active].sum())
    excess0 = c0_h - n_h
    unknown = None
    explained_now = final.explained if final is not None else 0.0
    final_res = ev.residual(final.model) if final is not None else res0
    if excess0 > 2 * Z_GATE * math.sqrt(2.0 * n_h) and explained_now < UNKNOWN_IF_EXPLAINED_BELOW:
        _say(progress, "no known effect explains the residual: fitting a sparse data-driven term")
        # the sparse term alone against the nominal model, and on top of the known findings
        alone = _unknown_term(ev, traj, vehicle, None, res0, split)
        unknown = _unknown_term(ev, traj, vehicle, final, final_res, split) if final is not None else alone
        if alone is not None and final is not None and alone["delta"] > final.delta_holdout:
            unknown = dict(alone, first=True)
        if unknown is not None:
            _say(progress, f"unknown term: {unknown['formula']}")
    # --- show: held-out multiple shooting, before and after
    _say(progress, "held-out multiple shooting, before and after")
    final_model = final.model if final is not None else ev.base
    extra = None
    if unknown is not None and unknown["delta"] > Z_GATE * math.sqrt(2.0 * n_h):
        extra = unknown["coefficients"]  # the data-driven term joins the corrected simulation
        if unknown.get("first"):
            final_model = ev.base
    shots = _shoot_holdout(ev, traj, split, ev.base, final_model, extra, replay.nominal_mass_diag(vehicle))
    res1 = final_res
    findings = [_finding(f, vehicle, split, traj, res0, noise, i == 0, fits) for i, f in enumerate(chosen)]
    if unknown is not None and unknown["delta"] > Z_GATE * math.sqrt(2.0 * n_h):
        entry = {"effect": "unknown", "kind": "missing",
                 "confidence": round(unknown["confidence"], 3), "parameters": {},
                 "explanation": unknown["explanation"], "formula": unknown["formula"],
                 "heldout_chi2_drop": round(unknown["delta"], 1)}
        # ranked by what it explains: first when it explains more than the known effects named
        findings.insert(0 if unknown.get("first") or not findings else len(findings), entry)
    report = {
        "recording": rec.summary(),
        "mismatch": {
            "signals": {s: {"nrmse": round(v, 4)} for s, v in shots["nrmse_before"].items()},
            "windows": [{k: w[k] for k in ("t0", "t1", "axes", "score", "regimes", "channels")} for w in windows],
            "noise_floor": {CHANNELS[c]: float(f"{split.sigma[c]:.4g}") for c in range(len(CHANNELS)) if split.active[c]},
            "heldout_chi2_per_sample": round(c0_h / max(n_h, 1e-9), 3),
        },
        "findings": findings,
        "fit": {
            "holdout": {
                "before": {"total": round(shots["total_before"], 4),
                           **{s: round(v, 4) for s, v in shots["nrmse_before"].items()}},
                "after": {"total": round(shots["total_after"], 4),
                          **{s: round(v, 4) for s, v in shots["nrmse_after"].items()}},
                "raw": {"before": round(shots["total_raw_before"], 4), "after": round(shots["total_raw_after"], 4)},
            },
            "holdout_fraction": round(split.holdout_fraction, 3),
            "method": (f"multiple shooting: {SHOOT_S:.0f} s windows re-initialised from the measurements, "
                       f"inside held-out blocks ({locate.BLOCK_S:.0f} s blocks, 3 of every 10); NRMSE against "
                       f"the measurement smoothed like the replay ({replay.SMOOTH_S} s Savitzky-Golay) with the "
                       "white sensor noise left in it removed in quadrature (variance estimated from the data); "
                       "'raw': plain NRMSE against the raw measurement"),
        },
        "candidates": [
            {"effect": f.candidate.effect, "kind": f.candidate.kind,
             "heldout_chi2_drop": round(f.delta_holdout, 1), "explained": round(f.explained, 3),
             "bic": round(f.bic, 1), "parameters": f.candidate.parameters(f.theta, vehicle)}
            for f in fits
        ],
        "elapsed_s": round(time.perf_counter() - t_start, 2),
    }
    return Diagnosis(report, traj, res0, res1, windows, fits, shots, replay.nominal_mass_diag(vehicle))


def _split_pair(pf: Fit, a: Fit, b: Fit):
    """The two findings of a pair fit: each with its share of the joint parameters."""
    na = a.candidate.n_params
    fa = Fit(a.candidate, pf.theta[:na], pf.chi2_train, pf.chi2_holdout, a.delta_holdout, a.explained,
             a.bic, a.per_channel, a.residual, a.model)
    fb = Fit(b.candidate, pf.theta[na:], pf.chi2_train, pf.chi2_holdout, pf.delta_holdout - a.delta_holdout,
             pf.explained - a.explained, pf.bic - a.bic, pf.per_channel - a.per_channel, pf.residual, pf.model)
    return fa, fb


def _finding(f: Fit, vehicle: Vehicle, split, traj, res0, noise, first: bool, fits) -> dict:
    c = f.candidate
    per = np.maximum(f.per_channel, 0.0)
    tot = per.sum()
    axes = []
    if tot > 0:
        order = np.argsort(-per)
        for ch in order:
            if per[ch] < 0.15 * tot:
                break
            ax = replay.AXES[CHANNEL_AXIS[ch]]
            label = CHANNELS[ch] if ch >= 6 else ax
            if label not in axes:
                axes.append(label)
    explained = max(0.0, min(f.explained, 1.0))
    params = c.parameters(f.theta, vehicle)
    ptxt = ", ".join(f"{k} = {_fmt(v)}" for k, v in params.items() if not k.endswith(".enabled"))
    verb = "adding" if c.kind == "missing" else "correcting"
    what = c.effect.replace("_", " ")
    explanation = (f"{' and '.join(axes) or 'the'} residual {PHRASES.get(c.effect, '')}; {verb} {what}"
                   + (f" with {ptxt}" if ptxt else "")
                   + f" explains {100 * explained:.0f} % of it on held-out data")
    # confidence: Akaike weight of this candidate against the nominal model and the other candidates
    aic = np.array([-(g.delta_holdout) + 2 * g.candidate.n_params for g in fits] + [0.0])
    own = -(f.delta_holdout) + 2 * c.n_params
    wts = np.exp(-0.5 * (aic - aic.min()))
    conf = float(np.exp(-0.5 * (own - aic.min())) / wts.sum()) if first else float(min(1.0, explained + 0.5))
    return {"effect": c.effect, "kind": c.kind, "confidence": round(min(max(conf, 0.0), 1.0), 3),
            "parameters": params, "explanation": explanation,
            "heldout_chi2_drop": round(f.delta_holdout, 1), "explained": round(explained, 3),
            "bic": round(f.bic, 1), "axes": axes}


def _fmt(v):
    if isinstance(v, list):
        return "[" + ", ".join(f"{x:.4g}" for x in v) + "]"
    if isinstance(v, float):
        return f"{v:.4g}"
    return str(v)


def _unknown_term(ev, traj, vehicle, final, base_res, split):
    cm = final.model if final is not None else ev.base
    p = model.pack_params(cm.vehicle)
    act = ev.actuators(ev.trajectory(cm.correction), p, cm)
    M = replay.nominal_mass_diag(vehicle)
    force = base_res[:, :6] * M
    term = sparse.fit_sparse(traj, vehicle, act, force, split.train)
    if not term.coefficients_.any():
        return None
    corr = sparse.sparse_force(term, traj, vehicle, act)
    corr = replay.smooth(traj, corr)
    res = base_res.copy()
    res[:, :6] -= corr / M
    c_before, _ = chi2(base_res, split, split.holdout)
    c_after, _ = chi2(res, split, split.holdout)
    delta = c_before - c_after
    if delta <= 0:
        return None
    n_h = len(split.holdout) * float(split.neff[split.active].sum())
    frac = delta / max(c_before - n_h, 1e-9)
    return {"formula": term.formula, "delta": float(delta), "confidence": float(min(max(frac, 0.0), 1.0)),
            "coefficients": term.coefficients_,
            "explanation": f"no known effect explains the residual; a sparse term {term.formula} "
                           f"explains {100 * min(max(frac, 0), 1):.0f} % of it on held-out data"}


def _shoot_holdout(ev: Evaluator, traj, split, before: CorrectedModel, after: CorrectedModel,
                   extra=None, mass_diag=None) -> dict:
    """Held-out NRMSE per signal (and total) of multiple-shooting windows, before and after."""
    n = int(round(SHOOT_S / traj.dt_s))
    mask = split.holdout_mask
    t = traj.time_s - traj.time_s[0]
    starts = []
    i = int(round(locate.EDGE_S / traj.dt_s))
    while i + n < len(t):
        if mask[i:i + n].all():
            starts.append(i)
            i += n
        else:
            i += 1
    starts = np.array(starts, np.int64)
    out = {"starts": starts, "length": n}
    for label, cm in (("before", before), ("after", after)):
        tr = ev.trajectory(cm.correction)
        p = model.pack_params(cm.vehicle)
        act = ev.actuators(tr, p, cm)
        ext = extra if label == "after" else None
        pred = (replay.shoot(tr, act, p, starts, n, substeps=2, command=ev.command(tr, cm), extra_force=ext,
                             mass_diag=mass_diag) if len(starts) else np.zeros((0, n, 10)))
        pred, meas = replay.predicted_vs_measured(traj, pred, starts, n, cm.vehicle, cm.correction)
        out[label] = pred
        out["meas"] = meas
        # NRMSE of the model, not of the sensor: the error against the measurement smoothed like
        # the replay, with the white noise left in that reference taken out in quadrature. Its
        # variance comes from the data: a noise probe of each signal's own estimated level, drawn
        # at the native sample times, gridded and smoothed the same way (replay.reconstruct).
        # "raw" is the plain NRMSE against the raw measurement.
        win = min(replay._odd(round(replay.SMOOTH_S / traj.dt_s)), n - (1 - n % 2))
        meas_s = savgol_filter(meas, win, 2, axis=1, mode="interp") if len(starts) else meas
        idx_w = starts[:, None] + np.arange(n)[None, :]
        probe = traj.noise_probe[idx_w] if len(starts) else np.zeros((0, n, 10))
        probe = probe - probe[:, :1] * (np.arange(10) == 9)  # yaw is compared as a change
        probe_s = savgol_filter(probe, win, 2, axis=1, mode="interp") if len(starts) else probe
        out["meas_smooth"] = meas_s
        for tag, ref in (("", meas_s), ("_raw", meas)):
            nr = {}
            for j, s in enumerate(replay.SIGNALS):
                m = ref[:, :, j].ravel()
                e = (pred[:, :, j] - ref[:, :, j]).ravel()
                var_sig = float(np.mean((m - m.mean()) ** 2)) if m.size else 0.0
                mse = float(np.mean(e ** 2)) if m.size else 0.0
                if tag == "":
                    noise_var = float(np.mean(probe_s[:, :, j] ** 2)) if m.size else 0.0
                    var_sig, mse = var_sig - noise_var, max(mse - noise_var, 0.0)
                nr[s] = float(np.sqrt(mse / var_sig)) if var_sig > 0 else float("nan")
            out[f"nrmse{tag}_{label}"] = nr
            vals = [v for v in nr.values() if math.isfinite(v)]
            out[f"total{tag}_{label}"] = float(np.mean(vals)) if vals else float("nan")
    return out
