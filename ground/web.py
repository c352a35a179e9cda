"""The live dashboard in the browser: `jetloop ground --web` serves the station's telemetry as Bokeh plots.

    jetloop ground --web [--port 8080] [--link udpin:127.0.0.1:14550] [--record DIR] [--key KEYFILE] ...

One description of the telemetry: the page plots `ground.station.Snapshot`s, the same the terminal
view draws (ground/view.py); nothing here reads MAVLink. Three parts:
- an IO thread owns the `GroundSession` (link, station, recorder): it polls the link, sends what the
  page asked for, and every `SAMPLE_PERIOD_S` turns a snapshot into one row of plot values
  (`row`, pure) appended to a `History` (a ring buffer, the only thing shared between threads);
- a Bokeh server (tornado, the main thread) makes one document per browser tab: a
  ColumnDataSource "telemetry" that a periodic callback streams the history's new rows into, the
  plots drawn from it, status, warnings and events, and the command buttons;
- the buttons are the terminal's commands (`ground.commands.parse_command`, the `--cmd` lines):
  arm, disarm, modes, depth/yaw, velocity, any command line. A click queues the messages; the
  IO thread sends them; the vehicle's COMMAND_ACK shows in the events.

Through link loss the page keeps running: rows keep coming, the vehicle's values are NaN (a gap
in each line) while the station says the link is down, the link-quality plot drops to 0 packets/s
and the status turns red; when packets come back the lines resume.

The server listens on 127.0.0.1 only: a page that arms the vehicle must not be open to a network
(from another machine: `ssh -L 8080:127.0.0.1:8080 GROUND_HOST`, then http://127.0.0.1:8080/).
"""

from __future__ import annotations

import math
import queue
import sys
import threading
import time
from collections import deque

from ground.station import Snapshot

SAMPLE_PERIOD_S = 0.1  # one plot row every 100 ms (telemetry comes at 10 Hz)
PUSH_PERIOD_MS = 500  # the page is sent new rows twice a second (a software-rendered browser on a busy
# 2-core machine kept up with 4 pushes a second of 120 s windows only barely: its clicks waited 120 s)
WINDOW_S = 60.0  # the plots' history: one minute
EVENTS_SHOWN = 15  # the event log's last lines on the page
ADDRESS = "127.0.0.1"
DEFAULT_PORT = 8080


class WebError(ValueError):
    """A dashboard that cannot start (bad port, port in use); the message says what was expected."""


def parse_port(text) -> int:
    """'8080' -> 8080; WebError naming the expected range otherwise."""
    try:
        port = int(str(text).strip())
    except ValueError:
        raise WebError(f"--port {text}: expected a TCP port number 1-65535") from None
    if not 1 <= port <= 65535:
        raise WebError(f"--port {text}: expected a TCP port number 1-65535")
    return port


# ------------------------------------------------------------------------------------------------
# Snapshot -> one row of plot values (pure)

FLAGS = ("link up", "armed", "failsafe", "fault", "warning")  # the flags plot, bottom to top
FLAG_HEIGHT = 0.7  # a raised flag is drawn FLAG_HEIGHT above its level


def columns(n_units: int) -> tuple:
    """The history's columns: time, then the plotted values (angles in deg, times in ms)."""
    jets = tuple(f"{q}{i}" for q in ("thrust", "az", "el") for i in range(n_units))
    return (("t_ms", "roll", "pitch", "yaw", "yaw_sp", "depth", "depth_sp", "u", "v", "w", "u_sp") + jets
            + ("residual", "alloc_err", "step_ms", "step_p99", "qp_ms", "rate_hz", "loss_pct", "jitter_ms", "rtt_ms")
            + tuple(f"flag_{f.replace(' ', '_')}" for f in FLAGS))


def _num(x, scale: float = 1.0) -> float:
    try:
        x = float(x) * scale
    except (TypeError, ValueError):
        return math.nan
    return x if math.isfinite(x) else math.nan


