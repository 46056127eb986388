"""SDFormat models: generated files are current, parse in Drake and match the specs."""

from __future__ import annotations

import numpy as np
import pytest
from pydrake.common.yaml import yaml_load_typed
from pydrake.math import RigidTransform
from pydrake.multibody.parsing import Parser
from pydrake.multibody.plant import MultibodyPlant
from pydrake.multibody.tree import ForceElementIndex, RevoluteSpring

from vlr_drake.hand import NOVEL_FINGER_NAMES, generic_hand, hand_by_name, novel_finger
from vlr_drake.models import (
    PAD_FRACTION,
    PAD_SPHERE_SPACING,
    configure_parser,
    finger_sdf,
    generated_models,
    hand_sdf,
    joint_name,
    link_name,
    models_dir,
    pad_frame_name,
    pad_geometry_name,
)
from vlr_drake.objects import (
    PAPER_OBJECTS,
    ObjectSpec,
    generated_object_files,
    object_model_path,
    object_sdf,
    preset,
    preset_names,
    tag_texture_path,
)

HANDS = ["model_o", "NH1", "NH2", "NH3"]


def _plant(text: str | None = None, url: str | None = None):
    plant = MultibodyPlant(0.001)
    parser = Parser(plant)
    configure_parser(parser)
    models = parser.AddModelsFromString(text, "sdf") if text is not None else parser.AddModels(url=url)
    return plant, models[0]


def _e(u, a):
    return np.sin(a) * u + np.cos(a) * np.array([0.0, 0.0, 1.0])


def test_generated_files_are_current():
    """The files in models/ are what the generator writes now (regenerate with
    `python -m vlr_drake.models --write`)."""
    root = models_dir()
    files = {**generated_models(), **generated_object_files()}
    for rel, text in files.items():
        path = root / rel
        assert path.exists(), f"{rel} missing: run python -m vlr_drake.models --write"
        assert path.read_text() == text, f"{rel} is stale: run python -m vlr_drake.models --write"
    import cv2

    from vlr_drake.perception.apriltag import tag_image

    ids = {preset(name).tag_id for name in preset_names()}
    for tag_id in ids:  # the textures too, pixel for pixel (as write_tag_texture makes them)
        png = cv2.imread(str(tag_texture_path(tag_id)), cv2.IMREAD_GRAYSCALE)
        assert png is not None, f"texture of tag {tag_id} missing: run python -m vlr_drake.models --write"
        np.testing.assert_array_equal(png, tag_image(tag_id, pixels_per_cell=32, quiet_cells=1),
                                      err_msg=f"texture of tag {tag_id} is stale")
    # and nothing else: a model the generator no longer writes is stale too
    expected = set(files) | {tag_texture_path(i).relative_to(root).as_posix() for i in ids}
    found = {p.relative_to(root).as_posix() for d in ("hands", "fingers", "objects") for p in (root / d).rglob("*")
             if p.is_file()}
    assert found <= expected, f"files the generator does not write: {sorted(found - expected)}"


@pytest.mark.parametrize(
    "rel", sorted(p.relative_to(models_dir()).as_posix() for p in models_dir().rglob("*.sdf"))
)
def test_every_model_file_parses(rel):
    plant, _ = _plant(url=f"package://vlr_drake/{rel}")
    plant.Finalize()
    assert plant.num_bodies() > 1


