"""The live terminal view of a `ground.station.Snapshot`: rich panels, or plain text.

`render_text(snap)` is the plain-text form (tests, logs, dumb terminals, `--plain`);
`render_rich(snap)` builds the rich renderable that `rich.live.Live` redraws. Both are pure:
the loop that feeds them lives in ground/ground_cli.py. Nothing here raises on missing data:
a value that has not come yet shows as "-".
"""

from __future__ import annotations

import math
import time

from ground.station import Snapshot


def _f(x, fmt="{:.2f}", scale=1.0) -> str:
    try:
        if x is None or not math.isfinite(float(x)):
            return "-"
        return fmt.format(float(x) * scale)
    except (TypeError, ValueError):
        return "-"


def _deg(x) -> str:
    return _f(x, "{:+.1f}", 180.0 / math.pi)


def _bool(b, yes="yes", no="no") -> str:
    return "-" if b is None else (yes if b else no)


def lines(s: Snapshot) -> dict:
    """The view's rows, grouped by panel (shared by both renderers)."""
    r, p, y = s.attitude_rad
    jets = []
    if s.jets is not None:
        for i, (t, n, a, e) in enumerate(zip(s.jets.thrust_n, s.jets.speed_rev_s, s.jets.azimuth_rad,
                                              s.jets.elevation_rad)):
            jets.append(f"jet {i + 1}: thrust {_f(t, '{:6.2f}')} N  n {_f(n, '{:5.1f}')} rev/s  "
                        f"az {_deg(a):>6} deg  el {_deg(e):>6} deg")
    else:
        jets.append("no SERVO_OUTPUT_RAW yet" if s.link_up else "-")
    link = "UP" if s.link_up else ("LOST" if s.packets else "waiting")
    return {
        "vehicle": [
            f"vehicle {s.vehicle[0]}/{s.vehicle[1]}" if s.vehicle else "vehicle: no heartbeat yet",
            f"armed {_bool(s.armed)}  mode {s.mode}  failsafe {_bool(s.failsafe, 'ACTIVE', 'off')}",
        ],
        "attitude": [
            f"roll {_deg(r)}  pitch {_deg(p)}  yaw {_deg(y)} deg",
            f"rates {_deg(s.rates_rad_s[0])} {_deg(s.rates_rad_s[1])} {_deg(s.rates_rad_s[2])} deg/s",
        ],
        "depth": [
            f"depth {_f(s.depth_m)} m  setpoint {_f(s.depth_setpoint_m)} m  yaw sp {_deg(s.yaw_setpoint_rad)} deg",
            f"velocity u {_f(s.velocity_m_s[0])} v {_f(s.velocity_m_s[1])} w {_f(s.velocity_m_s[2])} m/s"
            f"  (u sp {_f(s.surge_setpoint_m_s)})",
        ],
        "jets": jets,
        "allocation": [
            f"residual |demand-achieved| {_f(s.residual_norm, '{:.3f}')}  weighted error "
            f"{_f(s.allocation_error, '{:.3g}')}  fallbacks {_f(s.allocation_fallbacks, '{:.0f}')}",
            f"loop step {_f(s.step_ms, '{:.2f}')} ms (p99 {_f(s.step_p99_ms, '{:.2f}')})  "
            f"QP {_f(s.qp_us, '{:.0f}')} us  estimator rejections {_f(s.estimator_rejections, '{:.0f}')}",
        ],
        "link": [
            f"link {link}  ({s.link_lost_count} drop(s))  last packet {_f(s.since_last_s, '{:.1f}')} s ago  "
            f"{_f(s.rate_hz, '{:.0f}')} pkt/s",
            f"packets {s.packets}  lost {s.lost} ({_f(s.loss_fraction, '{:.2f}', 100)} %)  garbage bytes "
            f"{s.garbage_bytes}  bad packets {s.bad_packets}",
            f"command round trip {_f(s.rtt_s, '{:.3f}', 1e3)} ms  delay jitter {_f(s.delay_jitter_s, '{:.1f}', 1e3)} ms",
        ],
        "warnings": list(s.warnings) or ["none"],
        "events": [f"{time.strftime('%H:%M:%S', time.localtime(t))} {text}" for t, text in s.events] or ["-"],
    }


def render_text(s: Snapshot) -> str:
    out = []
    for title, rows in lines(s).items():
        out.append(f"[{title}]")
        out.extend("  " + r for r in rows)
    return "\n".join(out)


def render_rich(s: Snapshot):
    from rich.console import Group
    from rich.panel import Panel
    from rich.table import Table
    from rich.text import Text

    ls = lines(s)
    grid = Table.grid(expand=True)
    grid.add_column(ratio=1)
    grid.add_column(ratio=1)
    for left, right in (("vehicle", "attitude"), ("depth", "link")):
        grid.add_row(Panel("\n".join(ls[left]), title=left), Panel("\n".join(ls[right]), title=right))
    warn_style = "bold red" if s.warnings else "green"
    return Group(
        grid,
        Panel("\n".join(ls["jets"]), title="jets"),
        Panel("\n".join(ls["allocation"]), title="allocation and loop timing"),
        Panel(Text("\n".join(ls["warnings"]), style=warn_style), title="warnings"),
        Panel("\n".join(ls["events"]), title="events"),
    )