def row(s: Snapshot, t_s: float, n_units: int) -> dict:
    """The plot values of snapshot `s` taken at wall time `t_s` (s since the epoch). While the link
    is down the vehicle's values are NaN (a gap: the station's last values are not news); the link's
    own figures and the flags are always there."""
    deg = 180.0 / math.pi
    live = s.link_up
    v = (lambda x, k=1.0: _num(x, k)) if live else (lambda x, k=1.0: math.nan)  # noqa: E731
    r = {"t_ms": t_s * 1e3}
    r.update(roll=v(s.attitude_rad[0], deg), pitch=v(s.attitude_rad[1], deg), yaw=v(s.attitude_rad[2], deg),
             yaw_sp=v(s.yaw_setpoint_rad, deg), depth=v(s.depth_m), depth_sp=v(s.depth_setpoint_m),
             u=v(s.velocity_m_s[0]), v=v(s.velocity_m_s[1]), w=v(s.velocity_m_s[2]), u_sp=v(s.surge_setpoint_m_s))
    for i in range(n_units):
        j = s.jets
        have = j is not None and i < len(j.thrust_n)
        r[f"thrust{i}"] = v(j.thrust_n[i]) if have else math.nan
        r[f"az{i}"] = v(j.azimuth_rad[i], deg) if have else math.nan
        r[f"el{i}"] = v(j.elevation_rad[i], deg) if have else math.nan
    r.update(residual=v(s.residual_norm), alloc_err=v(s.allocation_error), step_ms=v(s.step_ms),
             step_p99=v(s.step_p99_ms), qp_ms=v(s.qp_us, 1e-3))
    # the link's own figures: measured by the ground, so they go on through a loss
    r.update(rate_hz=_num(s.rate_hz), loss_pct=_num(s.loss_fraction, 100.0), jitter_ms=_num(s.delay_jitter_s, 1e3),
             rtt_ms=_num(s.rtt_s, 1e3))
    flags = {"link up": s.link_up, "armed": s.armed if live else None, "failsafe": s.failsafe if live else None,
             "fault": (s.faults != 0) if live and s.faults is not None else None,
             "warning": bool(s.warnings)}
    for level, name in enumerate(FLAGS):
        f = flags[name]
        r[f"flag_{name.replace(' ', '_')}"] = math.nan if f is None else level + FLAG_HEIGHT * bool(f)
    return r


class History:
    """The last `maxlen` rows, numbered from 1; `since(n)` gives the rows after row n. Thread-safe."""

    def __init__(self, names, maxlen: int):
        self.names = tuple(names)
        self.maxlen = int(maxlen)
        self._rows: deque = deque(maxlen=self.maxlen)
        self.count = 0
        self._lock = threading.Lock()

    def append(self, r: dict) -> None:
        values = tuple(r.get(n, math.nan) for n in self.names)
        with self._lock:
            self._rows.append(values)
            self.count += 1

    def since(self, n: int) -> tuple:
        """(count now, {column: list of the values of rows n+1..count}); at most `maxlen` rows."""
        with self._lock:
            new = min(self.count - n, len(self._rows))
            rows = list(self._rows)[len(self._rows) - new:] if new > 0 else []
            count = self.count
        cols = list(zip(*rows)) if rows else [() for _ in self.names]
        return count, {name: list(c) for name, c in zip(self.names, cols)}


# ------------------------------------------------------------------------------------------------
# The IO side: the session in its own thread


