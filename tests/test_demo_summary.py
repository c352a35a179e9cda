"""`jetloop demo`'s summary.json and console table when a figure could not be measured (issue 15
item 11): a run whose onboard loop reported nothing, or with no settled leg, has NaN figures."""

from __future__ import annotations

import json

from hil.demo import ClosedLoopResult, reference_mission, summarise, summary_json, table
from onboard.vehicle import load_vehicle


def _unmeasured_summary() -> dict:
    """The real summarise() of a run that produced no truth samples and no onboard figures."""
    result = ClosedLoopResult(truth=[], commands=[], endpoint={"periods": 0}, onboard={}, recorder={}, wall_s=0.5)
    mission = reference_mission()
    summary = summarise(result, mission, load_vehicle())
    assert summary["depth_rms_m"] != summary["depth_rms_m"]  # NaN: nothing was measured
    return summary


def test_summary_json_is_strict_json_with_null_for_what_was_not_measured():
    """json.dumps wrote NaN, which is not JSON (jq, browsers and strict parsers refuse the file)."""
    text = summary_json(_unmeasured_summary())

    def refuse(name):
        raise AssertionError(f"{name} in summary.json")

    doc = json.loads(text, parse_constant=refuse)
    assert doc["depth_rms_m"] is None and doc["step_p99_ms"] is None and doc["control_steps"] == 0


def test_console_table_says_n_a_not_nan():
    """The table printed 'nan cm'."""
    text = table(_unmeasured_summary())
    assert "nan" not in text.lower() and "inf" not in text.lower()
    assert "depth RMS" in text and "n/a cm" in text
