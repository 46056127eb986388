"""Camera calibration helper: synthetic views of targets rendered with a known K."""

from __future__ import annotations

import numpy as np
import pytest
from pydrake.math import RollPitchYaw

from vlr_drake.hardware.calibrate import (
    calibrate_charuco,
    calibrate_chessboard,
    chessboard_image,
    main,
    render_planar_target,
)
from vlr_drake.hardware.camera import read_intrinsics

K_TRUE = np.array([[610.0, 0.0, 322.5], [0.0, 604.0, 236.0], [0.0, 0.0, 1.0]])
SIZE = (640, 480)
# Target frame T faces the camera: x_T = x_C, y_T = -y_C, z_T = -z_C.
R_FACING = np.diag([1.0, -1.0, -1.0])


def random_views(texture, metres_per_pixel, rng, n, distance=(0.45, 0.6)):
    views = []
    for _ in range(n):
        rpy = np.deg2rad([rng.uniform(-35, 35), rng.uniform(-35, 35), rng.uniform(-20, 20)])
        R = R_FACING @ RollPitchYaw(*rpy).ToRotationMatrix().matrix()
        p = np.array([rng.uniform(-0.04, 0.04), rng.uniform(-0.03, 0.03), rng.uniform(*distance)])
        views.append(render_planar_target(texture, metres_per_pixel, K_TRUE, R, p, SIZE))
    return views


def test_render_planar_target_projects_with_K():
    """A single dark pixel at the texture centre lands at the principal point when the
    target is square-on at the optical axis."""
    tex = np.full((101, 101), 255, np.uint8)
    tex[50, 50] = 0
    img = render_planar_target(tex, 0.0005, K_TRUE, R_FACING, np.array([0.0, 0.0, 0.3]), SIZE, supersample=1)
    v, u = np.unravel_index(np.argmin(img), img.shape)
    assert (u, v) == (round(K_TRUE[0, 2]), round(K_TRUE[1, 2]))


def test_chessboard_calibration_recovers_focal_length(rng, tmp_path):
    pattern, square = (9, 6), 0.025
    tex = chessboard_image(pattern, square_px=40)
    views = random_views(tex, square / 40, rng, n=10)
    res = calibrate_chessboard(views, pattern, square)
    assert all(res.used)
    K = res.intrinsics.K
    assert abs(K[0, 0] / K_TRUE[0, 0] - 1) < 0.01
    assert abs(K[1, 1] / K_TRUE[1, 1] - 1) < 0.01
    assert np.allclose(K[:2, 2], K_TRUE[:2, 2], atol=2.0)
    assert res.rms_px < 0.3
    assert (res.intrinsics.width, res.intrinsics.height) == SIZE
    # round trip through the OpenCV YAML file
    res.save(tmp_path / "cam.yaml")
    back = read_intrinsics(tmp_path / "cam.yaml")
    assert np.allclose(back.K, K) and np.allclose(back.dist, res.intrinsics.dist)


ROS_CALIBRATION = """image_width: 640
image_height: 480
camera_name: palm
camera_matrix:
  rows: 3
  cols: 3
  data: [500.0, 0.0, 319.5, 0.0, 501.0, 239.5, 0.0, 0.0, 1.0]
distortion_model: plumb_bob
distortion_coefficients:
  rows: 1
  cols: 5
  data: [-0.1, 0.01, 0.0, 0.0, 0.0]
"""