class Dashboard:
    """A `GroundSession` polled in a thread, its snapshots sampled into a `History`, commands queued
    from the pages; `serve()` runs the Bokeh server on `port` until `duration_s` or Ctrl-C/SIGTERM."""

    def __init__(self, session, port: int = DEFAULT_PORT, sample_period_s: float = SAMPLE_PERIOD_S,
                 window_s: float = WINDOW_S):
        self.session = session
        self.port = port
        vehicle = session.station.vehicle
        self.n_units = vehicle.n_units if vehicle is not None else 0
        self.sample_period_s = sample_period_s
        self.history = History(columns(self.n_units), maxlen=int(round(window_s / sample_period_s)))
        self.latest: Snapshot = session.snapshot()
        self._outbox: queue.Queue = queue.Queue()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._io, name="jetloop-ground-io", daemon=True)
        self.io_errors = 0
        self.commands_sent = 0

    # -- IO thread ---------------------------------------------------------------------------------
    def _io(self) -> None:
        next_sample = 0.0
        while not self._stop.is_set():
            try:
                self.session.poll(0.02)
                while True:
                    try:
                        msgs = self._outbox.get_nowait()
                    except queue.Empty:
                        break
                    for m in msgs:
                        self.session.send(m)
                    self.commands_sent += 1
                now = time.monotonic()
                if now >= next_sample:
                    next_sample = now + self.sample_period_s
                    snap = self.session.station.snapshot(self.session.clock(), n_events=EVENTS_SHOWN)
                    self.latest = snap
                    self.history.append(row(snap, self.session.clock(), self.n_units))
            except Exception as exc:  # the operator's page outlives a bad moment; said once a second at most
                self.io_errors += 1
                if self.io_errors == 1 or self.io_errors % 100 == 0:
                    print(f"jetloop ground: dashboard IO error ({self.io_errors}): {type(exc).__name__}: {exc}",
                          file=sys.stderr, flush=True)
                time.sleep(0.01)

    def submit(self, line: str) -> str:
        """An operator's command line (the `--cmd` forms) queued for the IO thread; returns what was
        queued, or raises ground.commands.CommandError."""
        from ground.commands import parse_command

        msgs = parse_command(line)
        self._outbox.put(msgs)
        return " ".join(str(line).split())

    # -- the server --------------------------------------------------------------------------------
    def serve(self, duration_s: float | None = None, ready=None) -> None:
        """Start the IO thread and the Bokeh server; block until `duration_s` has passed (forever if
        None) or KeyboardInterrupt. Raises WebError if the port cannot be listened on. `ready(url)`
        is called once the server listens."""
        from bokeh.application import Application
        from bokeh.application.handlers.function import FunctionHandler
        from bokeh.server.server import Server
        from tornado.ioloop import IOLoop

        loop = IOLoop.current()
        origins = [f"{ADDRESS}:{self.port}", f"localhost:{self.port}"]
        try:
            server = Server({"/": Application(FunctionHandler(self.make_document))}, io_loop=loop,
                            port=self.port, address=ADDRESS, allow_websocket_origin=origins)
        except OSError as exc:
            import errno

            why = ("already in use (another dashboard or server?); choose another with --port"
                   if exc.errno == errno.EADDRINUSE else exc.strerror or str(exc))
            raise WebError(f"--port {self.port}: cannot listen on {ADDRESS}:{self.port}: {why}") from None
        self._thread.start()
        try:
            server.start()
            if duration_s is not None:
                loop.call_later(duration_s, loop.stop)
            if ready is not None:
                ready(f"http://{ADDRESS}:{self.port}/")
            loop.start()
        finally:
            self._stop.set()
            self._thread.join(2.0)
            try:
                server.stop(wait=False)
                server.unlisten()
            except Exception:  # noqa: BLE001 - a loop stopped by Ctrl-C may refuse; the process ends anyway
                pass

    # -- one browser tab -----------------------------------------------------------------------------
    def make_document(self, doc) -> None:
        """Build the page for one browser session (runs in the server's thread)."""
        page = _Page(self)
        doc.add_root(page.layout)
        doc.title = "jetloop ground"
        page.push()
        doc.add_periodic_callback(page.push, PUSH_PERIOD_MS)


# ------------------------------------------------------------------------------------------------
# The page

PALETTE = ("#1f77b4", "#d62728", "#2ca02c", "#ff7f0e", "#9467bd", "#8c564b", "#e377c2", "#17becf")


def _esc(text) -> str:
    import html

    return html.escape(str(text))