@pytest.mark.parametrize("name", HANDS)
def test_hand_file_matches_spec(name):
    """Joint positions, axes, link lengths, springs, limits and pad frames of the file in
    models/hands, parsed by Drake, follow DESIGN.md section 2 for random joint angles."""
    spec = hand_by_name(name)
    plant, inst = _plant(url=f"package://vlr_drake/hands/{name}.sdf")
    plant.WeldFrames(plant.world_frame(), plant.GetFrameByName("palm", inst), RigidTransform())
    plant.Finalize()
    hm = spec.model()
    assert plant.num_positions() == hm.num_angles
    ctx = plant.CreateDefaultContext()
    rng = np.random.default_rng(1)
    elements = [plant.get_force_element(ForceElementIndex(i)) for i in range(plant.num_force_elements())]
    springs = {e.joint().name(): e for e in elements if isinstance(e, RevoluteSpring)}
    assert len(springs) == hm.num_angles
    theta = rng.uniform(-0.2, 1.2, size=(hm.N, hm.K))
    for i, f in enumerate(spec.fingers):
        for k in range(hm.K):
            j = plant.GetJointByName(joint_name(f.name, k + 1), inst)
            j.set_angle(ctx, theta[i, k])
            assert j.position_lower_limits()[0] == pytest.approx(f.joint_lower[k])
            assert j.position_upper_limits()[0] == pytest.approx(f.joint_upper[k])
            assert j.default_damping() == pytest.approx(f.joint_damping[k])
            s = springs[j.name()]
            assert s.default_stiffness() == pytest.approx(f.stiffness[k])
            assert s.default_nominal_angle() == pytest.approx(f.rest_angles[k])
    palm = plant.GetFrameByName("palm", inst)
    for i, f in enumerate(spec.fingers):
        u = hm.u[i]
        q = hm.base[i].copy()
        phi = 0.0
        lengths = list(f.link_lengths) + [f.distal_length]
        for k in range(hm.K):
            phi += theta[i, k]
            X = plant.GetFrameByName(link_name(f.name, k + 1), inst).CalcPose(ctx, palm)
            np.testing.assert_allclose(X.translation(), q, atol=1e-12)
            # Joint axis w = z x u, link axis e(phi).
            w = np.cross([0.0, 0.0, 1.0], u)
            j = plant.GetJointByName(joint_name(f.name, k + 1), inst)
            np.testing.assert_allclose(X.rotation() @ j.revolute_axis(), w, atol=1e-12)
            np.testing.assert_allclose(X.rotation().col(2), _e(u, phi), atol=1e-12)
            q = q + lengths[k] * _e(u, phi)
        # Pad frame: p = q_K + d e(phi_K + gamma), a = PAD_FRACTION * distal, n = pad_offset.
        a, n = PAD_FRACTION * f.distal_length, f.pad_offset
        q_K = q - f.distal_length * _e(u, phi)
        p = q_K + np.hypot(a, n) * _e(u, phi + np.arctan2(n, a))
        X_pad = plant.GetFrameByName(pad_frame_name(f.name), inst).CalcPose(ctx, palm)
        np.testing.assert_allclose(X_pad.translation(), p, atol=1e-12)


def test_pad_geometry():
    """Two spheres across the finger whose surfaces touch the pad plane at pad_offset."""
    spec = hand_by_name("NH3")
    plant, inst = _plant(text=hand_sdf(spec))
    from pydrake.geometry import SceneGraph

    sg = SceneGraph()
    plant.RegisterAsSourceForSceneGraph(sg)
    plant2 = MultibodyPlant(0.001)
    plant2.RegisterAsSourceForSceneGraph(sg)
    parser = Parser(plant2)
    configure_parser(parser)
    (inst2,) = parser.AddModelsFromString(hand_sdf(spec), "sdf")
    plant2.Finalize()
    insp = sg.model_inspector()
    for i, f in enumerate(spec.fingers):
        body = plant2.GetBodyByName(link_name(f.name, spec.num_joints_per_finger), inst2)
        ids = {insp.GetName(g).split("::")[-1]: g for g in plant2.GetCollisionGeometriesForBody(body)}
        centers = []
        for side in (0, 1):
            g = ids[pad_geometry_name(f.name, side)]
            assert insp.GetShape(g).radius() == pytest.approx(f.pad_radius)
            centers.append(insp.GetPoseInFrame(g).translation())
        centers = np.array(centers)
        assert abs(centers[0, 1] - centers[1, 1]) == pytest.approx(PAD_SPHERE_SPACING)
        np.testing.assert_allclose(centers[:, 0] + f.pad_radius, f.pad_offset)
        # the VLR contact offset is the spheres' centre (the pad's centre of curvature)
        np.testing.assert_allclose(centers[:, 0], spec.model().pad[i])
        np.testing.assert_allclose(centers[:, 2], PAD_FRACTION * f.distal_length)
        assert insp.GetProximityProperties(g).GetProperty(
            "material", "coulomb_friction"
        ).static_friction() == pytest.approx(f.friction)
    del plant, inst


@pytest.mark.parametrize("name", NOVEL_FINGER_NAMES)
def test_finger_file_matches_spec(name):
    f = novel_finger(name)
    plant, inst = _plant(url=f"package://vlr_drake/fingers/{name}.sdf")
    plant.WeldFrames(plant.world_frame(), plant.GetFrameByName("mount", inst), RigidTransform())
    plant.Finalize()
    ctx = plant.CreateDefaultContext()
    K = f.num_joints
    mount = plant.GetFrameByName("mount", inst)
    z = 0.0
    for k in range(K):
        X = plant.GetFrameByName(link_name(f.name, k + 1), inst).CalcPose(ctx, mount)
        np.testing.assert_allclose(X.translation(), [0, 0, z], atol=1e-12)
        z += (list(f.link_lengths) + [f.distal_length])[k]
    X_pad = plant.GetFrameByName(pad_frame_name(f.name), inst).CalcPose(ctx, mount)
    np.testing.assert_allclose(
        X_pad.translation(),
        [f.pad_offset, 0, sum(f.link_lengths) + PAD_FRACTION * f.distal_length],
        atol=1e-12,
    )
    assert finger_sdf(f) in generated_models()[f"fingers/{name}.sdf"]


