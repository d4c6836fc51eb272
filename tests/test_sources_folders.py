"""Folder sources: generic, KITTI (stereo, object, raw, odometry), Middlebury; selection; errors."""

import os
import re
import shutil
import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
from log_copies import YAML_BOMB

from terrainmap.errors import CalibrationError, ConfigError, DamagedImageError, InputError
from terrainmap.sources import open_source, source_class
from terrainmap.sources.folder import GenericFolder
from terrainmap.sources.images import decode_compressed
from terrainmap.sources.kitti import KittiOdometryFolder, KittiRawFolder, KittiStereoFolder
from terrainmap.sources.middlebury import MiddleburyFolder
from terrainmap.stereo import matching_pinhole

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
KITTI = DATA / "kitti2015_000005"

CALIB_YAML = """width: 8
height: 6
fx: 500.0
fy: 501.0
cx: 4.0
cy: 3.0
baseline_m: 0.3
"""
KITTI_P2 = "7.215377e+02 0 6.095593e+02 4.485728e+01 0 7.215377e+02 1.728540e+02 2.163791e-01 0 0 1 2.745884e-03"
KITTI_P3 = "7.215377e+02 0 6.095593e+02 -3.395242e+02 0 7.215377e+02 1.728540e+02 2.199936e+00 0 0 1 2.729905e-03"
KITTI_BASELINE = (44.85728 + 339.5242) / 721.5377
KITTI_P3_GREY = "7.215377e+02 0 6.095593e+02 -3.460000e+02 0 7.215377e+02 1.728540e+02 0 0 0 1 0"
KITTI_BASELINE_GREY = (44.85728 + 346.0) / 721.5377


def image(seed: int, shape=(6, 8, 3), dtype=np.uint8) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, np.iinfo(dtype).max, shape, dtype=dtype)


def write(path: Path, array: np.ndarray) -> Path:
    """Write an RGB (or mono) array as an image file; OpenCV stores BGR."""
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), cv2.cvtColor(array, cv2.COLOR_RGB2BGR) if array.ndim == 3 else array)
    return path


def generic_folder(root: Path, n: int = 5, calib: str = CALIB_YAML, suffix: str = ".png", digits: int = 6) -> Path:
    for i in range(n):
        write(root / "left" / f"{i:0{digits}d}{suffix}", image(2 * i))
        write(root / "right" / f"{i:0{digits}d}{suffix}", image(2 * i + 1))
    (root / "calibration.yaml").write_text(calib)
    return root


def test_webp_images_are_read(tmp_path):
    root = generic_folder(tmp_path, n=2, suffix=".webp")
    with open_source(root) as source:
        (first, _) = list(source.frames())
    assert first.left.shape == (6, 8, 3)


def test_images_numbered_without_leading_zeros_are_read_in_their_numbers_order(tmp_path):
    root = generic_folder(tmp_path, n=12, digits=1)
    (root / "timestamps.txt").write_text("".join(f"{i * 10**8}\n" for i in range(12)))
    with open_source(root) as source:
        frames = list(source.frames())
    assert [f.stamp_ns for f in frames] == [i * 10**8 for i in range(12)]
    for i in (2, 10):
        np.testing.assert_array_equal(frames[i].left, image(2 * i))


def test_a_stray_mcap_file_does_not_make_an_image_folder_a_log(tmp_path):
    root = generic_folder(tmp_path)
    (root / "notes.mcap").write_bytes(b"not a log")
    assert source_class(root) is GenericFolder


def test_generic_folder_yields_rgb_pairs_with_calibration(tmp_path):
    root = generic_folder(tmp_path)
    with open_source(root) as source:
        assert isinstance(source, GenericFolder)
        frames = list(source.frames())
        info = source.describe()
    assert [f.index for f in frames] == list(range(5))
    assert [f.stamp_ns for f in frames] == [i * 100_000_000 for i in range(5)]
    np.testing.assert_array_equal(frames[2].left, image(4))
    np.testing.assert_array_equal(frames[2].right, image(5))
    assert frames[0].left.dtype == np.uint8 and frames[0].left.shape == (6, 8, 3)
    calib = frames[0].calibration
    assert (calib.fx, calib.fy, calib.cx, calib.cy, calib.baseline_m) == (500.0, 501.0, 4.0, 3.0, 0.3)
    assert frames[0].extrinsics is None
    assert info["format"] == "folder" and info["frames"] == 5
    assert info["calibration"]["baseline_m"] == 0.3 and "estimated" in info["extrinsics"]