class _Page:
    """One tab's document: its own ColumnDataSource fed from the shared history."""

    def __init__(self, dash: Dashboard):
        import numpy as np
        from bokeh.layouts import column, gridplot, row as brow
        from bokeh.models import Button, ColumnDataSource, Div, TextInput

        self.dash = dash
        self.np = np
        self.count = 0
        names = dash.history.names
        # "zero": the baseline every plot draws, so a range stays finite while its values are all gaps
        # (no link yet, or a long loss): BokehJS re-renders without end when a range cannot be set
        self.source = ColumnDataSource({n: np.zeros(0) for n in names + ("zero",)}, name="telemetry")
        k = dash.n_units
        figs = [
            self._figure("attitude (deg)", [("roll", "roll"), ("pitch", "pitch"), ("yaw", "yaw"),
                                            ("yaw_sp", "yaw setpoint", "dashed")]),
            self._figure("depth (m, down)", [("depth", "depth"), ("depth_sp", "setpoint", "dashed")], flip=True),
            self._figure("body velocity (m/s)", [("u", "u surge"), ("v", "v sway"), ("w", "w heave"),
                                                 ("u_sp", "u setpoint", "dashed")]),
            self._figure("jet thrust (N)", [(f"thrust{i}", f"jet {i + 1}") for i in range(k)]),
            self._figure("joints (deg): azimuth solid, elevation dashed",
                         [(f"az{i}", f"az {i + 1}", "solid", PALETTE[i % 8]) for i in range(k)]
                         + [(f"el{i}", f"el {i + 1}", "dashed", PALETTE[i % 8]) for i in range(k)], legend_columns=2),
            self._figure("allocation residual", [("residual", "|demand - achieved|"),
                                                 ("alloc_err", "weighted error")]),
            self._figure("loop timing (ms)", [("step_ms", "control step"), ("step_p99", "step p99"),
                                              ("qp_ms", "QP solve")]),
            self._figure("link quality", [("rate_hz", "packets/s"), ("loss_pct", "loss %"),
                                          ("jitter_ms", "delay jitter ms"), ("rtt_ms", "command round trip ms")]),
            self._flags_figure(),
        ]
        for f in figs[1:]:
            f.x_range = figs[0].x_range  # pan and zoom together
        self.status = Div(text="", name="status", sizing_mode="stretch_width")
        self.warnings = Div(text="", name="warnings", sizing_mode="stretch_width")
        self.events = Div(text="", name="events", sizing_mode="stretch_width")
        self.feedback = Div(text="", name="feedback", width=420)

        def button(label, line, name, kind="default"):
            b = Button(label=label, name=name, button_type=kind, width=95)
            b.on_click(lambda: self.send(line))
            return b

        from onboard.loop import MODES

        buttons = [button("Arm", "arm", "cmd-arm", "danger"), button("Disarm", "disarm", "cmd-disarm", "success")]
        buttons += [button(m.replace("_", " "), f"mode {m}", f"mode-{m}") for m in MODES]
        depth = TextInput(value="0.5", value_input="0.5", title="depth (m)", width=70, name="in-depth")
        yaw = TextInput(value="0", value_input="0", title="yaw (deg)", width=70, name="in-yaw")
        go_depth = Button(label="Set depth/yaw", name="cmd-depth", width=110)
        typed = lambda box: box.value_input  # noqa: E731 - what the box shows, Enter pressed or not
        go_depth.on_click(lambda: self.send(f"depth {typed(depth)} yaw {typed(yaw)}"))
        surge = TextInput(value="0", value_input="0", title="u (m/s)", width=70, name="in-u")
        sway = TextInput(value="0", value_input="0", title="v (m/s)", width=70, name="in-v")
        go_vel = Button(label="Set velocity", name="cmd-velocity", width=100)
        go_vel.on_click(lambda: self.send(f"velocity {typed(surge)} {typed(sway)}"))
        from ground.commands import COMMAND_HELP

        line = TextInput(value="", value_input="", title="command line (as jetloop ground --cmd)", width=420,
                         placeholder=COMMAND_HELP, name="in-command")
        go_line = Button(label="Send", name="cmd-send", width=70)
        go_line.on_click(lambda: self.send(typed(line)))
        head = Div(text="<b style='font-size:150%'>jetloop ground</b>", width=170)
        controls = column(
            brow(*buttons),
            brow(depth, yaw, go_depth, surge, sway, go_vel, line, go_line, align="end"),
            self.feedback)
        grid = gridplot(figs, ncols=3, sizing_mode="stretch_width", height=230, toolbar_location="right",
                        merge_tools=True)
        self.layout = column(brow(head, self.status, sizing_mode="stretch_width"), controls,
                             brow(self.warnings, self.events, sizing_mode="stretch_width"), grid,
                             sizing_mode="stretch_width")

    def _figure(self, title: str, lines, flip: bool = False, legend_columns: int = 1):
        from bokeh.plotting import figure

        p = figure(title=title, x_axis_type="datetime", height=230, sizing_mode="stretch_width",
                   tools="pan,xwheel_zoom,box_zoom,reset,save", name=title)
        p.line("t_ms", "zero", source=self.source, color="#bbbbbb", line_width=1)  # the zero (surface, level) line
        for i, spec in enumerate(lines):
            col, label = spec[0], spec[1]
            dash = spec[2] if len(spec) > 2 else "solid"
            color = spec[3] if len(spec) > 3 else PALETTE[i % 8]
            p.line("t_ms", col, source=self.source, legend_label=label, line_dash=dash, color=color, line_width=2)
        if flip:
            p.y_range.flipped = True
        p.legend.location = "top_left"
        p.legend.click_policy = "hide"
        p.legend.label_text_font_size = "8pt"
        p.legend.background_fill_alpha = 0.6
        p.legend.spacing = 0
        p.legend.padding = 2
        p.legend.ncols = legend_columns
        p.xaxis.axis_label = "time (UTC)"
        return p

    def _flags_figure(self):
        from bokeh.models import FixedTicker, Range1d
        from bokeh.plotting import figure

        p = figure(title="failsafe and fault flags (raised = high)", x_axis_type="datetime", height=230,
                   sizing_mode="stretch_width", tools="pan,xwheel_zoom,box_zoom,reset,save",
                   y_range=Range1d(-0.2, len(FLAGS)), name="flags")
        colors = ("#2ca02c", "#1f77b4", "#d62728", "#ff7f0e", "#9467bd")
        for level, name in enumerate(FLAGS):
            p.step("t_ms", f"flag_{name.replace(' ', '_')}", source=self.source, mode="after",
                   color=colors[level], line_width=2)
        p.yaxis.ticker = FixedTicker(ticks=[i + FLAG_HEIGHT / 2 for i in range(len(FLAGS))])
        p.yaxis.major_label_overrides = {i + FLAG_HEIGHT / 2: n for i, n in enumerate(FLAGS)}
        p.ygrid.visible = False
        p.xaxis.axis_label = "time (UTC)"
        return p

    # -- callbacks (the server's thread) ------------------------------------------------------------
    def send(self, line: str) -> None:
        from ground.commands import CommandError

        try:
            sent = self.dash.submit(line)
        except CommandError as exc:
            self.feedback.text = f"<span style='color:#d62728'>not sent: {_esc(exc)}</span>"
            return
        note = "" if self.dash.latest.vehicle else " (no vehicle seen yet: the link has nowhere to send it)"
        self.feedback.text = f"sent <b>{_esc(sent)}</b> at {time.strftime('%H:%M:%S')}{_esc(note)}"

    def push(self) -> None:
        """Stream the rows the history has gained since the last push; refresh the text panels."""
        count, new = self.dash.history.since(self.count)
        if count > self.count and new["t_ms"]:
            np = self.np
            cols = {k: np.asarray(v, dtype=float) for k, v in new.items()}
            cols["zero"] = np.zeros(len(cols["t_ms"]))
            self.source.stream(cols, rollover=self.dash.history.maxlen)
        self.count = count
        s = self.dash.latest
        status = _status_html(s)
        if status != self.status.text:
            self.status.text = status
        warn = ("<b>warnings</b><br>" + ("<br>".join(f"<span style='color:#d62728'>{_esc(w)}</span>"
                                                     for w in s.warnings) or "none"))
        if warn != self.warnings.text:
            self.warnings.text = warn
        ev = "<b>events</b><br>" + ("<br>".join(
            f"{time.strftime('%H:%M:%S', time.localtime(t))} {_esc(text)}" for t, text in s.events) or "-")
        if ev != self.events.text:
            self.events.text = ev


