"""Tests of the POM pose sensors (vlr_drake.systems.tag_observer): the TagObserver on
Drake-rendered images (accuracy, lost tags, a simulated periodic update), its ports with
FixValue + Eval on synthetic images, and the NoisyPoseSensor.

The rendered scene (built here, independent of models/): the palm is the world frame; a
free, gravity-free body per tag carries a thin box whose +z face holds the tag texture
(``PerceptionProperties`` ("phong", "diffuse_map"), the PNG of ``tag_image`` with its 1-cell
quiet zone, so the face is 10/8 of the tag size); the body frame is the tag frame T (the
textured face at z = 0, facing +z). Drake's VTK box maps the whole texture onto each face,
the image's top row towards +y and its left column towards -x of the +z face, which is
the tag frame convention of ``vlr_drake.perception.apriltag``. An RgbdSensor at X_PC
renders at ``render_scale`` x the delivered resolution; the observer downsamples.

Measured property of drake 1.51.1's RenderEngineVtk (checked with the box silhouette and
the tag edges at 1x and 2x): its images are shifted by -0.5 rendered pixels in x and y
relative to ``CameraInfo``'s principal point, i.e. -0.5 / render_scale delivered pixels.
``vtk_render_intrinsics`` puts that shift into the observer's K.
"""

from __future__ import annotations

import time

import cv2
import numpy as np
import pytest
from pydrake.geometry import (
    Box,
    ClippingRange,
    ColorRenderCamera,
    DepthRange,
    DepthRenderCamera,
    GeometryInstance,
    MakeRenderEngineVtk,
    PerceptionProperties,
    RenderCameraCore,
    RenderEngineVtkParams,
    RenderLabel,
    Rgba,
)
from pydrake.math import RigidTransform, RollPitchYaw, RotationMatrix
from pydrake.multibody.plant import AddMultibodyPlantSceneGraph
from pydrake.multibody.tree import SpatialInertia
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder
from pydrake.systems.sensors import CameraInfo, ImageRgba8U, RgbdSensor
from test_tag_pose import pose_errors, render_tag_view

from vlr_drake.perception.apriltag import tag_image
from vlr_drake.perception.camera import CameraConfig
from vlr_drake.perception.image_noise import add_pixel_noise, downsample_area
from vlr_drake.perception.tag_pose import TagObserverConfig, to_gray, vtk_render_intrinsics
from vlr_drake.systems.tag_observer import NoisyPoseSensor, TagObserver, rotation_from_vector

#: The two tags of the rendered scene: (id, black-square size [m]).
TAGS = ((3, 0.03), (7, 0.04))
#: Where unused bodies wait: behind the camera, never rendered.
AWAY = RigidTransform([0.0, 0.0, -1.0])


def render_intrinsics(camera: CameraConfig) -> np.ndarray:
    """K of the delivered (downsampled) image of Drake's VTK camera."""
    return vtk_render_intrinsics(camera)


def to_rgba(gray: np.ndarray) -> ImageRgba8U:
    image = ImageRgba8U(gray.shape[1], gray.shape[0])
    image.mutable_data[:] = np.dstack([gray, gray, gray, np.full_like(gray, 255)])
    return image


