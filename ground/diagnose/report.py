"""The diagnosis written out: JSON exactly per spec/recording.md section 2, and an HTML report.

The HTML report (`--report DIR`) holds: the findings in words with their parameters as a
vehicle-file fragment to paste back; measured vs nominal vs corrected signals over held-out
shooting windows; the residual over time per axis with the flagged windows shaded; each
finding's evidence (the residual it explains against what it predicts).
"""

from __future__ import annotations

import html
import json
from pathlib import Path

import numpy as np

from onboard.vehicle import fragment_toml

from . import replay
from .candidates import CHANNELS


def nothing_testable(rep: dict) -> bool:
    """Every candidate untestable (too short, too sparse): 'within its noise' would claim a test."""
    tested = rep.get("candidates")
    if tested is not None:
        return bool(tested) and not any(c.get("testable") for c in tested)
    return bool(rep.get("untestable")) and rep.get("fit", {}).get("method", "").startswith("none")


def findings_withheld(rep: dict) -> bool:
    """No finding could be named at all (too few null draws to calibrate, or the estimator could
    not follow the recording): its warnings say why; 'within its noise' would contradict them."""
    from .core import MIN_DRAWS

    draws = rep.get("calibration", {}).get("null_draws")
    diverged = rep.get("mismatch", {}).get("disturbance", {}).get("divergences")
    return (draws is not None and draws < MIN_DRAWS) or bool(diverged)


def no_finding_text(rep: dict) -> str:
    """The one line a report without findings opens with (summary and page alike)."""
    if findings_withheld(rep):
        return "no finding named: the recording could not be tested against the nominal model (see the warnings)"
    rejected, weak = rep.get("rejected") or [], rep.get("negligible") or []
    # significant, but the held-out blocks cannot test it (core._unconfirmable)
    blind = [u["effect"] for u in rep.get("untestable") or [] if u.get("significant")]
    blind_text = (f"{', '.join(blind)} passed the calibrated test but the held-out blocks cannot test "
                  f"{'it' if len(blind) == 1 else 'them'} (see 'not testable')") if blind else ""
    if rejected:  # significant, but not shown to fit better
        line = (f"no finding named: {', '.join(rejected)} passed the calibrated test but "
                f"{'was' if len(rejected) == 1 else 'were'} withdrawn, the held-out fit not shown to be better than "
                "the nominal model's")
        return line + (f"; {blind_text}" if blind else "") + ("; other candidates " + _negligible(weak) if weak else "")
    if blind:
        return f"no finding named: {blind_text}" + ("; other candidates " + _negligible(weak) if weak else "")
    if weak:  # significant, but too small to name (core.py: MIN_EXPLAINED, correction size, one sd)
        return "no finding named: candidates " + _negligible(weak)
    if nothing_testable(rep):
        return "no finding: this recording cannot test any candidate (see 'not testable')"
    return "no finding: the nominal model explains the recording within its noise"


def _negligible(weak: list) -> str:
    """'passed the calibrated test but too small to name: added_mass (its fit removes 1.5 % ...)'."""
    def why(w):
        return w.get("why") or f"its fit removes {100 * w['explained']:.1f} % of the held-out mismatch"
    return "passed the calibrated test but too small to name: " + "; ".join(f"{w['effect']} ({why(w)})" for w in weak)


def write_json(report: dict, path) -> None:
    """Strict JSON: a value that could not be computed (NaN, e.g. a signal with no spread or no
    held-out window) is written as null."""
    Path(path).write_text(json.dumps(_finite(report), indent=2, allow_nan=False, default=_jsonable) + "\n")


def _finite(o):
    if isinstance(o, dict):
        return {k: _finite(v) for k, v in o.items()}
    if isinstance(o, (list, tuple)):
        return [_finite(v) for v in o]
    if isinstance(o, (float, np.floating)) and not np.isfinite(o):
        return None
    return o


