"""Diagnosis of a recording against a vehicle model: where they differ, what physics is missing,
its fitted parameters and the improvement on held-out data (spec/recording.md section 2)."""

from .core import Diagnosis, diagnose

__all__ = ["Diagnosis", "diagnose"]