def test_selection_start_end_every_max_and_index_from_source_start(tmp_path):
    root = generic_folder(tmp_path, n=10)
    (root / "timestamps.txt").write_text("\n".join(str(1_000_000_000 + i * 50_000_000) for i in range(10)))
    with open_source(root) as source:
        assert [f.index for f in source.frames(start_s=0.1, end_s=0.35)] == [2, 3, 4, 5, 6, 7]
        assert [f.index for f in source.frames(start_s=0.1, every=3)] == [2, 5, 8]
        assert [f.index for f in source.frames(every=2, max_frames=3)] == [0, 2, 4]
        assert list(source.frames(max_frames=0)) == []
        assert next(source.frames(start_s=0.2)).stamp_ns == 1_200_000_000
        with pytest.raises(ConfigError, match="every"):
            list(source.frames(every=0))
        # stamped out of order (0.30 and 0.45 s swapped): the window is by stamp, for --end as for --start
        stamps = [0, 5, 10, 15, 20, 25, 45, 35, 40, 30]
        (root / "timestamps.txt").write_text("\n".join(str(1_000_000_000 + s * 10_000_000) for s in stamps))
    with open_source(root) as source:
        assert [f.index for f in source.frames(end_s=0.37)] == [0, 1, 2, 3, 4, 5, 7, 9]
        assert [f.index for f in source.frames(start_s=0.37)] == [6, 8]
        for bad, message in (({"start_s": float("nan")}, "start: must be a finite number"),
                             ({"end_s": "1"}, "end: must be a finite number"),
                             ({"every": 2.5}, "every: must be a whole number"),
                             ({"max_frames": 1.0}, "max_frames: must be a whole number")):
            with pytest.raises(ConfigError, match=message):
                list(source.frames(**bad))


def test_a_left_image_without_its_right_one_keeps_the_later_pairs_stamps(tmp_path, caplog):
    """timestamps.txt has one line per left image: a pair lost to a missing right image takes its
    line with it, so the pairs after it keep their own stamps; the warning names the image left out."""
    root = generic_folder(tmp_path, n=4)
    (root / "right" / "000001.png").unlink()
    (root / "timestamps.txt").write_text("10\n20\n30\n40\n")
    with open_source(root) as source:
        frames = list(source.frames())
    assert caplog.messages[0] == (f"{root}: 4 left and 3 right images, 3 with the same name on both sides; left out "
                                  f"for want of a partner: {root / 'left' / '000001.png'}")
    assert [(f.stamp_ns, Path(f.source.split(" + ")[0]).name) for f in frames] == [
        (10, "000000.png"), (30, "000002.png"), (40, "000003.png")]
    (root / "timestamps.txt").write_text("10\n30\n40\n")  # one line per pair: taken in order
    with open_source(root) as source:
        assert [f.stamp_ns for f in source.frames()] == [10, 30, 40]


@pytest.mark.parametrize(
    ("lines", "stamps", "warning"),
    [
        ("10\n20\n30\n40\n", [10, 20, 30], "4 timestamps for 3 image pairs; the first 3 are used"),
        ("10\n10\n5\n", [10, 10, 5], "2 of 3 pair stamps are not later than the one before (repeated or out of order)"),
    ],
)
def test_odd_timestamps_are_warned_about(tmp_path, caplog, lines, stamps, warning):
    """Extra lines, and stamps that repeat or go back."""
    root = generic_folder(tmp_path, n=3)
    (root / "timestamps.txt").write_text(lines)
    with open_source(root) as source:
        assert [f.stamp_ns for f in source.frames()] == stamps
    assert warning in caplog.text


@pytest.mark.parametrize("lines", ["-5\n0\n5\n", f"0\n1\n{2**63}\n"])
def test_a_stamp_no_log_can_hold_is_named_in_its_file(tmp_path, lines):
    """Where ``info`` reads it too, not at the frame in ``process`` naming its images."""
    root = generic_folder(tmp_path, n=3)
    (root / "timestamps.txt").write_text(lines)
    with pytest.raises(InputError, match=r"timestamps.txt: stamp -?\d+ ns lies outside 1970–2262"):
        open_source(root)


def test_calibration_toml_extrinsics_and_unrectified(tmp_path):
    root = generic_folder(tmp_path, n=1)
    (root / "calibration.yaml").unlink()
    (root / "calibration.toml").write_text(
        CALIB_YAML.replace(": ", " = ")
        + "rectified = false\nK_left = [[500, 0, 4], [0, 500, 3], [0, 0, 1]]\nK_right = [[500, 0, 4], [0, 500, 3], [0, 0, 1]]\n"
        "dist_left = [0.1, 0, 0, 0, 0]\ndist_right = [0.1, 0, 0, 0, 0]\nR = [[1, 0, 0], [0, 1, 0], [0, 0, 1]]\n"
        "T = [-0.3, 0, 0]\n[extrinsics]\ntranslation_m = [0.5, 0.0, 1.5]\nquaternion_xyzw = [-0.5, 0.5, -0.5, 0.5]\n"
    )
    frame = next(open_source(root).frames())
    calib, ext = frame.calibration, frame.extrinsics
    assert not calib.rectified and calib.K_left.shape == (3, 3) and calib.T.tolist() == [-0.3, 0, 0]
    assert ext.source == "calibration" and ext.translation.tolist() == [0.5, 0.0, 1.5]
    # optical z (forward) maps to vehicle x, optical x (right) to vehicle -y, optical y (down) to -z
    np.testing.assert_allclose(ext.rotation, [[0, 0, 1], [-1, 0, 0], [0, -1, 0]], atol=1e-12)