def _jsonable(o):
    if isinstance(o, (np.floating, np.integer)):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def write_html(diag, out_dir) -> Path:
    """index.html plus PNG figures in `out_dir`; returns the HTML path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rep = diag.report
    traj = diag.traj
    figs = []
    if traj is None:  # nothing could be tested: the page says why
        return _page(out, rep, figs)
    t = traj.time_s

    # 0. the smoothed disturbance: where the nominal model is wrong, with its 95 % band
    est = traj.estimate
    if est is not None:
        fig, axs = plt.subplots(6, 1, figsize=(11, 10), sharex=True)
        d, s = est.disturbance, est.disturbance_std
        for i, ax in enumerate(axs):
            ax.fill_between(est.time_s, d[:, i] - 1.96 * s[:, i], d[:, i] + 1.96 * s[:, i], color="tab:blue", alpha=0.25,
                            lw=0, label="95 % band")
            ax.plot(est.time_s, d[:, i], lw=0.7, color="tab:blue", label="smoothed disturbance")
            ax.axhline(0.0, color="0.3", lw=0.5)
            ax.set_ylabel(f"{replay.AXES[i]}\n[{'N' if i < 3 else 'N m'}]")
        axs[0].legend(loc="upper right", fontsize=8)
        axs[-1].set_xlabel("vehicle time [s]")
        fig.suptitle("generalised-force disturbance the nominal model needs to follow the recording (EKF + RTS)")
        figs.append(_save(fig, out / "disturbance.png", plt))

    # 1. residual over time with flagged windows
    fig, axs = plt.subplots(6, 1, figsize=(11, 10), sharex=True)
    M = diag.mass_diag
    r0 = replay.smooth(traj, diag.residual0[:, :6]) * M
    r1 = replay.smooth(traj, diag.residual1[:, :6]) * M
    for i, ax in enumerate(axs):
        ax.plot(t, r0[:, i], lw=0.6, color="tab:red", label="nominal")
        ax.plot(t, r1[:, i], lw=0.6, color="tab:green", label="with findings")
        for w in diag.windows:
            ax.axvspan(w["t0"], w["t1"], color="orange", alpha=0.25 if replay.AXES[i] in w["axes"] else 0.08)
        ax.set_ylabel(f"{replay.AXES[i]}\n[{'N' if i < 3 else 'N m'}]")
    axs[0].legend(loc="upper right", fontsize=8)
    axs[-1].set_xlabel("vehicle time [s]")
    fig.suptitle("generalised-force residual (measured motion minus model), flagged windows shaded")
    figs.append(_save(fig, out / "residual.png", plt))

    # 2. measured vs nominal vs corrected over the held-out shooting windows
    shots = diag.shots
    if len(shots["starts"]):
        n = shots["length"]
        idx = (np.asarray(shots["starts"])[:, None] + np.arange(n)[None, :])
        fig, axs = plt.subplots(5, 2, figsize=(12, 11), sharex=True)
        for j, name in enumerate(replay.SIGNALS):
            ax = axs[j % 5, j // 5]
            for w in range(len(shots["starts"])):
                tt = t[idx[w]]
                ax.plot(tt, shots["meas"][w, :, j], color="0.6", lw=0.5, label="measured" if w == 0 else None)
                ax.plot(tt, shots["before"][w, :, j], color="tab:red", lw=0.8, label="nominal" if w == 0 else None)
                ax.plot(tt, shots["after"][w, :, j], color="tab:green", lw=0.8, label="corrected" if w == 0 else None)
            ax.set_ylabel(name, fontsize=8)
        axs[0, 0].legend(fontsize=8)
        fig.suptitle("held-out multiple-shooting windows: measured, nominal and corrected")
        figs.append(_save(fig, out / "signals.png", plt))

    # 3. evidence per finding: what it explains vs the residual
    for k, f in enumerate(rep["findings"]):
        fit = next((g for g in diag.fits if g.candidate.public == f["effect"]), None)
        if fit is None:
            continue
        fig, axs = plt.subplots(2, 1, figsize=(11, 5), sharex=True)
        per = np.maximum(fit.per_channel, 0)
        ch = int(np.argmax(per))
        scale = M[ch] if ch < 6 else 1.0
        res0 = replay.smooth(traj, diag.residual0[:, ch:ch + 1])[:, 0] * scale
        explained = res0 - replay.smooth(traj, fit.residual[:, ch:ch + 1])[:, 0] * scale if len(fit.residual) == len(t) else None
        axs[0].plot(t, res0, lw=0.6, color="tab:red", label=f"residual ({CHANNELS[ch]})")
        if explained is not None:
            axs[0].plot(t, explained, lw=0.8, color="tab:blue", label=f"what {f['effect']} predicts")
        axs[0].legend(fontsize=8)
        if explained is not None:
            axs[1].plot(t, res0 - explained, lw=0.6, color="tab:green", label="left over")
            axs[1].legend(fontsize=8)
        axs[1].set_xlabel("vehicle time [s]")
        fig.suptitle(f"finding {k + 1}: {f['effect']} ({f['kind']})")
        figs.append(_save(fig, out / f"finding_{k + 1}.png", plt))

    return _page(out, rep, figs)


def _page(out: Path, rep: dict, figs: list) -> Path:
    """index.html: findings, what cannot be tested, held-out NRMSE, windows, the figures."""
    rows = "".join(
        f"<tr><td>{i + 1}</td><td><b>{html.escape(f['effect'])}</b></td><td>{f['kind']}</td>"
        f"<td>{f['confidence']:.2f}</td><td>{html.escape(f['explanation'])}</td></tr>"
        for i, f in enumerate(rep["findings"]))
    frag = {}
    for f in rep["findings"]:
        frag.update({k: v for k, v in f["parameters"].items() if not k.startswith("thruster_fault.")})
    hold = rep["fit"]["holdout"]
    sig_rows = "".join(
        f"<tr><td>{s}</td><td>{hold['before'].get(s, float('nan')):.3f}</td><td>{hold['after'].get(s, float('nan')):.3f}</td></tr>"
        for s in ["total", *replay.SIGNALS])
    win_rows = "".join(
        f"<tr><td>{w['t0']:.1f}-{w['t1']:.1f}</td><td>{', '.join(w['axes'])}</td><td>{w['score']:.1f}</td>"
        f"<td>{', '.join(w.get('regimes', []))}</td></tr>" for w in rep["mismatch"]["windows"])
    untest = "".join(f"<tr><td>{html.escape(u['effect'])} ({html.escape(u.get('kind', ''))})</td>"
                     f"<td>{html.escape(u['reason'])}</td></tr>" for u in rep.get("untestable", []))
    cal = rep.get("calibration")
    calib = (f"<p>Decision thresholds calibrated on {cal['null_draws']} null draws of this recording (the nominal "
             f"model re-flown under its commands with its estimated noise): at most {100 * cal['alpha_family']:.2f} % "
             f"false alarms per candidate family, {100 * cal['alpha_recording']:.0f} % per recording.</p>") if cal else ""
    page = f"""<!doctype html><html><head><meta charset="utf-8"><title>jetloop diagnosis</title>