def test_a_ros_calibration_file_is_read_and_a_bad_one_named(tmp_path):
    """ROS's camera_calibration writes the same node names with plain rows, cols and data: it
    is read. It, an empty file and a malformed one had ended in OpenCV's tracebacks (a review)."""
    from vlr_drake.hardware.camera import CameraError

    (tmp_path / "ros.yaml").write_text(ROS_CALIBRATION)
    intr = read_intrinsics(tmp_path / "ros.yaml")
    np.testing.assert_array_equal(intr.K, [[500.0, 0.0, 319.5], [0.0, 501.0, 239.5], [0.0, 0.0, 1.0]])
    np.testing.assert_array_equal(intr.dist, [-0.1, 0.01, 0.0, 0.0, 0.0])
    assert (intr.width, intr.height) == (640, 480)
    for name, text, said in (("empty", "", "cannot parse camera calibration file"),
                             ("broken", "camera_matrix: [1, 2\n", "cannot parse camera calibration file"),
                             ("lists", "image_width: 640\nimage_height: 480\ncamera_matrix: [[500, 0, 320], [0, 500, "
                              "240], [0, 0, 1]]\ndistortion_coefficients: [0, 0, 0, 0, 0]\n", "must be matrices")):
        (tmp_path / f"{name}.yaml").write_text(text)
        with pytest.raises(CameraError, match=said):
            read_intrinsics(tmp_path / f"{name}.yaml")


def test_images_without_the_board_are_skipped(rng):
    pattern, square = (9, 6), 0.025
    tex = chessboard_image(pattern, square_px=40)
    views = random_views(tex, square / 40, rng, n=4)
    blank = np.full(SIZE[::-1], 128, np.uint8)
    res = calibrate_chessboard([views[0], blank, *views[1:]], pattern, square)
    assert res.used == [True, False, True, True, True]
    with pytest.raises(ValueError, match="at least 3 images"):
        calibrate_chessboard([blank, blank, views[0]], pattern, square)


