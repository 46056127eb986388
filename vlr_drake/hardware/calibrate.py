"""Camera calibration helper: chessboard or ChArUco images -> an OpenCV YAML intrinsics file.

The real palm camera needs K and its distortion for the AprilTag pose (DESIGN.md section 5).
Photograph a printed target from 10-20 views (tilted by 20-45 degrees, covering the image),
then

    python -m vlr_drake.hardware.calibrate --pattern 9x6 --square 0.024 --out cam.yaml imgs/*.png
    python -m vlr_drake.hardware.calibrate --charuco 7x5 --square 0.03 --marker 0.022 --out cam.yaml imgs/*.png

``--pattern`` is the number of *inner* chessboard corners (columns x rows); ``--charuco`` the
number of squares. The result is written with :func:`vlr_drake.hardware.camera.write_intrinsics`
and read back by the hardware interface. :func:`render_planar_target` renders a planar target
seen by a known camera, so the calibration can be checked against a known K.
"""

from __future__ import annotations

import argparse
import logging
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from vlr_drake.entry import path_text
from vlr_drake.hardware.camera import CameraIntrinsics, write_intrinsics

__all__ = [
    "CalibrationResult",
    "calibrate_chessboard",
    "calibrate_charuco",
    "chessboard_image",
    "render_planar_target",
    "main",
]

log = logging.getLogger(__name__)


@dataclass
class CalibrationResult:
    """Intrinsics from a calibration, its RMS reprojection error and which images were used."""

    intrinsics: CameraIntrinsics
    # RMS reprojection error over all used corners [px].
    rms_px: float
    # For each input image, whether the target was found in it.
    used: list[bool]

    def save(self, path: str | Path) -> None:
        write_intrinsics(path, self.intrinsics, rms_px=self.rms_px)


def _gray(image) -> np.ndarray:
    import cv2

    if isinstance(image, str | Path):
        img = cv2.imread(str(image), cv2.IMREAD_GRAYSCALE)
        if img is None:
            raise FileNotFoundError(f"cannot read image '{image}'")
        return img
    img = np.asarray(image)
    if img.size == 0 or not (img.ndim == 2 or (img.ndim == 3 and img.shape[2] in (1, 3, 4))):
        raise ValueError(f"calibration images must be non-empty gray, BGR or BGRA images, got shape {img.shape}")
    if img.ndim == 3 and img.shape[2] == 1:
        img = img[:, :, 0]
    if img.ndim == 3:
        img = cv2.cvtColor(img, cv2.COLOR_BGR2GRAY if img.shape[2] == 3 else cv2.COLOR_BGRA2GRAY)
    if img.dtype != np.uint8:
        raise ValueError(f"calibration images must be uint8, got {img.dtype}")
    return img


#: The least angle between two of the calibration target's views [deg] (_calibrate).
MIN_VIEW_SPREAD_DEG = 10.0


def _calibrate(object_points, image_points, size, used, fix_aspect: bool) -> CalibrationResult:
    import cv2

    if len(object_points) < 3:
        raise ValueError(
            f"calibration needs the target in at least 3 images, found it in {len(object_points)} of {len(used)}"
        )
    flags = cv2.CALIB_FIX_ASPECT_RATIO if fix_aspect else 0
    K0 = np.eye(3)
    rms, K, dist, rvecs, _ = cv2.calibrateCamera(object_points, image_points, size, K0, None, flags=flags)
    # Views of one plane that are all parallel (the same view again, or turned about the
    # optical axis only) do not determine the focal length: a review's gave fx 14,000 and
    # 164,000 (true 610) at 0.013 px rms, which nothing refused.
    normals = np.array([cv2.Rodrigues(np.asarray(r, float))[0][:, 2] for r in rvecs])
    spread = float(np.rad2deg(np.arccos(np.clip(normals @ normals.T, -1.0, 1.0)).max()))
    if spread < MIN_VIEW_SPREAD_DEG:
        raise ValueError(
            f"calibration: the target's {len(rvecs)} views are (nearly) parallel (at most {spread:.1f} deg between "
            f"them): tilt it towards and away from the camera, views at least {MIN_VIEW_SPREAD_DEG:g} deg apart, "
            "or the focal length is not determined")
    intr = CameraIntrinsics(K=K, dist=dist.ravel(), width=int(size[0]), height=int(size[1])).validate()
    log.info(
        "calibrated from %d of %d images: rms %.3f px, fx %.2f fy %.2f",
        len(object_points),
        len(used),
        rms,
        K[0, 0],
        K[1, 1],
    )
    return CalibrationResult(intrinsics=intr, rms_px=float(rms), used=used)


