"""The runner: iterate a source, run the pure per-frame core, feed the sinks, keep statistics.

The first half of each frame (reading it, SGM matching, points: :func:`match_frame`) runs ahead
in two worker threads, one frame each, while the main thread finishes the frame before them
(terrain, labels, obstacles: :func:`finish_frame`) and writes it. OpenCV and numpy release the
GIL in their heavy loops, so the three overlap; OpenCV's thread count is divided between the
workers for the run (one thread each on two cores: on the 2-core benchmark machine that gave
13.0–19.8 frames/s, median 16.7, against 13.5–16.7, median 14.1, with one worker and SGBM's two
threads; docs/speed.md). The results are the same as running :func:`process_frame` frame by
frame, byte for byte, as long as the config is not changed while the run is under way (the
workers match up to two frames ahead with it). The runner copies each frame's images as it reads
them, so the frames' iterator may fill the same buffers for every frame.

Frames that yield no terrain (:class:`~terrainmap.errors.FrameError`) are counted by reason and
skipped; any other error ends the run. Either way every sink is closed, so the outputs written
so far are finalised and readable. Memory is bounded whatever the length of the log: the
runner holds at most ``MATCH_WORKERS + 2`` frames (the one being finished, the last written
until the next is done, and those matched ahead) and a fixed-size sample of per-stage times.
"""

from __future__ import annotations

import itertools
import logging
import random
import statistics
import threading
import time
from collections import Counter, deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import ThreadPoolExecutor
from contextlib import contextmanager
from dataclasses import dataclass, field, replace

import cv2
import numpy as np

from .config import Config
from .errors import FrameError, TerrainmapError
from .pipeline import Matched, PipelineState, Prepared, finish_frame, match_frame, prepare_match
from .sinks.base import Sink
from .types import Extrinsics, FrameResult, StereoFrame

log = logging.getLogger(__name__)

_RESERVOIR = 4096  # per-stage time samples kept for the medians
MATCH_WORKERS = 2
"""Threads matching frames ahead of the main thread, a frame each."""


@dataclass
class RunSummary:
    """What a run did: frames done and failed (by reason), wall time, per-stage medians."""

    frames_done: int = 0
    failures: Counter = field(default_factory=Counter)
    first_failures: dict[str, str] = field(default_factory=dict)
    """Reason → what the first frame that failed for it says (``frame 3: ground fit: ...``)."""
    wall_s: float = 0.0
    extrinsics: Extrinsics | None = None
    _times: dict[str, list[float]] = field(default_factory=dict)
    _seen: int = 0
    _rng: random.Random = field(default_factory=lambda: random.Random(0))

    @property
    def frames_failed(self) -> int:
        return sum(self.failures.values())

    @property
    def fps(self) -> float:
        """Frames read per second of wall time, failed frames included (the run's throughput)."""
        return (self.frames_done + self.frames_failed) / self.wall_s if self.wall_s > 0 else 0.0

    def add_timings(self, timings_ms: dict[str, float]) -> None:
        """Reservoir-sample the frame's stage times (bounded memory for any log length)."""
        self._seen += 1
        slot = self._seen - 1 if self._seen <= _RESERVOIR else self._rng.randrange(self._seen)
        if slot >= _RESERVOIR:
            return
        for stage, ms in {**timings_ms, "total": sum(timings_ms.values())}.items():
            values = self._times.setdefault(stage, [])
            if slot < len(values):
                values[slot] = ms
            else:
                values.append(ms)

    def median_ms(self) -> dict[str, float]:
        return {stage: statistics.median(values) for stage, values in self._times.items() if values}


def run(
    frames: Iterable[StereoFrame],
    config: Config,
    sinks: list[Sink],
    *,
    on_frame: Callable[[RunSummary, StereoFrame, FrameResult | None], None] | None = None,
) -> RunSummary:
    """Process every frame of ``frames`` and write each result to every sink, the next frames
    matched ahead in :data:`MATCH_WORKERS` worker threads (module docstring; while the run is under
    way, OpenCV's process-wide thread count is divided between them).

    ``on_frame`` is called after each frame (the result is None for a failed frame) — the CLI
    draws its progress line there. Sinks are closed when the run ends, however it ends. Each
    frame's images are copied as it is read (the iterator may reuse its buffers); anything but a
    :class:`StereoFrame` among the frames (a None too) ends the run with an error.

    The worker threads advance ``frames`` (an iterator tied to one thread, as some middleware's
    are, is not for ``run``) and read up to :data:`MATCH_WORKERS` frames ahead, which an error
    leaves unprocessed; after an error, ``run`` returns once the iterator's pending ``next()``
    has: a live camera's iterator that waits for the next image holds the error until it comes.
    There, :func:`~terrainmap.pipeline.process_frame` in one's own loop is the simpler tool.
    """
    usable = isinstance(sinks, list | tuple) and all(callable(getattr(s, m, None)) for s in sinks for m in ("write", "close"))
    if not usable:
        raise TerrainmapError(f"run: sinks must be a list of sinks (write and close), got {sinks!r}")
    summary = RunSummary()
    start = time.perf_counter()
    ahead = None
    try:
        state = PipelineState(config)  # validates the config: a ConfigError still closes the sinks
        try:
            frames = iter(frames)
        except TypeError:
            raise TerrainmapError(f"run: frames must be an iterable of StereoFrame, got {type(frames).__name__}") from None
        ahead = _matched_ahead(frames, config, state)
        for frame, matched in ahead:
            try:
                if isinstance(matched, FrameError):
                    raise matched
                result = finish_frame(frame, matched, config, state)
            except FrameError as exc:
                summary.failures[exc.reason] += 1
                summary.first_failures.setdefault(exc.reason, f"frame {frame.index}: {exc}")
                log.info("frame %d: %s", frame.index, exc)
                result = None
                for sink in sinks:  # those that show a timeline say so there (Sink.failed)
                    if callable(getattr(sink, "failed", None)):
                        sink.failed(frame, exc)
            else:
                for sink in sinks:
                    sink.write(frame, result)
                summary.frames_done += 1
                summary.extrinsics = result.extrinsics
                summary.add_timings(result.timings_ms)
            summary.wall_s = time.perf_counter() - start
            if on_frame is not None:
                on_frame(summary, frame, result)
    finally:
        summary.wall_s = time.perf_counter() - start
        try:
            if ahead is not None:
                ahead.close()  # ends the worker threads now, not whenever the generator is collected
        finally:
            _close_all(sinks)
    return summary