class TagScene:
    """Rendered test scene: tag bodies, an occluder, a palm camera, one observer per tag."""

    def __init__(self, texture_dir, camera: CameraConfig, update_period_sec: float = 0.1):
        builder = DiagramBuilder()
        plant, scene_graph = AddMultibodyPlantSceneGraph(builder, time_step=0.0)
        plant.mutable_gravity_field().set_gravity_vector([0.0, 0.0, 0.0])
        self.bodies = []
        for tag_id, size in TAGS:
            png = texture_dir / f"tag_{tag_id}.png"
            cv2.imwrite(str(png), tag_image(tag_id, pixels_per_cell=32, quiet_cells=1))
            face, thickness = size * 10 / 8, 0.004
            body = plant.AddRigidBody(
                f"tag_{tag_id}", SpatialInertia.SolidBoxWithMass(0.01, face, face, thickness)
            )
            props = PerceptionProperties()
            props.AddProperty("phong", "diffuse_map", str(png))
            props.AddProperty("phong", "diffuse", Rgba(1, 1, 1, 1))
            props.AddProperty("label", "id", RenderLabel(tag_id))
            visual = GeometryInstance(
                RigidTransform([0, 0, -thickness / 2]), Box(face, face, thickness), "tag"
            )
            visual.set_perception_properties(props)
            plant.RegisterVisualGeometry(body, visual)
            self.bodies.append(body)
        self.occluder = plant.AddRigidBody("occluder", SpatialInertia.SolidBoxWithMass(0.01, 0.1, 0.1, 0.002))
        props = PerceptionProperties()
        props.AddProperty("phong", "diffuse", Rgba(0.3, 0.3, 0.3, 1))
        props.AddProperty("label", "id", RenderLabel(99))
        visual = GeometryInstance(RigidTransform(), Box(0.1, 0.1, 0.002), "occluder")
        visual.set_perception_properties(props)
        plant.RegisterVisualGeometry(self.occluder, visual)
        plant.Finalize()
        scene_graph.AddRenderer("vtk", MakeRenderEngineVtk(RenderEngineVtkParams()))
        s = camera.render_scale
        core = RenderCameraCore(
            "vtk",
            CameraInfo(camera.width * s, camera.height * s, np.deg2rad(camera.fov_y_deg)),
            ClippingRange(camera.near, camera.far),
            RigidTransform(),
        )
        sensor = builder.AddNamedSystem(
            "camera",
            RgbdSensor(
                parent_id=scene_graph.world_frame_id(),
                X_PB=camera.X_PC(),
                color_camera=ColorRenderCamera(core, False),
                depth_camera=DepthRenderCamera(core, DepthRange(camera.near * 1.01, camera.far * 0.99)),
            ),
        )
        builder.Connect(scene_graph.get_query_output_port(), sensor.query_object_input_port())
        self.observers = []
        for tag_id, size in TAGS:
            observer = builder.AddNamedSystem(
                f"tag_observer_{tag_id}",
                TagObserver(
                    TagObserverConfig(tag_id=tag_id, tag_size=size),
                    render_intrinsics(camera),
                    None,
                    camera.X_PC(),
                    update_period_sec=update_period_sec,
                    input_scale=s,
                    image_size=(camera.width, camera.height),
                ),
            )
            builder.Connect(sensor.color_image_output_port(), observer.rgb_image_input_port())
            self.observers.append(observer)
        self.plant, self.sensor = plant, sensor
        self.diagram = builder.Build()
        self.context = self.diagram.CreateDefaultContext()
        self.plant_context = plant.GetMyMutableContextFromRoot(self.context)
        self.place(None, AWAY)

    def place(self, which: int | None, X_PT: RigidTransform, X_P_occluder: RigidTransform = AWAY) -> None:
        """Put tag ``which`` (index into TAGS) at X_PT, the other tags away."""
        for k, body in enumerate(self.bodies):
            self.plant.SetFreeBodyPose(self.plant_context, body, X_PT if k == which else AWAY)
        self.plant.SetFreeBodyPose(self.plant_context, self.occluder, X_P_occluder)

    def observer_context(self, which: int):
        return self.observers[which].GetMyMutableContextFromRoot(self.context)

    def read(self, which: int) -> tuple[RigidTransform, float, float]:
        """(X_PO_measured, valid, reprojection error) of observer ``which``."""
        observer, context = self.observers[which], self.observer_context(which)
        return (
            RigidTransform(observer.X_PO_measured_output_port().Eval(context)),  # a copy, not the cache
            float(observer.X_PO_valid_output_port().Eval(context)[0]),
            float(observer.reprojection_error_output_port().Eval(context)[0]),
        )


