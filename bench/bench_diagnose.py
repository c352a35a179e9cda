"""Benchmark: a 10-minute, 100 Hz pool recording diagnosed end to end (target: at most 60 s).

    python bench/bench_diagnose.py [--minutes 10] [--keep DIR]

Makes the recording with the plant (not timed: the plant is the slow part), then times
reading it and `diagnose` (the EKF + RTS smoother over the whole recording, every candidate
scored on the fitting windows, the null draws that calibrate the thresholds, the nonlinear fits
of the significant ones, held-out shooting) in this process, and prints the figures with the
machine's load for context. The baseline ratio is against one smoother pass over the whole
recording plus its residual (`Evaluator`), measured in the same run.
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from ground.diagnose import diagnose  # noqa: E402
from ground.diagnose.candidates import Evaluator  # noqa: E402
from ground.prove import record_session  # noqa: E402
from ground.recording import read_recording  # noqa: E402
from onboard.vehicle import load_vehicle  # noqa: E402


def main() -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--minutes", type=float, default=10.0)
    ap.add_argument("--keep", default=None, help="directory to keep (and reuse) the recording in")
    args = ap.parse_args()
    ref = load_vehicle()
    truth = ref.with_values({"body.volume": ref.body.volume * 1.005})  # a concealed buoyancy error
    folder = Path(args.keep) if args.keep else Path(tempfile.mkdtemp(prefix="bench_diag_"))
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"pool_{args.minutes:g}min.tlog"
    if not path.exists():
        t0 = time.perf_counter()
        record_session(truth, path, args.minutes * 60.0, seed=11)
        print(f"recording made by the plant in {time.perf_counter() - t0:.1f} s (not part of the figure)")
    # warm the compiled code (numba cache) so the figure is the steady-state cost
    warm = read_recording(path).between(0.0, 30.0)
    Evaluator(warm, ref).residual(Evaluator(warm, ref).base)
    t0 = time.perf_counter()
    rec = read_recording(path)
    t_read = time.perf_counter() - t0
    t1 = time.perf_counter()
    ev = Evaluator(rec, ref)
    ev.residual(ev.base)
    t_replay = time.perf_counter() - t1
    t2 = time.perf_counter()
    diag = diagnose(rec, ref)
    t_diag = time.perf_counter() - t2
    total = t_read + t_diag
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    print(f"recording: {rec.duration_s:.0f} s, {sum(rec.messages.values())} messages, {path.stat().st_size / 1e6:.1f} MB")
    print(f"read:      {t_read:6.2f} s")
    print(f"estimate:  {t_replay:6.2f} s (one smoother pass + residual: the baseline)")
    print(f"diagnose:  {t_diag:6.2f} s = {t_diag / t_replay:.0f} x the baseline")
    print(f"total:     {total:6.2f} s (target <= 60 s) on {os.cpu_count()} cores, load {load:.1f}")
    cal = diag.report.get("calibration", {})
    print(f"null draws: {cal.get('null_draws')}; untestable: {[u['effect'] for u in diag.report.get('untestable', [])]}")
    f = diag.report["findings"]
    print(f"named:     {f[0]['effect'] if f else 'nothing'}; held-out NRMSE "
          f"{diag.report['fit']['holdout']['before']['total']:.3f} -> {diag.report['fit']['holdout']['after']['total']:.3f}"
          f" (held-out blocks moved {diag.report['fit']['holdout_phase']} near a boundary)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
