"""`jetloop`: the one command line for the whole package; each subcommand is its own module.

A subcommand module defines `configure(parser)` (its arguments) and `run(args) -> int`.
A module is imported only when its subcommand runs, so `jetloop onboard` on the robot never
imports the ground station's plotting stack.
"""

from __future__ import annotations

import argparse
import importlib
import sys

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
}


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
    module = importlib.import_module(module_name)
    parser = argparse.ArgumentParser(prog=f"jetloop {name}", description=help_text)
    module.configure(parser)
    args = parser.parse_args(argv[1:])
    try:
        return int(module.run(args) or 0)
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