def palm_poses(count: int, seed: int, camera: CameraConfig) -> list[tuple[int, RigidTransform]]:
    """(tag index, X_PT): a tag on an object 45-90 mm in front of the palm camera (55-90 mm
    for the 40 mm tag, so it stays in view), facing the palm, tilted up to 25 deg about
    x and y, any roll about its normal, up to 8 mm off the camera axis."""
    rng = np.random.default_rng(seed)
    p_PC = np.asarray(camera.xyz)
    poses = []
    for k in range(count):
        which = k % len(TAGS)
        near = 0.045 if TAGS[which][1] <= 0.03 else 0.055
        rpy = RollPitchYaw(
            np.deg2rad(rng.uniform(-25, 25)), np.deg2rad(rng.uniform(-25, 25)), rng.uniform(-np.pi, np.pi)
        )
        R_PT = RotationMatrix(rpy) @ RotationMatrix.MakeXRotation(np.pi)
        p_PT = p_PC + [rng.uniform(-0.008, 0.008), rng.uniform(-0.008, 0.008), rng.uniform(near, 0.09)]
        poses.append((which, RigidTransform(R_PT, p_PT)))
    return poses


@pytest.fixture(scope="module")
def camera() -> CameraConfig:
    return CameraConfig().validate()


@pytest.fixture(scope="module")
def scene(tmp_path_factory, camera) -> TagScene:
    return TagScene(tmp_path_factory.mktemp("textures"), camera)


def test_rendered_pose_accuracy(scene, camera):
    """The observer against the true pose over 20 rendered views (DESIGN section 8 goal:
    < 0.1 mm and < 0.3 deg mean)."""
    errors, detect_s, render_s = [], [], []
    for which, X_PT in palm_poses(20, seed=1, camera=camera):
        scene.place(which, X_PT)
        start = time.perf_counter()
        scene.sensor.color_image_output_port().Eval(scene.sensor.GetMyContextFromRoot(scene.context))
        render_s.append(time.perf_counter() - start)
        start = time.perf_counter()
        X_PO, valid, error_px = scene.read(which)
        detect_s.append(time.perf_counter() - start)
        assert valid == 1.0, f"tag {TAGS[which]} not found at {X_PT.translation()}"
        assert error_px < 0.5
        errors.append(pose_errors(X_PO, X_PT))
        # The other observer does not see its tag: invalid, identity held.
        _, other_valid, other_error = scene.read(1 - which)
        assert other_valid == 0.0 and np.isnan(other_error)
    errors = np.array(errors)
    print(
        f"\nrendered ({camera.render_scale}x, {camera.width}x{camera.height}): position mean "
        f"{errors[:, 0].mean():.4f} max {errors[:, 0].max():.4f} mm; rotation mean {errors[:, 1].mean():.3f} "
        f"max {errors[:, 1].max():.3f} deg; render {1e3 * np.median(render_s):.0f} ms, observer (downsample, "
        f"detect, refine, PnP) {1e3 * np.median(detect_s):.1f} ms per frame (median)"
    )
    assert errors[:, 0].mean() < 0.1 and errors[:, 0].max() < 0.3
    assert errors[:, 1].mean() < 0.3 and errors[:, 1].max() < 1.0


def test_rendered_lost_tag_holds_the_last_pose(scene, camera):
    which = 0
    observer, context = scene.observers[which], scene.observer_context(which)
    X_PT = RigidTransform(RotationMatrix(RollPitchYaw(np.pi + 0.1, -0.15, 0.7)), [0.003, -0.002, 0.045])
    scene.place(which, X_PT)
    X_PO, valid, _ = scene.read(which)
    assert valid == 1.0
    observer.ExecuteForcedEvents(context, publish=False)
    held = observer.held_pose(context)
    np.testing.assert_array_equal(held.GetAsMatrix4(), X_PO.GetAsMatrix4())
    lost_views = {
        "blank": (AWAY, AWAY),
        "out_of_view": (RigidTransform(X_PT.rotation(), X_PT.translation() + [0.08, 0.0, 0.0]), AWAY),
        # The occluder's edge on the tag's centre, 10 mm in front of it: half the tag hidden.
        "occluded_half": (X_PT, RigidTransform(X_PT.translation() + [0.05, 0.0, -0.01])),
    }
    for name, (X_tag, X_occluder) in lost_views.items():
        scene.place(which, X_tag, X_occluder)
        X_PO_lost, valid, _ = scene.read(which)
        assert valid == 0.0, name
        np.testing.assert_array_equal(X_PO_lost.GetAsMatrix4(), held.GetAsMatrix4(), err_msg=name)
        observer.ExecuteForcedEvents(context, publish=False)  # an invalid frame keeps the held pose
        np.testing.assert_array_equal(observer.held_pose(context).GetAsMatrix4(), held.GetAsMatrix4())


