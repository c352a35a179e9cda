"""DIR/index.html of a campaign: what a reader wants from the rows, with plots beside the tables.

- missions: tracking errors (depth, yaw, surge speed) per allocator and fault as box plots over
  the draws and seeds; failure cases (raised, a limit violated, or beyond the spec's [missions.fail]
  thresholds) listed with links to their recordings;
- prove: the benchmark table of `ground.prove.family_table` (rates with 95 % Wilson intervals, by
  sensor set, pilot and effect, and the confusion matrix);
- diagnose: which findings recur across recordings, and each recording's findings with its report;
- every kind: tasks per worker and their wall time.
"""

from __future__ import annotations

import html
import math
from collections import Counter, defaultdict
from pathlib import Path


def write_report(campaign, out: Path, rows: list[dict]) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    out = Path(out)
    (out / "plots").mkdir(exist_ok=True)
    ok = [r for r in rows if r.get("status") == "ok"]
    bad = [r for r in rows if r.get("status") != "ok"]
    parts = [f"<h1>jetloop campaign: {html.escape(campaign.kind)}</h1>",
             f"<p>spec <code>{html.escape(campaign.source)}</code>; {len(campaign.tasks)} tasks, {len(rows)} with a "
             f"result: {len(ok)} ok, {len(bad)} failed to run; table <a href='results.parquet'>results.parquet</a>"
             + (f"; {campaign.skipped} cases left out by the spec's filters" if campaign.skipped else "") + "</p>"]
    if campaign.kind == "missions":
        parts += _missions(campaign, out, rows)
    elif campaign.kind == "prove":
        parts += _prove(rows)
    else:
        parts += _diagnose(out, rows)
    if bad:
        parts.append("<h2>Tasks that raised</h2>" + _table(
            ["task", "error", "files"],
            [[html.escape(r["label"]), f"<code>{html.escape(str(r.get('error')))}</code>", _links(r)] for r in bad],
            raw=True))
    parts.append("<h2>Workers</h2>" + _table(
        ["worker", "tasks", "mean wall time (s)", "max (s)"],
        [[w, len(v), f"{sum(v) / len(v):.2f}", f"{max(v):.2f}"] for w, v in sorted(_by_worker(rows).items())]))
    page = ("<!doctype html><html><head><meta charset='utf-8'><title>jetloop campaign</title><style>"
            "body{font-family:sans-serif;max-width:1100px;margin:1em auto}table{border-collapse:collapse;margin:.5em 0}"
            "td,th{border:1px solid #ccc;padding:2px 6px;font-size:90%}img{max-width:100%}</style></head><body>"
            + "\n".join(parts) + "</body></html>\n")
    path = out / "index.html"
    path.write_text(page)
    return path


def _by_worker(rows):
    d = defaultdict(list)
    for r in rows:
        if isinstance(r.get("wall_s"), (int, float)):
            d[str(r.get("worker"))].append(float(r["wall_s"]))
    return d


def _links(r: dict) -> str:
    return " ".join(f"<a href='tasks/{r['task_id']}/{html.escape(f)}'>{html.escape(f)}</a>" for f in r.get("files", []))


def _table(head, body, raw: bool = False) -> str:
    esc = (lambda x: str(x)) if raw else (lambda x: html.escape(str(x)))
    return ("<table><tr>" + "".join(f"<th>{html.escape(str(h))}</th>" for h in head) + "</tr>"
            + "".join("<tr>" + "".join(f"<td>{esc(c)}</td>" for c in row) + "</tr>" for row in body) + "</table>")


def _num(v) -> float:
    return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) else math.nan


# ------------------------------------------------------------------------------------------------


def failure_reasons(row: dict, fail: dict) -> list[str]:
    """Why a mission task is a failure case ([] if it is not)."""
    if row.get("status") != "ok":
        return [f"{row.get('status')}: {row.get('error')}"]
    why = []
    dmax = fail.get("depth_max_m", 0.25)
    ymax = fail.get("yaw_rms_deg", 10.0)
    if _num(row.get("depth_max_abs_m")) > dmax:
        why.append(f"depth error {100 * row['depth_max_abs_m']:.1f} cm > {100 * dmax:g} cm")
    if _num(row.get("yaw_rms_rad")) > math.radians(ymax):
        why.append(f"yaw RMS {math.degrees(row['yaw_rms_rad']):.1f} deg > {ymax:g} deg")
    if isinstance(row.get("limit_violations"), int) and row["limit_violations"] > 0:
        why.append(f"{row['limit_violations']} limit violations")
    if math.isnan(_num(row.get("depth_rms_m"))) and math.isnan(_num(row.get("yaw_rms_rad"))):
        why.append("no settled leg: nothing measured")
    return why