def _matched_ahead(
    source: Iterator[StereoFrame], config: Config, state: PipelineState
) -> Iterator[tuple[StereoFrame, Matched | FrameError]]:
    """Yield each frame of ``source`` in order with its :func:`match_frame` result (or the
    FrameError it raised), the next frames being read and matched in :data:`MATCH_WORKERS` worker threads
    meanwhile. Other errors re-raise here, in frame order.

    Each worker reads its frame and calls :func:`prepare_match` in turn (ticket order), so the
    state changes happen frame by frame as in :func:`process_frame`; a frame whose camera pose
    must be estimated is matched whole in its turn, so that the frames after it use that pose.
    """
    turn = threading.Condition()
    served = 0  # tickets whose turn has passed

    def step(ticket: int):
        nonlocal served
        with turn:
            turn.wait_for(lambda: served == ticket)
            try:
                frame = next(source, _END)
                if frame is _END:
                    return None
                frame = _own_images(frame)
                try:
                    prepared = prepare_match(frame, config, state)
                except FrameError as exc:  # (none is raised there today: counted as elsewhere)
                    return frame, exc
                if prepared.extrinsics is None:  # the pose is estimated from this frame, in its turn
                    return matched(frame, prepared)
            finally:
                served += 1
                turn.notify_all()
        return matched(frame, prepared)

    def matched(frame: StereoFrame, prepared: Prepared):
        try:
            return frame, match_frame(frame, config, state, prepared)
        except FrameError as exc:
            return frame, exc

    tickets = itertools.count()
    with _OPENCV_THREADS.divided(MATCH_WORKERS), ThreadPoolExecutor(MATCH_WORKERS, "terrainmap-match") as pool:
        pending = deque(pool.submit(step, next(tickets)) for _ in range(MATCH_WORKERS))
        try:
            while (item := pending.popleft().result()) is not None:
                pending.append(pool.submit(step, next(tickets)))
                yield item
        finally:
            pool.shutdown(cancel_futures=True)  # a ticket not started is not waited for


_END = object()  # what the frames' iterator gives when it is done (a None in them is an error)


def _own_images(frame):
    """``frame`` with copies of its images (arrays; anything else is left for the checks to
    refuse): a caller's iterator may fill the same buffers for every frame it yields, as camera
    drivers do, and the runner reads frames ahead while earlier ones are still matched and
    written (about 1 ms a 640×480 frame)."""
    if not isinstance(frame, StereoFrame):
        return frame
    images = {side: image.copy() for side in ("left", "right") if isinstance(image := getattr(frame, side), np.ndarray)}
    return replace(frame, **images)


class _OpenCVThreads:
    """OpenCV's thread count (process-wide) divided among the matching workers while runs are
    under way, and restored when the last of them ends (runs may overlap, in threads): the workers
    match at once, so SGBM's own threads would only take turns with them. On two cores each
    worker matches on one thread."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._runs = 0
        self._before = 0

    @contextmanager
    def divided(self, workers: int):
        with self._lock:
            if self._runs == 0:
                self._before = cv2.getNumThreads()  # the caller's setting, or OpenCV's own count of the CPUs
                cv2.setNumThreads(max(1, self._before // workers))
            self._runs += 1
        try:
            yield
        finally:
            with self._lock:
                self._runs -= 1
                if self._runs == 0:
                    cv2.setNumThreads(self._before)


_OPENCV_THREADS = _OpenCVThreads()


def _close_all(sinks: list[Sink]) -> None:
    """Close every sink even if one of them fails; re-raise the first failure."""
    first: BaseException | None = None
    for sink in sinks:
        try:
            sink.close()
        except BaseException as exc:  # noqa: BLE001 - the others must still be finalised
            first = first or exc
    if first is not None:
        raise first
