"""`jetloop`: the one command line for the whole package; each subcommand is its own module.

A subcommand module defines `configure(parser)` (its arguments) and `run(args) -> int`.
A module is imported only when its subcommand runs, so `jetloop onboard` on the robot never
imports the ground station's plotting stack.
"""

from __future__ import annotations

import argparse
import importlib
import os
import signal
import sys
import threading

# name -> (module, one-line help). Add a subcommand by adding a line here.
SUBCOMMANDS = {
    "sim": ("hil.sim", "open-loop simulation of a commands CSV to a .tlog recording"),
    "identify": ("ground.identify.cli", "the seed papers' identification methods: thrust, free-decay, pendulum, tables, azimuth"),
    "diagnose": ("ground.diagnose.cli", "where simulation and a recording differ, the missing physics named, fitted and shown"),
    "prove": ("ground.prove", "diagnose proven on plant recordings with concealed effects: prove.json and a table"),
    "demo": ("hil.demo", "plant + onboard loop + recorder over loopback UDP in lock-step: a scripted mission, scored"),
    "onboard": ("onboard.cli", "the onboard loop on a MAVLink link (autopilot, HIL plant or log replay)"),
    "hil": ("hil.cli", "the plant as a MAVLink sensor endpoint (or SITL JSON physics) for a controller"),
    "ground": ("ground.ground_cli", "ground station: live telemetry view, .tlog recorder, commands, stream rates, signing"),
    "soak": ("hil.soak", "an hour (or --duration) of random missions and faults in lock-step: deadlines, memory, packets"),
    "plot": ("ground.plot", "standard plots of a .tlog/.bin recording (HIL, sim or ArduSub) as PNGs and index.html"),
    "campaign": ("ground.campaign.cli", "missions, prove cases or diagnoses by the hundred on Dask (local cluster or existing)"),
}


# distributed's nanny sets these to 1 before a worker starts (pre-spawn-environ); OpenBLAS 0.3.31
# started with threads rounds a mission's figures differently in the 10th digit, and limiting it
# to one thread later does not undo that: only the environment before numpy's first import does
SINGLE_THREAD_BLAS = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    top = argparse.ArgumentParser(
        prog="jetloop",
        description="Firmware-in-the-loop for small underwater robots driven by vectored water-jets.",
        epilog="commands:\n" + "\n".join(f"  {n:10s} {h}" for n, (_, h) in SUBCOMMANDS.items())
        + "\n\n'jetloop COMMAND --help' shows a command's options.",
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    top.add_argument("command", choices=sorted(SUBCOMMANDS), metavar="COMMAND")
    if not argv or argv[0] not in SUBCOMMANDS:
        top.parse_args(argv[:1])  # prints usage / help / the unknown-command error
        return 2
    name = argv[0]
    module_name, help_text = SUBCOMMANDS[name]
    if name == "campaign":  # BLAS started single-threaded, as Dask's nanny starts its workers
        for var in SINGLE_THREAD_BLAS:  # (a serial run's table equals a cluster's, to the last digit)
            os.environ.setdefault(var, "1")
    module = importlib.import_module(module_name)
    parser = argparse.ArgumentParser(prog=f"jetloop {name}", description=help_text)
    module.configure(parser)
    args = parser.parse_args(argv[1:])
    previous = _stop_on_sigterm()
    try:
        code = int(module.run(args) or 0)
        sys.stdout.flush()  # a reader gone while the output sat in the buffer: raised here, not at exit
        return code
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # `jetloop prove --table ... | head`: the reader left; no traceback
        # (the Python documentation's recipe, "Note on SIGPIPE": stdout to devnull so the
        # interpreter's own flush at exit does not raise again)
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141  # as a shell reports a process ended by SIGPIPE (128 + 13)
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)


def make_output_dir(path, command: str):
    """The output directory `path` of `jetloop COMMAND`, created with its parents; if it cannot be,
    one line on stderr ("jetloop COMMAND: cannot create output directory PATH: why") and None, for
    the command to return 2."""
    from pathlib import Path

    out = Path(path)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        print(f"{command}: cannot create output directory {out}: {exc.strerror or exc}", file=sys.stderr)
        return None
    return out


def _raise_interrupt(signum, frame):
    # An exception raised inside a gc callback is swallowed by the interpreter ("Exception ignored
    # in gc callback"): onboard.loop times each collection with one, so a SIGTERM landing there
    # was lost (seen by the dashboard test). There it is sent again 20 ms later instead.
    loop = sys.modules.get("onboard.loop")
    if loop is not None and frame is not None and frame.f_code is loop._gc_timer.__code__:
        threading.Timer(0.02, os.kill, args=(os.getpid(), signum)).start()
        return
    raise KeyboardInterrupt(f"signal {signum}")


def _stop_on_sigterm():
    """SIGTERM (what systemd, supervisors and `kill` send) stops a command as Ctrl-C does: each
    command's KeyboardInterrupt path closes its links and recordings and prints its summary.
    Not SIGINT itself: a process started with SIGINT ignored (a shell's background job, or a
    child spawned while its parent was inside system()) keeps it ignored, as it should. Only
    from the main thread (the only one that may set handlers). Returns the handler it replaced,
    or None if it set none."""
    if threading.current_thread() is not threading.main_thread():
        return None
    return signal.signal(signal.SIGTERM, _raise_interrupt)


if __name__ == "__main__":
    sys.exit(main())
