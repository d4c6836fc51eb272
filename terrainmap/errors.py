"""The small exception hierarchy of terrainmap.

The library raises these; the CLI turns them into one-line messages and exit codes.
Inside a run, a per-frame failure is a :class:`FrameError` that the runner counts and
skips, while the other errors end the run (after the outputs are finalised).
"""

from __future__ import annotations

import numbers
import reprlib

_BRIEF = reprlib.Repr()  # (keyword arguments only from Python 3.12)
_BRIEF.maxlevel, _BRIEF.maxlist, _BRIEF.maxtuple, _BRIEF.maxdict, _BRIEF.maxset = 2, 4, 4, 4, 4
_BRIEF.maxstring = _BRIEF.maxother = 60


def is_whole(value) -> bool:
    """Whether ``value`` is a whole number (any integer type, numpy's too), not a bool: what a
    stamp, an index or a count must be."""
    return isinstance(value, numbers.Integral) and not isinstance(value, bool)


STAMP_RANGE = "1970–2262 (0 to 2^63 − 1 ns)"
"""The times an MCAP or ROS stamp (unsigned, signed 64-bit in Rerun) can hold, for messages."""


def is_stamp(value: int) -> bool:
    """Whether a whole number of nanoseconds lies in :data:`STAMP_RANGE`."""
    return 0 <= value <= 2**63 - 1


def counted(count: int, noun: str) -> str:
    """``1 frame``, ``2 frames``: a count with its noun in the right number, for messages."""
    return f"{count} {noun}{'s' * (count != 1)}"


def brief(value) -> str:
    """``repr(value)`` cut short (nesting, items, characters), for a message naming a value read
    from a file: a YAML alias bomb or a huge list stays one short line (``[[...], [...], ...]``)."""
    return _BRIEF.repr(value)


class TerrainmapError(Exception):
    """Base class: every error the library raises on purpose."""


class ConfigError(TerrainmapError, ValueError):
    """A configuration value or option that makes no sense (names the field)."""


class InputError(TerrainmapError):
    """A file, folder, log or topic that cannot be used (names the path or topic)."""


class NoStereoError(InputError):
    """A log without a usable pair of stereo image topics; ``contents`` holds what it does hold
    (format, files, damage, topics with their types and counts) for ``terrainmap info``."""

    def __init__(self, message: str, contents: dict):
        super().__init__(message)
        self.contents = contents


class DamagedImageError(InputError):
    """One image's data cannot be decoded (a compressed image cut short or corrupt). A log skips
    that stereo pair with a warning and goes on (:meth:`~terrainmap.sources.Source.skipped`)."""


class CalibrationError(InputError):
    """Calibration missing or nonsensical (zero baseline, non-positive focal length...)."""


class FrameError(TerrainmapError):
    """One frame could not be processed (no terrain found, too few valid cells...).

    The runner counts these by ``reason`` and goes on with the next frame.
    """

    def __init__(self, reason: str, message: str | None = None):
        super().__init__(message or reason)
        self.reason = reason
