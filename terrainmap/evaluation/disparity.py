"""Stereo disparity against ground truth: KITTI stereo and Middlebury folders, simulated logs.

    from terrainmap.config import Config
    from terrainmap.evaluation.disparity import evaluate_disparity

    report = evaluate_disparity("kitti2015/training", Config())
    report["bands"]["all"]["median_abs_error_px"]

Runs terrainmap's stereo front end (:func:`terrainmap.pipeline.match_frame`: SGBM with its
filters, the sky dropped, as ``process`` runs it) on each pair of a folder whose layout ships
ground-truth disparity, and compares the disparities pixel by pixel:

- KITTI stereo 2015 / 2012: ``disp_occ_0/`` (2012: ``disp_occ/``), else ``disp_noc_0/``
  (``disp_noc/``), beside the left image folder: a 16-bit PNG of the left image's name,
  disparity = value / 256, 0 = unknown. Only the ``_10`` pairs have one.
- Middlebury: ``disp0GT.pfm`` (MiddEval3), else ``disp0.pfm`` (2014 scenes), in the scene
  folder; ``inf`` = unknown.
- A log written by ``terrainmap simulate`` (MCAP or folder): ``f·B / depth − doffs`` from its
  per-pixel depth truth; the sky has none.

KITTI and Middlebury pairs without a ground-truth file are skipped (``pairs_without_truth``); a
simulated log's truth must hold every stereo pair (one missing is an error naming its stamp, as
for ``eval accuracy``: the log is damaged); pairs the front end
cannot match are counted by reason (``failed_frames``); pairs whose images cannot be decoded are
skipped as ``process`` skips them, and listed (``skipped``). Metrics over the pixels with a true
disparity, per band of true camera depth ``Z = f·B / (d + doffs)`` (``0-10``, ``10-20``, ``0-20``,
``20-35``, ``all``, metres; :data:`.scores.BANDS`) and summed over the pairs:

- ``truth_pixels``; ``coverage``: the share of them where terrainmap gives a disparity;
- over those: ``median_abs_error_px`` and ``mean_abs_error_px`` (the end-point error) of
  ``|Δd|``, ``bias_px`` (the median of ``Δd = estimate − truth``: negative reads the scene
  farther than it is), ``over_1px`` and ``over_3px`` (shares of ``|Δd|`` above 1 and 3 px) and
  ``d1`` (KITTI's D1: ``|Δd| > 3`` px and ``> 5 %`` of the truth).

Medians come from 0.01 px histograms (within 0.005 px), so memory stays bounded for any number
of pairs.
"""

from __future__ import annotations

import logging
import os
from collections import Counter
from collections.abc import Callable
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..config import Config, check_config
from ..errors import FrameError, InputError
from ..pipeline import PipelineState, match_frame
from ..sim.truth import NoTruthError, open_truth, truth_at
from ..sources import open_source
from ..sources.images import read_image
from ..types import StereoFrame
from .scores import BANDS, Histogram, ratio

logger = logging.getLogger(__name__)

_KITTI_TRUTH = {"image_2": ("disp_occ_0", "disp_noc_0"), "colored_0": ("disp_occ", "disp_noc"),
                "image_0": ("disp_occ", "disp_noc")}
"""Left image folder → its ground-truth folders, preferred first (KITTI 2015, then 2012)."""
_MIDDLEBURY_TRUTH = ("disp0GT.pfm", "disp0.pfm")
_SIGNED_OFFSET_PX = 32.0
"""Signed errors are histogrammed shifted by this (and clipped to ±it) for their median."""


def truth_file(left_image: Path) -> Path | None:
    """The ground-truth disparity file of a left image in a KITTI or Middlebury layout, or None."""
    left_image = Path(left_image)
    folders = _KITTI_TRUTH.get(left_image.parent.name, ())
    candidates = [left_image.parent.parent / f / left_image.name for f in folders]
    if left_image.name == "im0.png":
        candidates += [left_image.parent / name for name in _MIDDLEBURY_TRUTH]
    return next((path for path in candidates if path.is_file()), None)


def read_truth(path: Path, shape: tuple[int, int]) -> np.ndarray:
    """A ground-truth disparity map as H×W float32 pixels, NaN where unknown; :class:`InputError`
    naming the file when it cannot be read or does not have the left image's ``shape`` (H, W)."""
    path = Path(path)
    if path.suffix.lower() == ".pfm":
        disparity = _read_pfm(path)
    else:
        raw = read_image(path)  # a damaged file is named, libpng says nothing of its own
        if raw.dtype != np.uint16 or raw.ndim != 2:
            raise InputError(f"{path}: not a 16-bit single-channel PNG (KITTI disparity × 256)")
        disparity = raw.astype(np.float32) / 256
    if disparity.shape != tuple(shape):
        raise InputError(f"{path}: ground truth is {disparity.shape[1]}×{disparity.shape[0]}, "
                         f"the left image {shape[1]}×{shape[0]}")
    return _unknown_as_nan(disparity)


