"""Guessing which topics of a log hold the left/right images and their calibration.

Two image topics of the same type form a stereo pair when their names differ in exactly one
token (runs of letters or of digits) and that token is a known side pair: ``left/right``,
``l/r``, ``0/1`` (``cam0/cam1``), ``1/2`` (``infra1/infra2``), ``2/3`` (KITTI ``image_2/image_3``).
Among several pairs, rectified (``rect`` in the name) beats raw, uncompressed beats compressed,
and ``left/right`` beats the numbered forms. A calibration topic belongs to the image topic with
which it shares the longest leading namespace (``/stereo/left/camera_info`` ↔
``/stereo/left/image_rect_color/compressed``); where two share as much, to the one whose side
token it names (``/cam/left_info`` ↔ ``/cam/left_image``).
"""

from __future__ import annotations

import logging
import re

from ..errors import InputError
from .messages import COMPRESSED_IMAGE_TYPES, IMAGE_TYPES, VIDEO_TYPES

logger = logging.getLogger(__name__)

SIDE_PAIRS = (("left", "right"), ("l", "r"), ("0", "1"), ("00", "01"), ("1", "2"), ("2", "3"), ("02", "03"))
_TOKEN = re.compile(r"[A-Za-z]+|\d+|[^A-Za-z\d]+")


def _tokens(topic: str) -> list[str]:
    return _TOKEN.findall(topic)


def rectified_name(topic: str) -> bool:
    """Whether the topic's name says its images are rectified: a word ``rect`` or ``rectified``
    (``image_rect``, ``/left/rectified``), not those letters inside another word (``/directional``)."""
    return any(token.lower() in ("rect", "rectified") for token in _tokens(topic))


def side_tokens(left: str, right: str) -> tuple[str, str] | None:
    """The (left, right) side token pair that turns topic ``left`` into ``right``, if any."""
    a, b = _tokens(left), _tokens(right)
    if len(a) != len(b):
        return None
    diffs = [(x.lower(), y.lower()) for x, y in zip(a, b, strict=True) if x != y]
    return diffs[0] if len(diffs) == 1 and diffs[0] in SIDE_PAIRS else None


def _preference(left: str, right: str, types: dict[str, str]) -> tuple:
    return (not rectified_name(left), types[left] in COMPRESSED_IMAGE_TYPES,
            SIDE_PAIRS.index(side_tokens(left, right)), left)


def _partner(topic: str, candidates: list[str], as_left: bool) -> str | None:
    found = [c for c in candidates if (side_tokens(topic, c) if as_left else side_tokens(c, topic))]
    return found[0] if found else None


def stereo_topics(
    types: dict[str, str], left_topic: str | None, right_topic: str | None, where: str
) -> tuple[str, str]:
    """Choose the left and right image topics; ``types`` maps every topic to its message type.

    Raises :class:`InputError` naming ``where`` when no pair is found or a given topic is not an
    image topic of the log.
    """
    images = sorted(t for t, kind in types.items() if kind in IMAGE_TYPES)
    listing = ", ".join(images) or "none"
    videos = sorted(t for t, kind in types.items() if kind in VIDEO_TYPES)
    video_note = (f"; video topics ({', '.join(videos)}) are not read: decode them to image messages first"
                  if videos else "")
    for name, topic in (("left", left_topic), ("right", right_topic)):
        if topic is not None and topic not in images:
            raise InputError(f"{where}: {name} topic {topic!r} is not an image topic of this log "
                             f"(image topics: {listing}){video_note}")
    if left_topic and right_topic:
        return left_topic, right_topic
    if left_topic or right_topic:
        same_type = [t for t in images if types[t] == types[left_topic or right_topic]]
        other = _partner(left_topic, same_type, True) if left_topic else _partner(right_topic, same_type, False)
        if other is None:
            given = left_topic or right_topic
            raise InputError(f"{where}: no partner image topic found for {given!r}; give both --left-topic and --right-topic")
        return (left_topic, other) if left_topic else (other, right_topic)
    cameras = [t for t in images if not depth_transport(t)]
    pairs = [(a, b) for a in cameras for b in cameras if types[a] == types[b] and side_tokens(a, b)]
    if not pairs:
        everything = ", ".join(f"{t} [{k}]" for t, k in sorted(types.items())) or "none"
        hint = "; give --left-topic and --right-topic" if len(images) >= 2 else ""  # none to choose from else
        raise InputError(
            f"{where}: no stereo image topics found (image topics: {listing}; all topics: {everything}){hint}{video_note}"
        )
    best = min(pairs, key=lambda pair: _preference(*pair, types))
    rank, namespace = _preference(*best, types)[:3], best[0].rsplit("/", 1)[0]
    alike = [pair for pair in pairs if _preference(*pair, types)[:3] == rank and pair[0].rsplit("/", 1)[0] != namespace]
    if alike:  # two rigs (front and rear) rank alike, not two renderings of one (image_rect and image_rect_color)
        logger.warning("%s: several stereo pairs of image topics: %s + %s is used; also %s (choose with --left-topic "
                       "and --right-topic)", where, *best, "; ".join(f"{a} + {b}" for a, b in sorted(alike)))
    return best


def depth_transport(topic: str) -> bool:
    """Whether ``topic`` is image_transport's ``compressedDepth`` of a depth image (its last name
    part), which carries depth maps in CompressedImage messages, not camera images."""
    return topic.rstrip("/").rsplit("/", 1)[-1] == "compressedDepth"


def _shared_namespace(a: str, b: str) -> int:
    count = 0
    for x, y in zip(a.strip("/").split("/")[:-1], b.strip("/").split("/"), strict=False):
        if x != y:
            break
        count += 1
    return count


def calibration_topic(
    image_topic: str, calibration_topics: list[str], exclude: str | None = None, side: tuple[str, str] | None = None
) -> str | None:
    """The calibration topic sharing the longest namespace with ``image_topic`` (at least one level);
    among equals, the one naming ``side[0]`` (the image topic's side token, :func:`side_tokens`)
    rather than ``side[1]`` (the other camera's). Topics at the top level (``/left_image``,
    ``/left_calibration``) share no namespace: there the one naming the side is taken."""

    def names_side(topic: str) -> int:
        tokens = {t.lower() for t in _tokens(topic)}
        return (side[0] in tokens) - (side[1] in tokens) if side else 0

    def top_level(topic: str) -> bool:
        return "/" not in topic.strip("/")

    scored = [(_shared_namespace(c, image_topic), names_side(c), c) for c in calibration_topics if c != exclude]
    best = max(scored, default=(0, 0, None))
    if best[0] == 0 and top_level(image_topic):
        best = max(((n, c) for _, n, c in scored if top_level(c)), default=(0, None))
    return best[-1] if best[0] > 0 else None
