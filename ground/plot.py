"""`jetloop plot REC --out DIR`: the standard plots of a recording as PNGs and one index.html.

Works on .tlog recordings from the HIL (`jetloop demo`), from `jetloop sim`, from this ground
station's recorder, and from a real ArduSub vehicle (SCALED_IMU2, SCALED_PRESSURE2,
SERVO_OUTPUT_RAW), and on dataflash .bin logs. The streams come from ground.recording
(`read_recording`: compiled framing with per-packet CRC, bad packets counted); the messages it
does not keep (NAMED_VALUE_FLOAT, DEBUG_FLOAT_ARRAY, SYS_STATUS, LOCAL_POSITION_NED, and the
sequence numbers) are read from the same scan's packet index (`read_extras`).

Panels: attitude, depth (and its setpoint), velocity, jets (thrust per jet through the
vehicle's PWM map for our vehicle; raw PWM per channel for an ArduPilot vehicle), joint angles,
allocation residual, loop timing, link quality (packet loss from sequence numbers per source,
packet rate). A panel with no data says so in the image and the page instead of failing.
"""

from __future__ import annotations

import functools
import html
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ground.recording import RecordingError, decode_message, read_recording, scan_packets

MAV_AUTOPILOT_ARDUPILOTMEGA = 3
MAX_RATE_BINS = 10_000  # bins of the packet-rate trace in the link panel
PANELS = ("attitude", "depth", "velocity", "jets", "joints", "allocation", "timing", "link")


class PlotError(ValueError):
    """A recording or output directory that cannot be used; the message names it."""


@dataclass
class Extras:
    """What read_recording does not keep, from the same packet scan (vehicle time in s)."""

    named: dict = field(default_factory=dict)  # name -> (t, value) arrays
    wrench: tuple | None = None  # (t, demand (N,6), achieved (N,6))
    local_velocity: tuple | None = None  # (t, (N,3) vx vy vz NED)
    sys_load: tuple | None = None  # (t_log, load 0..1)
    link: dict = field(default_factory=dict)  # (sys, comp) -> (t_log, cumulative lost, received)
    log_time: np.ndarray | None = None  # tlog stamps of all good packets (s since the first)
    autopilot: int | None = None


def _seq(buf, off, plen, mid) -> np.ndarray:
    """Sequence number of each packet from its header (v2: 10-byte header, v1: 6)."""
    off = np.asarray(off)
    v2 = np.zeros(len(off), bool)
    ok = off >= 10
    o = off[ok]
    v2[ok] = ((buf[o - 10] == 0xFD) & (buf[o - 9] == plen[ok])
              & ((buf[o - 3].astype(np.int64) | (buf[o - 2].astype(np.int64) << 8)
                  | (buf[o - 1].astype(np.int64) << 16)) == mid[ok]))
    return np.where(v2, buf[np.maximum(off - 6, 0)], buf[np.maximum(off - 4, 0)]).astype(np.int64)


