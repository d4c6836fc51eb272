"""Pairing left and right image messages by header stamp, with bounded buffers."""

from __future__ import annotations

import logging
from collections import deque
from typing import Any

logger = logging.getLogger(__name__)


class StereoPairer:
    """Match left/right messages whose stamps differ by at most ``tolerance_ns``.

    Messages arrive in log order and wait in one buffer per side (``max_buffer`` each, so memory
    stays bounded however long the log; the oldest unmatched message is dropped when full: 32
    holds a second of a 30 Hz camera whose messages are logged late).
    A new message pairs with the closest-stamped waiting message of the other side; messages of
    either side older than the matched ones can no longer pair and are dropped.
    """

    def __init__(self, tolerance_ns: int, max_buffer: int = 32):
        self.tolerance_ns, self.max_buffer = int(tolerance_ns), max_buffer
        self._waiting: tuple[deque, deque] = (deque(maxlen=max_buffer), deque(maxlen=max_buffer))
        self.pushed = 0
        self.dropped = 0
        self.overflowed = 0
        """Of ``dropped``, the messages pushed out of a full buffer (one side logged far behind the other)."""

    def push(self, side: int, stamp_ns: int, item: Any) -> tuple[int, Any, Any] | None:
        """Add a message of ``side`` (0 left, 1 right); return ``(left_stamp_ns, left, right)``
        when it completes a pair, else None."""
        self.pushed += 1
        other = self._waiting[1 - side]
        best = min(range(len(other)), key=lambda i: abs(other[i][0] - stamp_ns), default=None)
        if best is None or abs(other[best][0] - stamp_ns) > self.tolerance_ns:
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

    def finish(self) -> None:
        """The log has ended: the messages still waiting have no partner (counted in ``dropped``)."""
        self.dropped += sum(len(waiting) for waiting in self._waiting)
        for waiting in self._waiting:
            waiting.clear()