def calibrate_chessboard(
    images: Iterable,
    pattern_size: tuple[int, int],
    square_size: float,
    fix_aspect: bool = False,
) -> CalibrationResult:
    """Intrinsics from chessboard images (arrays or file paths).

    ``pattern_size`` = (inner corners per row, inner corners per column); ``square_size`` [m]
    (only scales the extrinsics; K does not depend on it). Corners are found with
    ``cv2.findChessboardCornersSB`` (sub-pixel by construction); images without the full
    board are skipped and reported in ``used``.
    """
    import cv2

    cols, rows = (int(x) for x in pattern_size)
    if cols < 2 or rows < 2:
        raise ValueError(f"pattern_size must count at least 2 x 2 inner corners, got {pattern_size}")
    if not 0 < square_size < np.inf:  # (inf had ended in OpenCV's traceback: a review)
        raise ValueError(f"square_size must be positive and finite, got {square_size}")
    obj = np.zeros((rows * cols, 3), np.float32)
    obj[:, :2] = np.mgrid[0:cols, 0:rows].T.reshape(-1, 2) * square_size
    object_points, image_points, used, size = [], [], [], None
    for image in images:
        gray = _gray(image)
        if size is None:
            size = (gray.shape[1], gray.shape[0])
        elif size != (gray.shape[1], gray.shape[0]):
            raise ValueError(
                f"all calibration images must have one size: {size} vs {(gray.shape[1], gray.shape[0])}"
            )
        found, corners = cv2.findChessboardCornersSB(gray, (cols, rows), flags=cv2.CALIB_CB_ACCURACY)
        used.append(bool(found))
        if found:
            object_points.append(obj)
            image_points.append(corners.astype(np.float32))
    if size is None:
        raise ValueError("no calibration images given")
    return _calibrate(object_points, image_points, size, used, fix_aspect)


def calibrate_charuco(
    images: Iterable,
    squares: tuple[int, int],
    square_size: float,
    marker_size: float,
    dictionary: int | None = None,
    fix_aspect: bool = False,
) -> CalibrationResult:
    """Intrinsics from ChArUco board images (``squares`` = squares across x down; sizes [m];
    default dictionary DICT_5X5_100). Views with fewer than 6 ChArUco corners are skipped."""
    import cv2

    aruco = cv2.aruco
    cols, rows = (int(s) for s in squares)
    if cols < 2 or rows < 2 or (cols - 1) * (rows - 1) < 6:  # its inner corners; a view needs 6 of them
        raise ValueError(f"squares must give the board at least 6 inner corners (e.g. 3 x 4 ChArUco squares), "
                         f"got {squares}")
    if not 0 < square_size < np.inf:
        raise ValueError(f"square_size must be positive and finite, got {square_size}")
    if not 0 < marker_size < square_size:
        raise ValueError(f"marker_size must be positive and smaller than square_size ({square_size}), got {marker_size}")
    dictionary = aruco.DICT_5X5_100 if dictionary is None else dictionary
    board = aruco.CharucoBoard(
        tuple(int(s) for s in squares),
        float(square_size),
        float(marker_size),
        aruco.getPredefinedDictionary(dictionary),
    )
    detector = aruco.CharucoDetector(board)
    object_points, image_points, used, size = [], [], [], None
    for image in images:
        gray = _gray(image)
        if size is None:
            size = (gray.shape[1], gray.shape[0])
        elif size != (gray.shape[1], gray.shape[0]):
            raise ValueError(
                f"all calibration images must have one size: {size} vs {(gray.shape[1], gray.shape[0])}"
            )
        ch_corners, ch_ids, _, _ = detector.detectBoard(gray)
        ok = ch_ids is not None and len(ch_ids) >= 6
        if ok:
            obj, img = board.matchImagePoints(ch_corners, ch_ids)
            ok = obj is not None and len(obj) >= 6
        used.append(bool(ok))
        if ok:
            object_points.append(obj.astype(np.float32))
            image_points.append(img.astype(np.float32))
    if size is None:
        raise ValueError("no calibration images given")
    return _calibrate(object_points, image_points, size, used, fix_aspect)