def test_generic_hand_parses_with_general_N_K():
    spec = generic_hand(5, 4)
    plant, inst = _plant(text=hand_sdf(spec))
    plant.WeldFrames(plant.world_frame(), plant.GetFrameByName("palm", inst), RigidTransform())
    plant.Finalize()
    assert plant.num_positions() == 20
    assert plant.HasFrameNamed(pad_frame_name("f4"), inst)


# -- objects ------------------------------------------------------------------------------


@pytest.mark.parametrize("name", preset_names())
def test_object_model_frames(name):
    """The generated model's tag and POM frames are where the spec puts them; mass matches."""
    spec = preset(name)
    plant, inst = _plant(url=object_model_path(name))
    plant.Finalize()
    body = plant.GetBodyByName("body", inst)
    assert body.default_mass() == pytest.approx(spec.mass)
    X_BO = plant.GetFrameByName("pom", inst).GetFixedPoseInBodyFrame()
    assert X_BO.IsNearlyEqualTo(spec.X_BO(), 1e-9)
    X_BT = plant.GetFrameByName("tag", inst).GetFixedPoseInBodyFrame()
    # The tag's z axis is the face's outward normal; it sits just outside the face.
    from vlr_drake.objects import FACES, TAG_STANDOFF

    n = np.array(FACES[spec.tag_face])
    np.testing.assert_allclose(X_BT.rotation().col(2), n, atol=1e-12)
    assert X_BT.translation() @ n == pytest.approx(spec.face_extent() + TAG_STANDOFF)


def test_paper_objects_present():
    assert set(PAPER_OBJECTS) <= set(preset_names())
    assert object_sdf(preset("marble_maze")).count("<link") == 1  # the plate; its marble is the maze task's


def test_object_spec_loads_from_yaml():
    spec = yaml_load_typed(
        schema=ObjectSpec,
        data="""
name: mug
shape: cylinder
size: [0.04, 0.09]
mass: 0.2
tag_id: 7
tag_size: 0.025
tag_face: "-z"
placement_xyz: [0.0, 0.0, 0.08]
""",
    )
    spec.validate()
    assert spec.shape == "cylinder" and spec.size == [0.04, 0.09] and spec.tag_id == 7
    assert spec.tag_to_pom_xyz == [0.0, 0.0, 0.0]


@pytest.mark.parametrize(
    ("changes", "field"),
    [
        (dict(mass=-0.1), "mass"),
        (dict(tag_id=587), "tag_id"),
        (dict(tag_id=-1), "tag_id"),
        (dict(shape="cone"), "shape"),
        (dict(size=[0.03, 0.04]), "size"),
        (dict(size=[-0.03]), "size"),
        (dict(tag_size=0.0), "tag_size"),
        (dict(tag_face="top"), "tag_face"),
        (dict(placement_xyz=[0.0, 0.0]), "placement_xyz"),
        (dict(marble_radius=0.01), "marble"),
        (dict(shape="box", size=[0.05, 0.05, 0.01], marble_radius=0.03), "marble_radius"),
        (dict(tag_id=float("nan")), "tag_id"),
        (dict(tag_id=None), "tag_id"),
        (dict(tag_id=2.5), "tag_id"),
        (dict(name='a"b'), "name"),
        (dict(name=""), "name"),
        (dict(name="a::b"), "name"),
        (dict(mass="heavy"), "mass"),
        (dict(size=["big"]), "size"),
        (dict(tag_size=0.2), "tag_size"),  # a 0.25 m plate on the default 37.5 mm sphere
        (dict(friction="1"), "friction"),
        (dict(friction=float("nan")), "friction"),
        (dict(tag_size=float("inf")), "tag_size"),
        (dict(rim_height=float("nan")), "rim_height"),
        # lengths in millimetres (the POM 20 m from its tag had been taken), positions of
        # another type, and a tag whose corners hang over a cylinder's flat end (a review)
        (dict(tag_to_pom_xyz=[0.0, 0.0, 20.0]), r"'tag_to_pom_xyz'.*given in millimetres"),
        (dict(placement_xyz=[0.0, 0.0, 70.0]), r"'placement_xyz'.*given in millimetres"),
        (dict(shape="box", size=[0.05, 0.05, 0.01], rim_height=8.0), r"'rim_height'.*given in millimetres"),
        (dict(tag_size=30.0), "tag_size"),
        (dict(tag_size="0.03"), "tag_size"),
        (dict(size=0.03), "size"),
        (dict(placement_xyz=["a", 0.0, 0.0]), "placement_xyz"),
        (dict(shape="cylinder", size=[0.02, 0.05], tag_size=0.03), "wider than the '-z' face"),
    ],
)
def test_bad_object_spec_names_the_field(changes, field):
    spec = ObjectSpec(**{"name": "bad", **changes})
    with pytest.raises(ValueError, match=field):
        spec.validate()