@pytest.mark.parametrize(
    "old, new, message",
    [
        ("K_left = [[500, 0, 4]", "K_left = [[nan, 0, 4]", "'K_left' must be a list of finite numbers"),
        ("quaternion_xyzw = [-0.5, 0.5, -0.5, 0.5]", "quaternion_xyzw = [0, 0, 0, 0]", "must not be zero"),
        ("quaternion_xyzw = [-0.5, 0.5, -0.5, 0.5]", "", "'rotation' is required in extrinsics \\(or quaternion_xyzw\\)$"),
        ("K_left = [[500, 0, 4], [0, 500, 3], [0, 0, 1]]", "", "'K_left' is required as rectified is false$"),
        ("translation_m = [0.5, 0.0, 1.5]", "translation_m = [nan, 0.0, 1.5]", "'translation_m' must be a list of finite"),
        ("translation_m = [0.5, 0.0, 1.5]", "translation_m = [0.5, 0.0, 1e30]", "translation_m must be within 1 km"),
        ("translation_m = [0.5, 0.0, 1.5]", "translation = [0.5, 0.0, 1.5]", "'translation_m' is required in extrinsics$"),
        ("rectified = false", 'rectified = "false"', "rectified must be true or false"),
        ("width = 8", "width = 8.5", "width must be a whole number of pixels, got 8.5$"),
        ("width = 8", "width = true", "width must be a number, got True$"),
        ("width = 8", 'width = "abc"', "width must be a number, got 'abc'$"),
    ],
)
def test_nonsense_in_a_calibration_file_is_named(tmp_path, old, new, message):
    test_calibration_toml_extrinsics_and_unrectified(tmp_path)  # writes a valid calibration.toml
    path = next(tmp_path.rglob("calibration.toml"))
    path.write_text(path.read_text().replace(old, new))
    with pytest.raises(CalibrationError, match=message):
        next(open_source(path.parent).frames())


@pytest.mark.parametrize(
    "old, new, message",
    [
        ("fx: 500.0", "fx: 1.0e+308", "fx must be within 1..1e\\+06 pixels, got 1e\\+308$"),
        ("baseline_m: 0.3", "baseline_m: 1.0e-300", "baseline_m must be within 0.001..100 m, got 1e-300$"),
        ("cy: 3.0", "cy: 3.0\ncx_right: .nan", "cx_right must be a finite number of pixels"),
    ],
)
def test_nonsense_in_a_rectified_pinhole_is_named(tmp_path, old, new, message):
    root = generic_folder(tmp_path, n=1, calib=CALIB_YAML.replace(old, new))
    with pytest.raises(CalibrationError, match=message):
        next(open_source(root).frames())


def test_raw_images_take_their_pinhole_from_rectifying_and_a_wrong_side_is_refused_where_read(tmp_path, caplog):
    """With ``rectified = false`` the pinhole keys are not needed, are warned about as unused when
    given, and ``describe()`` (``info``) shows the pinhole that rectifying gives, which ``process``
    matches with; a right camera on the left is refused when the file is read (``info --check`` too)."""
    test_calibration_toml_extrinsics_and_unrectified(tmp_path)
    path = next(tmp_path.rglob("calibration.toml"))
    assert "fx, fy, cx, cy, baseline_m not used" in caplog.text
    text = path.read_text()
    for key in ("fx", "fy", "cx", "cy", "baseline_m"):
        text = "\n".join(line for line in text.splitlines() if not line.startswith(f"{key} ="))
    path.write_text(text)
    with open_source(path.parent) as source:
        shown, calib = source.describe()["calibration"], next(source.frames()).calibration
    pinhole = matching_pinhole(calib)
    assert (shown["fx"], shown["cx"], shown["cy"], shown["baseline_m"]) == (pinhole.fx, pinhole.cx, pinhole.cy,
                                                                          pinhole.baseline_m)
    assert shown["baseline_m"] == pytest.approx(0.3) and not shown["rectified"]
    path.write_text(text.replace("T = [-0.3, 0, 0]", "T = [0.3, 0, 0]"))
    with pytest.raises(CalibrationError, match="the right camera is not to the right of the left"):
        open_source(path.parent).describe()


def test_an_unknown_key_in_the_extrinsics_is_warned_about(tmp_path, caplog):
    test_calibration_toml_extrinsics_and_unrectified(tmp_path)  # writes a valid calibration.toml
    path = next(tmp_path.rglob("calibration.toml"))
    path.write_text(path.read_text().replace("[extrinsics]\n", "[extrinsics]\nheight_m = 1.5\n"))
    with open_source(path.parent) as source:
        assert next(source.frames()).extrinsics.translation[2] == 1.5
    assert "ignoring unknown keys in extrinsics: height_m (known: translation_m, rotation, quaternion_xyzw)" in caplog.text


def test_a_calibration_value_that_is_a_yaml_alias_bomb_is_named_in_one_short_line(tmp_path):
    """A YAML anchor that expands to 9⁹ items (2 GB printed in full) where a number belongs."""
    root = generic_folder(tmp_path, n=1, calib=YAML_BOMB + CALIB_YAML.replace("fx: 500.0", "fx: *i"))
    with pytest.raises(CalibrationError, match=r"calibration.yaml: fx must be a number, got \[\[\[\.\.\.\], ") as exc:
        next(open_source(root).frames())
    assert len(str(exc.value)) < 300


@pytest.mark.parametrize(
    "old, new, message",
    [
        ("fx: 500.0", "fx: 1" + "0" * 400, "fx must be a number, got 1000"),  # YAML reads an int too big for a float
        ("baseline_m: 0.3", "baseline_m: 0.3\nextrinsics: {translation_m: [0, 0, 1" + "0" * 400 + "], rotation: "
         "[[0, 0, 1], [-1, 0, 0], [0, -1, 0]]}", "'translation_m' must be a list of finite numbers"),
    ],
)
def test_numbers_too_big_for_a_float_are_named(tmp_path, old, new, message):
    root = generic_folder(tmp_path, n=1, calib=CALIB_YAML.replace(old, new))
    with pytest.raises(CalibrationError, match=message):
        next(open_source(root).frames())