def _missions(campaign, out: Path, rows: list[dict]) -> list[str]:
    import matplotlib.pyplot as plt

    fail = campaign.settings.get("fail", {}) if isinstance(campaign.settings.get("fail"), dict) else {}
    ok = [r for r in rows if r.get("status") == "ok"]
    groups = sorted({(r["allocator"], r["fault"]) for r in rows})
    parts = ["<h2>Tracking errors per allocator and fault</h2>",
             "<p>RMS of the plant's true state against the setpoint, leg by leg after its settling time "
             "(hil.demo.tracking_errors), over the Monte Carlo draws and seeds of each group.</p>"]
    figures = (("depth_rms_m", 100.0, "depth RMS (cm)"), ("yaw_rms_rad", 180 / math.pi, "yaw RMS (deg)"),
               ("speed_rms_m_s", 100.0, "surge RMS (cm/s)"))
    fig, axes = plt.subplots(len(figures), 1, figsize=(max(6.0, 1.2 * len(groups) + 2), 3.0 * len(figures)))
    for ax, (key, scale, label) in zip(axes, figures):
        data = [[_num(r.get(key)) * scale for r in ok if (r["allocator"], r["fault"]) == g] for g in groups]
        data = [[v for v in d if not math.isnan(v)] for d in data]
        if any(data):
            ax.boxplot([d if d else [math.nan] for d in data], showfliers=False)
            for i, d in enumerate(data):
                ax.plot([i + 1] * len(d), d, ".", color="C1", alpha=0.6)
        ax.set_xticks(range(1, len(groups) + 1))
        ax.set_xticklabels([f"{a}\n{f}" for a, f in groups], fontsize=8)
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(out / "plots" / "tracking.png", dpi=80)
    plt.close(fig)
    parts.append("<img src='plots/tracking.png'>")
    body = []
    for g in groups:
        sel = [r for r in ok if (r["allocator"], r["fault"]) == g]
        n_all = sum(1 for r in rows if (r["allocator"], r["fault"]) == g)
        med = lambda k, s: _median([_num(r.get(k)) * s for r in sel])  # noqa: E731
        body.append([g[0], g[1], f"{len(sel)}/{n_all}", med("depth_rms_m", 100), med("yaw_rms_rad", 180 / math.pi),
                     med("speed_rms_m_s", 100), sum(1 for r in sel if failure_reasons(r, fail))])
    parts.append(_table(["allocator", "fault", "ran", "depth RMS median (cm)", "yaw RMS median (deg)",
                         "surge RMS median (cm/s)", "failure cases"], body))
    failures = [(r, failure_reasons(r, fail)) for r in rows]
    failures = [(r, w) for r, w in failures if w and r.get("status") == "ok"]
    parts.append(f"<h2>Failure cases ({len(failures)})</h2><p>thresholds: depth error {fail.get('depth_max_m', 0.25)} m, "
                 f"yaw RMS {fail.get('yaw_rms_deg', 10.0)} deg ([missions.fail]), any limit violation.</p>")
    if failures:
        parts.append(_table(["task", "why", "recording"],
                            [[html.escape(r["label"]), html.escape("; ".join(w)), _links(r)] for r, w in failures],
                            raw=True))
    return parts


def _median(v):
    v = sorted(x for x in v if not math.isnan(x))
    if not v:
        return "-"
    m = v[len(v) // 2] if len(v) % 2 else 0.5 * (v[len(v) // 2 - 1] + v[len(v) // 2])
    return f"{m:.2f}"


def _prove(rows: list[dict]) -> list[str]:
    from ground.prove import family_table

    from .engine import family_row

    fam = [family_row(r) for r in rows]
    return ["<h2>The diagnosis benchmark</h2><p>ground.prove.family_table: rates with 95 % Wilson intervals "
            "by sensor set, pilot and effect; the confusion matrix of concealed primary effect against first "
            "finding.</p>", markdown_tables(family_table(fam))]


def markdown_tables(text: str) -> str:
    """The markdown of family_table as HTML: pipe tables become tables, other lines paragraphs."""
    out, table = [], []

    def flush():
        if table:
            cells = [[c.strip() for c in line.strip().strip("|").split("|")] for line in table]
            body = [c for c in cells[1:] if not all(set(x) <= {"-"} for x in c)]
            out.append(_table(cells[0], body))
            table.clear()

    for line in text.splitlines():
        if line.strip().startswith("|"):
            table.append(line)
        else:
            flush()
            if line.strip():
                out.append(f"<p>{html.escape(line)}</p>")
    flush()
    return "\n".join(out)


def _diagnose(out: Path, rows: list[dict]) -> list[str]:
    import matplotlib.pyplot as plt

    ok = [r for r in rows if r.get("status") == "ok"]
    seen = Counter(e for r in ok for e in set(r.get("findings") or []))
    first = Counter(r.get("first_finding") or "(none)" for r in ok)
    parts = ["<h2>Findings that recur across recordings</h2>",
             f"<p>{len(ok)} recordings diagnosed; {sum(1 for r in ok if not r.get('findings'))} with no finding.</p>"]
    if seen:
        names = [n for n, _ in seen.most_common()]
        fig, ax = plt.subplots(figsize=(7, 0.4 * len(names) + 1.2))
        ax.barh(names[::-1], [seen[n] for n in names[::-1]])
        ax.set_xlabel("recordings with this finding")
        ax.grid(alpha=0.3, axis="x")
        fig.tight_layout()
        fig.savefig(out / "plots" / "findings.png", dpi=80)
        plt.close(fig)
        parts.append("<img src='plots/findings.png'>")
        parts.append(_table(["effect", "recordings with it", "named first"],
                            [[n, seen[n], first.get(n, 0)] for n in names]))
    parts.append("<h2>Recordings</h2>" + _table(
        ["recording", "duration (s)", "findings", "not testable", "held-out NRMSE", "report"],
        [[html.escape(r["label"]), f"{_num(r.get('recording_s')):.0f}",
          html.escape(", ".join(r.get("findings") or []) or "none"),
          html.escape(", ".join(r.get("untestable") or [])),
          f"{_num(r.get('nrmse_before')):.3f} -> {_num(r.get('nrmse_after')):.3f}", _links(r)] for r in ok], raw=True))
    return parts


__all__ = ["write_report", "failure_reasons", "markdown_tables"]
