"""Streaming accumulators for the accuracy evaluation: bounded memory over any number of frames.

Quantiles (95th percentile of the elevation error, median slope error) come from fixed-width
histograms (1 mm and 0.01° bins), so a long log costs no more memory than a short one.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

BANDS: dict[str, tuple[float, float]] = {"0-10": (0.0, 10.0), "10-20": (10.0, 20.0), "0-20": (0.0, 20.0),
                                         "20-35": (20.0, 35.0), "all": (0.0, math.inf)}
"""Range bands (horizontal distance from the vehicle origin, m): ``lo <= r < hi``. ``0-20`` pools
the first two: "within 20 m"."""

METRICS = (
    "elevation_rmse_m", "elevation_mae_m", "elevation_bias_m", "elevation_p95_m", "slope_error_median_deg",
    "coverage", "terrain_precision", "terrain_recall", "terrain_f1", "obstacle_recall", "false_obstacles_per_frame",
)


PROFILE_STEP_M = 2.0
PROFILE_BINS = 20
"""Range bins of the elevation RMSE profile (for the plot): ``k·2 m <= r < (k+1)·2 m``, the last open."""


def band_masks(range_m: np.ndarray) -> dict[str, np.ndarray]:
    """One boolean mask per band for an array of ranges (m)."""
    return {name: (range_m >= lo) & (range_m < hi) for name, (lo, hi) in BANDS.items()}


def ratio(num: float, den: float) -> float | None:
    """``num / den`` as a float, None when ``den`` is 0 (a metric with nothing to measure)."""
    return float(num) / den if den > 0 else None


class Histogram:
    """Counts of non-negative values in bins of ``step`` up to ``limit`` (the rest in the last bin)."""

    def __init__(self, step: float, limit: float):
        self.step = step
        self.counts = np.zeros(int(math.ceil(limit / step)) + 1, np.int64)

    def add(self, values: np.ndarray) -> None:
        bins = np.minimum((np.asarray(values, float) / self.step).astype(np.int64), len(self.counts) - 1)
        self.counts += np.bincount(bins, minlength=len(self.counts))

    def quantile(self, q: float) -> float | None:
        """The ``q`` quantile (bin centre, so within ``step / 2``), None when empty."""
        total = self.counts.sum()
        if total == 0:
            return None
        k = int(np.searchsorted(np.cumsum(self.counts), q * total))
        return (k + 0.5) * self.step


@dataclass
class ErrorStats:
    """Signed errors (m): count, sums, and a histogram of |error| for the 95th percentile."""

    n: int = 0
    total: float = 0.0
    total_sq: float = 0.0
    total_abs: float = 0.0
    hist: Histogram = field(default_factory=lambda: Histogram(0.001, 10.0))

    def add(self, errors: np.ndarray) -> None:
        self.n += errors.size
        self.total += float(errors.sum())
        self.total_sq += float((errors * errors).sum())
        self.total_abs += float(np.abs(errors).sum())
        self.hist.add(np.abs(errors))

    def summary(self) -> dict[str, float | None]:
        rmse = math.sqrt(self.total_sq / self.n) if self.n else None
        return {"elevation_rmse_m": rmse, "elevation_mae_m": ratio(self.total_abs, self.n),
                "elevation_bias_m": ratio(self.total, self.n), "elevation_p95_m": self.hist.quantile(0.95)}


@dataclass
class BandScores:
    """Everything one method accumulates in one range band."""

    elevation: ErrorStats = field(default_factory=ErrorStats)
    slope_deg: Histogram = field(default_factory=lambda: Histogram(0.01, 90.0))
    observed_cells: int = 0
    covered_cells: int = 0
    tp: int = 0
    fp: int = 0
    fn: int = 0
    obstacles_eligible: int = 0
    obstacles_matched: int = 0
    false_obstacles: int = 0

    def summary(self, frames: int, *, slope: bool, labels: bool, obstacles: bool) -> dict[str, float | None]:
        precision, recall = ratio(self.tp, self.tp + self.fp), ratio(self.tp, self.tp + self.fn)
        f1 = ratio(2 * self.tp, 2 * self.tp + self.fp + self.fn)
        out = {
            **self.elevation.summary(),
            "slope_error_median_deg": self.slope_deg.quantile(0.5) if slope else None,
            "coverage": ratio(self.covered_cells, self.observed_cells),
            "terrain_precision": precision if labels else None,
            "terrain_recall": recall if labels else None,
            "terrain_f1": f1 if labels else None,
            "obstacle_recall": ratio(self.obstacles_matched, self.obstacles_eligible) if obstacles else None,
            "false_obstacles_per_frame": ratio(self.false_obstacles, frames) if obstacles else None,
        }
        return {k: out[k] for k in METRICS}


class MethodScores:
    """Per-band accumulators of one method, fed one frame at a time."""

    def __init__(self) -> None:
        self.bands = {name: BandScores() for name in BANDS}
        self.has_slope = self.has_labels = self.has_obstacles = False
        self.common = {name: ErrorStats() for name in BANDS}
        self.profile_n = np.zeros(PROFILE_BINS, np.int64)
        self.profile_sq = np.zeros(PROFILE_BINS)

    def add_cells(self, elevation_m, slope_rad, truth_height_m, truth_slope_rad, observed, range_m) -> None:
        """Grid outputs of one frame, all (m0, m1); ``elevation_m`` NaN where the method says nothing,
        ``slope_rad`` None for a method without slope."""
        covered = observed & np.isfinite(elevation_m)
        error = elevation_m - truth_height_m
        k = np.minimum((range_m[covered] / PROFILE_STEP_M).astype(np.int64), PROFILE_BINS - 1)
        self.profile_n += np.bincount(k, minlength=PROFILE_BINS)
        self.profile_sq += np.bincount(k, weights=error[covered] ** 2, minlength=PROFILE_BINS)
        if slope_rad is not None:
            self.has_slope = True
            slope_error = np.degrees(np.abs(slope_rad - truth_slope_rad))
        for name, in_band in band_masks(range_m).items():
            band, cells = self.bands[name], covered & in_band
            band.observed_cells += int((observed & in_band).sum())
            band.covered_cells += int(cells.sum())
            band.elevation.add(error[cells])
            if slope_rad is not None:
                band.slope_deg.add(slope_error[cells & np.isfinite(slope_error)])

    def add_common(self, elevation_m, truth_height_m, common, range_m) -> None:
        """Elevation errors over ``common`` (m0, m1) bool: the cells every compared method covers."""
        error = elevation_m - truth_height_m
        for name, in_band in band_masks(range_m).items():
            self.common[name].add(error[common & in_band])

    def common_summary(self) -> dict[str, dict[str, float | None]]:
        """Elevation metrics over the common cells, per band (plus their ``cells`` count)."""
        return {name: {**stats.summary(), "cells": stats.n} for name, stats in self.common.items()}

    def add_points(self, predicted_terrain: np.ndarray, truth_terrain: np.ndarray, range_m: np.ndarray) -> None:
        """Scored points of one frame (bool each, (N,)): predicted TERRAIN, truth terrain."""
        self.has_labels = True
        for name, in_band in band_masks(range_m).items():
            band = self.bands[name]
            p, t = predicted_terrain[in_band], truth_terrain[in_band]
            band.tp += int((p & t).sum())
            band.fp += int((p & ~t).sum())
            band.fn += int((~p & t).sum())

    def add_obstacles(self, eligible_range_m, matched: np.ndarray, false_range_m) -> None:
        """Truth obstacles eligible this frame (their ranges, whether matched) and the ranges of
        the false detections."""
        self.has_obstacles = True
        eligible_range_m, false_range_m = np.asarray(eligible_range_m, float), np.asarray(false_range_m, float)
        for name, in_band in band_masks(eligible_range_m).items():
            self.bands[name].obstacles_eligible += int(in_band.sum())
            self.bands[name].obstacles_matched += int((in_band & matched).sum())
        for name, in_band in band_masks(false_range_m).items():
            self.bands[name].false_obstacles += int(in_band.sum())

    def rmse_profile(self) -> list[float | None]:
        """Elevation RMSE (m) per range bin of :data:`PROFILE_STEP_M`, None for empty bins."""
        return [math.sqrt(sq / n) if n else None for n, sq in zip(self.profile_n.tolist(), self.profile_sq)]

    def summary(self, frames: int) -> dict[str, dict[str, float | None]]:
        flags = {"slope": self.has_slope, "labels": self.has_labels, "obstacles": self.has_obstacles}
        return {name: band.summary(frames, **flags) for name, band in self.bands.items()}
