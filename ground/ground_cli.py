"""`jetloop ground` (live view, recorder, commands) and `jetloop plot` (a recording's plots).

    jetloop ground [--link udpin:127.0.0.1:14550] [--record DIR] [--key KEYFILE]
                   [--rates ATTITUDE=10,NAMED_VALUE_FLOAT=5] [--cmd "depth 1.5"]...
                   [--duration S | --once] [--plain]
    jetloop ground --web [--port 8080] ...          (the live dashboard in a browser: ground/web.py)
    jetloop plot REC.tlog --out DIR [--vehicle V.toml]

`GroundSession` is the IO loop: it reads the link, records every packet (both directions),
updates the `Station` model, sends a GCS HEARTBEAT at 1 Hz (so a udpin vehicle learns where
the ground is) and, once the vehicle's first HEARTBEAT arrives, the requested stream rates
(SET_MESSAGE_INTERVAL) and the `--cmd` commands. The view redraws 4 times a second and keeps
running through link loss, garbage and truncated packets: the station says what happened.

The default link listens on 127.0.0.1 only (the HIL and `jetloop onboard` on this machine): a
vehicle on another machine is named explicitly, best by the interface it is reached on
(`--link udpin:192.168.2.1:14550` on a BlueROV tether) rather than every interface (0.0.0.0):
a udpin link keeps the first sender of valid MAVLink as its peer (onboard.link), but until the
vehicle speaks, or after it is silent for 5 s, any host that can reach the port could become
that peer, receive the ground's (signed) commands and feed the view false telemetry.
"""

from __future__ import annotations

import sys
import time

from pymavlink.dialects.v20 import ardupilotmega as mavlink

GCS_SYSTEM = 255
GCS_COMPONENT = 190
HEARTBEAT_PERIOD_S = 1.0
VIEW_PERIOD_S = 0.25


class GroundSession:
    """Link + Station + Recorder; `poll(timeout_s)` handles what has arrived, `send(msg)` sends."""

    def __init__(self, connection: str, vehicle=None, record_dir=None, key: bytes | None = None,
                 rates: dict | None = None, commands=(), max_bytes: int | None = None, clock=time.time,
                 limits=None):
        from onboard.link import Link

        from ground.commands import enable_signing, message_interval
        from ground.recorder import DEFAULT_MAX_BYTES, Recorder
        from ground.station import Limits, Station

        self.clock = clock
        self.link = Link(connection, source_system=GCS_SYSTEM, source_component=GCS_COMPONENT)
        if key is not None:
            enable_signing(self.link.mav, key)
        self.station = Station(vehicle, limits or Limits(), own_system=GCS_SYSTEM)
        self.recorder = Recorder(record_dir, max_bytes=max_bytes or DEFAULT_MAX_BYTES, clock=clock) \
            if record_dir is not None else None
        self._startup = [message_interval(name, hz) for name, hz in (rates or {}).items()] + list(commands)
        self._next_heartbeat = 0.0
        self.messages_in = 0

    def send(self, msg) -> bytes:
        if self.link.mav.signing.sign_outgoing:
            from onboard.signing import refresh_timestamp

            refresh_timestamp(self.link.mav)  # a restarted robot judges a new stream by its clock
        buf = self.link.send(msg)
        if self.recorder is not None:
            self.recorder.record(buf, msg.get_type(), outgoing=True)
        if msg.get_type() == "COMMAND_LONG":
            self.station.command_sent(int(msg.command), self.clock())
        return buf

    def poll(self, timeout_s: float = 0.05, max_messages: int = 100_000) -> int:
        """Take in what arrives within `timeout_s` (and all that is queued); returns how many."""
        now = self.clock()
        if now >= self._next_heartbeat:
            self._next_heartbeat = now + HEARTBEAT_PERIOD_S
            self.send(mavlink.MAVLink_heartbeat_message(mavlink.MAV_TYPE_GCS, mavlink.MAV_AUTOPILOT_INVALID,
                                                        0, 0, mavlink.MAV_STATE_ACTIVE, 3))
        n = 0
        st, rec = self.station, self.recorder
        m = self.link.recv(timeout_s)
        while m is not None and n < max_messages:
            now = self.clock()
            if rec is not None:
                rec.record(bytes(m.get_msgbuf()), m.get_type())
            st.update(m, now)
            n += 1
            m = self.link.recv(0.0)
        now = self.clock()
        if self._startup and st.vehicle_id is not None:
            startup, self._startup = self._startup, []
            for msg in startup:
                self.send(msg)
        st.link_counters(self.link.garbage_bytes, self.link.bad_packets + self.link.unknown_packets, now)
        st.tick(now)
        if rec is not None:
            rec.flush_if_due()
        self.messages_in += n
        return n

    def snapshot(self):
        return self.station.snapshot(self.clock())

    def close(self) -> None:
        if self.recorder is not None:
            self.recorder.close()
        self.link.close()


def run_view(session: GroundSession, duration_s: float | None = None, once: bool = False, plain: bool = False,
             out=None) -> None:
    """Poll and redraw until `duration_s` has passed (forever if None); `once`: one poll window
    of 1 s then one frame. `plain` (or a non-terminal output) prints text frames instead of rich."""
    from ground.view import render_rich, render_text

    out = out or sys.stdout
    t_end = None if duration_s is None else time.monotonic() + duration_s
    if once:
        t_end = time.monotonic() + 1.0
    use_rich = not plain and not once and out.isatty()
    live = None
    if use_rich:
        from rich.live import Live

        live = Live(render_rich(session.snapshot()), refresh_per_second=4, screen=False)
        live.start()
    next_draw = time.monotonic() + VIEW_PERIOD_S
    try:
        while t_end is None or time.monotonic() < t_end:
            session.poll(0.02)
            if time.monotonic() >= next_draw:
                next_draw = time.monotonic() + (VIEW_PERIOD_S if use_rich else 1.0)
                if live is not None:
                    live.update(render_rich(session.snapshot()))
                elif not once:
                    print(render_text(session.snapshot()) + "\n", file=out, flush=True)
    finally:
        if live is not None:
            live.stop()
        print(render_text(session.snapshot()), file=out, flush=True)