def _unknown_as_nan(disparity: np.ndarray) -> np.ndarray:
    """``disparity`` with every value that is not finite and positive (KITTI's 0, Middlebury's
    inf, the sky's f·B / inf) set to NaN, in place."""
    disparity[~(np.isfinite(disparity) & (disparity > 0))] = np.nan
    return disparity


def _read_pfm(path: Path) -> np.ndarray:
    """A one-channel PFM (``Pf``) as H×W float32, top row first."""
    try:
        with open(path, "rb") as f:
            kind = f.readline().strip()
            width, height = (int(v) for v in f.readline().split())
            scale = float(f.readline())
            held = (os.fstat(f.fileno()).st_size - f.tell()) // 4
            if kind != b"Pf" or width <= 0 or height <= 0 or width * height > held:  # before allocating what the header says
                raise InputError(f"{path}: not a one-channel PFM image of the size its header gives "
                                 f"({width}×{height}, the file holds {held} values)")
            data = np.fromfile(f, "<f4" if scale < 0 else ">f4", width * height)
    except (OSError, ValueError) as exc:
        raise InputError(f"{path}: cannot read as PFM ({exc})") from None
    if data.size != width * height:
        raise InputError(f"{path}: not a one-channel PFM image of the size its header gives")
    return np.flipud(data.reshape(height, width)).astype(np.float32)  # PFM stores the bottom row first


@dataclass
class _BandStats:
    """Counts, sums and |Δd| / Δd histograms of one depth band, over every pair so far."""

    truth: int = 0
    matched: int = 0
    total_abs: float = 0.0
    over_1: int = 0
    over_3: int = 0
    d1: int = 0
    abs_hist: Histogram = field(default_factory=lambda: Histogram(0.01, 2 * _SIGNED_OFFSET_PX))
    signed_hist: Histogram = field(default_factory=lambda: Histogram(0.01, 2 * _SIGNED_OFFSET_PX))

    def add(self, estimate: np.ndarray, truth: np.ndarray) -> None:
        """``estimate`` (NaN: none) and ``truth`` disparities (px) of this band's true pixels."""
        self.truth += truth.size
        found = np.isfinite(estimate)
        error = estimate[found] - truth[found]
        size = np.abs(error)
        self.matched += error.size
        self.total_abs += float(size.sum())
        self.over_1 += int(np.count_nonzero(size > 1))
        self.over_3 += int(np.count_nonzero(size > 3))
        self.d1 += int(np.count_nonzero((size > 3) & (size > 0.05 * truth[found])))
        self.abs_hist.add(size)
        self.signed_hist.add(np.clip(error + _SIGNED_OFFSET_PX, 0, 2 * _SIGNED_OFFSET_PX))

    def summary(self) -> dict[str, float | int | None]:
        median_signed = self.signed_hist.quantile(0.5)
        return {
            "truth_pixels": self.truth,
            "coverage": ratio(self.matched, self.truth),
            "median_abs_error_px": self.abs_hist.quantile(0.5),
            "mean_abs_error_px": ratio(self.total_abs, self.matched),
            "bias_px": None if median_signed is None else median_signed - _SIGNED_OFFSET_PX,
            "over_1px": ratio(self.over_1, self.matched),
            "over_3px": ratio(self.over_3, self.matched),
            "d1": ratio(self.d1, self.matched),
        }


def score_disparity(
    stats: dict[str, _BandStats], estimate: np.ndarray, truth: np.ndarray, focal_baseline: float, doffs: float
) -> None:
    """Add one pair to ``stats`` (band → accumulator): ``estimate`` and ``truth`` are H×W
    disparities in pixels (NaN where none), ``focal_baseline`` f·B in px·m, ``doffs`` in px."""
    known = np.isfinite(truth)
    estimate, truth = estimate[known], truth[known]
    depth = focal_baseline / (truth + doffs)
    for name, (lo, hi) in BANDS.items():
        band = (depth >= lo) & (depth < hi)
        stats[name].add(estimate[band], truth[band])