def read_extras(path: Path) -> Extras:
    buf, off, plen, mid, src, ts = scan_packets(path.read_bytes())
    ex = Extras()
    if len(off) == 0:
        return ex
    t_log = (ts - ts[0]).astype(np.float64) / 1e6
    ex.log_time = t_log
    seq = _seq(buf, off, plen, mid)
    for s in np.unique(src):
        sel = np.nonzero(src == s)[0]
        gaps = (np.diff(seq[sel]) - 1) % 256
        lost = np.concatenate([[0], np.cumsum(gaps)])
        ex.link[(int(s) // 256, int(s) % 256)] = (t_log[sel], lost, np.arange(1, len(sel) + 1))

    def decode(name):
        a, sel = decode_message(buf, off, plen, mid, name)
        return a, t_log[sel]

    hb, _ = decode("HEARTBEAT")
    if hb is not None:
        ok = hb["autopilot"] != 8
        ex.autopilot = int(hb["autopilot"][ok][0]) if ok.any() else None
    a, _ = decode("NAMED_VALUE_FLOAT")
    if a is not None:
        names = np.char.rstrip(np.asarray(a["name"]).astype("S10"), b"\x00")
        t = a["time_boot_ms"] / 1e3
        for n in np.unique(names):
            k = names == n
            ex.named[n.decode("ascii", "replace")] = (t[k], a["value"][k].astype(float))
    a, _ = decode("DEBUG_FLOAT_ARRAY")
    if a is not None:
        k = np.char.rstrip(np.asarray(a["name"]).astype("S10"), b"\x00") == b"wrench"
        if k.any():
            data = np.asarray(a["data"][k], float)
            ex.wrench = (a["time_usec"][k] / 1e6, data[:, :6], data[:, 6:12])
    a, _ = decode("LOCAL_POSITION_NED")
    if a is not None:
        ex.local_velocity = (a["time_boot_ms"] / 1e3, np.column_stack([a["vx"], a["vy"], a["vz"]]).astype(float))
    a, t = decode("SYS_STATUS")
    if a is not None:
        ex.sys_load = (t, a["load"] / 1000.0)
    return ex


# ------------------------------------------------------------------------------------------------


def _no_data(ax, text):
    ax.text(0.5, 0.5, text, ha="center", va="center", wrap=True, transform=ax.transAxes, fontsize=11)
    ax.set_xticks([])
    ax.set_yticks([])


REPLAY_LEAD_S, REPLAY_TAIL_S, REPLAY_DT_S = 3.0, 5.0, 0.01


def replay_fixed(rec, vehicle, t0: float, t1: float, dt_s: float = REPLAY_DT_S):
    """The recorded SERVO_OUTPUT_RAW rows (each held until the next) through the vehicle model from
    t0 to t1: (t, roll/pitch/yaw rad (n, 3), depth m). The start is the recorded attitude and
    pressure depth at t0, at rest (a recording holds no body velocity). Pure: onboard.model's RK4."""
    from ground.diagnose.replay import flown_commands
    from onboard import model
    from onboard.sensors import depth_from_pressure

    a, pr, sv = rec.attitude, rec.pressure, rec.servo
    e0 = [float(np.interp(t0, a.time_s, np.unwrap(a.euler_rad[:, i]))) for i in range(3)]
    d0 = float(np.interp(t0, pr.time_s, depth_from_pressure(pr.press_abs_pa, vehicle)))
    cmds = flown_commands(rec, vehicle)  # with the log's motor directions
    p = model.pack_params(vehicle)
    x = model.initial_state(vehicle, d0)
    x[3:7] = model.euler_to_quat(*e0)
    t = t0 + dt_s * np.arange(int(round((t1 - t0) / dt_s)) + 1)
    rows = np.clip(np.searchsorted(sv.time_s, t, side="right") - 1, 0, len(sv.time_s) - 1)
    euler, depth = np.empty((len(t), 3)), np.empty(len(t))
    for i in range(len(t)):
        euler[i] = model.quat_to_euler(x[3:7])
        depth[i] = x[2] - vehicle.environment.surface_depth
        if i + 1 < len(t):
            x = model.rk4_steps(x, cmds[rows[i]], p, dt_s, 1)
    return t, euler, depth


def make_plots(path, out_dir, vehicle=None) -> dict:
    """Write DIR/<panel>.png for every panel and DIR/index.html; returns the page's summary."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from onboard.vehicle import load_vehicle

    path, out = Path(path), Path(out_dir)
    try:
        rec = read_recording(path)
    except RecordingError as exc:
        raise PlotError(str(exc)) from None
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise PlotError(f"output directory {out}: cannot create: {exc.strerror or exc}") from None
    ex = read_extras(path) if rec.format == "tlog" else Extras()
    vehicle = vehicle if vehicle is not None else load_vehicle()
    ardupilot = ex.autopilot == MAV_AUTOPILOT_ARDUPILOTMEGA or rec.format == "dataflash"
    notes: dict = {}

    def panel(name, title, draw):
        fig, ax = plt.subplots(figsize=(9, 4))
        try:
            note = draw(ax)
        except Exception as exc:  # a panel that cannot be drawn is reported, the others still are
            ax.clear()
            note = f"could not draw: {type(exc).__name__}: {exc}"
        if note:
            _no_data(ax, note)
        else:
            ax.set_xlabel("vehicle time (s)" if name != "link" else "log time (s)")
            ax.grid(alpha=0.3)
            if ax.get_legend_handles_labels()[0]:
                ax.legend(loc="best", fontsize=8)
        ax.set_title(title)
        fig.tight_layout()
        fig.savefig(out / f"{name}.png", dpi=90)
        plt.close(fig)
        notes[name] = note or ""

    @functools.cache
    def servo_commands():
        """Commands of every SERVO_OUTPUT_RAW row through the [pwm] maps (jets and joints share them)."""
        from onboard.pwm import pwm_to_command

        return np.array([pwm_to_command(vehicle, row) for row in rec.servo.pwm_us])

    def attitude(ax):
        a = rec.attitude
        if a is None or not len(a.time_s):
            return "no attitude in this recording (no ATTITUDE / ATT)"
        for i, lbl in enumerate(("roll", "pitch", "yaw")):
            ax.plot(a.time_s, np.degrees(a.euler_rad[:, i]), label=lbl, lw=0.8)
        ax.set_ylabel("deg")

    def depth(ax):
        drawn = False
        if "depth" in ex.named:
            ax.plot(*ex.named["depth"], label="depth (estimate)", lw=0.8)
            drawn = True
        if rec.pressure is not None and len(rec.pressure.time_s):
            from onboard.sensors import depth_from_pressure

            ax.plot(rec.pressure.time_s, depth_from_pressure(rec.pressure.press_abs_pa, vehicle),
                    label=f"depth from {rec.pressure.message}", lw=0.8, alpha=0.7)
            drawn = True
        if "depth_sp" in ex.named:
            t, v = ex.named["depth_sp"]
            ax.plot(t, v, "--", label="setpoint", lw=1.0)
        if not drawn:
            return "no depth in this recording (no SCALED_PRESSURE2 / BARO / depth value)"
        ax.invert_yaxis()
        ax.set_ylabel("depth below surface (m)")

    def velocity(ax):
        drawn = False
        if "u_est" in ex.named:
            ax.plot(*ex.named["u_est"], label="surge u (estimate)", lw=0.8)
            drawn = True
        if "u_sp" in ex.named:
            ax.plot(*ex.named["u_sp"], "--", label="surge setpoint", lw=1.0)
        if ex.local_velocity is not None:
            t, v = ex.local_velocity
            for i, lbl in enumerate(("vN", "vE", "vD")):
                ax.plot(t, v[:, i], label=lbl, lw=0.8)
            drawn = True
        if rec.mocap is not None and len(rec.mocap.time_s) > 2:
            v = np.gradient(rec.mocap.pos_ned_m, rec.mocap.time_s, axis=0)
            for i, lbl in enumerate(("vN truth", "vE truth", "vD truth")):
                ax.plot(rec.mocap.time_s, v[:, i], ":", label=lbl, lw=0.8)
            drawn = True
        if not drawn:
            return "no velocity in this recording (no u_est, LOCAL_POSITION_NED or motion capture)"
        ax.set_ylabel("m/s")

    def jets(ax):
        s = rec.servo
        if s is None or not len(s.time_s):
            return "no actuator output in this recording (no SERVO_OUTPUT_RAW / RCOU)"
        if vehicle.fixed:  # fixed thrusters: PWM through the vehicle file's thrust curve (spec 3.1)
            u = servo_commands()
            for i in range(len(vehicle.fixed)):
                ax.plot(s.time_s, u[:, vehicle.n_jets + i], label=f"thruster {i + 1}", lw=0.8)
            ax.set_ylabel("commanded static thrust (N), [fixed_thruster] curve")
            return None
        if ardupilot:
            used = [c for c in range(16) if np.any(s.pwm_us[:, c] > 0)]
            for c in used:
                ax.plot(s.time_s, s.pwm_us[:, c], label=f"ch{c + 1}", lw=0.7)
            ax.set_ylabel("PWM (us)")
            return None
        from onboard.model import jet_thrust, pack_params

        p = pack_params(vehicle)
        k = vehicle.n_units
        u = servo_commands()
        for i in range(k):
            thrust = [jet_thrust(float(n), 0.0, p) for n in u[:, i]]
            ax.plot(s.time_s, thrust, label=f"jet {i + 1}", lw=0.8)
        ax.set_ylabel("commanded thrust at zero inflow (N)")

    def joints(ax):
        s = rec.servo
        if s is None or not len(s.time_s):
            return "no actuator output in this recording (no SERVO_OUTPUT_RAW / RCOU)"
        if not vehicle.n_jets:
            return f"no joints: {vehicle.name} has fixed thrusters only (see jets.png for their thrust)"
        if ardupilot:
            return "no jet joints: an ArduPilot vehicle with fixed thrusters (see jets.png for PWM)"
        k = vehicle.n_units
        u = servo_commands()
        for i in range(k):
            ax.plot(s.time_s, np.degrees(u[:, k + i]), label=f"azimuth {i + 1}", lw=0.8)
            ax.plot(s.time_s, np.degrees(u[:, 2 * k + i]), "--", label=f"elevation {i + 1}", lw=0.8)
        ax.set_ylabel("commanded angle (deg)")

    def allocation(ax):
        drawn = False
        if ex.wrench is not None:
            t, dem, ach = ex.wrench
            ax.plot(t, np.linalg.norm(dem[:, :3] - ach[:, :3], axis=1), label="|force residual| (N)", lw=0.8)
            ax.plot(t, np.linalg.norm(dem[:, 3:] - ach[:, 3:], axis=1), label="|moment residual| (N m)", lw=0.8)
            drawn = True
        if "alloc_err" in ex.named:
            ax.plot(*ex.named["alloc_err"], label="allocator weighted error", lw=0.8)
            drawn = True
        if not drawn:
            return "no allocation telemetry in this recording (the onboard loop's wrench / alloc_err)"

    def timing(ax):
        drawn = False
        for name, lbl in (("step_ms", "control step (ms)"), ("step_p99", "step p99 (ms)")):
            if name in ex.named:
                ax.plot(*ex.named[name], label=lbl, lw=0.8)
                drawn = True
        if "qp_us" in ex.named:
            t, v = ex.named["qp_us"]
            ax.plot(t, v / 1e3, label="QP solve (ms)", lw=0.8)
            drawn = True
        if rec.imu is not None and len(rec.imu.time_s) > 1:
            ax.plot(rec.imu.time_s[1:], np.diff(rec.imu.time_s) * 1e3, label=f"{rec.imu.message} interval (ms)",
                    lw=0.6, alpha=0.7)
            drawn = True
        if not drawn:
            return "no loop timing in this recording"
        ax.set_ylabel("ms")

    def link(ax):
        if not ex.link:
            return ("no MAVLink sequence numbers: a dataflash log is written on board, not sent"
                    if rec.format == "dataflash" else "no packets")
        for (s_, c_), (t, lost, got) in sorted(ex.link.items()):
            frac = lost[-1] / (lost[-1] + got[-1])
            ax.plot(t, lost, label=f"{s_}/{c_}: {int(lost[-1])} lost of {int(lost[-1] + got[-1])} "
                                   f"({100 * frac:.2f} %)", lw=0.8)
        ax.set_ylabel("packets lost (cumulative, from seq gaps)")
        if ex.log_time is not None and len(ex.log_time) > 1:
            ax2 = ax.twinx()
            # one-second bins, at most MAX_RATE_BINS of them: a log spanning a long gap gets
            # wider bins, never memory by its time span
            span = float(np.max(ex.log_time))
            width = max(1.0, span / MAX_RATE_BINS)
            edges = np.arange(int(span / width) + 2) * width
            counts, _ = np.histogram(ex.log_time, edges)
            ax2.step(edges[:-1], counts / width, where="post", color="0.6", lw=0.6)
            ax2.set_ylabel("packets/s (grey)")

    def replay(ax):
        """The thrusters' active stretch replayed through the model against the recording."""
        s, a, pr = rec.servo, rec.attitude, rec.pressure
        if s is None or a is None or pr is None or not (len(s.time_s) and len(a.time_s) and len(pr.time_s)):
            return "nothing to replay: the recording needs actuator outputs, attitude and pressure"
        thrust = servo_commands()[:, vehicle.n_jets:vehicle.n_units]
        active = np.flatnonzero(np.any(thrust != 0.0, axis=1))
        if not len(active):
            return "nothing to replay: every thruster stays in its dead band throughout"
        t0 = max(float(s.time_s[active[0]]) - REPLAY_LEAD_S, float(a.time_s[0]), float(pr.time_s[0]))
        t1 = min(float(s.time_s[active[-1]]) + REPLAY_TAIL_S, float(a.time_s[-1]))
        t, e_sim, d_sim = replay_fixed(rec, vehicle, t0, t1)
        m = (a.time_s >= t0) & (a.time_s <= t1)
        e_rec = np.unwrap(a.euler_rad[m], axis=0)
        for i, lbl in enumerate(("roll", "pitch", "yaw")):
            line, = ax.plot(a.time_s[m], np.degrees(e_rec[:, i] - e_rec[0, i]), lw=0.9, label=f"{lbl} recorded")
            ax.plot(t, np.degrees(np.unwrap(e_sim[:, i]) - e_sim[0, i]), "--", color=line.get_color(), lw=0.9,
                    label=f"{lbl} model")
        ax.set_ylabel("change since the replay's start (deg)")
        from onboard.sensors import depth_from_pressure

        mp = (pr.time_s >= t0) & (pr.time_s <= t1)
        ax2 = ax.twinx()
        ax2.plot(pr.time_s[mp], depth_from_pressure(pr.press_abs_pa[mp], vehicle), color="0.3", lw=0.8)
        ax2.plot(t, d_sim, "--", color="0.3", lw=0.8)
        ax2.set_ylabel("depth (m): recorded solid, model dashed")
        ax2.invert_yaxis()
        return None

    titles = {"attitude": "Attitude", "depth": "Depth", "velocity": "Velocity",
              "jets": "Jets" if not vehicle.fixed else "Thrusters" if not vehicle.n_jets else "Jets and thrusters",
              "joints": "Joint angles", "allocation": "Allocation residual", "timing": "Loop timing",
              "link": "Link quality",
              "replay": f"Replay: the recorded thruster outputs through the {vehicle.name} model"}
    draws = {"attitude": attitude, "depth": depth, "velocity": velocity, "jets": jets, "joints": joints,
             "allocation": allocation, "timing": timing, "link": link, "replay": replay}
    # a vehicle of fixed thrusters (an ArduSub vehicle) also gets the replay of its recorded outputs
    for name in PANELS + (("replay",) if vehicle.fixed else ()):
        panel(name, titles[name], draws[name])
    summary = rec.summary()
    summary["panels"] = notes
    _write_index(out, path, summary)
    return summary


def _write_index(out: Path, path: Path, summary: dict) -> None:
    esc = html.escape
    rows = "".join(f"<tr><td>{esc(str(k))}</td><td>{esc(str(v))}</td></tr>" for k, v in
                   (("source", summary["source"]), ("format", summary["format"]),
                    ("duration (s)", summary["duration_s"]), ("bad-CRC packets", summary["bad_crc_packets"]),
                    ("skipped bytes", summary["skipped_bytes"]), ("truncated bytes", summary["truncated_bytes"]),
                    ("unknown packets", summary["unknown_packets"]),
                    ("non-monotonic samples", summary["non_monotonic"])))
    msgs = ", ".join(f"{esc(k)} {v}" for k, v in summary["messages"].items())
    figs = "".join(
        f"<h2>{esc(n)}</h2>" + (f"<p><em>{esc(summary['panels'][n])}</em></p>" if summary["panels"][n] else "")
        + f'<img src="{n}.png" alt="{esc(n)}">' for n in summary["panels"])
    page = (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{esc(path.name)}</title>"
            "<style>body{font-family:sans-serif;max-width:960px;margin:auto}img{width:100%}"
            "td{padding:2px 8px}</style></head><body>"
            f"<h1>{esc(path.name)}</h1><table>{rows}</table><p>messages: {msgs}</p>{figs}</body></html>")
    (out / "index.html").write_text(page)


def report(summary: dict) -> str:
    s = summary
    lines = [f"{s['source']}: {s['format']}, {s['duration_s']} s",
             f"  bad-CRC packets {s['bad_crc_packets']}, skipped bytes {s['skipped_bytes']}, "
             f"truncated bytes {s['truncated_bytes']}, unknown packets {s['unknown_packets']}"]
    empty = [f"{n} ({t})" for n, t in s["panels"].items() if t]
    lines.append(f"  panels: {len(s['panels']) - len(empty)} plotted" + (", without data: " + "; ".join(empty) if empty else ""))
    return "\n".join(lines)


# `jetloop plot` (ground/cli.py imports this module; the command line lives in ground_cli.py)
def configure(parser) -> None:
    from ground.ground_cli import configure_plot

    configure_plot(parser)


def run(args) -> int:
    from ground.ground_cli import run_plot

    return run_plot(args)
