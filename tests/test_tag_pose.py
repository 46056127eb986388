"""Tests of the AprilTag pose functions (vlr_drake.perception.tag_pose) and the image
post-processing (vlr_drake.perception.image_noise) on synthetic pinhole images.

Synthetic images: the tag texture from ``tag_image`` is warped into the image by the exact
homography of a known pose, ``H = K_s [r1 r2 t] A`` with ``A`` mapping texture pixels to the
tag plane, rendered at ``supersample`` times the resolution and shrunk with INTER_AREA.
Conventions (OpenCV's integer pixel centres throughout): texture pixel u covers tag-frame
x = ((u + 0.5) - n / 2) s / (8 ppc); the supersampled intrinsics are f_s = s f and
c_s = s (c + 0.5) - 0.5, so that INTER_AREA brings them back to K exactly.
"""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from pydrake.math import RigidTransform, RollPitchYaw, RotationMatrix

from vlr_drake.perception.apriltag import tag_corners, tag_image
from vlr_drake.perception.camera import CameraConfig
from vlr_drake.perception.image_noise import add_pixel_noise, downsample_area
from vlr_drake.perception.tag_pose import (
    APRILTAG_CORNER_OFFSET_PX,
    TagObserverConfig,
    detect_tag,
    detect_tag_all,
    estimate_tag_pose,
    faces_camera,
    make_detector,
    observe_pom,
    refine_corners_edges,
    to_gray,
)

TAG_ID = 3
TAG_SIZE = 0.03


def render_tag_view(
    X_CT: RigidTransform,
    K: np.ndarray,
    width: int = 640,
    height: int = 480,
    tag_id: int = TAG_ID,
    tag_size: float = TAG_SIZE,
    supersample: int = 4,
    background: int = 180,
    pixels_per_cell: int = 32,
) -> np.ndarray:
    """Grayscale uint8 pinhole image of the tag (with its white quiet zone) at pose X_CT."""
    texture = tag_image(tag_id, pixels_per_cell=pixels_per_cell, quiet_cells=1)
    n = texture.shape[0]
    m = tag_size / (8 * pixels_per_cell)  # metres per texture pixel
    A = np.array([[m, 0.0, -(n / 2 - 0.5) * m], [0.0, -m, (n / 2 - 0.5) * m], [0.0, 0.0, 1.0]])
    s = supersample
    K_s = np.array(K, dtype=float)
    K_s[:2, :2] *= s
    K_s[:2, 2] = s * (K_s[:2, 2] + 0.5) - 0.5
    R, t = X_CT.rotation().matrix(), X_CT.translation()
    H = K_s @ np.column_stack([R[:, 0], R[:, 1], t]) @ A
    image = cv2.warpPerspective(
        texture, H, (width * s, height * s), flags=cv2.INTER_LINEAR, borderValue=background
    )
    return downsample_area(image, s)


def project(X_CT: RigidTransform, K: np.ndarray, tag_size: float = TAG_SIZE) -> np.ndarray:
    """True corner pixels (4 x 2) of the tag at X_CT."""
    p_C = (X_CT.rotation().matrix() @ tag_corners(tag_size).T).T + X_CT.translation()
    uv = (K @ p_C.T).T
    return uv[:, :2] / uv[:, 2:]


def random_views(count: int, seed: int) -> list[RigidTransform]:
    """Tag poses typical of an object 45-90 mm in front of the palm camera: tag facing the
    camera, tilted up to 25 deg, any roll, up to 10 mm off the axis."""
    rng = np.random.default_rng(seed)
    views = []
    for _ in range(count):
        rpy = RollPitchYaw(
            np.deg2rad(rng.uniform(-25, 25)), np.deg2rad(rng.uniform(-25, 25)), rng.uniform(-np.pi, np.pi)
        )
        R_CT = RotationMatrix(rpy) @ RotationMatrix.MakeXRotation(np.pi)
        p_CT = [rng.uniform(-0.01, 0.01), rng.uniform(-0.01, 0.01), rng.uniform(0.05, 0.09)]
        views.append(RigidTransform(R_CT, p_CT))
    return views