def test_an_unknown_calibration_key_is_warned_about(tmp_path, caplog):
    root = generic_folder(tmp_path, n=1, calib=CALIB_YAML + "dofs: 2.5\n1: 2\n")  # doffs misspelt; a number as key
    frame = next(open_source(root).frames())
    assert frame.calibration.doffs == 0.0
    assert "calibration.yaml: ignoring unknown calibration keys: 1, dofs (known: width, height" in caplog.text
    (root / "calibration.yaml").write_text(CALIB_YAML.replace("fx: 500.0", "fx:"))  # a key without a value
    with pytest.raises(CalibrationError, match=r"calibration.yaml: missing calibration keys: fx$"):
        next(open_source(root).frames())


def kitti_stereo(root: Path, left="image_2", right="image_3", calib_dir="calib_cam_to_cam", names=("000000_10", "000000_11")):
    for i, name in enumerate(names):
        write(root / left / f"{name}.png", image(i))
        write(root / right / f"{name}.png", image(10 + i))
    (root / calib_dir).mkdir()
    keys = ("P_rect_02", "P_rect_03") if calib_dir == "calib_cam_to_cam" else ("P2", "P3")
    text = f"{keys[0]}: {KITTI_P2}\n{keys[1]}: {KITTI_P3}\n"
    if left == "image_0":
        text = f"P0: {KITTI_P2}\nP1: {KITTI_P3}\nP2: 1 0 0 0 0 1 0 0 0 0 1 0\nP3: 1 0 0 0 0 1 0 0 0 0 1 0\n"
    (root / calib_dir / f"{names[0].split('_')[0]}.txt").write_text(text)
    return root


@pytest.mark.parametrize(
    "layout",
    [
        {},  # stereo 2015
        {"calib_dir": "calib", "names": ("000007",)},  # object
        {"left": "colored_0", "right": "colored_1", "calib_dir": "calib"},  # stereo 2012 colour
        {"left": "image_0", "right": "image_1", "calib_dir": "calib"},  # stereo 2012 grey
    ],
)
def test_kitti_stereo_layouts(tmp_path, layout):
    root = kitti_stereo(tmp_path, **layout)
    assert source_class(root) is KittiStereoFolder
    frames = list(open_source(root).frames())
    assert len(frames) == len(layout.get("names", (1, 2)))
    np.testing.assert_array_equal(frames[0].left, image(0))
    calib = frames[0].calibration
    assert calib.fx == pytest.approx(721.5377) and calib.cx == pytest.approx(609.5593)
    assert calib.baseline_m == pytest.approx(KITTI_BASELINE) and (calib.width, calib.height) == (8, 6)


def test_kitti_raw_drive_with_timestamps_and_calibration_two_levels_up(tmp_path):
    drive = tmp_path / "2011_09_26" / "2011_09_26_drive_0001_sync"
    for i in range(3):
        write(drive / "image_02" / "data" / f"{i:010d}.png", image(i))
        write(drive / "image_03" / "data" / f"{i:010d}.png", image(5 + i))
    (drive / "image_02" / "timestamps.txt").write_text(
        "2011-09-26 13:02:25.964389445\n2011-09-26 13:02:26.074343666\n2011-09-26 13:02:26.184319344\n"
    )
    cx_right = "7.215377e+02 0 6.1e+02 -3.395242e+02 0 7.215377e+02 1.728540e+02 0 0 0 1 0"
    (tmp_path / "2011_09_26" / "calib_cam_to_cam.txt").write_text(
        f"calib_time: 09-Jan-2012 13:57:47\nS_rect_02: 8 6\nP_rect_02: {KITTI_P2}\nP_rect_03: {cx_right}\n"
    )
    source = open_source(drive)
    assert isinstance(source, KittiRawFolder)
    frames = list(source.frames(start_s=0.1))
    assert [f.index for f in frames] == [1, 2]
    assert frames[0].stamp_ns == 1317042146074343666  # 2011-09-26 13:02:26.074343666 UTC
    assert frames[0].calibration.cx_right == pytest.approx(610.0)


@pytest.mark.parametrize("size", ["8.5 6", "8 nan"])
def test_kitti_image_size_must_be_whole_pixels(tmp_path, size):
    path = tmp_path / "calib_cam_to_cam.txt"
    path.write_text(f"S_rect_02: {size}\nP_rect_02: {KITTI_P2}\nP_rect_03: {KITTI_P3}\n")
    from terrainmap.sources.calibration import kitti_calibration

    with pytest.raises(CalibrationError, match="S_rect_02 must be the image width and height in pixels"):
        kitti_calibration(path)


