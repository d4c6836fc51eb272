"""Image decoding shared by every source: files, compressed and raw image messages.

Every function returns H×W (mono) or H×W×3 (RGB order) arrays; 16-bit images stay uint16
until :func:`stereo_pair` scales the left and right image of a pair with one common factor
(a per-image scale would make the two views differ in brightness and hurt matching).
"""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import cv2
import numpy as np

from ..errors import DamagedImageError, InputError, brief
from ..stereo import MAX_PIXELS, MAX_SIDE_PX

# ROS / Foxglove raw encodings (lower case) -> (dtype, channels on the wire, conversion to RGB or None).
# Bayer names give the colours of the first two pixels of the first two rows (rggb: R G / G B);
# uyvy / yuv422 carry [U, Y1, V, Y2] per pixel pair, yuyv / yuv422_yuy2 [Y1, U, Y2, V].
_RAW_ENCODINGS: dict[str, tuple[type, int, int | None]] = {
    "rgb8": (np.uint8, 3, None),
    "bgr8": (np.uint8, 3, cv2.COLOR_BGR2RGB),
    "rgba8": (np.uint8, 4, cv2.COLOR_RGBA2RGB),
    "bgra8": (np.uint8, 4, cv2.COLOR_BGRA2RGB),
    "mono8": (np.uint8, 1, None),
    "8uc1": (np.uint8, 1, None),
    "8uc3": (np.uint8, 3, cv2.COLOR_BGR2RGB),
    "rgb16": (np.uint16, 3, None),
    "bgr16": (np.uint16, 3, cv2.COLOR_BGR2RGB),
    "rgba16": (np.uint16, 4, cv2.COLOR_RGBA2RGB),
    "bgra16": (np.uint16, 4, cv2.COLOR_BGRA2RGB),
    "16uc3": (np.uint16, 3, cv2.COLOR_BGR2RGB),
    "mono16": (np.uint16, 1, None),
    "16uc1": (np.uint16, 1, None),
    "uyvy": (np.uint8, 2, cv2.COLOR_YUV2RGB_UYVY),
    "yuv422": (np.uint8, 2, cv2.COLOR_YUV2RGB_UYVY),
    "yuyv": (np.uint8, 2, cv2.COLOR_YUV2RGB_YUY2),
    "yuv422_yuy2": (np.uint8, 2, cv2.COLOR_YUV2RGB_YUY2),
    **{
        f"bayer_{pattern}{bits}": (dtype, 1, code)
        for pattern, code in (
            ("rggb", cv2.COLOR_BayerRGGB2RGB),
            ("bggr", cv2.COLOR_BayerBGGR2RGB),
            ("gbrg", cv2.COLOR_BayerGBRG2RGB),
            ("grbg", cv2.COLOR_BayerGRBG2RGB),
        )
        for bits, dtype in (("8", np.uint8), ("16", np.uint16))
    },
}


# YUV 4:2:0, semi-planar: a Y plane of ``height`` rows, then ``height / 2`` rows of interleaved
# chroma at half the resolution, U first (nv12) or V first (nv21); both planes have ``step`` bytes a row.
_YUV420_ENCODINGS = {"nv12": cv2.COLOR_YUV2RGB_NV12, "nv21": cv2.COLOR_YUV2RGB_NV21}


def _to_rgb(image: np.ndarray) -> np.ndarray:
    """OpenCV's BGR(A) or gray decoding result → RGB or mono (dtype kept)."""
    if image.ndim == 3 and image.shape[2] == 1:
        return image[:, :, 0]
    if image.ndim == 3 and image.shape[2] == 4:
        return cv2.cvtColor(image, cv2.COLOR_BGRA2RGB)
    if image.ndim == 3:
        return cv2.cvtColor(image, cv2.COLOR_BGR2RGB)
    return image


def _check_dtype(image: np.ndarray, name: str) -> np.ndarray:
    if image.dtype not in (np.uint8, np.uint16):
        raise InputError(f"{name}: unsupported image depth {image.dtype} (need 8 or 16 bit)")
    return image


def read_image(path: str, name: str | None = None) -> np.ndarray:
    """Read an image file (png, jpg, pgm, ppm...) as mono or RGB, uint8 or uint16.

    Raises :class:`InputError` naming the file when it cannot be read, and its
    :class:`DamagedImageError` when its contents cannot be decoded (a folder skips that pair).
    """
    name = name or str(path)
    try:
        data = Path(path).read_bytes()
    except OSError as exc:
        raise InputError(f"{name}: cannot read the image file ({exc.strerror or exc})") from None
    return _decode(data, name, "cannot decode the image file (not an image, damaged or cut short)")


def decode_compressed(data: bytes, name: str) -> np.ndarray:
    """Decode a compressed image (PNG, JPEG...) from bytes; ``name`` (topic) goes in errors."""
    data = bytes(data)
    return _decode(data, name, f"cannot decode the compressed image ({len(data)} bytes)")