def chessboard_image(pattern_size: tuple[int, int], square_px: int = 40) -> np.ndarray:
    """A printable chessboard (uint8) with ``pattern_size`` inner corners and a one-square
    white margin. Inner corner (i, j) sits at texture coordinates
    ((i + 2) * square_px - 0.5, (j + 2) * square_px - 0.5) (OpenCV pixel centres)."""
    cols, rows = pattern_size
    nx, ny = cols + 1, rows + 1
    board = ((np.indices((ny, nx)).sum(axis=0) % 2) * 255).astype(np.uint8)
    board = np.kron(board, np.ones((square_px, square_px), np.uint8))
    return np.pad(board, square_px, constant_values=255)


def render_planar_target(
    texture: np.ndarray,
    metres_per_pixel: float,
    K: np.ndarray,
    R_CT: np.ndarray,
    p_CT: np.ndarray,
    size: tuple[int, int],
    supersample: int = 3,
    background: int = 128,
) -> np.ndarray:
    """Image (uint8, ``size`` = (width, height)) of a planar texture seen by a pinhole camera.

    The target frame T has its origin at the texture centre, x to the right and y up in the
    texture, z out of its face (the tag convention of ``vlr_drake.perception.apriltag``);
    (R_CT, p_CT) is its pose in the camera frame C (+z forward, OpenCV). Pixels follow
    OpenCV's integer-centred convention. The texture is mapped by the plane's homography
    H = K [r1 r2 p] A, rendered ``supersample`` times larger and averaged down (INTER_AREA).
    """
    import cv2

    h_t, w_t = texture.shape[:2]
    s = float(metres_per_pixel)
    # texture pixel (u, v) -> target plane (x, y): pixel centres at integers, y up.
    A = np.array([[s, 0.0, s * (0.5 - w_t / 2.0)], [0.0, -s, -s * (0.5 - h_t / 2.0)], [0.0, 0.0, 1.0]])
    R = np.asarray(R_CT, float)
    H = np.asarray(K, float) @ np.column_stack([R[:, 0], R[:, 1], np.asarray(p_CT, float)]) @ A
    f = int(supersample)
    S = np.array([[f, 0.0, (f - 1) / 2.0], [0.0, f, (f - 1) / 2.0], [0.0, 0.0, 1.0]])
    big = cv2.warpPerspective(
        texture,
        S @ H,
        (size[0] * f, size[1] * f),
        flags=cv2.INTER_LINEAR,
        borderMode=cv2.BORDER_CONSTANT,
        borderValue=background,
    )
    return cv2.resize(big, size, interpolation=cv2.INTER_AREA) if f > 1 else big


def _pair(text: str) -> tuple[int, int]:
    """``9x6`` as (9, 6); otherwise an error argparse prints after the flag's name (it had
    printed "invalid _pair value: '9by6'")."""
    try:
        a, b = text.lower().split("x")
        return int(a), int(b)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected two counts as COLSxROWS, e.g. 9x6, got '{text}'") from None


def main(argv: Sequence[str] | None = None) -> int:
    """Command line: images -> intrinsics YAML (see the module docstring)."""
    p = argparse.ArgumentParser(
        prog="python -m vlr_drake.hardware.calibrate", description=__doc__.split("\n")[0]
    )
    g = p.add_mutually_exclusive_group(required=True)
    g.add_argument("--pattern", type=_pair, help="chessboard inner corners, e.g. 9x6")
    g.add_argument("--charuco", type=_pair, help="ChArUco squares, e.g. 7x5")
    p.add_argument("--square", type=float, required=True, help="square side [m]")
    p.add_argument("--marker", type=float, help="ChArUco marker side [m]")
    p.add_argument("--fix-aspect", action="store_true", help="fix fx = fy")
    p.add_argument("--out", type=path_text, required=True, help="output OpenCV YAML file")
    p.add_argument("images", nargs="+")
    a = p.parse_args(argv)
    from vlr_drake.entry import check_output

    check_output("--out", a.out)  # before the calibration, not after it
    if a.charuco:
        if a.marker is None:
            p.error("--charuco needs --marker")
        res = calibrate_charuco(a.images, a.charuco, a.square, a.marker, fix_aspect=a.fix_aspect)
    else:
        res = calibrate_chessboard(a.images, a.pattern, a.square, fix_aspect=a.fix_aspect)
    res.save(a.out)
    K = res.intrinsics.K
    print(
        f"{sum(res.used)} of {len(res.used)} images used, rms {res.rms_px:.3f} px, fx {K[0, 0]:.2f} fy {K[1, 1]:.2f} cx {K[0, 2]:.2f} cy {K[1, 2]:.2f} -> {a.out}"
    )
    return 0


if __name__ == "__main__":
    from vlr_drake.entry import run

    raise SystemExit(run("python -m vlr_drake.hardware.calibrate", main, hardware=True))
