"""`jetloop diagnose RECORDING [--vehicle V] [--json R.json] [--report DIR]` (spec/recording.md 2)."""

from __future__ import annotations

import sys
import time

import numpy as np


def configure(parser) -> None:
    parser.add_argument("recording", help=".tlog or dataflash .bin recording")
    parser.add_argument("--vehicle", default=None,
                        help="vehicle TOML: the nominal model (default: the reference vehicle asr4)")
    parser.add_argument("--json", dest="json_path", default=None, help="write the JSON report here")
    parser.add_argument("--report", dest="report_dir", default=None, help="write an HTML report with plots here")
    parser.add_argument("--quiet", action="store_true", help="no progress on the console")


def run(args) -> int:
    from onboard.vehicle import VehicleFileError, load_vehicle

    from ground.recording import RecordingError, read_recording

    from . import diagnose
    from .replay import ReplayError
    from .report import write_html, write_json

    t0 = time.perf_counter()

    def say(msg: str) -> None:
        if not args.quiet:
            print(f"[{time.perf_counter() - t0:6.1f} s] {msg}", file=sys.stderr, flush=True)

    try:
        vehicle = load_vehicle(args.vehicle)
        say(f"reading {args.recording}")
        rec = read_recording(args.recording)
        s = rec.skipped
        say(f"{rec.duration_s:.1f} s, {sum(rec.messages.values())} messages; skipped {s.skipped_bytes} bytes "
            f"({s.bad_crc_packets} bad-CRC packets, {s.truncated_bytes} truncated), "
            f"non-monotonic {sum(s.non_monotonic.values())}, gaps {len(s.gaps)}")
        with np.errstate(all="ignore"):  # a recording far from the model overflows; the report says so
            diag = diagnose(rec, vehicle, progress=say)
    except (VehicleFileError, RecordingError, ReplayError) as exc:
        print(f"jetloop diagnose: {exc}", file=sys.stderr)
        return 2
    rep = diag.report
    print(summary_text(rep))
    try:
        if args.json_path:
            write_json(rep, args.json_path)
            say(f"wrote {args.json_path}")
        if args.report_dir:
            path = write_html(diag, args.report_dir)
            say(f"wrote {path}")
    except OSError as exc:
        print(f"jetloop diagnose: cannot write the report: {exc}", file=sys.stderr)
        return 2
    return 0


def summary_text(rep: dict) -> str:
    from .report import no_finding_text

    lines = [] if rep["findings"] else [no_finding_text(rep)]
    for i, f in enumerate(rep["findings"]):
        lines.append(f"{i + 1}. {f['effect']} ({f['kind']}, confidence {f['confidence']:.2f}): {f['explanation']}")
        if f.get("std"):
            lines.append("   sd: " + ", ".join(f"{k} {v}" for k, v in f["std"].items()))
    if rep.get("reversed_by_autopilot"):
        lines.append(f"thrusters {rep['reversed_by_autopilot']} reversed by the autopilot (the log's MOT_n_DIRECTION): "
                     "modelled pushing against their `direction`")
    for w in rep.get("warnings", []):
        lines.append(f"warning: {w}")
    unt = rep.get("untestable", [])
    twice = {u["effect"] for u in unt if sum(v["effect"] == u["effect"] for v in unt) > 1}
    for u in unt:  # an effect listed as two candidates (a unit's fault, the curve) says which
        kind = f" ({u.get('kind')})" if u["effect"] in twice and u.get("kind") else ""
        lines.append(f"not testable: {u['effect']}{kind}: {u['reason']}")
    h = rep["fit"]["holdout"]
    fmt = lambda v: f"{v:.3f}" if isinstance(v, (int, float)) and v == v else "n/a"  # noqa: E731
    lines.append(f"held-out NRMSE total: {fmt(h['before']['total'])} -> {fmt(h['after']['total'])}")
    if rep["mismatch"]["windows"]:
        lines.append(f"{len(rep['mismatch']['windows'])} window(s) above the noise floor, e.g. "
                     + "; ".join(f"{w['t0']:.1f}-{w['t1']:.1f} s {'/'.join(w['axes'])}"
                                 for w in rep["mismatch"]["windows"][:4]))
    return "\n".join(lines)