def test_rendered_periodic_update_in_a_simulation(tmp_path, camera):
    """With update_period_sec the held pose is refreshed by the simulator's periodic event."""
    scene = TagScene(tmp_path, camera, update_period_sec=0.05)
    X_PT = RigidTransform(RotationMatrix(RollPitchYaw(np.pi - 0.1, 0.2, -1.2)), [-0.004, 0.003, 0.05])
    scene.place(0, X_PT)
    simulator = Simulator(scene.diagram, scene.context)
    simulator.AdvanceTo(0.12)
    held = scene.observers[0].held_pose(scene.observer_context(0))
    assert pose_errors(held, X_PT)[0] < 0.3
    assert pose_errors(scene.observers[1].held_pose(scene.observer_context(1)), RigidTransform())[0] == 0.0


# ----------------------------------------------------------------- FixValue + Eval, synthetic


@pytest.fixture(scope="module")
def synthetic(camera):
    K = camera.intrinsic_matrix()
    X_CT = RigidTransform(RotationMatrix(RollPitchYaw(np.pi + 0.15, -0.1, 0.4)), [0.002, -0.003, 0.06])
    return K, X_CT, render_tag_view(X_CT, K, camera.width, camera.height)


def make_observer(K, camera, **kwargs) -> TagObserver:
    return TagObserver(TagObserverConfig(tag_id=3, tag_size=0.03), K, None, camera.X_PC(), **kwargs)


def test_observer_ports_fixvalue_eval(synthetic, camera):
    K, X_CT, gray = synthetic
    observer = make_observer(K, camera)
    assert observer.rgb_image_input_port().get_name() == "rgb_image"
    assert observer.X_PO_measured_output_port().get_name() == "X_PO_measured"
    assert observer.X_PO_valid_output_port().get_name() == "X_PO_valid"
    assert observer.reprojection_error_output_port().get_name() == "reprojection_error"
    assert observer.X_PO_held_output_port().get_name() == "X_PO_held"
    assert observer.X_PO_held_valid_output_port().get_name() == "X_PO_held_valid"
    context = observer.CreateDefaultContext()
    np.testing.assert_array_equal(observer.held_pose(context).GetAsMatrix4(), np.eye(4))
    np.testing.assert_array_equal(observer.X_PO_held_output_port().Eval(context).GetAsMatrix4(), np.eye(4))
    assert observer.X_PO_held_valid_output_port().Eval(context)[0] == 0.0  # no update yet
    # Blank image first: identity (the initial held pose), invalid.
    observer.rgb_image_input_port().FixValue(context, to_rgba(np.full_like(gray, 180)))
    np.testing.assert_array_equal(
        observer.X_PO_measured_output_port().Eval(context).GetAsMatrix4(), np.eye(4)
    )
    assert observer.X_PO_valid_output_port().Eval(context)[0] == 0.0
    assert np.isnan(observer.reprojection_error_output_port().Eval(context)[0])
    # The tag: a valid pose X_PC X_CT from the current image, before any update.
    observer.rgb_image_input_port().FixValue(context, to_rgba(gray))
    X_PO = RigidTransform(observer.X_PO_measured_output_port().Eval(context))
    assert observer.X_PO_valid_output_port().Eval(context)[0] == 1.0
    assert 0.0 <= observer.reprojection_error_output_port().Eval(context)[0] < 0.5
    dp, dr = pose_errors(X_PO, camera.X_PC() @ X_CT)
    assert dp < 0.2 and dr < 0.3
    # Forced update stores it; a blank image then returns it, invalid.
    state = context.get_mutable_state()
    observer.CalcForcedUnrestrictedUpdate(context, state)
    np.testing.assert_array_equal(observer.held_pose(context).GetAsMatrix4(), X_PO.GetAsMatrix4())
    np.testing.assert_array_equal(observer.X_PO_held_output_port().Eval(context).GetAsMatrix4(), X_PO.GetAsMatrix4())
    assert observer.X_PO_held_valid_output_port().Eval(context)[0] == 1.0
    observer.rgb_image_input_port().FixValue(context, to_rgba(np.full_like(gray, 180)))
    assert observer.X_PO_held_valid_output_port().Eval(context)[0] == 1.0  # the held ports read no frame
    assert observer.X_PO_valid_output_port().Eval(context)[0] == 0.0
    np.testing.assert_array_equal(
        observer.X_PO_measured_output_port().Eval(context).GetAsMatrix4(), X_PO.GetAsMatrix4()
    )
    # An update on the blank frame keeps the pose and says its frame was not valid.
    observer.ExecuteForcedEvents(context, publish=False)
    np.testing.assert_array_equal(observer.X_PO_held_output_port().Eval(context).GetAsMatrix4(), X_PO.GetAsMatrix4())
    assert observer.X_PO_held_valid_output_port().Eval(context)[0] == 0.0