def test_charuco_calibration(rng):
    import cv2

    squares, square, marker = (7, 5), 0.04, 0.03
    board = cv2.aruco.CharucoBoard(
        squares, square, marker, cv2.aruco.getPredefinedDictionary(cv2.aruco.DICT_5X5_100)
    )
    px = 60
    tex = board.generateImage((squares[0] * px, squares[1] * px), marginSize=0, borderBits=1)
    tex = np.pad(tex, px // 2, constant_values=255)
    views = random_views(tex, square / px, rng, n=8, distance=(0.5, 0.65))
    res = calibrate_charuco(views, squares, square, marker)
    assert sum(res.used) >= 6
    assert abs(res.intrinsics.K[0, 0] / K_TRUE[0, 0] - 1) < 0.01


def test_command_line_writes_intrinsics(rng, tmp_path):
    import cv2

    pattern, square = (9, 6), 0.025
    tex = chessboard_image(pattern, square_px=40)
    files = []
    for k, img in enumerate(random_views(tex, square / 40, rng, n=6)):
        files.append(str(tmp_path / f"view{k}.png"))
        cv2.imwrite(files[-1], img)
    out = tmp_path / "intrinsics.yaml"
    assert main(["--pattern", "9x6", "--square", "0.025", "--fix-aspect", "--out", str(out), *files]) == 0
    intr = read_intrinsics(out)
    assert abs(intr.K[0, 0] / K_TRUE[0, 0] - 1) < 0.02
    assert intr.K[0, 0] == pytest.approx(intr.K[1, 1])  # --fix-aspect


def test_bad_targets_and_images_are_named():
    """ChArUco sizes OpenCV refuses raised its SystemError; images of other sizes went into
    one ChArUco calibration; an empty, 1-D or 2-channel image failed inside OpenCV."""
    blank = np.full(SIZE[::-1], 128, np.uint8)
    for squares, square, marker, field in [((7, 5), 0.0, 0.02, "square_size"), ((7, 5), 0.03, 0.04, "marker_size"),
                                           ((1, 1), 0.03, 0.02, "squares"), ((2, 2), 0.03, 0.02, "squares")]:
        with pytest.raises(ValueError, match=field):
            calibrate_charuco([blank], squares, square, marker)
    with pytest.raises(ValueError, match="square_size must be positive and finite, got nan"):  # was accepted
        calibrate_chessboard([blank], (9, 6), float("nan"))
    for calibrate in (lambda: calibrate_chessboard([blank], (9, 6), float("inf")),  # (OpenCV's traceback)
                      lambda: calibrate_charuco([blank], (7, 5), float("inf"), 0.02)):
        with pytest.raises(ValueError, match="square_size must be positive and finite, got inf"):
            calibrate()
    with pytest.raises(ValueError, match="all calibration images must have one size"):
        calibrate_charuco([blank, blank[:240, :320]], (7, 5), 0.03, 0.02)
    for image in (np.zeros((0, 0), np.uint8), np.zeros(10, np.uint8), np.zeros((10, 10, 2), np.uint8)):
        with pytest.raises(ValueError, match="calibration images must be"):
            calibrate_chessboard([image], (9, 6), 0.025)


def test_an_unwritable_out_is_refused_before_the_calibration(tmp_path):
    """``--out`` a folder, or under a missing parent that cannot be made, is refused before
    any image is read (it had been found only after the calibration, whose work was lost,
    with an OSError traceback); saving to a folder names the file."""
    from vlr_drake.hardware.camera import CameraIntrinsics, write_intrinsics

    missing = tmp_path / "none.png"  # never read: the check comes first
    with pytest.raises(ValueError, match="--out: .* is a folder"):
        main(["--pattern", "9x6", "--square", "0.024", "--out", str(tmp_path), str(missing)])
    blocked = tmp_path / "a_file"
    blocked.write_text("")
    with pytest.raises(ValueError, match="--out"):
        main(["--pattern", "9x6", "--square", "0.024", "--out", str(blocked / "cam.yaml"), str(missing)])
    intr = CameraIntrinsics(width=SIZE[0], height=SIZE[1], K=K_TRUE.tolist(), dist=[0.0] * 5)
    with pytest.raises(ValueError, match="cannot write intrinsics file"):
        write_intrinsics(tmp_path, intr)


def test_views_that_do_not_determine_the_focal_length_are_refused(rng):
    """One view repeated, or views turned about the optical axis only, had given fx 14,000
    and 164,000 (true 610) at 0.013 px rms, written as the camera's calibration; and a
    principal point outside the image passed the intrinsics' check."""
    from vlr_drake.hardware.camera import CameraIntrinsics

    tex = chessboard_image((9, 6), 40)
    square_on = render_planar_target(tex, 0.025 / 40, K_TRUE, R_FACING, np.array([0.0, 0.0, 0.5]), SIZE)
    turned = [render_planar_target(tex, 0.025 / 40, K_TRUE, R_FACING @ RollPitchYaw(0.0, 0.0, a).ToRotationMatrix()
                                   .matrix(), np.array([0.0, 0.0, 0.5]), SIZE) for a in (-0.3, -0.1, 0.1, 0.3)]
    for views in ([square_on] * 5, turned):
        with pytest.raises(ValueError, match=r"views are \(nearly\) parallel \(at most \d+\.\d deg between them\)"):
            calibrate_chessboard(views, (9, 6), 0.025)
    K = K_TRUE.copy()
    K[1, 2] = -33.5
    with pytest.raises(ValueError, match=r"principal point \(322.5, -33.5\) px lies outside the 640 x 480 image"):
        CameraIntrinsics(K=K, dist=np.zeros(5), width=640, height=480).validate()


def test_a_bad_board_size_is_named(capsys):
    """--pattern 9by6 had ended in "argument --pattern: invalid _pair value: '9by6'"."""
    for text in ("9by6", "9x", "9x6x2"):
        with pytest.raises(SystemExit) as info:
            main(["--pattern", text, "--square", "0.024", "--out", "cam.yaml", "a.png"])
        assert info.value.code == 2
        err = capsys.readouterr().err
        assert f"argument --pattern: expected two counts as COLSxROWS, e.g. 9x6, got '{text}'" in err
        assert "_pair" not in err