def pose_errors(X_est: RigidTransform, X_true: RigidTransform) -> tuple[float, float]:
    """(position error [mm], rotation error [deg])."""
    dp = np.linalg.norm(X_est.translation() - X_true.translation()) * 1e3
    angle = (X_est.rotation().inverse() @ X_true.rotation()).ToAngleAxis().angle()
    return float(dp), float(np.rad2deg(abs(angle)))


@pytest.fixture(scope="module")
def K() -> np.ndarray:
    return CameraConfig().intrinsic_matrix()


@pytest.fixture(scope="module")
def views(K) -> list[tuple[RigidTransform, np.ndarray]]:
    return [(X, render_tag_view(X, K)) for X in random_views(12, seed=0)]


def test_apriltag_corner_offset_is_removed(K, views):
    """Raw APRILTAG corners sit +0.43 px off OpenCV's convention; detect_tag removes it.
    SUBPIX corners need no offset."""
    raw, corrected, subpix = [], [], []
    apriltag = make_detector("apriltag")
    for X, image in views:
        truth = project(X, K)
        raw.append(detect_tag(image, TAG_ID, apriltag, corner_offset_px=0.0) - truth)
        corrected.append(detect_tag(image, TAG_ID, apriltag) - truth)
        subpix.append(detect_tag(image, TAG_ID, make_detector("subpix")) - truth)
    raw, corrected, subpix = (np.concatenate(v) for v in (raw, corrected, subpix))
    np.testing.assert_allclose(raw.mean(axis=0), APRILTAG_CORNER_OFFSET_PX, atol=0.05)
    np.testing.assert_allclose(corrected.mean(axis=0), 0.0, atol=0.05)
    np.testing.assert_allclose(subpix.mean(axis=0), 0.0, atol=0.08)
    assert np.sqrt(np.mean(corrected**2)) < 0.15