def test_observer_applies_X_TO_and_input_scale(synthetic, camera):
    K, X_CT, _ = synthetic
    K2 = K.copy()
    K2[:2, :2] *= 2
    K2[:2, 2] = 2 * K[:2, 2] + 0.5  # downsampling by 2 maps this back to K
    big = render_tag_view(X_CT, K2, 2 * camera.width, 2 * camera.height)
    X_TO = RigidTransform(RotationMatrix(RollPitchYaw(0.3, 0.0, 0.1)), [0.0, 0.0, -0.025])
    observer = make_observer(K, camera, X_TO=X_TO, input_scale=2, image_size=(camera.width, camera.height))
    context = observer.CreateDefaultContext()
    observer.rgb_image_input_port().FixValue(context, to_rgba(big))
    assert observer.X_PO_valid_output_port().Eval(context)[0] == 1.0
    dp, dr = pose_errors(observer.X_PO_measured_output_port().Eval(context), camera.X_PC() @ X_CT @ X_TO)
    assert dp < 0.3 and dr < 0.3
    # The same image without input_scale does not match image_size: a clear error.
    wrong = make_observer(K, camera, image_size=(camera.width, camera.height))
    wrong_context = wrong.CreateDefaultContext()
    wrong.rgb_image_input_port().FixValue(wrong_context, to_rgba(big))
    with pytest.raises(ValueError, match="rgb_image"):
        wrong.X_PO_valid_output_port().Eval(wrong_context)


def test_observer_pixel_noise_is_seeded_by_time(synthetic, camera):
    K, X_CT, gray = synthetic
    observer = make_observer(K, camera, pixel_noise_std=4.0, seed=5)
    context = observer.CreateDefaultContext()
    observer.rgb_image_input_port().FixValue(context, to_rgba(gray))
    first = observer.reprojection_error_output_port().Eval(context)[0]
    assert observer.X_PO_valid_output_port().Eval(context)[0] == 1.0
    dp, dr = pose_errors(observer.X_PO_measured_output_port().Eval(context), camera.X_PC() @ X_CT)
    assert dp < 0.3 and dr < 0.5
    image = observer.prepare_image(to_rgba(gray).data, time=0.0)
    np.testing.assert_array_equal(image, observer.prepare_image(to_rgba(gray).data, time=0.0))
    assert not np.array_equal(image, observer.prepare_image(to_rgba(gray).data, time=0.1))
    context.SetTime(0.1)
    assert observer.reprojection_error_output_port().Eval(context)[0] != first
    quiet = make_observer(K, camera)
    np.testing.assert_array_equal(quiet.prepare_image(to_rgba(gray).data), to_rgba(gray).data)


