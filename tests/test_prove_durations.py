"""The benchmark family's flight durations live in one place (ground.prove.DURATIONS_S,
DURATION_P), read by family_case and by bench/bench_campaign.py; the extraction changed no case."""

from __future__ import annotations

import hashlib
import importlib.util
from pathlib import Path

import pytest

from ground import prove

# sha256 of repr([family_case(split, i) for i in range(51)]), computed before the constants were
# extracted from family_case (commit ec60043): other work depends on these exact cases
BEFORE = {"eval": "01311689023b55f405d137a6b8482bbdfaf71f5ef89085573aeae4c28a2f8b7f",
          "dev": "37cdbb9db31aa144a269bb654bf4b1c7ba200c39cd20a4347aff166847646b29"}


def _as_before(case):
    """The case as drawn before 2026-11-25, when a thruster fault was always on the third jet:
    since then the faulty jet comes from the case's seed, and nothing else changed."""
    import dataclasses

    c, flight, m = case
    if c.thrust_fraction is None:
        return case
    f = min(c.thrust_fraction)
    return dataclasses.replace(c, thrust_fraction=(1.0, 1.0, f, 1.0),
                               check={"thruster_fault.unit[2].thrust_fraction": f}), flight, m


@pytest.mark.parametrize("split", ["eval", "dev"])
def test_family_cases_0_to_50_are_the_ones_drawn_before_the_extraction(split):
    cases = [prove.family_case(split, i) for i in range(51)]
    assert hashlib.sha256(repr([_as_before(c) for c in cases]).encode()).hexdigest() == BEFORE[split]
    more = [prove.family_case(split, i)[0] for i in range(300)]
    faulty = {c.thrust_fraction.index(min(c.thrust_fraction)) for c in more if c.thrust_fraction}
    assert faulty == {0, 1, 2, 3}  # the faulty jet varies
    assert {c[1].duration_s for c in cases} <= set(prove.DURATIONS_S)


def test_the_campaign_bench_uses_proves_duration_distribution():
    """Before, the bench held its own copy of the distribution (FAMILY_DURATIONS)."""
    path = Path(__file__).resolve().parents[1] / "bench" / "bench_campaign.py"
    spec = importlib.util.spec_from_file_location("bench_campaign_under_test", path)
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    assert bench.DURATIONS_S is prove.DURATIONS_S and bench.DURATION_P is prove.DURATION_P
    assert bench.FAMILY_DURATIONS == tuple(zip(prove.DURATIONS_S, prove.DURATION_P))
    assert sum(prove.DURATION_P) == pytest.approx(1.0) and len(prove.DURATION_P) == len(prove.DURATIONS_S)
