"""Shared fixtures: the real data beside the project (skipped cleanly when absent)."""

from pathlib import Path

import pytest

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


@pytest.fixture
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip(f"real data not found at {SHARED_DATA}")
    return SHARED_DATA


class KeepSink:
    """A sink that keeps every result it is given, in ``results``."""

    def __init__(self) -> None:
        self.results = []

    def write(self, frame, result) -> None:
        self.results.append(result)

    def close(self) -> None:
        pass


@pytest.fixture
def keep_sink() -> KeepSink:
    return KeepSink()


def load_kitti():
    """(left RGB, right RGB, GT disparity (NaN = unknown), StereoCalibration) of KITTI 000005_10,
    read directly with OpenCV (independent of terrainmap's sources); skips when absent."""
    import cv2
    import numpy as np

    from terrainmap.types import StereoCalibration

    folder = SHARED_DATA / "kitti2015_000005"
    if not folder.is_dir():
        pytest.skip("shared KITTI data not available")
    left, right = (cv2.imread(str(folder / d / "000005_10.png"))[:, :, ::-1].copy() for d in ("image_2", "image_3"))
    raw = cv2.imread(str(folder / "disp_occ_0" / "000005_10.png"), cv2.IMREAD_UNCHANGED)
    gt = np.where(raw > 0, raw / 256.0, np.nan).astype(np.float32)
    P = {}
    for line in (folder / "calib_cam_to_cam" / "000005.txt").read_text().splitlines():
        key, _, values = line.partition(":")
        P[key] = np.array(values.split(), float).reshape(3, 4)
    P2, P3 = P["P_rect_02"], P["P_rect_03"]
    calib = StereoCalibration(
        width=left.shape[1], height=left.shape[0], fx=P2[0, 0], fy=P2[1, 1], cx=P2[0, 2], cy=P2[1, 2],
        baseline_m=(P2[0, 3] - P3[0, 3]) / P2[0, 0], source="kitti 000005",
    )
    return left, right, gt, calib
