"""The :class:`Source` interface every loader implements, and the frame selection they share."""

from __future__ import annotations

import logging
import math
import numbers
import re
from abc import ABC, abstractmethod
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path

from ..errors import ConfigError, InputError, is_whole
from ..types import Extrinsics, StereoFrame

logger = logging.getLogger(__name__)

DEFAULT_PERIOD_NS = 100_000_000
"""Stamp spacing of folders without timestamps: index × 100 ms."""

END_SLACK_S = 1.0
"""How far past ``end_s`` reading goes on for pairs stamped out of order (:meth:`Source.frames`)."""

MAX_DAMAGED_IN_A_ROW = 20
"""Selected stereo pairs skipped as damaged one after the other that end the reading with
:class:`InputError`: images that never decode are not damage but the wrong kind of data."""


@dataclass
class PairRef:
    """A stereo pair found in a source, not loaded yet (so skipped pairs cost no image decoding)."""

    index: int
    stamp_ns: int
    load: Callable[[], StereoFrame | None]
    """The frame; None for a pair the source skipped as damaged (:meth:`Source.skipped`)."""


def extrinsics_entry(extrinsics: Extrinsics | None) -> dict | str:
    """The ``extrinsics`` entry of ``describe()``: their dict, or a note that they will be estimated."""
    return extrinsics.to_dict() if extrinsics is not None else "none (will be estimated from the ground)"


def natural_key(name: str) -> list:
    """Sort key of a file name in natural order: its runs of digits compare as numbers, so that
    ``rec_2.mcap`` comes before ``rec_10.mcap`` (as rosbag2 numbers split files, and as image
    sequences written without leading zeros are numbered)."""
    return [(0, int(part), "") if part.isdigit() else (1, 0, part) for part in re.split(r"(\d+)", name) if part]


def check_selection(start_s: float | None, end_s: float | None, every: int, max_frames: int | None) -> None:
    """Raise :class:`ConfigError` naming the option for a selection that makes no sense."""
    for name, value in (("start", start_s), ("end", end_s)):
        if value is not None and (isinstance(value, bool) or not isinstance(value, numbers.Real)
                                  or not math.isfinite(value)):
            raise ConfigError(f"{name}: must be a finite number of seconds, got {value!r}")
    for name, value in (("every", every), ("max_frames", max_frames)):
        if value is not None and not is_whole(value):
            raise ConfigError(f"{name}: must be a whole number, got {value!r}")
    if every < 1:
        raise ConfigError(f"every: must be >= 1, got {every}")
    if max_frames is not None and max_frames < 0:
        raise ConfigError(f"max_frames: must be >= 0, got {max_frames}")
    if start_s is not None and end_s is not None and end_s < start_s:
        raise ConfigError(f"end_s (--end) {end_s} s is before start_s (--start) {start_s} s")


@dataclass
class Tally:
    """What the last :meth:`Source.frames` read: stereo ``pairs`` (all, as far as it read),
    ``selected`` (in the start/end window, every N-th), and ``span_s``, the last pair's seconds
    after the first. Says why a selection came out empty."""

    pairs: int = 0
    selected: int = 0
    span_s: float = 0.0


class Source(ABC):
    """Stereo pairs from a folder or a log; a context manager (``close()`` is idempotent).

    Subclasses set ``format``, implement :meth:`matches` (path guessing for the registry),
    :meth:`describe` and :meth:`_pairs` (pairs in time order, lazily loadable).
    """

    format: str = "source"

    def __init__(self, path: str | Path):
        self.path = Path(path)
        self._closed = False
        self.tally = Tally()
        self._damaged: list[str] = []  # stereo pairs skipped for an image that cannot be decoded

    @classmethod
    @abstractmethod
    def matches(cls, path: Path) -> bool:
        """True when ``path`` looks like this format (cheap: names and directory listings only)."""

    @abstractmethod
    def describe(self) -> dict:
        """What the source holds and what ``process`` would use (format, counts, topics,
        calibration summary, extrinsics)."""

    @abstractmethod
    def _pairs(self) -> Iterator[PairRef]:
        """Every stereo pair of the source, from the start, in time order."""

    def frames(
        self,
        *,
        start_s: float | None = None,
        end_s: float | None = None,
        every: int = 1,
        max_frames: int | None = None,
    ) -> Iterator[StereoFrame]:
        """Yield the selected stereo pairs as :class:`~terrainmap.types.StereoFrame`.

        Parameters
        ----------
        start_s, end_s : float, optional
            Window in seconds relative to the first stereo pair's stamp (inclusive).
        every : int
            Keep every N-th pair of the window.
        max_frames : int, optional
            Stop after this many frames.

        ``StereoFrame.index`` counts pairs from the start of the source, not from ``start_s``.
        The window is by stamp: a pair stamped out of order is kept where its stamp lies in it, and
        reading stops at the first pair stamped :data:`END_SLACK_S` past ``end_s``. A damaged pair is
        skipped (:meth:`skipped`); :data:`MAX_DAMAGED_IN_A_ROW` of them in a row raise
        :class:`InputError`, as does reading a source that was closed.
        """
        check_selection(start_s, end_s, every, max_frames)
        closed = InputError(f"{self.path}: the source is closed; open it again to read its frames")
        if self._closed:
            raise closed
        first_ns: int | None = None
        in_window = kept = damaged_in_a_row = 0
        tally = self.tally = Tally()
        for ref in self._pairs():
            if self._closed:  # closed while frames were being read (a log's reader may still read on)
                raise closed
            if max_frames is not None and kept >= max_frames:
                return
            first_ns = ref.stamp_ns if first_ns is None else first_ns
            offset_s = (ref.stamp_ns - first_ns) / 1e9
            tally.pairs, tally.span_s = tally.pairs + 1, offset_s
            if start_s is not None and offset_s < start_s:
                continue
            if end_s is not None and offset_s > end_s:
                if offset_s > end_s + END_SLACK_S:
                    return
                continue
            if in_window % every == 0:
                tally.selected += 1
                frame = ref.load()
                damaged_in_a_row = 0 if frame is not None else damaged_in_a_row + 1  # None: skipped as damaged
                if damaged_in_a_row >= MAX_DAMAGED_IN_A_ROW:
                    raise InputError(f"{self.path}: {MAX_DAMAGED_IN_A_ROW} stereo pairs in a row cannot be read, "
                                     f"which is no damage here and there (the last: {self._damaged[-1]})")
                if frame is not None:
                    kept += 1
                    yield frame
            in_window += 1

    def skipped(self) -> list[str]:
        """What reading has skipped so far, one line each (the damaged chunks and messages of an
        MCAP, the stereo pairs whose images cannot be decoded)."""
        return list(self._damaged)

    def _skip_damaged(self, pair: str, exc: Exception, why: str = "damaged") -> None:
        """Record a stereo pair lost (the run goes on), to an image that cannot be decoded or as
        ``why`` says; a :meth:`PairRef.load` then returns None."""
        self._damaged.append(f"{pair} ({exc})")
        logger.warning("%s: %s, skipped", self._damaged[-1], why)

    def close(self) -> None:
        self._closed = True

    def __enter__(self) -> Source:
        return self

    def __exit__(self, *exc) -> None:
        self.close()

    def __repr__(self) -> str:
        return f"{type(self).__name__}({str(self.path)!r})"