<style>body{{font-family:sans-serif;max-width:1100px;margin:auto}} td,th{{padding:2px 8px;border-bottom:1px solid #ddd}}</style></head><body>
<h1>Diagnosis of {html.escape(rep['recording'].get('source', ''))}</h1>
<p>{rep['recording']['duration_s']:.1f} s; skipped bytes {rep['recording']['skipped_bytes']},
bad-CRC packets {rep['recording'].get('bad_crc_packets', 0)}.</p>
<h2>Findings</h2>
{'<table><tr><th>#</th><th>effect</th><th>kind</th><th>confidence</th><th>evidence</th></tr>' + rows + '</table>' if rows else '<p>' + html.escape(no_finding_text(rep).capitalize()) + '.</p>'}
{'<h3>Vehicle-file fragment</h3><pre>' + html.escape(fragment_toml(frag)) + '</pre>' if frag else ''}
<h2>Not testable on this recording</h2>
{'<table><tr><th>effect</th><th>why</th></tr>' + untest + '</table>' if untest else '<p>every candidate could be tested</p>'}
{calib}
<h2>Held-out NRMSE</h2><table><tr><th>signal</th><th>before</th><th>after</th></tr>{sig_rows}</table>
<p>{html.escape(rep['fit']['method'])}</p>
<h2>Windows above the noise floor</h2>
{'<table><tr><th>time [s]</th><th>axes</th><th>score</th><th>regimes</th></tr>' + win_rows + '</table>' if win_rows else '<p>none</p>'}
{''.join(f'<p><img src="{p.name}" width="100%"></p>' for p in figs)}
</body></html>"""
    path = out / "index.html"
    path.write_text(page)
    return path


def _save(fig, path: Path, plt) -> Path:
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
    return path
