"""Campaigns on Dask: the same task hundreds of times, on this machine or a cluster (`jetloop campaign`).

spec.py (the TOML spec, its tasks and their content addresses) -> engine.py (serial, a local
Dask cluster or an existing scheduler; results.parquet and resume) -> tasks.py (what one task
does, on a worker) -> report.py (DIR/index.html). Example specs: ground/campaign/examples/.
"""

from .engine import Outcome, read_table, run_campaign
from .spec import Campaign, CampaignSpecError, Task, load_spec, parse_spec

__all__ = ["Campaign", "CampaignSpecError", "Outcome", "Task", "load_spec", "parse_spec", "read_table", "run_campaign"]