def test_observer_bad_arguments(camera):
    K = camera.intrinsic_matrix()
    with pytest.raises(ValueError, match="K"):
        make_observer(np.eye(2), camera)
    for bad in (0, 1.5, np.inf, np.nan):  # inf and NaN ended in int()'s errors, which name nothing
        with pytest.raises(ValueError, match="input_scale.*must be a positive integer"):
            make_observer(K, camera, input_scale=bad)
        with pytest.raises(ValueError, match="scale: must be a positive integer"):
            downsample_area(np.zeros((4, 4), np.uint8), bad)
    with pytest.raises(ValueError, match="update_period_sec"):
        make_observer(K, camera, update_period_sec=0.0)
    for offset in (-0.01, 0.1, np.nan):  # within the period, or the update never lines up with the filter's
        with pytest.raises(ValueError, match=r"'update_offset_sec' must be in \[0, update_period_sec = 0.1\)"):
            make_observer(K, camera, update_period_sec=0.1, update_offset_sec=offset)
    with pytest.raises(ValueError, match="'update_offset_sec' needs a periodic update"):
        make_observer(K, camera, update_offset_sec=0.05)
    with pytest.raises(ValueError, match="pixel_noise_std"):
        make_observer(K, camera, pixel_noise_std=-1.0)
    with pytest.raises(ValueError, match="image_size"):
        make_observer(K, camera, image_size=(640,))
    # a negative seed failed at the first frame, in numpy, without naming the field
    for seed in (-1, 2.5):
        with pytest.raises(ValueError, match=rf"'seed' must be an integer >= 0, got {seed}"):
            make_observer(K, camera, seed=seed)
        with pytest.raises(ValueError, match=rf"'seed' must be an integer >= 0, got {seed}"):
            NoisyPoseSensor(sigma_p=1e-4, sigma_r=1e-3, seed=seed)
    with pytest.raises(TypeError, match="X_PC"):
        TagObserver(TagObserverConfig(), K, None, np.eye(4))
    with pytest.raises(ValueError, match="tag_size"):
        TagObserver(TagObserverConfig(tag_size=-0.01), K, None, RigidTransform())
    with pytest.raises(TypeError, match="X_PC must be a pydrake.math.RigidTransform, got NoneType"):
        TagObserver(TagObserverConfig(), K, None, None)  # the camera's pose is no default (X_TO is)
    # a period or a noise that is not finite froze the sensor after one draw, or blanked the image
    with pytest.raises(ValueError, match="'update_period_sec' must be a positive finite number"):
        make_observer(K, camera, update_period_sec=np.inf)
    with pytest.raises(ValueError, match="'pixel_noise_std' must be a finite number >= 0"):
        make_observer(K, camera, pixel_noise_std=np.inf)
    with pytest.raises(ValueError, match="standard deviation must be a finite number"):
        add_pixel_noise(np.zeros((4, 4), np.uint8), np.inf, np.random.default_rng(0))
    # a tag id that is no whole number was read as another tag (3.5 as 3)
    for bad in (3.5, np.nan, True, "3"):
        with pytest.raises(ValueError, match="'tag_id' must be a whole number"):
            TagObserverConfig(tag_id=bad).validate()
    assert TagObserverConfig(tag_id=np.int64(3)).validate().tag_id == 3
    observer = make_observer(K, camera)
    context = observer.CreateDefaultContext()
    observer.rgb_image_input_port().FixValue(context, ImageRgba8U(1, 1))
    with pytest.raises(ValueError, match="image: too small"):
        observer.X_PO_valid_output_port().Eval(context)
    # an empty frame (a camera that delivered nothing) is a lost frame, as the docstring says
    for scale in (1, 2):
        observer = make_observer(K, camera, input_scale=scale)
        context = observer.CreateDefaultContext()
        observer.rgb_image_input_port().FixValue(context, ImageRgba8U())
        assert observer.X_PO_valid_output_port().Eval(context)[0] == 0.0
        assert np.isnan(observer.reprojection_error_output_port().Eval(context)[0])
    with pytest.raises(ValueError, match="image: too small"):
        to_gray(np.zeros((0, 0, 4), np.uint8))  # named before OpenCV's assertion


# ----------------------------------------------------------------- NoisyPoseSensor


X_TRUE = RigidTransform(RotationMatrix(RollPitchYaw(0.2, -0.1, 0.5)), [0.01, -0.02, 0.07])