def evaluate_disparity(
    path: str | Path, config: Config, *, max_frames: int | None = None, calibration: str | Path | None = None
) -> dict:
    """Score terrainmap's disparities against the ground truth of ``path`` (module docstring):
    a KITTI stereo or Middlebury folder, or a log written by ``terrainmap simulate``.

    Returns ``{"path", "pairs", "pairs_without_truth", "failed_frames", "skipped", "bands": {band:
    {metric: value or None}}}``. Raises :class:`InputError` when the path holds no ground-truth disparity
    (the message says what is looked for) or a file cannot be read, and :class:`ConfigError` for
    a bad config.
    """
    check_config("eval stereo", config)
    stats = {name: _BandStats() for name in BANDS}
    failed: Counter = Counter()
    scored = without_truth = 0
    with ExitStack() as stack:
        source = stack.enter_context(open_source(path, calibration=calibration))
        truth_for = _truth_reader(Path(path), source, stack)
        state = PipelineState(config)
        for frame in source.frames(max_frames=max_frames):
            truth = truth_for(frame)
            if truth is None:
                without_truth += 1
                continue
            if not frame.calibration.rectified:
                raise InputError(f"{frame.source}: the pair is not rectified; ground-truth disparity "
                                 "refers to rectified images")
            try:
                matched = match_frame(frame, config, state)
            except FrameError as exc:
                failed[exc.reason] += 1
                logger.info("pair %d failed: %s", frame.index, exc)
                continue
            pinhole = matched.stereo.pinhole
            score_disparity(stats, matched.stereo.disparity, truth, pinhole.fx * pinhole.baseline_m, pinhole.doffs)
            scored += 1
        skipped = source.skipped()
    return {"path": str(path), "pairs": scored, "pairs_without_truth": without_truth, "failed_frames": dict(failed),
            "skipped": skipped, "bands": {name: s.summary() for name, s in stats.items()}}


def _truth_reader(path: Path, source, stack: ExitStack) -> Callable[[StereoFrame], np.ndarray | None]:
    """frame → its H×W ground-truth disparity (NaN unknown), or None where it has none: from the
    files beside a KITTI or Middlebury folder's images, else from a simulated log's depth truth."""
    pairs = getattr(source, "pairs", [])
    files = [truth_file(pair.left) for pair in pairs]
    if any(files):
        return lambda frame: None if files[frame.index] is None else read_truth(files[frame.index], frame.left.shape[:2])
    try:
        truth = stack.enter_context(open_truth(path))
    except NoTruthError as exc:  # damage in a simulated log is its own error
        raise InputError(f"{path}: no ground-truth disparity found (KITTI: disp_occ_0/ or disp_noc_0/ beside "
                         "image_2/, named like its images; Middlebury: disp0GT.pfm or disp0.pfm beside im0.png; "
                         f"or a log written by terrainmap simulate: {str(exc).removeprefix(f'{path}: ')})") from None
    frames = truth.frames()

    def simulated(frame: StereoFrame) -> np.ndarray:
        depth = truth_at(frames, frame.stamp_ns, path, frame.left.shape[:2]).depth  # along the optical axis, inf: sky
        calib = frame.calibration
        with np.errstate(divide="ignore"):
            return _unknown_as_nan((calib.fx * calib.baseline_m / depth - calib.doffs).astype(np.float32))

    return simulated


def format_table(report: dict) -> str:
    """The report as a table: one row per band of true depth."""
    columns = (("truth_pixels", "pixels", "{:d}"), ("coverage", "cover", "{:.3f}"),
               ("median_abs_error_px", "med|Δd|", "{:.2f}"), ("mean_abs_error_px", "mean|Δd|", "{:.2f}"),
               ("bias_px", "bias", "{:+.2f}"), ("over_1px", ">1px", "{:.3f}"), ("over_3px", ">3px", "{:.3f}"),
               ("d1", "D1", "{:.3f}"))
    pairs = f"{report['pairs']} pair" + ("" if report["pairs"] == 1 else "s")
    skipped = f", {len(report['skipped'])} damaged and skipped" if report.get("skipped") else ""
    lines = [f"{report['path']}: {pairs} scored, {report['pairs_without_truth']} without ground "
             f"truth, failed {report['failed_frames'] or 0}{skipped}",
             "disparity against the ground truth (px), by true depth (m)",
             f"{'depth':<6}" + "".join(f"{title:>10}" for _, title, _ in columns)]
    for band, scores in report["bands"].items():
        cells = ["—" if scores[key] is None else fmt.format(scores[key]) for key, _, fmt in columns]
        lines.append(f"{band:<6}" + "".join(f"{c:>10}" for c in cells))
    return "\n".join(lines)