def _decode(data: bytes, name: str, failure: str) -> np.ndarray:
    # A PNG or JPEG cut short (or a PNG with bytes changed) is refused before libpng/libjpeg see
    # it: they would print their own lines to stderr (or decode a grey remainder) before OpenCV gives up.
    size = _declared_size(data)
    if size is not None and (max(size) > MAX_SIDE_PX or size[0] * size[1] > MAX_PIXELS):  # not decoded at all
        raise DamagedImageError(f"{name}: its header declares a {size[0]}×{size[1]} image, larger than terrainmap "
                                f"reads ({MAX_SIDE_PX} px a side, {MAX_PIXELS} pixels)")
    buffer = np.frombuffer(data, dtype=np.uint8)  # a view of the bytes, no copy
    try:
        image = cv2.imdecode(buffer, cv2.IMREAD_UNCHANGED) if data and _complete(data) else None
    except cv2.error:  # e.g. a header claiming more pixels than OpenCV decodes (CV_IO_MAX_IMAGE_PIXELS)
        image = None
    if image is None:
        raise DamagedImageError(f"{name}: {failure}")
    return _check_dtype(_to_rgb(image), name)


_PNG = b"\x89PNG\r\n\x1a\n"
_DEFLATE_MAX_RATIO = 1032
"""Deflate's largest expansion: one 258-byte match per bit pair, at best (zlib's technical notes)."""
_JPEG_FRAME_MARKERS = frozenset(range(0xC0, 0xD0)) - {0xC4, 0xC8, 0xCC}
"""JPEG's start-of-frame markers (SOF0–SOF15 but DHT, JPG and DAC), whose header holds the size."""


def _declared_size(data: bytes) -> tuple[int, int] | None:
    """``(width, height)`` that a PNG's or JPEG's header declares (None for other formats, or where
    it cannot be found): checked before decoding, which would allocate the whole image first."""
    if data.startswith(_PNG) and data[12:16] == b"IHDR" and len(data) >= 24:
        return struct.unpack_from(">II", data, 16)
    if not data.startswith(b"\xff\xd8"):
        return None
    pos = 2
    while pos + 9 <= len(data) and data[pos] == 0xFF:
        marker = data[pos + 1]
        if marker == 0xFF:  # a fill byte
            pos += 1
        elif marker in _JPEG_FRAME_MARKERS:
            height, width = struct.unpack_from(">HH", data, pos + 5)  # after length and precision
            return width, height
        elif marker == 0xDA:  # the image data begins: no frame header before it
            return None
        else:  # a segment: its length counts itself
            pos += 2 + struct.unpack_from(">H", data, pos + 2)[0]
    return None


def _complete(data: bytes) -> bool:
    """False for a PNG whose chunks run past its end, whose critical chunks fail their CRC (bytes
    changed), that ends before IEND, or whose image data is too short to inflate to the size its
    header claims, and for a JPEG without an end-of-image marker (searched in the whole file, so
    that data a camera appends after the end never fails a good image)."""
    if data.startswith(_PNG):
        return _png_complete(data)
    if data.startswith(b"\xff\xd8"):
        return b"\xff\xd9" in data
    return True