def test_kitti_odometry_sequence(tmp_path):
    for i in range(4):
        write(tmp_path / "image_2" / f"{i:06d}.png", image(i))
        write(tmp_path / "image_3" / f"{i:06d}.png", image(9 + i))
    (tmp_path / "calib.txt").write_text(f"P0: {KITTI_P2}\nP1: {KITTI_P3_GREY}\nP2: {KITTI_P2}\nP3: {KITTI_P3}\n")
    (tmp_path / "times.txt").write_text("0.0\n1.036e-01\n2.072e-01\n3.108e-01\n")
    source = open_source(tmp_path)
    assert isinstance(source, KittiOdometryFolder)
    frames = list(source.frames(every=2))
    assert [f.stamp_ns for f in frames] == [0, 207_200_000]
    assert frames[1].calibration.baseline_m == pytest.approx(KITTI_BASELINE)
    for bad in ("inf", "-5"):
        (tmp_path / "times.txt").write_text(f"0.0\n{bad}\n2.072e-01\n3.108e-01\n")
        with pytest.raises(InputError, match="times.txt: need one finite time of 0 or more seconds per line"):
            open_source(tmp_path)


def test_kitti_odometry_grey_cameras(tmp_path):
    """The grey download of a sequence: image_0/ image_1/ with P0/P1 (its baseline differs from P2/P3's)."""
    for i in range(2):
        write(tmp_path / "image_0" / f"{i:06d}.png", image(i)[:, :, 0])
        write(tmp_path / "image_1" / f"{i:06d}.png", image(5 + i)[:, :, 0])
    (tmp_path / "calib.txt").write_text(f"P0: {KITTI_P2}\nP1: {KITTI_P3_GREY}\nP2: {KITTI_P2}\nP3: {KITTI_P3}\n")
    source = open_source(tmp_path)
    assert isinstance(source, KittiOdometryFolder) and source.describe()["format"] == "kitti-odometry"
    frames = list(source.frames())
    assert len(frames) == 2 and frames[1].left.ndim == 2
    np.testing.assert_array_equal(frames[1].right, image(6)[:, :, 0])
    assert frames[0].calibration.baseline_m == pytest.approx(KITTI_BASELINE_GREY)


MIDDLEBURY_CALIB = """cam0=[1758.23 0 953.34; 0 1758.23 552.29; 0 0 1]
cam1=[1758.23 0 965.84; 0 1758.23 552.29; 0 0 1]
doffs=12.5
baseline=97.99
width=8
height=6
ndisp=290
"""


def test_middlebury_folder_of_scenes(tmp_path, caplog):
    for k, scene in enumerate(("Adirondack", "Jadeplant")):
        write(tmp_path / scene / "im0.png", image(k))
        write(tmp_path / scene / "im1.png", image(k + 3))
        (tmp_path / scene / "calib.txt").write_text(MIDDLEBURY_CALIB)
    assert source_class(tmp_path / "Adirondack") is MiddleburyFolder
    frames = list(open_source(tmp_path).frames())
    assert len(frames) == 2
    np.testing.assert_array_equal(frames[1].right, image(4))
    calib = frames[0].calibration
    assert calib.baseline_m == pytest.approx(0.09799) and calib.doffs == 12.5 and calib.fx == pytest.approx(1758.23)
    assert "cam1" not in caplog.text  # cam1 is cam0 moved by doffs, as in Middlebury's files
    (tmp_path / "Jadeplant" / "calib.txt").write_text(MIDDLEBURY_CALIB.replace("965.84", "1065.84"))
    list(open_source(tmp_path).frames())
    assert "Jadeplant/calib.txt: cam1 (fx 1758.23, cx 1065.84) is not cam0 shifted by doffs 12.5" in caplog.text
    (tmp_path / "Jadeplant" / "calib.txt").write_text(MIDDLEBURY_CALIB.replace("cam0=", "camera0="))
    with pytest.raises(CalibrationError, match="Jadeplant/calib.txt: Middlebury calibration lacks 'cam0'$"):
        list(open_source(tmp_path).frames())
    for old, new, message in [
        ("baseline=97.99", "baseline=0.09799", "baseline must be 1..100000 mm \\(Middlebury's unit\\), got 0.09799$"),
        ("doffs=12.5", "doffs=abc", "doffs must be a number of pixels, got 'abc'$"),
        ("cam0=[1758.23 0", "cam0=[1758.23", "cam0 must be a 3×3 matrix"),
        ("width=8", "width=8.5", "width must be a whole number of pixels, got '8.5'$"),
        ("doffs=12.5", "doffs=nan", "doffs must be a finite number of pixels, got nan$"),
    ]:
        caplog.clear()
        (tmp_path / "Jadeplant" / "calib.txt").write_text(MIDDLEBURY_CALIB.replace(old, new))
        with pytest.raises(CalibrationError, match=message):
            list(open_source(tmp_path).frames())
        assert "cam1" not in caplog.text  # one line: not a warning on the bad value before the error


def test_sixteen_bit_grey_images_are_scaled_together(tmp_path):
    root = generic_folder(tmp_path, n=1)
    left, right = image(1, (6, 8), np.uint16) // 4, image(2, (6, 8), np.uint16) // 2
    write(root / "left" / "000000.png", left)
    write(root / "right" / "000000.png", right)
    frame = next(open_source(root).frames())
    assert frame.left.dtype == np.uint8 and frame.left.shape == (6, 8)
    scale = 255.0 / max(left.max(), right.max())
    np.testing.assert_allclose(frame.left, np.round(left * scale), atol=1)
    np.testing.assert_allclose(frame.right, np.round(right * scale), atol=1)


