"""``terrainmap eval stereo``: disparities against ground truth (KITTI, Middlebury, simulated logs)."""

import json

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

from terrainmap.cli.eval_cmd import eval_group
from terrainmap.config import Config
from terrainmap.errors import InputError
from terrainmap.evaluation import disparity as ev


def _stats():
    return {name: ev._BandStats() for name in ev.BANDS}


# --- metrics on hand-built maps ------------------------------------------------------------------------

def test_errors_coverage_and_bands_of_a_hand_built_map():
    truth = np.array([[30, 30, 30, 30, np.nan], [10, 10, 10, 5, 5]], np.float32)  # f·B = 150: 5, 15, 30 m
    estimate = np.array([[30.5, 29, 40, np.nan, 3], [10.2, 9.6, 10.1, 5.3, np.nan]], np.float32)
    stats = _stats()
    ev.score_disparity(stats, estimate, truth, 150.0, 0.0)
    near, mid, far, every = (stats[b].summary() for b in ("0-10", "10-20", "20-35", "all"))
    assert near["truth_pixels"] == 4 and near["coverage"] == pytest.approx(0.75)
    assert near["mean_abs_error_px"] == pytest.approx((0.5 + 1.0 + 10.0) / 3)
    assert near["median_abs_error_px"] == pytest.approx(1.0, abs=0.006)
    assert near["over_1px"] == pytest.approx(1 / 3) and near["over_3px"] == pytest.approx(1 / 3)
    assert near["d1"] == pytest.approx(1 / 3)  # 10 px > 3 px and > 5 % of 30
    assert mid["truth_pixels"] == 3 and mid["bias_px"] == pytest.approx(0.1, abs=0.006)  # median of .2, −.4, .1
    assert far["truth_pixels"] == 2 and far["coverage"] == 0.5 and far["over_1px"] == 0
    assert every["truth_pixels"] == 9 and every["coverage"] == pytest.approx(7 / 9)  # unknown truth: not scored


def test_d1_needs_both_3_px_and_5_percent():
    truth = np.array([[100.0, 100.0, 20.0]], np.float32)
    estimate = np.array([[104.0, 106.0, 24.0]], np.float32)  # 4 % | 6 % | 20 %, each over 3 px
    stats = _stats()
    ev.score_disparity(stats, estimate, truth, 150.0, 0.0)
    summary = stats["all"].summary()
    assert summary["over_3px"] == 1 and summary["d1"] == pytest.approx(2 / 3)


def test_an_empty_band_has_no_figures():
    stats = _stats()
    ev.score_disparity(stats, np.full((2, 2), np.nan, np.float32), np.full((2, 2), 15.0, np.float32), 150.0, 0.0)
    assert stats["10-20"].summary()["coverage"] == 0
    assert stats["10-20"].summary()["median_abs_error_px"] is None
    assert stats["0-10"].summary() == {**stats["0-10"].summary(), "truth_pixels": 0, "coverage": None}


# --- ground-truth files ----------------------------------------------------------------------------------

def _write_pfm(path, image):
    with open(path, "wb") as f:
        f.write(f"Pf\n{image.shape[1]} {image.shape[0]}\n-1\n".encode())
        np.flipud(image).astype("<f4").tofile(f)