def _png_complete(data: bytes) -> bool:
    pos, idat, raw = len(_PNG), 0, None
    while pos + 8 <= len(data):
        length, kind = struct.unpack_from(">I4s", data, pos)
        end = pos + 12 + length  # length, type, data, CRC
        if end > len(data):
            return False
        critical = not kind[0] & 0x20  # IHDR, PLTE, IDAT, IEND: libpng fails on their CRC (and prints why)
        if critical and zlib.crc32(memoryview(data)[pos + 4 : end - 4]) != struct.unpack_from(">I", data, end - 4)[0]:
            return False
        if kind == b"IHDR" and length >= 13:
            width, height, depth, colour = struct.unpack_from(">IIBB", data, pos + 8)
            channels = {0: 1, 2: 3, 3: 1, 4: 2, 6: 4}.get(colour, 4)
            raw = height * (1 + (width * channels * depth + 7) // 8)  # a filter byte per row
        elif kind == b"IDAT":
            idat += length
        elif kind == b"IEND":
            return raw is None or raw <= _DEFLATE_MAX_RATIO * idat + 1024
        pos = end
    return False


def decode_raw(
    data: bytes, *, width: int, height: int, step: int, encoding: str, name: str, big_endian: bool = False
) -> np.ndarray:
    """Turn a raw image message's bytes into an array (RGB or mono, uint8 or uint16).

    Supported encodings (case-insensitive): rgb8, bgr8, rgba8, bgra8, mono8/8UC1, 8UC3 (as BGR),
    their 16-bit forms rgb16, bgr16, rgba16, bgra16, 16UC3 (as BGR), mono16/16UC1; Bayer mosaics
    bayer_rggb8, _bggr8, _gbrg8, _grbg8 and their 16-bit forms (demosaiced bilinearly); YUV 4:2:2
    uyvy/yuv422 and yuyv/yuv422_yuy2 (even widths); YUV 4:2:0 nv12 and nv21 (even sizes).

    Raises :class:`InputError` naming ``name`` for an encoding, size or ``step`` it cannot read,
    and its :class:`DamagedImageError` when ``data`` is shorter than the size and ``step`` need.
    """
    if encoding.lower() in _YUV420_ENCODINGS:
        return _decode_yuv420(data, width, height, step, encoding, name)
    spec = _RAW_ENCODINGS.get(encoding.lower())
    if spec is None:
        supported = ", ".join(sorted([*_RAW_ENCODINGS, *_YUV420_ENCODINGS]))
        raise InputError(f"{name}: unsupported image encoding {brief(encoding)} (supported: {supported})")
    dtype, channels, conversion = spec
    if width <= 0 or height <= 0:
        raise InputError(f"{name}: {encoding} image of size {width}×{height} (no pixel)")
    if channels == 2 and width % 2:
        raise InputError(f"{name}: {encoding} image of odd width {width} (YUV 4:2:2 pairs the pixels of each row)")
    itemsize = np.dtype(dtype).itemsize
    row_bytes = width * channels * itemsize
    pixels = _rows(data, height, row_bytes, step or row_bytes, f"{name}: image of {width}×{height} {encoding}")
    wire_dtype = np.dtype(dtype).newbyteorder(">" if big_endian else "<")
    image = pixels.view(wire_dtype).astype(dtype).reshape(height, width, channels)
    if channels == 1:
        image = image[:, :, 0]
    return image if conversion is None else cv2.cvtColor(image, conversion)


def _decode_yuv420(data: bytes, width: int, height: int, step: int, encoding: str, name: str) -> np.ndarray:
    """RGB (H, W, 3) uint8 of a semi-planar YUV 4:2:0 image (:data:`_YUV420_ENCODINGS`)."""
    if width <= 0 or height <= 0 or width % 2 or height % 2:
        raise InputError(f"{name}: {encoding} image of size {width}×{height}: YUV 4:2:0 needs an even width and height")
    planes = _rows(data, height * 3 // 2, width, step or width, f"{name}: image of {width}×{height} {encoding}")
    return cv2.cvtColor(planes, _YUV420_ENCODINGS[encoding.lower()])


def _rows(data: bytes, rows: int, row_bytes: int, step: int, what: str) -> np.ndarray:
    """The first ``row_bytes`` of each of ``rows`` rows ``step`` bytes apart: (rows, row_bytes)
    uint8, contiguous. :class:`InputError` starting with ``what`` when ``step`` is shorter than a
    row (the header is wrong, on every message alike), and its :class:`DamagedImageError` when
    ``data`` is too short for the header (one message cut short: a log skips that pair)."""
    if step < row_bytes:
        raise InputError(f"{what}: a step of {step} bytes is shorter than a row of {row_bytes}")
    if len(data) < step * (rows - 1) + row_bytes:
        raise DamagedImageError(f"{what} with step {step} needs more than the {len(data)} bytes given")
    buffer = np.frombuffer(bytes(data), dtype=np.uint8)
    if buffer.size < step * rows:  # the last row may omit its padding
        buffer = np.pad(buffer, (0, step * rows - buffer.size))
    return np.ascontiguousarray(buffer[: step * rows].reshape(rows, step)[:, :row_bytes])


def stereo_pair(
    left: np.ndarray, right: np.ndarray, left_name: str, right_name: str
) -> tuple[np.ndarray, np.ndarray]:
    """Make a left/right pair the pipeline can use: same size, same channels, uint8.

    16-bit images are scaled to 8 bit with one factor for both (255 / the pair's maximum).
    A colour image paired with a mono one is converted to mono. Different sizes or bit depths
    raise :class:`InputError` naming both images.
    """
    if left.shape[:2] != right.shape[:2]:
        raise InputError(
            f"left and right images differ in size: {left_name} is {left.shape[1]}×{left.shape[0]}, "
            f"{right_name} is {right.shape[1]}×{right.shape[0]}"
        )
    if left.dtype != right.dtype:
        raise InputError(
            f"left and right images differ in bit depth: {left_name} is {left.dtype}, {right_name} is {right.dtype}"
        )
    if left.ndim != right.ndim:
        left, right = (cv2.cvtColor(im, cv2.COLOR_RGB2GRAY) if im.ndim == 3 else im for im in (left, right))
    if left.dtype != np.uint8:  # both 16-bit (equal depths checked above)
        peak = float(max(int(left.max()), int(right.max()), 1))
        left, right = (np.clip(im.astype(np.float32) * (255.0 / peak) + 0.5, 0, 255).astype(np.uint8)
                       for im in (left, right))
    return np.ascontiguousarray(left), np.ascontiguousarray(right)
