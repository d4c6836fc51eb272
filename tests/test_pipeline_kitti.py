"""The whole pipeline on the real KITTI 2015 frame 000005, scored with its ground-truth disparity."""

import cv2
import numpy as np
import pytest

from terrainmap.config import Config
from terrainmap.grid import cell_index
from terrainmap.pipeline import PipelineState, process_frame
from terrainmap.sources import open_source
from terrainmap.stereo import to_vehicle
from terrainmap.types import Label


@pytest.fixture(scope="module")
def kitti():
    from conftest import SHARED_DATA

    folder = SHARED_DATA / "kitti2015_000005"
    if not folder.is_dir():
        pytest.skip("real data not found")
    config = Config()
    state = PipelineState(config)
    with open_source(folder) as source:
        result = process_frame(next(source.frames()), config, state)
    gt = cv2.imread(str(folder / "disp_occ_0" / "000005_10.png"), cv2.IMREAD_UNCHANGED).astype(np.float32) / 256
    gt[gt == 0] = np.nan
    points_cam, pixels = state.matcher.reproject(gt)
    gt_points = to_vehicle(points_cam, result.extrinsics)  # ground truth, in the estimated vehicle frame
    return config, result, gt_points, pixels


def _labels_at(result, pixels):
    image = np.full((result.disparity.shape[0], result.disparity.shape[1]), 255, np.uint8)
    image[result.pixels[:, 1], result.pixels[:, 0]] = result.point_labels
    labels = image[pixels[:, 1], pixels[:, 0]]
    return labels[labels != 255]


def test_camera_pose_is_found_from_the_ground(kitti):
    _, result, _, _ = kitti
    assert result.extrinsics.source == "estimated"
    assert result.extrinsics.translation[2] == pytest.approx(1.62, abs=0.05)


def test_road_ahead_is_terrain_with_slope_under_5_degrees(kitti):
    config, result, gt, pixels = kitti
    road = (np.abs(gt[:, 2]) < 0.15) & (np.abs(gt[:, 1]) < 1.5) & (gt[:, 0] < 20)  # the lane ahead
    cells = np.unique(cell_index(gt[road], config.grid))
    cells = cells[cells < result.grid.z.size]
    slope_deg = np.degrees(result.layers["slope"].ravel()[cells])
    assert np.median(slope_deg) < 5.0
    assert np.mean(_labels_at(result, pixels[road]) == Label.TERRAIN) > 0.95
    elevation = result.layers["elevation"].ravel()[cells]
    assert np.median(np.abs(elevation)) < 0.1  # the road is z = 0 in the estimated vehicle frame


def test_parked_cars_are_obstacles(kitti):
    _, result, gt, pixels = kitti
    cars = (gt[:, 2] > 0.5) & (gt[:, 2] < 1.6) & (np.abs(gt[:, 1]) > 2.0) & (np.abs(gt[:, 1]) < 6) & (gt[:, 0] < 20)
    assert np.mean(_labels_at(result, pixels[cars]) == Label.OBSTACLE) > 0.65  # 0.676 measured (2026-11-26)
    big = [o for o in result.obstacles if o.kind == "positive" and o.height_m > 0.8 and o.range_m < 20]
    assert len(big) >= 3  # the van ahead and parked cars on both kerbs
