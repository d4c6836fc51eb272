"""Pairing left and right image messages by header stamp, with bounded buffers."""

from __future__ import annotations

import logging
import statistics
from collections import deque
from typing import Any

logger = logging.getLogger(__name__)

PERIOD_GAPS = 5
"""Stamp gaps per camera whose median is taken for its frame period (a dropped image doubles one)."""


class StereoPairer:
    """Match left/right messages whose stamps differ by at most ``tolerance_ns``.

    Messages arrive in log order and wait in one buffer per side (``max_buffer`` each, so memory
    stays bounded however long the log; the oldest unmatched message is dropped when full: 32
    holds a second of a 30 Hz camera whose messages are logged late).
    A new message pairs with the closest-stamped waiting message of the other side; messages of
    either side older than the matched ones can no longer pair and are dropped.

    Once both cameras' frame periods are known (the median of each one's last
    :data:`PERIOD_GAPS` stamp gaps), a pair's stamps must also differ by less than half the
    shorter period: only then is each message the other's nearest, whatever comes later. With
    a tolerance of a period or more (100 Hz cameras at the default 10 ms), one dropped image
    would otherwise pair every later image with its neighbour's partner, one frame apart.
    """

    def __init__(self, tolerance_ns: int, max_buffer: int = 32, same=None):
        self.tolerance_ns, self.max_buffer = int(tolerance_ns), max_buffer
        self._same = same
        """``same(a, b)``: whether two messages of one side with one stamp are one message twice
        (skipped, :attr:`repeated`); None: never (both kept)."""
        self._waiting: tuple[deque, deque] = (deque(maxlen=max_buffer), deque(maxlen=max_buffer))
        self._gaps: tuple[deque, deque] = (deque(maxlen=PERIOD_GAPS), deque(maxlen=PERIOD_GAPS))
        self._last: list[int | None] = [None, None]  # the latest stamp of each side
        self._previous: list[tuple | None] = [None, None]  # each side's message before: (stamp, item)
        self.pushed = 0
        self.dropped = 0
        self.overflowed = 0
        """Of ``dropped``, the messages pushed out of a full buffer (one side logged far behind the other)."""
        self.repeated = 0
        """Messages skipped as the message before on their side again (its stamp and, by ``same``, content)."""
        self._missed_by: deque = deque(maxlen=64)  # ns from recent unpaired messages to the nearest waiting partner

    def push(self, side: int, stamp_ns: int, item: Any) -> tuple[int, Any, Any] | None:
        """Add a message of ``side`` (0 left, 1 right); return ``(left_stamp_ns, left, right)``
        when it completes a pair, else None. A message that is the one before it on its side
        again (its stamp, and its content by ``same``: a log recorded twice over, a driver
        republishing) is skipped and counted in ``repeated``, so that no frame is made twice; one
        with the same stamp but other content (a clock coarser than the frame rate) is kept."""
        self.pushed += 1
        previous, self._previous[side] = self._previous[side], (stamp_ns, item)
        if self._same is not None and previous is not None and previous[0] == stamp_ns and self._same(previous[1], item):
            self.repeated += 1
            return None
        last = self._last[side]
        if last is None or stamp_ns > last:
            if last is not None:
                self._gaps[side].append(stamp_ns - last)
            self._last[side] = stamp_ns
        other = self._waiting[1 - side]
        best = min(range(len(other)), key=lambda i: abs(other[i][0] - stamp_ns), default=None)
        if best is None or not self._close(abs(other[best][0] - stamp_ns)):
            if best is not None:
                self._missed_by.append(abs(other[best][0] - stamp_ns))
            own = self._waiting[side]
            if len(own) == own.maxlen:
                self.dropped += 1
                self.overflowed += 1
                logger.debug("pairing buffer full: dropping an unpaired message stamped %d", own[0][0])
            own.append((stamp_ns, item))
            return None
        match_stamp, match = other[best]
        self.dropped += best + len(self._waiting[side])
        for _ in range(best + 1):
            other.popleft()
        self._waiting[side].clear()
        return (stamp_ns, item, match) if side == 0 else (match_stamp, match, item)

    @property
    def offset_ns(self) -> int | None:
        """How far apart the two cameras' stamps lie where they found no partner in time (ns), or
        None: the lower quartile of the distances from recent unpaired messages to the nearest
        waiting message of the other side, which is their partner (δ) for one side and the
        partner's predecessor (period − δ) for the other."""
        return sorted(self._missed_by)[len(self._missed_by) // 4] if self._missed_by else None

    @property
    def half_period_ns(self) -> float | None:
        """Half the shorter frame period of the two cameras, once both are known, else None."""
        return min(statistics.median_low(gaps) for gaps in self._gaps) / 2 if all(self._gaps) else None

    def _close(self, difference_ns: int) -> bool:
        half = self.half_period_ns
        return difference_ns <= self.tolerance_ns and (half is None or difference_ns < half)

    def finish(self) -> None:
        """The log has ended: the messages still waiting have no partner (counted in ``dropped``)."""
        self.dropped += sum(len(waiting) for waiting in self._waiting)
        for waiting in self._waiting:
            waiting.clear()
