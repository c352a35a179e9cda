"""`jetloop campaign SPEC.toml --out DIR [--scheduler tcp://HOST:8786] [--workers N]`."""

from __future__ import annotations

import re
import sys
from pathlib import Path

EXAMPLES = Path(__file__).parent / "examples"


def configure(parser) -> None:
    parser.description = ("Run a campaign (missions, prove or diagnose) on Dask: a local cluster of worker processes "
                          "by default, or an existing cluster (dask scheduler / dask worker). Results land in "
                          "DIR/results.parquet as they finish; running the same command again resumes.")
    parser.add_argument("spec", help=f"campaign spec (TOML); examples in {EXAMPLES}")
    parser.add_argument("--out", required=True, metavar="DIR", help="results: results.parquet, tasks/, index.html")
    parser.add_argument("--scheduler", default=None, metavar="tcp://HOST:PORT",
                        help="submit to this existing Dask scheduler (default: start a local cluster)")
    parser.add_argument("--workers", type=int, default=None, metavar="N",
                        help="worker processes of the local cluster (default: the cores, at most 8; never more than "
                             "the tasks to run); "
                             "0 runs the tasks one after the other in this process")
    parser.add_argument("--quiet", action="store_true", help="no progress on the console")


def run(args) -> int:
    from .engine import run_campaign
    from .spec import CampaignSpecError, load_spec

    name = "jetloop campaign"
    if args.workers is not None and args.workers < 0:
        print(f"{name}: --workers {args.workers}: expected a number of worker processes >= 0", file=sys.stderr)
        return 2
    if args.scheduler is not None:
        if args.workers is not None:
            print(f"{name}: --workers with --scheduler: the cluster's workers are started with `dask worker`",
                  file=sys.stderr)
            return 2
        if not re.fullmatch(r"(tcp|tls)://[A-Za-z0-9.\-\[\]:]+:\d{1,5}", args.scheduler):
            print(f"{name}: --scheduler {args.scheduler!r}: expected tcp://HOST:PORT (what `dask scheduler` prints)",
                  file=sys.stderr)
            return 2
    try:
        campaign = load_spec(args.spec)
    except CampaignSpecError as exc:
        print(f"{name}: {exc}", file=sys.stderr)
        return 2
    from ground.cli import make_output_dir

    out = make_output_dir(args.out, name)
    if out is None:
        return 2
    # What the campaign writes there, checked before any task runs (a directory named
    # results.parquet failed the first write, after the tasks, with a raw errno message, exit 1)
    for entry, want_dir in (("results.parquet", False), ("results.parquet.tmp", False), ("index.html", False),
                            ("campaign.json", False), ("tasks", True)):
        path = out / entry
        if path.exists() and path.is_dir() != want_dir:
            print(f"{name}: {path} is {'not a directory' if want_dir else 'a directory'}; the campaign writes its "
                  f"{'task folders' if want_dir else 'file'} there: move it away or choose another --out",
                  file=sys.stderr)
            return 2
    if not args.quiet:
        where = (f"scheduler {args.scheduler}" if args.scheduler else "this process, one task after the other"
                 if args.workers == 0 else "a local Dask cluster")
        print(f"{name}: {campaign.kind}, {len(campaign.tasks)} tasks from {args.spec}, on {where}", file=sys.stderr,
              flush=True)
    try:
        outcome = run_campaign(campaign, out, scheduler=args.scheduler, workers=args.workers, quiet=args.quiet)
    except (OSError, TimeoutError) as exc:  # no scheduler there, a refused connection
        print(f"{name}: cannot reach the scheduler {args.scheduler}: {exc}" if args.scheduler
              else f"{name}: {exc}", file=sys.stderr)
        return 1
    c = outcome.counts
    print(f"{len(outcome.rows)}/{len(campaign.tasks)} tasks have a row: {c.get('ok', 0)} ok, {c.get('error', 0)} "
          f"raised, {c.get('lost', 0)} lost; ran {outcome.ran} now ({outcome.skipped} already done) in "
          f"{outcome.wall_s:.1f} s" + (f" on {outcome.mode}" if outcome.mode else ""))
    print(f"wrote {out / 'results.parquet'}, {out / 'index.html'}, {out / 'tasks'}/")
    return 1 if c.get("lost") else 0