def test_real_kitti_folder():
    if not KITTI.is_dir():
        pytest.skip("shared KITTI data not available")
    with open_source(KITTI) as source:
        frames = list(source.frames())
    assert len(frames) == 1 and frames[0].left.shape == (375, 1242, 3) and frames[0].right.shape == (375, 1242, 3)
    calib = frames[0].calibration
    assert calib.fx == pytest.approx(721.5377) and calib.cx == pytest.approx(609.5593)
    assert calib.cy == pytest.approx(172.854) and calib.baseline_m == pytest.approx(0.5327, abs=1e-4)
    assert calib.cx_right is None and frames[0].extrinsics is None


def test_calibration_override_replaces_the_folder_calibration(tmp_path):
    root = generic_folder(tmp_path / "run", n=1)
    other = tmp_path / "other.yaml"
    other.write_text(CALIB_YAML.replace("baseline_m: 0.3", "baseline_m: 0.12"))
    assert next(open_source(root, calibration=other).frames()).calibration.baseline_m == 0.12


def test_a_calibration_without_a_size_whose_principal_point_is_far_off_the_images_centre_is_warned_about(
    tmp_path, caplog
):
    """A KITTI calibration (no image size: cx = 609.6 px) given for 8×6 images: one warning for the
    run, naming the file; a principal point near the centre raises none."""
    root = generic_folder(tmp_path / "run", n=3)
    kitti = tmp_path / "calib.txt"
    kitti.write_text(f"P2: {KITTI_P2}\nP3: {KITTI_P3}\n")
    with open_source(root, calibration=kitti) as source:
        assert len(list(source.frames())) == 3
    assert caplog.messages == [f"{kitti}: the principal point (609.6, 172.9) lies far from the centre of the 8×6 "
                               "images it is used for; is the calibration for these images?"]
    caplog.clear()
    centred = tmp_path / "centred.txt"
    centred.write_text(f"P2: {KITTI_P2.replace('6.095593e+02', '4.1').replace('1.728540e+02', '2.9')}\n"
                       f"P3: {KITTI_P3.replace('6.095593e+02', '4.1').replace('1.728540e+02', '2.9')}\n")
    with open_source(root, calibration=centred) as source:
        list(source.frames())
    assert caplog.messages == []


def png_claiming(data: bytes, width: int, height: int) -> bytes:
    """The PNG ``data`` with its header (IHDR, CRC made good) claiming another size."""
    header = data[12:16] + struct.pack(">II", width, height) + data[24:29]  # type, size, depth ... interlace
    return data[:12] + header + struct.pack(">I", zlib.crc32(header)) + data[33:]


def broken_link(root: Path) -> None:
    (root / "left" / "000000.png").unlink()
    (root / "left" / "000000.png").symlink_to(root / "nowhere.png")