def _status_html(s: Snapshot) -> str:
    from ground.view import _f

    if s.link_up:
        link = f"<span style='color:#2ca02c'>link UP</span> {_f(s.rate_hz, '{:.0f}')} pkt/s"
    elif s.packets:
        link = f"<span style='background:#d62728;color:white'>&nbsp;LINK LOST&nbsp;</span> " \
               f"{_f(s.since_last_s, '{:.1f}')} s without a packet"
    else:
        link = "link waiting"
    fs = "-" if s.failsafe is None else ("<span style='color:#d62728'>FAILSAFE</span>" if s.failsafe else "off")
    faults = "-"
    if s.faults is not None:
        from onboard.monitor import fault_names

        faults = _esc(fault_names(s.faults)) or "none"
    vehicle = f"vehicle {s.vehicle[0]}/{s.vehicle[1]}" if s.vehicle else "no heartbeat yet"
    armed = "-" if s.armed is None else ("<b style='color:#d62728'>ARMED</b>" if s.armed else "disarmed")
    return (f"<span style='font-size:120%'>{vehicle} &middot; {armed} &middot; mode {_esc(s.mode)} &middot; "
            f"failsafe {fs} &middot; faults {faults} &middot; {link} &middot; lost {s.lost} "
            f"({_f(s.loss_fraction, '{:.1f}', 100)} %) &middot; round trip {_f(s.rtt_s, '{:.0f}', 1e3)} ms</span>")


def serve(session, port: int, duration_s: float | None = None, out=None) -> None:
    """`jetloop ground --web`: the dashboard on http://127.0.0.1:PORT/ until `duration_s` or Ctrl-C."""
    out = out or sys.stdout
    dash = Dashboard(session, port)
    dash.serve(duration_s, ready=lambda url: print(f"jetloop ground: dashboard at {url} (Ctrl-C stops)",
                                                  file=out, flush=True))