def sample(sensor: NoisyPoseSensor, context, count: int) -> tuple[list, np.ndarray]:
    poses, valid = [], []
    for _ in range(count):
        sensor.ExecuteForcedEvents(context, publish=False)
        poses.append(RigidTransform(sensor.X_PO_measured_output_port().Eval(context)))  # copy the cache
        valid.append(sensor.X_PO_valid_output_port().Eval(context)[0])
    return poses, np.array(valid)


def test_noisy_sensor_without_noise_is_exact():
    sensor = NoisyPoseSensor(sigma_p=0.0, sigma_r=0.0)
    assert sensor.X_PO_true_input_port().get_name() == "X_PO_true"
    assert sensor.X_PO_measured_output_port().get_name() == "X_PO_measured"
    assert sensor.X_PO_valid_output_port().get_name() == "X_PO_valid"
    context = sensor.CreateDefaultContext()
    sensor.X_PO_true_input_port().FixValue(context, X_TRUE)
    np.testing.assert_allclose(
        sensor.X_PO_measured_output_port().Eval(context).GetAsMatrix4(), X_TRUE.GetAsMatrix4(), atol=1e-15
    )
    assert sensor.X_PO_valid_output_port().Eval(context)[0] == 1.0


def test_noisy_sensor_statistics_and_seed():
    sigma_p, sigma_r = 2e-4, np.deg2rad(0.5)
    sensor = NoisyPoseSensor(sigma_p=sigma_p, sigma_r=sigma_r, seed=11)
    context = sensor.CreateDefaultContext()
    sensor.X_PO_true_input_port().FixValue(context, X_TRUE)
    poses, valid = sample(sensor, context, 600)
    assert np.all(valid == 1.0)
    dp = np.array([X.translation() - X_TRUE.translation() for X in poses])
    w = np.array(
        [
            (X.rotation() @ X_TRUE.rotation().inverse()).ToAngleAxis().axis()
            * (X.rotation() @ X_TRUE.rotation().inverse()).ToAngleAxis().angle()
            for X in poses
        ]
    )
    np.testing.assert_allclose(dp.std(axis=0), sigma_p, rtol=0.12)
    np.testing.assert_allclose(w.std(axis=0), sigma_r, rtol=0.12)
    assert np.all(np.abs(dp.mean(axis=0)) < 4 * sigma_p / np.sqrt(600))
    # Same seed, same stream; another seed, another stream.
    again = sensor.CreateDefaultContext()
    sensor.X_PO_true_input_port().FixValue(again, X_TRUE)
    repeat, _ = sample(sensor, again, 5)
    for a, b in zip(poses[:5], repeat, strict=True):
        np.testing.assert_array_equal(a.GetAsMatrix4(), b.GetAsMatrix4())
    other = NoisyPoseSensor(sigma_p=sigma_p, sigma_r=sigma_r, seed=12)
    other_context = other.CreateDefaultContext()
    other.X_PO_true_input_port().FixValue(other_context, X_TRUE)
    assert not np.allclose(sample(other, other_context, 1)[0][0].translation(), poses[0].translation())


def test_noisy_sensor_follows_the_current_input():
    sensor = NoisyPoseSensor(sigma_p=1e-3, sigma_r=0.01, seed=3)
    context = sensor.CreateDefaultContext()
    sensor.X_PO_true_input_port().FixValue(context, X_TRUE)
    before = RigidTransform(sensor.X_PO_measured_output_port().Eval(context))
    moved = RigidTransform(X_TRUE.rotation(), X_TRUE.translation() + [0.005, 0.0, 0.0])
    sensor.X_PO_true_input_port().FixValue(context, moved)
    after = sensor.X_PO_measured_output_port().Eval(context)
    np.testing.assert_allclose(after.translation() - before.translation(), [0.005, 0.0, 0.0], atol=1e-15)


def test_noisy_sensor_dropout_holds_the_last_valid_pose():
    sensor = NoisyPoseSensor(sigma_p=1e-3, sigma_r=0.01, dropout_probability=0.3, seed=4)
    context = sensor.CreateDefaultContext()
    sensor.X_PO_true_input_port().FixValue(context, X_TRUE)
    poses, valid = sample(sensor, context, 500)
    assert abs((valid == 0.0).mean() - 0.3) < 0.06
    last_valid = None
    for X, v in zip(poses, valid, strict=True):
        if v == 1.0:
            last_valid = X
        elif last_valid is not None:
            np.testing.assert_array_equal(X.GetAsMatrix4(), last_valid.GetAsMatrix4())
    assert len({tuple(X.translation()) for X in poses}) == int(valid.sum())