PNG = cv2.imencode(".png", image(0, (48, 64, 3)))[1].tobytes()
DAMAGED_PNGS = {
    "not an image": b"not a png",
    "empty": b"",
    "without its end (IEND)": PNG[:-30],
    "cut short, IEND kept": PNG[: len(PNG) // 2] + PNG[-12:],  # its data chunk runs past IEND
    "bytes changed in its image data": PNG[:100] + bytes(b ^ 0xFF for b in PNG[100:200]) + PNG[200:],  # libpng: "IDAT: invalid ..."
    "header claiming 30000² pixels": png_claiming(PNG, 30000, 30000),  # libpng would try to inflate 2.7 GB
    "header claiming 100000² pixels": png_claiming(PNG, 100000, 100000),  # beyond OpenCV's limit (cv2.error)
}


@pytest.mark.parametrize(
    "break_it, error, match",
    [
        (lambda r: (r / "calibration.yaml").unlink(), CalibrationError, "no calibration found"),
        (lambda r: (r / "calibration.yaml").write_text(CALIB_YAML.replace("0.3", "0.0")), CalibrationError, "baseline_m must be > 0"),
        (lambda r: (r / "calibration.yaml").write_text(CALIB_YAML.replace("500.0", "-1")), CalibrationError, "fx must be > 0"),
        (lambda r: (r / "calibration.yaml").write_text("width: 8\nfx: [1"), CalibrationError, "cannot parse"),
        (lambda r: (r / "calibration.yaml").write_text("width: 8\n"), CalibrationError, "missing calibration keys: height"),
        (lambda r: (r / "calibration.yaml").write_text(CALIB_YAML.replace("width: 8", "width: 9")), CalibrationError, "9×6"),
        (lambda r: write(r / "right" / "000000.png", image(0, (7, 8, 3))), InputError, "differ in size.*8×6.*8×7"),
        (lambda r: write(r / "right" / "000000.png", image(0, (6, 8), np.uint16)), InputError, "differ in bit depth"),
        (broken_link, InputError, "000000.png: cannot read the image file \\(No such file"),  # ends the run
        (lambda r: (r / "timestamps.txt").write_text("12\nabc\n"), InputError, "timestamps.txt"),
    ],
)
def test_bad_folders_raise_one_line_errors(tmp_path, capfd, break_it, error, match):
    root = generic_folder(tmp_path, n=1)
    break_it(root)
    with pytest.raises(error, match=match) as info:
        list(open_source(root).frames())
    assert "\n" not in str(info.value)
    assert capfd.readouterr().err == ""  # nothing from libpng on stderr either



@pytest.mark.parametrize("damage", DAMAGED_PNGS)
def test_a_pair_with_an_image_file_that_cannot_be_decoded_is_skipped(tmp_path, capfd, damage):
    root = generic_folder(tmp_path, n=3)
    bad = root / "left" / "000001.png"
    bad.write_bytes(DAMAGED_PNGS[damage])
    source = open_source(root)
    assert [frame.index for frame in source.frames()] == [0, 2]
    why = "cannot decode the image file (not an image, damaged or cut short)"
    if "claiming" in damage:  # said from its header, before any decoding
        side = damage.split()[2].rstrip("²")
        why = f"its header declares a {side}×{side} image, larger than terrainmap reads (16384 px a side, 67108864 pixels)"
    assert source.skipped() == [f"{root}: stereo pair 1 ({bad}: {why})"]
    with pytest.raises(DamagedImageError):  # the same from the decoder of log messages
        decode_compressed(DAMAGED_PNGS[damage], "/cam")
    assert "libpng" not in capfd.readouterr().err  # nothing from libpng on stderr


def test_a_folder_whose_first_image_is_damaged_is_described_by_the_next(tmp_path):
    root = generic_folder(tmp_path, n=3)
    (root / "left" / "000000.png").write_bytes(DAMAGED_PNGS["without its end (IEND)"])
    source = open_source(root)  # what info shows: the calibration checked against pair 1's image
    assert source.describe()["first_pair"] == ["000000.png", "000000.png"]
    assert [frame.index for frame in source.frames()] == [1, 2]


def test_a_folder_of_scenes_whose_first_image_is_damaged_is_described_by_the_next_scene(tmp_path):
    """Scenes of their own sizes and calibrations (Middlebury): the scene whose image describes
    the folder gives the calibration too, not the first scene's (which does not fit that image)."""
    for scene, shape in (("Adirondack", (6, 8, 3)), ("Jadeplant", (10, 12, 3))):
        write(tmp_path / scene / "im0.png", image(0, shape))
        write(tmp_path / scene / "im1.png", image(1, shape))
        calib = MIDDLEBURY_CALIB.replace("width=8", f"width={shape[1]}").replace("height=6", f"height={shape[0]}")
        (tmp_path / scene / "calib.txt").write_text(calib)
    (tmp_path / "Adirondack" / "im0.png").write_bytes(DAMAGED_PNGS["without its end (IEND)"])
    info = open_source(tmp_path).describe()
    assert (info["calibration"]["width"], info["calibration"]["height"]) == (12, 10)
    assert info["calibration"]["source"].endswith("Jadeplant/calib.txt")


@pytest.mark.parametrize("ext", [".png", ".jpg"])
def test_compressed_images_cut_short_are_refused_and_trailing_data_is_not(ext, capfd):
    data = cv2.imencode(ext, image(0, (48, 64, 3)))[1].tobytes()
    assert decode_compressed(data + bytes(300), "/cam").shape == (48, 64, 3)  # some cameras pad
    with pytest.raises(InputError, match="/cam: cannot decode the compressed image"):
        decode_compressed(data[: len(data) // 2], "/cam")
    assert capfd.readouterr().err == ""


def test_unknown_and_missing_paths(tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        open_source(tmp_path / "nope")
    (tmp_path / "stuff").mkdir()
    with pytest.raises(InputError, match="not a known stereo source"):
        open_source(tmp_path / "stuff")
    (tmp_path / "left").mkdir()
    (tmp_path / "right").mkdir()
    with pytest.raises(InputError, match=r"no left/right image pairs in it \(image files: \.png, .*, \.webp\)$"):
        open_source(tmp_path)


def test_topics_given_for_an_image_folder_are_an_error(tmp_path):
    root = generic_folder(tmp_path, n=1)
    with pytest.raises(ConfigError, match=r"left_topic/right_topic \(--left-topic/--right-topic\): .* is an image folder"):
        open_source(root, left_topic="/camera/left")


def test_a_kitti_folder_without_its_calibration_folder_takes_calibration(tmp_path):
    root = kitti_stereo(tmp_path)
    shutil.rmtree(root / "calib_cam_to_cam")
    with pytest.raises(CalibrationError, match="no calibration found .*or pass --calibration"):
        next(open_source(root).frames())
    (tmp_path / "calib.yaml").write_text(CALIB_YAML)
    frame = next(open_source(root, calibration=tmp_path / "calib.yaml").frames())
    assert frame.calibration.fx == 500.0


def test_a_colour_image_paired_with_a_mono_one_makes_a_mono_pair():
    from terrainmap.sources.images import stereo_pair

    colour = image(1, (6, 8, 3))
    left, right = stereo_pair(colour, image(2, (6, 8)), "left.png", "right.png")
    assert left.shape == right.shape == (6, 8) and left.dtype == right.dtype == np.uint8
    np.testing.assert_array_equal(left, cv2.cvtColor(colour, cv2.COLOR_RGB2GRAY))
    left16, right16 = stereo_pair(np.full((6, 8), 1000, np.uint16), np.full((6, 8), 2000, np.uint16), "l", "r")
    assert (left16.max(), right16.max()) == (128, 255)  # one scale for both: 255 / the pair's peak


def test_a_folder_named_like_an_image_is_not_an_image(tmp_path):
    root = generic_folder(tmp_path, n=2)
    (root / "left" / "000002.png").mkdir()
    (root / "right" / "000002.png").mkdir()
    with open_source(root) as source:
        assert len(list(source.frames())) == 2


def test_two_calibration_files_are_refused_unless_one_is_named(tmp_path):
    root = generic_folder(tmp_path, n=1)
    (root / "calibration.toml").write_text(CALIB_YAML.replace(": ", " = "))
    with pytest.raises(CalibrationError, match="calibration.yaml and calibration.toml are both there; keep one"):
        open_source(root)
    with open_source(root, calibration=root / "calibration.toml") as source:
        assert next(source.frames()).calibration.baseline_m == 0.3


def test_hidden_files_are_no_images(tmp_path):
    """macOS leaves ``._NAME.png`` resource forks beside images copied to a USB or network drive:
    they must not count as pairs (a right ``timestamps.txt`` would no longer fit the count)."""
    root = generic_folder(tmp_path, n=2)
    (root / "timestamps.txt").write_text("1000\n2000\n")
    for side in ("left", "right"):
        (root / side / "._000000.png").write_bytes(b"\x00\x05\x16\x07 not an image")
    with open_source(root) as source:
        assert [f.stamp_ns for f in source.frames()] == [1000, 2000]


def test_warnings_reach_the_terminal_as_one_plain_line_each(tmp_path):
    """The CLI shows a library warning as "warning: <what>", without the logger's module name
    (which ``-v`` adds)."""
    import subprocess
    import sys

    root = generic_folder(tmp_path, n=1, calib=CALIB_YAML + "dofs: 2.5\n")
    code = "from terrainmap.cli.main import main; main()"
    for flags, prefix in (([], "warning: "), (["-v"], "WARNING terrainmap.sources.calibration: ")):
        done = subprocess.run([sys.executable, "-c", code, *flags, "info", str(root)], capture_output=True, text=True,
                              timeout=120)
        assert done.returncode == 0, done.stderr
        (line,) = [line for line in done.stderr.splitlines() if "unknown calibration keys" in line]
        assert line.startswith(f"{prefix}{root / 'calibration.yaml'}: ignoring unknown calibration keys: dofs")


def test_a_window_that_starts_where_it_ends_selects_the_pair_stamped_there(tmp_path):
    """--start and --end are both inclusive: equal, they select the one pair at that time."""
    root = generic_folder(tmp_path, n=4)  # stamped 0, 0.1, 0.2, 0.3 s
    with open_source(root) as source:
        assert [f.index for f in source.frames(start_s=0.2, end_s=0.2)] == [2]
        with pytest.raises(ConfigError, match=r"end_s \(--end\) 0.1 s is before start_s \(--start\) 0.2 s"):
            list(source.frames(start_s=0.2, end_s=0.1))


def test_kitti_raw_calibration_two_levels_above_the_drive(tmp_path):
    """calib_cam_to_cam.txt is found in the drive folder or one or two folders up (here two)."""
    drive = tmp_path / "raw" / "2011_09_26" / "2011_09_26_drive_0001_sync"
    for i in range(2):
        write(drive / "image_02" / "data" / f"{i:010d}.png", image(i))
        write(drive / "image_03" / "data" / f"{i:010d}.png", image(5 + i))
    (tmp_path / "raw" / "calib_cam_to_cam.txt").write_text(f"S_rect_02: 8 6\nP_rect_02: {KITTI_P2}\nP_rect_03: {KITTI_P3}\n")
    with open_source(drive) as source:
        assert isinstance(source, KittiRawFolder)
        frame = next(source.frames())
    assert frame.calibration.baseline_m == pytest.approx(KITTI_BASELINE)


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs FIFOs")
def test_a_fifo_or_device_is_no_log(tmp_path):
    """Named as a log, a FIFO (whose reading would wait for a writer) or /dev/zero behind a link."""
    os.mkfifo(tmp_path / "fifo.mcap")
    (tmp_path / "zero.mcap").symlink_to("/dev/zero")
    for name in ("fifo.mcap", "zero.mcap"):
        with pytest.raises(InputError, match=r"neither a file nor a folder \(a device, FIFO or socket\)"):
            open_source(tmp_path / name)


@pytest.mark.parametrize("suffix", [".png", ".jpg"])
def test_an_image_declaring_more_pixels_than_terrainmap_reads_is_refused_before_decoding(tmp_path, suffix):
    """A header that claims 20000×20000 (400 MB grey once decoded, as a crafted or broken file may)
    is read first: damage naming the file and the size, and nothing allocated for it."""
    from terrainmap.sources.images import decode_compressed, read_image

    data = bytearray(cv2.imencode(suffix, np.zeros((6, 8), np.uint8))[1].tobytes())
    if suffix == ".png":
        struct.pack_into(">II", data, 16, 20000, 20000)
        struct.pack_into(">I", data, 29, zlib.crc32(bytes(data[12:29])))  # the IHDR's CRC
    else:
        sof = data.index(b"\xff\xc0")
        struct.pack_into(">HH", data, sof + 5, 20000, 20000)  # height, width
    path = tmp_path / f"big{suffix}"
    path.write_bytes(data)
    message = "its header declares a 20000×20000 image, larger than terrainmap reads (16384 px a side, 67108864 pixels)"
    with pytest.raises(DamagedImageError, match=f"^{re.escape(f'{path}: {message}')}$"):  # a folder skips the pair
        read_image(str(path))
    with pytest.raises(DamagedImageError, match=f"^/cam: {re.escape(message)}$"):
        decode_compressed(bytes(data), "/cam")
