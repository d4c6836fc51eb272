"""terrainmap: terrain maps from stereo camera logs.

Implements Broggi, Cardarelli, Cattani, Sabbatelli, "Terrain Mapping for Off-road Autonomous
Ground Vehicles Using Rational B-Spline Surfaces and Stereo Vision": 3D points → 2.5D grid →
rational B-spline terrain surface by re-weighted least squares and equalization → slope →
terrain/obstacle segmentation.
"""

import logging

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