def test_noisy_sensor_periodic_update_in_a_simulation():
    builder = DiagramBuilder()
    sensor = builder.AddNamedSystem("pose_sensor", NoisyPoseSensor(1e-4, 1e-3, seed=2, update_period_sec=0.1))
    diagram = builder.Build()
    context = diagram.CreateDefaultContext()
    sensor_context = sensor.GetMyMutableContextFromRoot(context)
    sensor.X_PO_true_input_port().FixValue(sensor_context, X_TRUE)
    Simulator(diagram, context).AdvanceTo(0.55)
    # Events at 0.0, 0.1, ..., 0.5: six samples drawn after the initial one.
    assert sensor_context.get_discrete_state(0).GetAtIndex(0) == 6.0
    np.testing.assert_array_equal(
        sensor.held_pose(sensor_context).GetAsMatrix4(),
        sensor.X_PO_measured_output_port().Eval(sensor_context).GetAsMatrix4(),
    )


def test_noisy_sensor_bad_arguments():
    with pytest.raises(ValueError, match="sigma_p"):
        NoisyPoseSensor(-1.0, 0.0)
    with pytest.raises(ValueError, match="sigma_r"):
        NoisyPoseSensor(0.0, -1.0)
    with pytest.raises(ValueError, match="dropout_probability"):
        NoisyPoseSensor(0.0, 0.0, dropout_probability=1.0)
    with pytest.raises(ValueError, match="rotation vector"):
        rotation_from_vector(np.zeros(4))
    with pytest.raises(ValueError, match="update_period_sec"):
        NoisyPoseSensor(0.0, 0.0, update_period_sec=-0.1)


def test_rotation_from_vector_matches_drake():
    w = np.array([0.3, -0.2, 0.5])
    from pydrake.common.eigen_geometry import AngleAxis

    expected = RotationMatrix(AngleAxis(np.linalg.norm(w), w / np.linalg.norm(w)))
    np.testing.assert_allclose(rotation_from_vector(w).matrix(), expected.matrix(), atol=1e-14)
    np.testing.assert_array_equal(rotation_from_vector(np.zeros(3)).matrix(), np.eye(3))


def test_observer_checks_its_intrinsics_at_construction(camera):
    """A zero K, or NaN distortion, used to be accepted and fail at the first frame with a
    tag, inside OpenCV."""
    K = camera.intrinsic_matrix()
    with pytest.raises(ValueError, match="K: camera matrix"):
        make_observer(np.zeros((3, 3)), camera)
    with pytest.raises(ValueError, match="dist"):
        TagObserver(TagObserverConfig(tag_id=3), K, np.full(5, np.nan), camera.X_PC())
    with pytest.raises(ValueError, match="dist"):
        TagObserver(TagObserverConfig(tag_id=3), K, np.zeros(3), camera.X_PC())
    with pytest.raises(ValueError, match="X_PC"):
        TagObserver(TagObserverConfig(tag_id=3), K, None, RigidTransform([np.nan, 0.0, 0.0]))


def test_noisy_sensor_refuses_a_non_finite_true_pose_and_noise():
    """A NaN true pose used to come out as a NaN measurement marked valid."""
    sensor = NoisyPoseSensor(1e-4, 1e-3)
    context = sensor.CreateDefaultContext()
    sensor.X_PO_true_input_port().FixValue(context, RigidTransform([np.nan, 0.0, 0.0]))
    with pytest.raises(ValueError, match="X_PO_true"):
        sensor.X_PO_measured_output_port().Eval(context)
    with pytest.raises(ValueError, match="sigma_p"):
        NoisyPoseSensor(np.inf, 0.0)
    with pytest.raises(ValueError, match="sigma_r"):
        NoisyPoseSensor(0.0, np.nan)
