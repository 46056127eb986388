"""AprilTag pose estimation: image in, POM pose out (DESIGN sections 5 and 8).

Pure functions, no Drake systems (the LeafSystem wrapper is
``vlr_drake.systems.tag_observer.TagObserver``):

- :func:`make_detector` / :func:`detect_tag`: OpenCV's aruco ``ArucoDetector`` for tag36h11,
  corner refinement APRILTAG by default (configurable).
- :func:`refine_corners_edges`: sub-pixel corners from the tag's four outer edges (on by
  default in :class:`TagObserverConfig`).
- :func:`estimate_tag_pose`: ``cv2.solvePnPGeneric`` with ``SOLVEPNP_IPPE_SQUARE`` (two
  candidate poses) plus SQPnP, keeping the candidate with the lowest reprojection error
  among those whose tag faces the camera (IPPE_SQUARE alone can return a flipped pose).
- :func:`observe_pom`: the measured POM pose X_PO = X_PC X_CT X_TO (DESIGN section 5).
- :func:`vtk_render_intrinsics`: K of an image rendered by Drake's VTK engine.

Frames (monogram notation): P palm, C camera (+z optical axis, +x right, +y down in the
image; OpenCV's and Drake's convention), T tag (``vlr_drake.perception.apriltag``: origin
at the tag centre, x right and y up in the tag image, z out of the printed face), O the POM
frame (the tag frame offset by a known X_TO).

Pixel convention: OpenCV's, integer pixel centres (``CameraConfig.intrinsic_matrix()`` and
Drake's ``CameraInfo`` put the principal point at c = size / 2 - 0.5 there). Measured here
(opencv 5.0, exact synthetic images, tests/test_tag_pose.py):
- APRILTAG-refined corners sit +0.43 px (x and y) off that convention, SUBPIX corners
  0.00 px; :func:`detect_tag` removes the APRILTAG offset (``APRILTAG_CORNER_OFFSET_PX``).
- Drake 1.51's RenderEngineVtk draws its images shifted by -0.5 rendered px in x and y
  from ``CameraInfo``'s principal point (-0.5 / render_scale px after downsampling). The
  two together are why DESIGN section 8 saw "no bias" with APRILTAG at 1x rendering.
  :func:`vtk_render_intrinsics` puts the renderer's shift into K.
- The aruco refinements quantise edges that are aligned with the pixel grid: on rendered,
  near-frontal, axis-aligned tags APRILTAG gave 0.26 deg mean rotation error (0.03-0.08 deg
  once turned a few degrees). The edge refinement gives 0.04 deg there, 0.006 deg mean on
  random views (tests/test_tag_observer.py reports the numbers).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import cv2
import numpy as np

from vlr_drake.kinematics import is_number
from vlr_drake.perception.apriltag import check_tag_id, dictionary, tag_corners

#: Corner refinement methods by name (``TagObserverConfig.corner_refinement``).
CORNER_REFINEMENTS = {
    "none": cv2.aruco.CORNER_REFINE_NONE,
    "subpix": cv2.aruco.CORNER_REFINE_SUBPIX,
    "contour": cv2.aruco.CORNER_REFINE_CONTOUR,
    "apriltag": cv2.aruco.CORNER_REFINE_APRILTAG,
}

#: Measured shift of CORNER_REFINE_APRILTAG corners from OpenCV's integer-centred pixel
#: convention [px] (both axes, sd 0.04-0.07 px over 30 synthetic views; tests/test_tag_pose.py).
APRILTAG_CORNER_OFFSET_PX = 0.43


@dataclass
class TagObserverConfig:
    """What the observer looks for and when it trusts a detection."""

    # Id of the object's tag in the tag36h11 family.
    tag_id: int = 0
    # Side of the tag's black square [m] (not counting the white quiet zone).
    tag_size: float = 0.03
    # The aruco detector's corner refinement: "apriltag" (default; its measured +0.43 px
    # offset is removed), "subpix", "contour" or "none".
    corner_refinement: str = "apriltag"
    # Refine the detector's corners from the four outer edges (refine_corners_edges).
    edge_refinement: bool = True
    # With edge_refinement, a frame whose edges cannot be measured (an edge covered or
    # blurred) is rejected ("edge_refinement_failed"); False falls back to the detector's
    # corners. On partly covered synthetic tags that fallback gave valid poses up to 6.6 deg
    # off within the reprojection limit, the refined ones 0.02 deg (docs/results.md).
    require_edge_refinement: bool = True
    # Added to detected corners [px]; None: undo the refinement's measured offset
    # (-APRILTAG_CORNER_OFFSET_PX for "apriltag", 0 otherwise).
    corner_offset_px: float | None = None
    # A detection whose RMS reprojection error exceeds this [px] is rejected (invalid frame).
    max_reprojection_error_px: float = 2.0
    # A detection whose tag side is shorter than this in the image [px] is rejected.
    min_tag_side_px: float = 8.0
    # Refine the IPPE_SQUARE pose with Levenberg-Marquardt on the reprojection error.
    refine_lm: bool = True
    # Extra aruco DetectorParameters attributes by name (e.g. {"aprilTagQuadDecimate": 1.0}).
    detector_overrides: dict[str, float] = field(default_factory=dict)

    def validate(self) -> TagObserverConfig:
        check_tag_id(self.tag_id)
        if not (np.isfinite(self.tag_size) and self.tag_size > 0):
            raise ValueError(f"tag observer: 'tag_size' must be a finite number > 0 [m], got {self.tag_size}")
        if self.corner_refinement not in CORNER_REFINEMENTS:
            raise ValueError(
                f"tag observer: 'corner_refinement' must be one of {sorted(CORNER_REFINEMENTS)}, "
                f"got {self.corner_refinement!r}"
            )
        if not self.max_reprojection_error_px > 0:
            raise ValueError(
                f"tag observer: 'max_reprojection_error_px' must be > 0, got {self.max_reprojection_error_px}"
            )
        if not (np.isfinite(self.min_tag_side_px) and self.min_tag_side_px >= 0):
            raise ValueError(f"tag observer: 'min_tag_side_px' must be a finite number >= 0, got {self.min_tag_side_px}")
        if self.corner_offset_px is not None and not np.isfinite(self.corner_offset_px):
            raise ValueError(f"tag observer: 'corner_offset_px' must be None or finite [px], got {self.corner_offset_px}")
        return self


def make_detector(
    corner_refinement: str = "apriltag", overrides: dict[str, float] | None = None
) -> cv2.aruco.ArucoDetector:
    """An aruco detector for tag36h11 with the named corner refinement."""
    if corner_refinement not in CORNER_REFINEMENTS:
        raise ValueError(
            f"'corner_refinement' must be one of {sorted(CORNER_REFINEMENTS)}, got {corner_refinement!r}"
        )
    params = cv2.aruco.DetectorParameters()
    params.cornerRefinementMethod = CORNER_REFINEMENTS[corner_refinement]
    for name, value in (overrides or {}).items():
        if not hasattr(params, name):
            raise ValueError(f"'detector_overrides': aruco DetectorParameters has no field {name!r}")
        kind = type(getattr(params, name))
        try:
            number = float(value)
        except (TypeError, ValueError):
            number = float("nan")
        if not np.isfinite(number) or (kind is int and number != int(number)):
            what = "an integer" if kind is int else "a finite number"
            raise ValueError(f"'detector_overrides': {name!r} must be {what}, got {value!r}")
        setattr(params, name, kind(number) if kind is not bool else bool(number))
    return cv2.aruco.ArucoDetector(dictionary(), params)


def to_gray(image: np.ndarray) -> np.ndarray:
    """Grayscale uint8 view of an RGB (H, W, 3), RGBA (H, W, 4) or gray (H, W) / (H, W, 1)
    uint8 image. Raises ValueError naming the shape or dtype otherwise."""
    image = np.asarray(image)
    if image.dtype != np.uint8:
        raise ValueError(f"image: dtype must be uint8, got {image.dtype}")
    if image.ndim in (2, 3) and min(image.shape[:2]) < 2:  # (before OpenCV, which asserts on an empty one)
        raise ValueError(f"image: too small, shape {image.shape}")
    if image.ndim == 2:
        gray = image
    elif image.ndim == 3 and image.shape[2] == 1:
        gray = image[:, :, 0]
    elif image.ndim == 3 and image.shape[2] == 3:
        gray = cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGB2GRAY)
    elif image.ndim == 3 and image.shape[2] == 4:
        gray = cv2.cvtColor(np.ascontiguousarray(image), cv2.COLOR_RGBA2GRAY)
    else:
        raise ValueError(f"image: shape must be (H, W), (H, W, 1), (H, W, 3) or (H, W, 4), got {image.shape}")
    return np.ascontiguousarray(gray)


def default_corner_offset(detector: cv2.aruco.ArucoDetector) -> float:
    """Offset [px] that brings this detector's corners to OpenCV's pixel convention."""
    method = detector.getDetectorParameters().cornerRefinementMethod
    return -APRILTAG_CORNER_OFFSET_PX if method == cv2.aruco.CORNER_REFINE_APRILTAG else 0.0


def detect_tag(
    image: np.ndarray,
    tag_id: int,
    detector: cv2.aruco.ArucoDetector | None = None,
    corner_offset_px: float | None = None,
) -> np.ndarray | None:
    """Corners (4 x 2, OpenCV pixel coordinates, order top-left, top-right, bottom-right,
    bottom-left of the tag image, matching ``tag_corners``) of the tag ``tag_id``, or None
    when it is not found. If the id is seen more than once, None (ambiguous:
    :func:`detect_tag_all` returns every sighting).

    ``corner_offset_px`` is added to both coordinates; None uses
    :func:`default_corner_offset` (removes APRILTAG refinement's +0.43 px)."""
    hits = detect_tag_all(image, tag_id, detector, corner_offset_px)
    return hits[0] if len(hits) == 1 else None


def detect_tag_all(
    image: np.ndarray,
    tag_id: int,
    detector: cv2.aruco.ArucoDetector | None = None,
    corner_offset_px: float | None = None,
) -> list[np.ndarray]:
    """Every sighting of the tag ``tag_id`` in ``image``: a list of 4 x 2 corner arrays as
    :func:`detect_tag` returns one (empty when it is not seen; two or more when the id is
    seen twice, e.g. a second printed tag or a reflection)."""
    check_tag_id(tag_id)
    gray = to_gray(image)
    if detector is None:
        detector = make_detector()
    if corner_offset_px is None:
        corner_offset_px = default_corner_offset(detector)
    corners, ids, _ = detector.detectMarkers(gray)
    if ids is None:
        return []
    return [np.asarray(c, dtype=np.float64).reshape(4, 2) + float(corner_offset_px)
            for c, i in zip(corners, np.asarray(ids).ravel(), strict=True) if int(i) == int(tag_id)]


def _line_intersection(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Intersection of two lines given as (point, unit direction) rows of 2 x 2 arrays."""
    (p, d), (q, e) = a, b
    A = np.column_stack([d, -e])
    t = np.linalg.solve(A, q - p)
    return p + t[0] * d


def refine_corners_edges(
    image: np.ndarray,
    corners: np.ndarray,
    K: np.ndarray | None = None,
    dist: np.ndarray | None = None,
    half_width_px: float = 3.0,
) -> np.ndarray | None:
    """Sub-pixel corners from the four outer edges of the tag's black square.

    Along each edge (the middle 70 %, one sample per pixel), the intensity profile across
    the edge is read with bilinear interpolation over +-w px (w = ``half_width_px``, at most
    0.4 of a tag cell, so it stays in the black border and the white quiet zone). With f the
    profile normalised from the black level (0) to the white level (1), the edge lies at
    s_e = w - integral_{-w}^{w} f(s) ds from the sample point along the outward normal:
    exact for a step blurred by any symmetric kernel, and free of the pixel-grid
    quantisation that the aruco refinements show on edges aligned with the image axes
    (measured here: APRILTAG refinement 0.26 deg mean rotation error on axis-aligned
    near-frontal tags, against 0.03-0.08 deg when turned a few degrees). A line is fitted
    to each edge's points (total least squares, outliers beyond 3 median deviations
    dropped: occlusion) and the corners are the intersections of adjacent lines. With
    ``dist`` the lines are fitted in undistorted pixel coordinates and the corners mapped
    back. Coordinates follow OpenCV's convention (integer pixel centres).

    Returns the refined corners (4 x 2) or None when an edge has too few good samples.
    """
    gray = to_gray(image).astype(np.float32)
    corners = np.asarray(corners, dtype=np.float64).reshape(4, 2)
    use_dist = dist is not None and bool(np.any(np.asarray(dist) != 0))
    if use_dist:
        if K is None:
            raise ValueError("K: needed to undistort the edges when dist is given")
        K, dist = _check_intrinsics(K, dist)
    centre = corners.mean(axis=0)
    side = float(np.min(np.linalg.norm(corners - np.roll(corners, -1, axis=0), axis=1)))
    w = min(half_width_px, 0.4 * side / 8.0)
    if w < 0.75:
        return None
    offsets = np.arange(-w, w + 1e-9, 0.25)
    lines = []
    for k in range(4):
        a, b = corners[k], corners[(k + 1) % 4]
        length = float(np.linalg.norm(b - a))
        d = (b - a) / length
        n = np.array([-d[1], d[0]])
        if n @ (0.5 * (a + b) - centre) < 0:
            n = -n  # outward: from the black square towards the white quiet zone
        t = np.linspace(0.15, 0.85, max(8, int(0.7 * length)))
        base = a + t[:, None] * (b - a)
        samples = base[:, None, :] + offsets[None, :, None] * n[None, None, :]
        map_x = samples[..., 0].astype(np.float32)
        map_y = samples[..., 1].astype(np.float32)
        profile = cv2.remap(gray, map_x, map_y, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE).astype(
            float
        )
        black = profile[:, :2].mean(axis=1)
        white = profile[:, -2:].mean(axis=1)
        contrast = white - black
        good = contrast > 0.25 * max(float(np.median(contrast)), 1e-6)
        if np.count_nonzero(good) < 5:
            return None
        f = np.clip((profile[good] - black[good, None]) / contrast[good, None], 0.0, 1.0)
        # Trapezoid integral over [-w, w] of the normalised profile.
        area = np.sum(0.5 * (f[:, 1:] + f[:, :-1]), axis=1) * 0.25
        s_edge = offsets[-1] - area
        points = base[good] + s_edge[:, None] * n
        if use_dist:
            points = cv2.undistortPoints(points.reshape(-1, 1, 2), K, dist, P=K).reshape(-1, 2)
        for _ in range(2):
            mean = points.mean(axis=0)
            direction = np.linalg.svd(points - mean, full_matrices=False)[2][0]
            normal = np.array([-direction[1], direction[0]])
            residual = (points - mean) @ normal
            mad = float(np.median(np.abs(residual - np.median(residual))))
            keep = np.abs(residual) <= max(3.0 * 1.4826 * mad, 0.05)
            if np.count_nonzero(keep) < 5:
                return None
            points = points[keep]
        mean = points.mean(axis=0)
        direction = np.linalg.svd(points - mean, full_matrices=False)[2][0]
        lines.append(np.array([mean, direction]))
    try:
        refined = np.array([_line_intersection(lines[(k - 1) % 4], lines[k]) for k in range(4)])
    except np.linalg.LinAlgError:
        return None  # parallel adjacent edges: not a tag
    if use_dist:
        normalized = np.column_stack([refined, np.ones(4)]) @ np.linalg.inv(K).T
        refined = cv2.projectPoints(normalized, np.zeros(3), np.zeros(3), K, dist)[0].reshape(4, 2)
    if np.max(np.linalg.norm(refined - corners, axis=1)) > 2.0:
        return None  # the edges moved far from the detection: do not trust them
    return refined


def _check_intrinsics(K: np.ndarray, dist: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """K as a pinhole matrix [[fx, s, cx], [0, fy, cy], [0, 0, 1]] (fx, fy > 0, finite) and
    dist as OpenCV's coefficients (None or none at all: no distortion), or a ValueError."""
    K = np.asarray(K, dtype=np.float64)
    if K.shape != (3, 3):
        raise ValueError(f"K: camera matrix must be 3 x 3, got shape {K.shape}")
    if not (np.all(np.isfinite(K)) and K[0, 0] > 0 and K[1, 1] > 0 and K[1, 0] == 0
            and np.allclose(K[2], [0.0, 0.0, 1.0])):
        raise ValueError(f"K: camera matrix must be finite [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0, "
                         f"got {K.tolist()}")
    dist = np.zeros(5) if dist is None or np.size(dist) == 0 else np.asarray(dist, dtype=np.float64).ravel()
    if dist.size not in (4, 5, 8, 12, 14):
        raise ValueError(f"dist: OpenCV distortion needs 4, 5, 8, 12 or 14 coefficients, got {dist.size}")
    if not np.all(np.isfinite(dist)):
        raise ValueError(f"dist: distortion coefficients must be finite, got {dist.tolist()}")
    return K, dist


def faces_camera(R_CT: np.ndarray, p_CT: np.ndarray) -> bool:
    """True when the tag lies in front of the camera (z > 0) and its printed face (+z of T)
    points back towards the camera centre: (R_CT e_z) . p_CT < 0."""
    return bool(p_CT[2] > 0 and float(R_CT[:, 2] @ p_CT) < 0)


def estimate_tag_pose(
    corners: np.ndarray,
    tag_size: float,
    K: np.ndarray,
    dist: np.ndarray | None = None,
    refine_lm: bool = True,
) -> tuple[np.ndarray, np.ndarray, float] | None:
    """Tag pose in the camera frame from its four corners (DESIGN section 8 advice).

    ``cv2.solvePnPGeneric`` with IPPE_SQUARE returns two candidates (the planar pose
    ambiguity); the one with the lowest RMS reprojection error among those that face the
    camera (:func:`faces_camera`) is kept, optionally polished by ``solvePnPRefineLM``.
    SQPnP adds a third candidate: on an exactly fronto-parallel view (integer corners, as
    rendered images give) OpenCV 5's IPPE_SQUARE returned two identical wrong poses with a
    120 px error, which the faces-the-camera check rejects.

    Returns (R_CT (3 x 3), p_CT (3,) [m], RMS reprojection error [px]) or None when no
    candidate faces the camera.
    """
    corners = np.asarray(corners, dtype=np.float64)
    if corners.shape != (4, 2):
        raise ValueError(f"corners: must be 4 x 2 pixel coordinates, got shape {corners.shape}")
    if not np.all(np.isfinite(corners)):
        raise ValueError(f"corners: must be finite, got {corners.tolist()}")
    if not (is_number(tag_size) and 0 < tag_size < np.inf):  # inf gave no pose, reported as a lost tag
        raise ValueError(f"tag_size: must be a finite number > 0 [m], got {tag_size!r}")
    K, dist = _check_intrinsics(K, dist)
    object_points = tag_corners(tag_size)
    candidates = []
    for method in (cv2.SOLVEPNP_IPPE_SQUARE, cv2.SOLVEPNP_SQPNP):
        try:
            n, rvecs, tvecs, _ = cv2.solvePnPGeneric(object_points, corners, K, dist, flags=method)
        except cv2.error:  # degenerate corners (e.g. all on one point): SQPnP asserts
            continue
        candidates += [(rvecs[k], tvecs[k]) for k in range(int(n))]
    best = None
    for rvec, tvec in candidates:
        rvec, tvec = np.asarray(rvec, float).reshape(3, 1), np.asarray(tvec, float).reshape(3, 1)
        if refine_lm:
            rvec, tvec = cv2.solvePnPRefineLM(object_points, corners, K, dist, rvec.copy(), tvec.copy())
        R_CT = cv2.Rodrigues(rvec)[0]
        p_CT = tvec.ravel()
        if not faces_camera(R_CT, p_CT):
            continue
        projected = cv2.projectPoints(object_points, rvec, tvec, K, dist)[0].reshape(4, 2)
        error = float(np.sqrt(np.mean(np.sum((projected - corners) ** 2, axis=1))))
        if best is None or error < best[2]:
            best = (R_CT, p_CT, error)
    return best


def check_pose(value: Any, name: str, optional: bool = False) -> Any:
    """``value`` if it is a finite ``pydrake.math.RigidTransform``; with ``optional``, None
    is the identity (X_TO: the tag's frame is the POM's). Otherwise a TypeError or ValueError
    that starts with ``name``."""
    from pydrake.math import RigidTransform

    if value is None and optional:
        return RigidTransform()
    if not isinstance(value, RigidTransform):
        raise TypeError(f"{name} must be a pydrake.math.RigidTransform, got {type(value).__name__}")
    if not np.all(np.isfinite(value.GetAsMatrix34())):
        raise ValueError(f"{name} is not finite: {value.GetAsMatrix34().tolist()}")
    return value


def observe_pom(
    image: np.ndarray,
    config: TagObserverConfig,
    K: np.ndarray,
    dist: np.ndarray | None,
    X_PC: Any,
    X_TO: Any = None,
    detector: cv2.aruco.ArucoDetector | None = None,
) -> tuple[Any, dict]:
    """Measured POM pose X_PO = X_PC X_CT X_TO from one camera image (DESIGN section 5).

    ``X_PC``, ``X_TO`` and the result are ``pydrake.math.RigidTransform`` (X_TO None means
    identity). Returns (X_PO or None, info) where info has ``valid`` (bool), ``reason``
    ("ok", "empty_image" (a frame with no pixels), "not_detected", "ambiguous" (the tag's id
    seen more than once), "too_small",
    "no_facing_solution", "reprojection_error", "edge_refinement_failed"),
    ``corners`` (4 x 2 or None), ``reprojection_error_px`` (nan when not detected) and
    ``X_CT`` (RigidTransform or None); with a detection also ``detector_corners``, and
    where the edges were tried (``edge_refinement``, a tag not too small) ``edge_refined``
    (whether :func:`refine_corners_edges` succeeded). A rejected detection
    returns None, never raises (bad arguments do).
    """
    from pydrake.math import RigidTransform, RotationMatrix

    info: dict = {
        "valid": False,
        "reason": "not_detected",
        "corners": None,
        "reprojection_error_px": float("nan"),
        "X_CT": None,
    }
    _check_intrinsics(K, dist)  # also when no tag is in view: a bad calibration is named at once
    config.validate()
    X_PC = check_pose(X_PC, "observe_pom: 'X_PC'")
    X_TO = check_pose(X_TO, "observe_pom: 'X_TO'", optional=True)
    if np.asarray(image).size == 0:  # a camera's empty frame: a lost frame, as no tag is
        info["reason"] = "empty_image"
        return None, info
    if detector is None:
        detector = make_detector(config.corner_refinement, config.detector_overrides)
    gray = to_gray(image)
    hits = detect_tag_all(gray, config.tag_id, detector, config.corner_offset_px)
    if len(hits) != 1:
        if hits:
            info["reason"] = "ambiguous"
        return None, info
    corners = hits[0]
    info["detector_corners"] = info["corners"] = corners
    side = float(np.min(np.linalg.norm(corners - np.roll(corners, -1, axis=0), axis=1)))
    if side < config.min_tag_side_px:
        info["reason"] = "too_small"
        return None, info
    if config.edge_refinement:
        refined = refine_corners_edges(gray, corners, K, dist)
        info["edge_refined"] = refined is not None
        if refined is not None:
            info["corners"] = corners = refined
        elif config.require_edge_refinement:
            info["reason"] = "edge_refinement_failed"
            return None, info
    pose = estimate_tag_pose(corners, config.tag_size, K, dist, refine_lm=config.refine_lm)
    if pose is None:
        info["reason"] = "no_facing_solution"
        return None, info
    R_CT, p_CT, error = pose
    info["reprojection_error_px"] = error
    X_CT = RigidTransform(RotationMatrix(R_CT), p_CT)
    info["X_CT"] = X_CT
    if error > config.max_reprojection_error_px:
        info["reason"] = "reprojection_error"
        return None, info
    X_PO = X_PC @ X_CT @ X_TO
    info["valid"] = True
    info["reason"] = "ok"
    return X_PO, info


def vtk_render_intrinsics(camera: Any) -> np.ndarray:
    """K of the delivered image of a camera rendered by Drake's RenderEngineVtk at
    ``camera.render_scale`` and downsampled with INTER_AREA (``CameraConfig``): its
    ``intrinsic_matrix()`` with the renderer's measured -0.5 rendered-pixel shift of the
    principal point, i.e. c -= 0.5 / render_scale (drake 1.51.1; tests/test_tag_observer.py
    checks it through the pose accuracy)."""
    K = np.array(camera.intrinsic_matrix(), dtype=np.float64)
    K[:2, 2] -= 0.5 / int(camera.render_scale)
    return K
