"""Shared bits of the benchmarks: the reference robot and per-call timing summaries."""

from __future__ import annotations

from pathlib import Path

import numpy as np

REFERENCE8 = Path(__file__).resolve().parent.parent / "config" / "robots" / "reference8.yaml"


def summary_us(samples_ns: np.ndarray) -> dict[str, float]:
    """Median and p99 of per-call times given in nanoseconds, in microseconds."""
    return {
        "median_us": round(float(np.median(samples_ns)) / 1e3, 2),
        "p99_us": round(float(np.percentile(samples_ns, 99)) / 1e3, 2),
    }
