"""terrainmap: terrain maps from stereo camera logs.

Implements Broggi, Cardarelli, Cattani, Sabbatelli, "Terrain Mapping for Off-road Autonomous
Ground Vehicles Using Rational B-Spline Surfaces and Stereo Vision": 3D points → 2.5D grid →
rational B-spline terrain surface by re-weighted least squares and equalization → slope →
terrain/obstacle segmentation.
"""

import logging
import os

# OpenBLAS threads that wait for work spin on the CPU beside OpenCV's stereo matcher. With
# scipy's OpenBLAS at its default thread count, 6 alternating runs each on the 2-core benchmark
# machine took 42–58 ms for SGBM on a 640×480 pair (27–41 ms with one thread) and 66–73 ms for
# the whole frame (43–62 ms). terrainmap's matrices are small enough for one thread. This must
# run before scipy.linalg loads OpenBLAS, so it is here; a value already in the environment wins.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

from .config import Config, load_config
from .errors import CalibrationError, ConfigError, FrameError, InputError, TerrainmapError
from .types import Extrinsics, FrameResult, Label, StereoCalibration, StereoFrame

__version__ = "0.1.0"

logging.getLogger(__name__).addHandler(logging.NullHandler())

__all__ = [
    "CalibrationError",
    "Config",
    "ConfigError",
    "Extrinsics",
    "FrameError",
    "FrameResult",
    "InputError",
    "Label",
    "StereoCalibration",
    "StereoFrame",
    "TerrainmapError",
    "load_config",
    "__version__",
]