def distort_image(image: np.ndarray, K: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """The image a lens with distortion ``dist`` would see, from an ideal pinhole image:
    each distorted pixel samples the pinhole image at its undistorted position."""
    h, w = image.shape[:2]
    u, v = np.meshgrid(np.arange(w, dtype=np.float64), np.arange(h, dtype=np.float64))
    pixels = np.stack([u.ravel(), v.ravel()], axis=1).reshape(-1, 1, 2)
    ideal = cv2.undistortPoints(pixels, K, dist, P=K).reshape(h, w, 2).astype(np.float32)
    return cv2.remap(image, ideal[..., 0], ideal[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def test_edge_refinement_fixes_axis_aligned_edges(K):
    """Edges along the pixel grid: the aruco corners are quantised, the edge fit is not."""
    raw_errors, refined_errors = [], []
    for k, dz in enumerate([0.04, 0.05, 0.065]):
        X_CT = RigidTransform(RotationMatrix.MakeXRotation(np.pi + 0.004 * k), [0.0013 * k, -0.0007 * k, dz])
        image = render_tag_view(X_CT, K)
        corners = detect_tag(image, TAG_ID)
        refined = refine_corners_edges(image, corners)
        raw_errors.append(corners - project(X_CT, K))
        refined_errors.append(refined - project(X_CT, K))
    raw_rms = np.sqrt(np.mean(np.concatenate(raw_errors) ** 2))
    refined_rms = np.sqrt(np.mean(np.concatenate(refined_errors) ** 2))
    assert refined_rms < 0.05
    assert refined_rms < 0.5 * raw_rms


def test_edge_refinement_gives_up_on_a_covered_edge(K, views):
    X_CT, image = views[3]
    corners = detect_tag(image, TAG_ID)
    covered = image.copy()
    cv2.fillConvexPoly(covered, np.round(corners).astype(np.int32), 0)  # black up to and past the edges
    cv2.circle(
        covered, tuple(np.round(corners.mean(axis=0)).astype(int)), 3 * int(np.ptp(corners[:, 0])), 0, -1
    )
    assert refine_corners_edges(covered, corners) is None
    # Too small to measure.
    assert refine_corners_edges(image, corners.mean(axis=0) + 0.05 * (corners - corners.mean(axis=0))) is None


def test_a_partly_covered_tag_is_refused_not_reported_wrong(K):
    """Discs over a corner or an edge of the tag (a fingertip, a glint): every frame the
    observer calls valid is within the design goal (0.1 mm, 0.3 deg); those whose edges
    cannot be measured are refused ("edge_refinement_failed"). Falling back to the
    detector's corners instead reports some of them degrees off, within the reprojection
    limit (a review found up to 6.6 deg): what the refusal is for."""
    X = RigidTransform(RotationMatrix(RollPitchYaw(np.pi + 0.15, -0.1, 0.4)), [0.002, -0.003, 0.06])
    image = render_tag_view(X, K)
    c = project(X, K)
    strict = TagObserverConfig(tag_id=TAG_ID, tag_size=TAG_SIZE)
    lenient = TagObserverConfig(tag_id=TAG_ID, tag_size=TAG_SIZE, require_edge_refinement=False)
    reasons, valid_errors, fallback_errors = [], [], []
    for k in range(4):
        for p in (c[k], 0.5 * (c[k] + c[(k + 1) % 4])):  # a corner, an edge's middle
            for radius in (6, 10):
                for value in (0, 255):
                    covered = image.copy()
                    cv2.circle(covered, tuple(int(v) for v in np.round(p)), radius, value, -1)
                    X_PO, info = observe_pom(covered, strict, K, None, RigidTransform())
                    reasons.append(info["reason"])
                    if X_PO is not None:
                        assert info["edge_refined"]
                        valid_errors.append(pose_errors(X_PO, X))
                    elif info["reason"] == "edge_refinement_failed":
                        assert info["edge_refined"] is False and info["corners"] is info["detector_corners"]
                        X_fb, fb = observe_pom(covered, lenient, K, None, RigidTransform())
                        if X_fb is not None:
                            fallback_errors.append(pose_errors(X_fb, X))
    valid_errors, fallback_errors = np.array(valid_errors), np.array(fallback_errors)
    assert len(valid_errors) >= 10 and reasons.count("edge_refinement_failed") >= 5
    assert valid_errors[:, 0].max() < 0.1 and valid_errors[:, 1].max() < 0.3
    assert fallback_errors[:, 1].max() > 1.0  # degrees off, and it would have been called valid


def test_pose_with_lens_distortion(K):
    dist = np.array([-0.25, 0.08, 0.0005, -0.0008, 0.0])
    X_CT = RigidTransform(RotationMatrix(RollPitchYaw(np.pi + 0.25, -0.15, 0.6)), [0.012, -0.008, 0.06])
    image = distort_image(render_tag_view(X_CT, K), K, dist)
    config = TagObserverConfig(tag_id=TAG_ID, tag_size=TAG_SIZE)
    X_PO, info = observe_pom(image, config, K, dist, RigidTransform())
    assert info["valid"] and info["edge_refined"]
    dp, dr = pose_errors(X_PO, X_CT)
    assert dp < 0.02 and dr < 0.05
    # Ignoring the distortion is visibly worse.
    X_bad, _ = observe_pom(image, config, K, None, RigidTransform())
    assert pose_errors(X_bad, X_CT)[0] > 10 * dp


@pytest.mark.parametrize("edge_refinement", [True, False])
def test_pose_accuracy_on_synthetic_views(K, views, edge_refinement):
    config = TagObserverConfig(tag_id=TAG_ID, tag_size=TAG_SIZE, edge_refinement=edge_refinement)
    errors = []
    for X_CT, image in views:
        X_PO, info = observe_pom(image, config, K, None, RigidTransform())
        assert info["valid"] and info["reason"] == "ok", info["reason"]
        assert info["reprojection_error_px"] < 0.5
        errors.append(pose_errors(X_PO, X_CT))
        assert info["edge_refined"] if edge_refinement else "edge_refined" not in info
    errors = np.array(errors)
    print(
        f"synthetic (edge refinement {edge_refinement}): position mean {errors[:, 0].mean():.4f} max "
        f"{errors[:, 0].max():.4f} mm, rotation mean {errors[:, 1].mean():.3f} max {errors[:, 1].max():.3f} deg"
    )
    if edge_refinement:
        assert errors[:, 0].mean() < 0.01 and errors[:, 0].max() < 0.05
        assert errors[:, 1].mean() < 0.03 and errors[:, 1].max() < 0.1
    else:
        assert errors[:, 0].mean() < 0.05 and errors[:, 0].max() < 0.3
        assert errors[:, 1].mean() < 0.15 and errors[:, 1].max() < 0.5


@pytest.mark.parametrize(
    "X_CT",
    [
        # Exactly fronto-parallel: OpenCV 5's IPPE_SQUARE alone returns a wrong pose here.
        RigidTransform(RotationMatrix.MakeXRotation(np.pi), [0.0, 0.0, 0.06]),
        RigidTransform(RotationMatrix(RollPitchYaw(np.pi + 0.3, -0.2, 1.0)), [0.004, -0.006, 0.07]),
        RigidTransform(RotationMatrix(RollPitchYaw(np.pi - 0.5, 0.4, -2.5)), [-0.01, 0.008, 0.05]),
    ],
)
def test_estimate_tag_pose_exact_corners(K, X_CT):
    R_CT, p_CT, error = estimate_tag_pose(project(X_CT, K), TAG_SIZE, K)
    np.testing.assert_allclose(R_CT, X_CT.rotation().matrix(), atol=1e-7)
    np.testing.assert_allclose(p_CT, X_CT.translation(), atol=1e-9)
    assert error < 1e-6
    assert faces_camera(R_CT, p_CT)


def test_estimate_tag_pose_rejects_a_tag_seen_from_behind(K):
    X_CT = RigidTransform(RotationMatrix(RollPitchYaw(0.2, 0.1, 0.3)), [0.0, 0.0, 0.06])  # z away from camera
    assert not faces_camera(X_CT.rotation().matrix(), X_CT.translation())
    assert estimate_tag_pose(project(X_CT, K), TAG_SIZE, K) is None


def test_estimate_tag_pose_with_distortion(K):
    X_CT = RigidTransform(RotationMatrix(RollPitchYaw(np.pi + 0.2, 0.1, 0.5)), [0.01, 0.0, 0.06])
    dist = np.array([-0.2, 0.05, 0.001, -0.001, 0.0])
    p_C = (X_CT.rotation().matrix() @ tag_corners(TAG_SIZE).T).T + X_CT.translation()
    rvec = cv2.Rodrigues(X_CT.rotation().matrix())[0]
    corners = cv2.projectPoints(tag_corners(TAG_SIZE), rvec, X_CT.translation(), K, dist)[0].reshape(4, 2)
    assert not np.allclose(corners, project(X_CT, K), atol=0.5)  # distortion matters here
    R_CT, p_CT, _ = estimate_tag_pose(corners, TAG_SIZE, K, dist)
    np.testing.assert_allclose(p_CT, p_C.mean(axis=0), atol=1e-8)
    np.testing.assert_allclose(R_CT, X_CT.rotation().matrix(), atol=1e-6)


def test_observe_pom_composes_X_PC_X_CT_X_TO(K, views):
    X_CT, image = views[0]
    X_PC = RigidTransform(RotationMatrix(RollPitchYaw(0.1, -0.05, 0.3)), [0.001, -0.002, -0.02])
    X_TO = RigidTransform(RotationMatrix(RollPitchYaw(0.0, 0.2, -0.4)), [0.0, 0.005, -0.03])
    config = TagObserverConfig(tag_id=TAG_ID, tag_size=TAG_SIZE)
    X_PO, info = observe_pom(image, config, K, None, X_PC, X_TO)
    assert info["valid"]
    # The composition itself is exact given the measured X_CT ...
    expected = X_PC @ info["X_CT"] @ X_TO
    np.testing.assert_allclose(X_PO.GetAsMatrix4(), expected.GetAsMatrix4(), atol=1e-12)
    # ... and the result is close to the true POM pose.
    dp, dr = pose_errors(X_PO, X_PC @ X_CT @ X_TO)
    assert dp < 0.3 and dr < 0.5


@pytest.mark.parametrize("channels", [1, 3, 4])
def test_image_formats_give_the_same_corners(K, views, channels):
    """A (H, W, 1), RGB or RGBA copy of a grey image gives the grey image's corners, which
    are the true ones to a fraction of a pixel."""
    X, gray = views[1]
    if channels == 4:
        image = np.dstack([gray, gray, gray, np.full_like(gray, 255)])
    else:
        image = np.dstack([gray] * channels)
    corners = detect_tag(image, TAG_ID)
    np.testing.assert_allclose(corners, detect_tag(gray, TAG_ID), atol=1e-9)
    assert np.sqrt(np.mean((corners - project(X, K)) ** 2)) < 0.15


def test_lost_tag_cases(K, views):
    config = TagObserverConfig(tag_id=TAG_ID, tag_size=TAG_SIZE)
    X_CT, image = views[2]
    blank = np.full_like(image, 180)
    X_PO, info = observe_pom(blank, config, K, None, RigidTransform())
    assert X_PO is None and not info["valid"] and info["reason"] == "not_detected"
    assert np.isnan(info["reprojection_error_px"])
    # bad poses and settings are named at once, not after a detection (a NaN X_PC had given
    # a NaN pose marked valid, a NaN threshold switched the rejection off)
    nan_pose = RigidTransform(np.array([np.nan, 0.0, 0.0]))
    with pytest.raises(ValueError, match="'X_PC' is not finite"):
        observe_pom(image, config, K, None, nan_pose)
    with pytest.raises(ValueError, match="'X_TO' is not finite"):
        observe_pom(image, config, K, None, RigidTransform(), nan_pose)
    with pytest.raises(TypeError, match="'X_PC' must be a pydrake.math.RigidTransform, got ndarray"):
        observe_pom(blank, config, K, None, np.eye(4))
    with pytest.raises(ValueError, match="max_reprojection_error_px"):
        observe_pom(image, TagObserverConfig(tag_id=TAG_ID, tag_size=TAG_SIZE, max_reprojection_error_px=np.nan),
                    K, None, RigidTransform())
    # Another tag id is not ours.
    other = TagObserverConfig(tag_id=TAG_ID + 1, tag_size=TAG_SIZE)
    assert observe_pom(image, other, K, None, RigidTransform())[0] is None
    # Half of the tag covered.
    corners = project(X_CT, K)
    occluded = image.copy()
    u_mid = int(corners[:, 0].mean())
    occluded[:, u_mid:] = 90
    assert observe_pom(occluded, config, K, None, RigidTransform())[1]["reason"] == "not_detected"
    # Out of view: the tag moved 60 mm sideways.
    far = render_tag_view(RigidTransform(X_CT.rotation(), X_CT.translation() + [0.06, 0.0, 0.0]), K)
    assert observe_pom(far, config, K, None, RigidTransform())[0] is None
    # The id seen twice (a second print, a reflection): which one is the object's is not
    # known, so neither is taken, and the reason says so (it had said "not_detected").
    left = render_tag_view(RigidTransform(X_CT.rotation(), X_CT.translation() + [-0.02, 0.0, 0.0]), K)
    right = render_tag_view(RigidTransform(X_CT.rotation(), X_CT.translation() + [0.02, 0.0, 0.0]), K)
    twice = np.minimum(left, right)  # the background is lighter than the tags' black
    assert len(detect_tag_all(twice, TAG_ID)) == 2 and detect_tag(twice, TAG_ID) is None
    X_PO, info = observe_pom(twice, config, K, None, RigidTransform())
    assert X_PO is None and info["reason"] == "ambiguous" and not info["valid"]
    assert observe_pom(left, config, K, None, RigidTransform())[1]["reason"] == "ok"
    # A tight reprojection threshold rejects a real detection, and says why.
    strict = TagObserverConfig(tag_id=TAG_ID, tag_size=TAG_SIZE, max_reprojection_error_px=1e-6)
    X_PO, info = observe_pom(image, strict, K, None, RigidTransform())
    assert X_PO is None and info["reason"] == "reprojection_error" and info["reprojection_error_px"] > 1e-6
    # Too small in the image.
    tiny = TagObserverConfig(tag_id=TAG_ID, tag_size=TAG_SIZE, min_tag_side_px=1000.0)
    assert observe_pom(image, tiny, K, None, RigidTransform())[1]["reason"] == "too_small"


def test_bad_inputs_raise_clear_errors(K, views):
    _, image = views[0]
    with pytest.raises(ValueError, match="dtype"):
        to_gray(image.astype(np.float32))
    with pytest.raises(ValueError, match="shape"):
        to_gray(np.zeros((48, 64, 2), np.uint8))
    with pytest.raises(ValueError, match="shape"):
        detect_tag(np.zeros((2, 48, 64, 3), np.uint8), TAG_ID)
    with pytest.raises(ValueError, match="'tag_id' 9999 is outside the tag36h11 dictionary"):
        detect_tag(image, 9999)
    with pytest.raises(ValueError, match="corners"):
        estimate_tag_pose(np.zeros((3, 2)), TAG_SIZE, K)
    with pytest.raises(ValueError, match="K"):
        estimate_tag_pose(np.zeros((4, 2)), TAG_SIZE, np.eye(2))
    for bad in (-1.0, np.inf, True):  # inf gave None (a lost tag), True a 1 m tag
        with pytest.raises(ValueError, match="tag_size: must be a finite number > 0"):
            estimate_tag_pose(project(views[0][0], K), bad, K)
    with pytest.raises(ValueError, match="dist"):
        estimate_tag_pose(project(views[0][0], K), TAG_SIZE, K, np.zeros(3))
    with pytest.raises(ValueError, match="corner_refinement"):
        TagObserverConfig(corner_refinement="magic").validate()
    with pytest.raises(ValueError, match="tag_size"):
        TagObserverConfig(tag_size=0.0).validate()
    with pytest.raises(ValueError, match="max_reprojection_error_px"):
        TagObserverConfig(max_reprojection_error_px=0.0).validate()
    with pytest.raises(ValueError, match="K"):
        refine_corners_edges(image, project(views[0][0], K), None, np.array([0.1, 0, 0, 0, 0]))
    with pytest.raises(ValueError, match="noSuchField"):
        make_detector("apriltag", {"noSuchField": 1.0})


def test_pixel_noise_is_seeded_and_has_the_asked_spread():
    image = np.full((100, 120, 4), 128, np.uint8)
    a = add_pixel_noise(image, 5.0, np.random.default_rng(7))
    b = add_pixel_noise(image, 5.0, np.random.default_rng(7))
    c = add_pixel_noise(image, 5.0, np.random.default_rng(8))
    np.testing.assert_array_equal(a, b)
    assert not np.array_equal(a, c)
    assert np.all(a[..., 3] == 128)  # alpha untouched
    noise = a[..., :3].astype(float) - 128
    assert abs(noise.std() - 5.0) < 0.2 and abs(noise.mean()) < 0.1
    np.testing.assert_array_equal(add_pixel_noise(image, 0.0, np.random.default_rng(0)), image)
    with pytest.raises(ValueError, match="std"):
        add_pixel_noise(image, -1.0, np.random.default_rng(0))
    with pytest.raises(TypeError, match="rng"):
        add_pixel_noise(image, 1.0, 7)


def test_downsample_area_keeps_the_pixel_convention(K):
    """A rendering at 2x with intrinsics c_2 = 2 c + 0.5 shrinks to an image whose corners
    match K."""
    X_CT = RigidTransform(RotationMatrix(RollPitchYaw(np.pi + 0.2, 0.1, 0.5)), [0.004, -0.003, 0.065])
    K2 = K.copy()
    K2[:2, :2] *= 2
    K2[:2, 2] = 2 * K[:2, 2] + 0.5
    big = render_tag_view(X_CT, K2, width=1280, height=960)
    small = downsample_area(big, 2)
    assert small.shape == (480, 640)
    corners = detect_tag(small, TAG_ID)
    assert np.abs((corners - project(X_CT, K)).mean(axis=0)).max() < 0.1
    assert downsample_area(np.zeros((4, 6, 1), np.uint8), 2).shape == (2, 3, 1)
    assert downsample_area(np.zeros((4, 4, 4), np.uint8), 2).shape == (2, 2, 4)
    with pytest.raises(ValueError, match="multiple"):
        downsample_area(np.zeros((5, 6), np.uint8), 2)
    with pytest.raises(ValueError, match="scale"):
        downsample_area(np.zeros((4, 6), np.uint8), 0)


# ----------------------------------------------------------------- bad intrinsics, degenerate input


def _bad_K(K, name):
    bad = np.array(K, float)
    if name == "zeros":
        return np.zeros((3, 3))
    if name == "nan":
        bad[0, 2] = np.nan
    elif name == "negative_focal":  # used to give a mirrored pose, reported valid
        bad[0, 0], bad[1, 1] = -bad[0, 0], -bad[1, 1]
    elif name == "bottom_row":
        bad[2, 2] = 0.0
    return bad


@pytest.mark.parametrize("name", ["zeros", "nan", "negative_focal", "bottom_row"])
def test_bad_camera_matrix_is_named(K, views, name):
    """A zero or NaN K used to end in an OpenCV assertion inside SQPnP; a negative focal
    length or a broken bottom row gave a pose, reported valid."""
    X_CT, image = views[0]
    config = TagObserverConfig(tag_id=TAG_ID, tag_size=TAG_SIZE)
    with pytest.raises(ValueError, match="K: camera matrix"):
        observe_pom(image, config, _bad_K(K, name), None, RigidTransform())
    with pytest.raises(ValueError, match="K: camera matrix"):
        estimate_tag_pose(project(X_CT, K), TAG_SIZE, _bad_K(K, name))


def test_non_finite_distortion_is_named(K, views):
    """NaN distortion used to end in numpy's "SVD did not converge" (edge refinement) or an
    OpenCV assertion (the pose)."""
    X_CT, image = views[0]
    dist = np.array([0.1, np.nan, 0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="dist"):
        observe_pom(image, TagObserverConfig(tag_id=TAG_ID, tag_size=TAG_SIZE), K, dist, RigidTransform())
    with pytest.raises(ValueError, match="dist"):
        estimate_tag_pose(project(X_CT, K), TAG_SIZE, K, dist)


def test_no_distortion_coefficients_mean_no_distortion(K, views):
    """hardware.camera.CameraIntrinsics accepts a calibration with 0 distortion
    coefficients; the pose then failed with "dist: OpenCV distortion needs 4, 5, ..."."""
    X_CT, _ = views[0]
    corners = project(X_CT, K)
    np.testing.assert_array_equal(estimate_tag_pose(corners, TAG_SIZE, K, np.zeros(0))[1],
                                  estimate_tag_pose(corners, TAG_SIZE, K, None)[1])


def test_degenerate_corners_give_no_pose_or_a_named_error(K):
    """Four corners on one point used to end in an OpenCV assertion inside SQPnP."""
    assert estimate_tag_pose(np.full((4, 2), 100.0), TAG_SIZE, K) is None
    assert estimate_tag_pose(np.array([[0.0, 0], [10, 0], [20, 0], [30, 0]]), TAG_SIZE, K) is None
    with pytest.raises(ValueError, match="corners"):
        estimate_tag_pose(np.full((4, 2), np.nan), TAG_SIZE, K)


@pytest.mark.parametrize("field, value", [("corner_offset_px", np.nan), ("min_tag_side_px", np.nan),
                                          ("min_tag_side_px", np.inf), ("tag_size", np.inf)])
def test_observer_config_refuses_non_finite_values(field, value):
    """corner_offset_px NaN was accepted and crashed at the first detection ("cannot
    convert float NaN to integer"); min_tag_side_px NaN switched the size check off."""
    with pytest.raises(ValueError, match=field):
        TagObserverConfig(**{field: value}).validate()


@pytest.mark.parametrize("name, value, match", [("adaptiveThreshWinSizeMin", np.nan, "must be an integer"),
                                                ("adaptiveThreshWinSizeMin", 3.5, "must be an integer"),
                                                ("minMarkerPerimeterRate", np.inf, "must be a finite number"),
                                                ("minMarkerPerimeterRate", "small", "must be a finite number"),
                                                ("noSuchField", 1, "has no field")])
def test_bad_detector_overrides_are_named(name, value, match):
    """An override that is not a number of its field's kind is named: NaN for an integer
    field used to fail with "cannot convert float NaN to integer", and 3.5 was cut to 3."""
    with pytest.raises(ValueError, match=f"detector_overrides.*{match}"):
        make_detector("apriltag", {name: value})


def test_detector_overrides_set_their_fields():
    params = make_detector("apriltag", {"adaptiveThreshWinSizeMin": 5.0, "minMarkerPerimeterRate": 0.02,
                                        "detectInvertedMarker": 1}).getDetectorParameters()
    assert params.adaptiveThreshWinSizeMin == 5 and isinstance(params.adaptiveThreshWinSizeMin, int)
    assert params.minMarkerPerimeterRate == pytest.approx(0.02) and params.detectInvertedMarker is True