# ------------------------------------------------------------------------------------------------
# CLI


def configure(parser) -> None:
    from ground.commands import COMMAND_HELP

    parser.add_argument("--link", default="udpin:127.0.0.1:14550",
                        help="udpin:HOST:PORT, udpout:HOST:PORT or /dev/ttyXXX:BAUD (default udpin:127.0.0.1:14550, "
                             "this machine only; a vehicle elsewhere: udpin:INTERFACE_ADDRESS:14550)")
    parser.add_argument("--record", default=None, metavar="DIR", help="record every packet to DIR/ground-*.tlog")
    parser.add_argument("--max-mb", type=float, default=64.0, help="start a new .tlog after this many MB (default 64)")
    parser.add_argument("--key", default=None, metavar="KEYFILE",
                        help="MAVLink 2 signing key (32 raw bytes or 64 hex digits): sign what the ground sends")
    parser.add_argument("--rates", default="", metavar="MSG=HZ,...",
                        help="stream rates to ask for with SET_MESSAGE_INTERVAL, e.g. ATTITUDE=10,NAMED_VALUE_FLOAT=5")
    parser.add_argument("--cmd", action="append", default=[], metavar="COMMAND",
                        help=f"send once the vehicle is seen (repeatable): {COMMAND_HELP}")
    parser.add_argument("--vehicle", default=None, metavar="V.toml", help="vehicle file for the jets panel (default asr4)")
    parser.add_argument("--duration", type=float, default=None, metavar="S", help="stop after S seconds")
    parser.add_argument("--once", action="store_true", help="listen 1 s, print one text frame, exit")
    parser.add_argument("--plain", action="store_true", help="plain-text frames instead of the rich view")
    parser.add_argument("--web", action="store_true",
                        help="serve the live dashboard (Bokeh plots and command buttons) on http://127.0.0.1:PORT/ "
                             "instead of the terminal view")
    parser.add_argument("--port", default=None, metavar="PORT", help="the dashboard's TCP port (default 8080; with --web)")


def run(args) -> int:
    from onboard.link import LinkError
    from onboard.vehicle import VehicleFileError, load_vehicle

    from ground.commands import CommandError, SigningError, load_key, parse_command, parse_rates
    from ground.recorder import RecorderError

    try:
        vehicle = load_vehicle(args.vehicle)
        key = load_key(args.key) if args.key else None
        rates = parse_rates(args.rates)
        commands = [m for line in args.cmd for m in parse_command(line)]
        if args.duration is not None and not args.duration > 0:
            raise CommandError(f"--duration {args.duration}: expected a number of seconds > 0")
        if not args.max_mb > 0:
            raise CommandError(f"--max-mb {args.max_mb}: expected a size in MB > 0")
        port = _web_port(args)
        session = GroundSession(args.link, vehicle, args.record, key, rates, commands,
                                max_bytes=int(args.max_mb * 1024 * 1024))
    except (CommandError, SigningError, LinkError, RecorderError, VehicleFileError, OSError) as exc:
        print(f"jetloop ground: {exc}", file=sys.stderr)
        return 2
    try:
        if args.web:
            from ground.view import render_text
            from ground.web import WebError, serve

            try:
                serve(session, port, args.duration)
            except WebError as exc:
                print(f"jetloop ground: {exc}", file=sys.stderr)
                return 2
            except KeyboardInterrupt:
                print(render_text(session.snapshot()), flush=True)  # the last frame, as the terminal view
                raise
            print(render_text(session.snapshot()), flush=True)
        else:
            run_view(session, args.duration, args.once, args.plain)
    finally:
        session.close()
        if session.recorder is not None:
            r = session.recorder
            print(f"recorded {r.packets} packets ({r.packets_in} in, {r.packets_out} out) to "
                  f"{', '.join(str(p) for p in r.files)}", file=sys.stderr)
    return 0


def _web_port(args) -> int | None:
    """--web's port (8080 by default), checked before anything opens; CommandError otherwise."""
    from ground.commands import CommandError

    web, port = getattr(args, "web", False), getattr(args, "port", None)
    if not web:
        if port is not None:
            raise CommandError("--port is the dashboard's: add --web")
        return None
    if args.once or args.plain:
        raise CommandError("--web serves the dashboard; --once and --plain are the terminal view's")
    from ground.web import DEFAULT_PORT, WebError, parse_port

    try:
        return DEFAULT_PORT if port is None else parse_port(port)
    except WebError as exc:
        raise CommandError(str(exc)) from None


def configure_plot(parser) -> None:
    parser.add_argument("recording", metavar="REC", help="a .tlog or dataflash .bin recording")
    parser.add_argument("--out", required=True, metavar="DIR", help="directory for the PNGs and index.html")
    parser.add_argument("--vehicle", default=None, metavar="V.toml",
                        help="vehicle file for PWM maps and depth (default: the reference vehicle asr4)")


def run_plot(args) -> int:
    from onboard.vehicle import VehicleFileError, load_vehicle

    from ground.plot import PlotError, make_plots, report

    try:
        vehicle = load_vehicle(args.vehicle)
        summary = make_plots(args.recording, args.out, vehicle)
    except (PlotError, VehicleFileError) as exc:
        print(f"jetloop plot: {exc}", file=sys.stderr)
        return 2
    print(report(summary))
    print(f"  wrote {args.out}/index.html")
    return 0