@pytest.mark.parametrize("shape, size", [("capsule", [0.02, 0.06]), ("cylinder", [0.03, 0.05]), ("box", [0.02, 0.03, 0.05]),
                                         ("sphere", [0.04])])
def test_object_inertia_matches_drake(shape, size):
    """ObjectSpec.inertia against Drake's CalcSpatialInertia of the same shape and mass, about
    the body origin (the capsule's hemispheres were once counted as cylinder: +26% Ixx)."""
    from pydrake.geometry import Box, Capsule, Cylinder, Sphere
    from pydrake.multibody.tree import CalcSpatialInertia

    shapes = {"capsule": lambda s: Capsule(*s), "cylinder": lambda s: Cylinder(*s), "box": lambda s: Box(*s),
              "sphere": lambda s: Sphere(*s)}
    m = 0.1
    unit = CalcSpatialInertia(shapes[shape](size), 1.0)
    M = CalcSpatialInertia(shapes[shape](size), m / unit.get_mass())
    np.testing.assert_allclose(M.get_com(), 0.0, atol=1e-15)
    I = M.CalcRotationalInertia().CopyToFullMatrix3()
    np.testing.assert_allclose(ObjectSpec(name="s", shape=shape, size=size, mass=m).inertia(), np.diag(I), rtol=1e-12)


def test_every_collision_geometry_has_a_hydroelastic_representation():
    """Strict hydroelastic contact builds (a review found the palm, and the marble the maze
    plate then carried, without one: Drake refused the model)."""
    from vlr_drake.systems.physics_plant import PhysicsConfig, build_physics_hand

    for obj in ("marble_maze", "apple"):
        _, ph, _ = build_physics_hand(hand_by_name("model_o"), preset(obj), PhysicsConfig(contact_model="hydroelastic"))
        assert ph.plant.num_bodies() == 2 + 3 * 2 + 1  # world, palm, six links, the object: no marble body


@pytest.mark.parametrize("changes, field", [(dict(stiffness=[0.1]), "stiffness"), (dict(link_radius=-0.01), "link_radius"),
                                            (dict(distal_length=float("nan")), "distal_length"),
                                            (dict(joint_lower=[0.5, 0.5], joint_upper=[0.1, 0.1]), "joint_lower"),
                                            (dict(moment_arms=0.009), "moment_arms")])
def test_a_bad_finger_is_refused_by_name(changes, field):
    """finger_sdf checks its finger as HandSpec.validate checks a hand's (it passed an
    IndexError, a NaN inertia or a negative radius on to Drake)."""
    from dataclasses import replace

    with pytest.raises(ValueError, match=field):
        finger_sdf(replace(novel_finger("NF1"), **changes))


def test_a_custom_tag_mesh_is_written_outside_the_repository_and_removed_at_exit():
    """A tag no preset uses gets its mesh in a temporary directory, which is gone when the
    process that wrote it exits (it had been left behind, one per process)."""
    import subprocess
    import sys
    from pathlib import Path
    from urllib.parse import unquote, urlparse

    used = {preset(n).tag_id for n in preset_names()}
    tag_id = next(i for i in range(500) if i not in used)
    code = (
        "from vlr_drake.objects import tag_mesh_uri\n"
        f"uri = tag_mesh_uri({tag_id})\n"
        "from pathlib import Path; from urllib.parse import urlparse, unquote\n"
        "p = Path(unquote(urlparse(uri).path)); assert p.exists() and p.with_suffix('.mtl').exists(), uri\n"
        "print(uri)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    uri = out.stdout.strip().splitlines()[-1]
    assert uri.startswith("file://"), uri
    path = Path(unquote(urlparse(uri).path))
    assert models_dir() not in path.parents
    assert not path.parents[1].exists(), f"{path.parents[1]} was left behind"