def test_truth_files_round_trip_with_unknown_pixels(tmp_path):
    disparity = np.array([[12.5, 0.0], [3.25, 200.0]], np.float32)
    png = tmp_path / "d.png"
    cv2.imwrite(str(png), np.round(disparity * 256).astype(np.uint16))
    read = ev.read_truth(png, (2, 2))
    assert np.isnan(read[0, 1]) and read[0, 0] == 12.5 and read[1, 0] == 3.25 and read[1, 1] == 200
    pfm = tmp_path / "d.pfm"
    _write_pfm(pfm, np.array([[12.5, np.inf], [3.25, 200.0]], np.float32))
    read = ev.read_truth(pfm, (2, 2))
    assert np.isnan(read[0, 1]) and read[0, 0] == 12.5 and read[1, 0] == 3.25  # top row first
    with pytest.raises(InputError, match=r"d\.png: ground truth is 2×2, the left image 3×2"):
        ev.read_truth(png, (2, 3))
    (tmp_path / "bad.pfm").write_bytes(b"P6\n2 2\n255\n")
    with pytest.raises(InputError, match=r"bad\.pfm: not a one-channel PFM"):
        ev.read_truth(tmp_path / "bad.pfm", (2, 2))
    (tmp_path / "huge.pfm").write_bytes(b"Pf\n100000 100000\n-1.0\n")  # nothing allocated for 37 GB
    with pytest.raises(InputError, match=r"huge\.pfm: .* \(100000×100000, the file holds 0 values\)"):
        ev.read_truth(tmp_path / "huge.pfm", (100000, 100000))
    (tmp_path / "negative.pfm").write_bytes(b"Pf\n-2 -2\n-1.0\n" + bytes(16))
    with pytest.raises(InputError, match=r"negative\.pfm: .* \(-2×-2, the file holds 4 values\)"):
        ev.read_truth(tmp_path / "negative.pfm", (2, 2))
    cv2.imwrite(str(tmp_path / "rgb.png"), np.zeros((2, 2, 3), np.uint8))
    with pytest.raises(InputError, match=r"rgb\.png: not a 16-bit single-channel PNG"):
        ev.read_truth(tmp_path / "rgb.png", (2, 2))
    cut = png.read_bytes()
    (tmp_path / "cut.png").write_bytes(cut[: len(cut) // 2])  # libpng would print "Read Error" of its own
    with pytest.raises(InputError, match=r"cut\.png: cannot decode the image file"):
        ev.read_truth(tmp_path / "cut.png", (2, 2))


def test_truth_files_are_found_beside_kitti_and_middlebury_images(tmp_path):
    for folder in ("image_2", "disp_noc_0", "disp_occ_0", "colored_0", "disp_noc", "scene"):
        (tmp_path / folder).mkdir()
    for path in ("disp_noc_0/000001_10.png", "disp_occ_0/000001_10.png", "disp_noc/000002_10.png",
                 "scene/disp0.pfm"):
        (tmp_path / path).touch()
    assert ev.truth_file(tmp_path / "image_2/000001_10.png") == tmp_path / "disp_occ_0/000001_10.png"
    assert ev.truth_file(tmp_path / "image_2/000001_11.png") is None
    assert ev.truth_file(tmp_path / "colored_0/000002_10.png") == tmp_path / "disp_noc/000002_10.png"
    assert ev.truth_file(tmp_path / "scene/im0.png") == tmp_path / "scene/disp0.pfm"


# --- whole folders -------------------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def rendered():
    """A simulated 320×240 pair, its calibration and its true disparity (f·B / depth)."""
    from terrainmap.sim import SimConfig
    from terrainmap.sim.scenes import build_scene

    renderer = SimConfig(scene="hills", frames=1, seed=1, width=320, height=240).renderer(
        build_scene("hills", 1, length_m=10.0))
    frame, calib = renderer.frame(0), renderer.rig.calibration()
    with np.errstate(divide="ignore"):
        truth = (calib.fx * calib.baseline_m / frame.depth).astype(np.float32)  # sky: 0, unknown
    return frame, calib, truth


def _bgr(image):
    return cv2.cvtColor(image, cv2.COLOR_RGB2BGR) if image.ndim == 3 else image


@pytest.fixture(scope="module")
def kitti_folder(tmp_path_factory, rendered):
    frame, calib, truth = rendered
    root = tmp_path_factory.mktemp("kitti")
    for folder in ("image_2", "image_3", "calib_cam_to_cam", "disp_occ_0"):
        (root / folder).mkdir()
    for name in ("000000_10.png", "000000_11.png"):  # KITTI: only the _10 pair has ground truth
        cv2.imwrite(str(root / "image_2" / name), _bgr(frame.left))
        cv2.imwrite(str(root / "image_3" / name), _bgr(frame.right))
    cv2.imwrite(str(root / "disp_occ_0/000000_10.png"), np.round(np.clip(truth, 0, 255) * 256).astype(np.uint16))
    row = f"{calib.fx} 0 {calib.cx} {{}} 0 {calib.fy} {calib.cy} 0 0 0 1 0"
    (root / "calib_cam_to_cam/000000.txt").write_text(
        f"P_rect_02: {row.format(0)}\nP_rect_03: {row.format(-calib.fx * calib.baseline_m)}\n")
    return root


def test_a_kitti_folder_is_scored_and_its_pair_without_truth_skipped(kitti_folder):
    report = ev.evaluate_disparity(kitti_folder, Config())
    assert report["pairs"] == 1 and report["pairs_without_truth"] == 1 and report["failed_frames"] == {}
    assert report["skipped"] == []
    every = report["bands"]["all"]
    assert every["truth_pixels"] > 0.6 * 320 * 240 and every["coverage"] > 0.5
    assert every["median_abs_error_px"] < 0.5 and every["d1"] < 0.1
    assert report["bands"]["0-10"]["truth_pixels"] + report["bands"]["10-20"]["truth_pixels"] == (
        report["bands"]["0-20"]["truth_pixels"])


def test_a_pair_whose_image_cannot_be_decoded_is_skipped_and_listed(tmp_path, kitti_folder):
    import shutil

    root = tmp_path / "kitti"
    shutil.copytree(kitti_folder, root)
    (root / "image_3" / "000000_11.png").write_bytes(b"not a png")
    report = ev.evaluate_disparity(root, Config())
    assert report["pairs"] == 1 and len(report["skipped"]) == 1 and "000000_11.png" in report["skipped"][0]
    assert ", 1 damaged and skipped" in ev.format_table(report).splitlines()[0]


def test_a_middlebury_scene_gives_the_same_figures(tmp_path, rendered, kitti_folder):
    frame, calib, truth = rendered
    scene = tmp_path / "scene"
    scene.mkdir()
    cv2.imwrite(str(scene / "im0.png"), _bgr(frame.left))
    cv2.imwrite(str(scene / "im1.png"), _bgr(frame.right))
    _write_pfm(scene / "disp0GT.pfm", np.where(truth > 0, truth, np.inf))
    K = f"[{calib.fx} 0 {calib.cx}; 0 {calib.fy} {calib.cy}; 0 0 1]"
    (scene / "calib.txt").write_text(f"cam0={K}\ncam1={K}\ndoffs=0\nbaseline={1000 * calib.baseline_m}\n"
                                     f"width=320\nheight=240\n")
    middlebury = ev.evaluate_disparity(scene, Config())["bands"]["all"]
    kitti = ev.evaluate_disparity(kitti_folder, Config())["bands"]["all"]
    assert middlebury["coverage"] == pytest.approx(kitti["coverage"], abs=0.01)  # KITTI's PNG rounds to 1/256 px
    assert middlebury["median_abs_error_px"] == pytest.approx(kitti["median_abs_error_px"], abs=0.02)


def test_a_simulated_log_is_scored_from_its_depth_truth(tiny_mcap):
    report = ev.evaluate_disparity(tiny_mcap, Config())
    assert report["pairs"] == 2 and report["pairs_without_truth"] == 0
    every = report["bands"]["all"]
    assert every["truth_pixels"] > 0.5 * 2 * 160 * 120 and every["coverage"] > 0.5
    assert every["median_abs_error_px"] < 0.5


def test_a_folder_no_pair_of_which_can_be_scored_is_an_error(tmp_path, kitti_folder):
    from click.testing import CliRunner

    from terrainmap.cli.eval_stereo import stereo

    out_json = tmp_path / "r.json"
    result = CliRunner().invoke(stereo, [str(kitti_folder), "--json", str(out_json), "--set", "extrinsics.min_points=10000000"])
    assert result.exit_code == 2 and f"no stereo pair of {kitti_folder} could be scored (" in result.output
    assert not out_json.exists()


def test_a_folder_whose_only_pair_with_ground_truth_is_damaged_says_so(tmp_path, kitti_folder):
    import shutil

    from click.testing import CliRunner

    from terrainmap.cli.eval_stereo import stereo

    damaged = tmp_path / "damaged"
    shutil.copytree(kitti_folder, damaged)
    left = damaged / "image_2/000000_10.png"
    left.write_bytes(left.read_bytes()[:-100])
    result = CliRunner().invoke(stereo, [str(damaged)])
    assert result.exit_code == 2 and result.output.strip().splitlines()[-1] == (
        f"Error: no stereo pair of {damaged} could be scored (1 pair damaged and skipped, 1 pair without ground truth)")


def test_a_folder_whose_ground_truth_holds_no_disparity_is_an_error(tmp_path, kitti_folder):
    """A ground-truth file of zeros (KITTI's "no disparity here") scores no pixel: an error, not
    exit 0 with a table of empty bands."""
    import shutil

    from click.testing import CliRunner

    from terrainmap.cli.eval_stereo import stereo

    empty = tmp_path / "empty"
    shutil.copytree(kitti_folder, empty)
    cv2.imwrite(str(empty / "disp_occ_0/000000_10.png"), np.zeros((240, 320), np.uint16))
    result = CliRunner().invoke(stereo, [str(empty)])
    assert result.exit_code == 2
    assert result.output.strip().splitlines()[-1] == (
        f"Error: no stereo pair of {empty} could be scored (the ground truth of its 1 pair holds no valid disparity)")


def test_folders_and_logs_without_ground_truth_are_named(tmp_path, kitti_folder, tiny_mcap):
    import shutil

    from test_accuracy import _strip_truth

    bare = tmp_path / "bare"
    shutil.copytree(kitti_folder, bare, ignore=shutil.ignore_patterns("disp_occ_0"))
    with pytest.raises(InputError, match=r"bare: no ground-truth disparity found \(KITTI: disp_occ_0/.*"
                                         r"or a log written by terrainmap simulate: no ground truth"):
        ev.evaluate_disparity(bare, Config())
    plain = tmp_path / "plain.mcap"
    _strip_truth(tiny_mcap, plain)
    with pytest.raises(InputError, match=r"plain\.mcap: no ground-truth disparity found .*missing topics"):
        ev.evaluate_disparity(plain, Config())
    damaged = tmp_path / "damaged.mcap"  # a simulated log whose summary fails its CRC: damage, said as such
    data = bytearray(tiny_mcap.read_bytes())
    data[data.rindex(b"/truth/left/depth") + 8] ^= 0x01
    damaged.write_bytes(bytes(data))
    with pytest.raises(InputError, match=r"damaged\.mcap: damaged log \(its summary fails its CRC\)") as info:
        ev.evaluate_disparity(damaged, Config())
    assert "no ground-truth disparity found" not in str(info.value)


@pytest.fixture(scope="module")
def tiny_mcap(tmp_path_factory):
    from terrainmap.sim import SimConfig, simulate

    path = tmp_path_factory.mktemp("sim") / "drive.mcap"
    simulate(path, SimConfig(scene="flat", frames=2, seed=1, width=160, height=120))
    return path


def test_cli_prints_the_table_and_writes_json(kitti_folder, tmp_path):
    out = tmp_path / "r.json"
    result = CliRunner().invoke(eval_group, ["stereo", str(kitti_folder), "--json", str(out)])
    assert result.exit_code == 0, result.output
    assert "1 pair scored, 1 without ground truth" in result.output
    assert result.output.splitlines()[-2].split()[0] == "all"  # the table's last row, then what was written
    assert result.output.splitlines()[-1] == f"wrote {out}"
    report = json.loads(out.read_text())
    assert set(report["bands"]) == set(ev.BANDS) and report["pairs"] == 1
    result = CliRunner().invoke(eval_group, ["stereo", str(kitti_folder), "--json", str(kitti_folder / "x" / "r.json")])
    assert result.exit_code == 2 and "--json" in result.output


def test_kitti_000005_disparities_agree_with_its_ground_truth():
    from conftest import SHARED_DATA

    folder = SHARED_DATA / "kitti2015_000005"
    if not folder.is_dir():
        pytest.skip("real data not found")
    every = ev.evaluate_disparity(folder, Config())["bands"]["all"]
    assert every["median_abs_error_px"] < 1.0  # issue 3's target; 0.58 px measured (2026-11-26)
    assert every["coverage"] > 0.7 and every["d1"] < 0.1  # 0.751 and 0.065 measured


def test_depth_bands_use_the_disparity_offset_and_take_their_lower_edge():
    """Z = f·B / (d + doffs): with f·B 100 px·m and doffs 5 px, 10 px of disparity lie at 6.7 m (band 0-10,
    not 10 m); 5 px lie at exactly 10 m, in 10-20 (lo ≤ Z < hi)."""
    stats = _stats()
    ev.score_disparity(stats, np.array([[10.0, 5.0]], np.float32), np.array([[10.0, 5.0]], np.float32), 100.0, 5.0)
    assert stats["0-10"].summary()["truth_pixels"] == 1 and stats["10-20"].summary()["truth_pixels"] == 1
    stats = _stats()
    ev.score_disparity(stats, np.array([[10.0]], np.float32), np.array([[10.0]], np.float32), 100.0, 0.0)
    assert stats["10-20"].summary()["truth_pixels"] == 1 and stats["0-10"].summary()["truth_pixels"] == 0
