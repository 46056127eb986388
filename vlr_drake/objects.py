"""Objects held by the hand: a documented spec, presets after the paper's objects, and
SDFormat generation with the AprilTag (tag36h11) the palm camera tracks.

An object is one rigid body B of a simple shape (DESIGN.md section 8). Its tag sits on one
face of the shape, printed on a thin textured quad whose frame is the tag frame T of
:mod:`vlr_drake.perception.apriltag` (x right and y up in the tag image, z out of the
printed face). The POM frame O (the point of manipulation, DESIGN.md section 5) is the tag
frame, optionally offset by a known ``X_TO``. The generated model defines both as frames
``tag`` and ``pom`` attached to the body.

Presets use the YCB object set's published sizes and masses where the paper used YCB
objects (approximate: each object is reduced to the simple shape the fingers touch); see
:func:`preset` for each one. ``python -m vlr_drake.models --write`` writes the models to
``models/objects/`` and the tag textures to ``models/objects/textures/``.
"""

import copy
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from vlr_drake import units
from vlr_drake.kinematics import is_number
from vlr_drake.perception.apriltag import TAG36H11_CELLS, TAG36H11_COUNT, tag_image

__all__ = [
    "ObjectSpec",
    "SHAPES",
    "FACES",
    "PAPER_OBJECTS",
    "CUP_NAMES",
    "preset",
    "preset_names",
    "object_sdf",
    "object_model_path",
    "write_object_models",
    "tag_texture_path",
    "tag_mesh_uri",
]

#: Shapes an object may have, with the meaning of ``size`` for each.
SHAPES = {
    "sphere": "[radius]",
    "box": "[x, y, z] side lengths",
    "cylinder": "[radius, length] (axis along the body's z)",
    "capsule": "[radius, length of the cylindrical part] (axis along the body's z)",
}
#: Faces the tag may sit on: the outward normal in the body frame.
FACES = {
    "+x": (1.0, 0.0, 0.0),
    "-x": (-1.0, 0.0, 0.0),
    "+y": (0.0, 1.0, 0.0),
    "-y": (0.0, -1.0, 0.0),
    "+z": (0.0, 0.0, 1.0),
    "-z": (0.0, 0.0, -1.0),
}
#: Side of the printed tag plate over the tag's side: the tag with its 1-cell quiet zone.
TAG_PLATE_RATIO = (TAG36H11_CELLS + 2) / TAG36H11_CELLS
#: The tag quad floats this far outside the face, so it never z-fights the body [m].
TAG_STANDOFF = 0.0003
#: The five objects of the paper's known-hand experiments.
PAPER_OBJECTS = ("apple", "wine_glass", "toy_block", "flat_screwdriver", "gelatin_box")
#: Cups for the stacking task, held cups in decreasing size, then the target cup.
CUP_NAMES = ("cup_1", "cup_2", "cup_3", "cup_4", "cup_target")


@dataclass
class ObjectSpec:
    """A rigid object with an AprilTag at its point of manipulation (POM)."""

    # Name of the object (model instance name in Drake; file name models/objects/<name>.sdf).
    name: str = "object"
    # Shape: "sphere" | "box" | "cylinder" | "capsule" (see SHAPES for the size meaning).
    shape: str = "sphere"
    # Size of the shape [m]: sphere [radius], box [x, y, z], cylinder/capsule [radius, length].
    size: list[float] = field(default_factory=lambda: [0.0375])
    # Mass [kg] (uniform density).
    mass: float = 0.068
    # Id of the tag36h11 marker on the object (0..586).
    tag_id: int = 0
    # Side of the tag's black square [m] (the size solvePnP needs).
    tag_size: float = 0.03
    # Face the tag sits on, as its outward normal in the body frame: "+x", "-x", ..., "-z".
    # The default "-z" faces the palm camera when the object sits in the palm unrotated.
    tag_face: str = "-z"
    # Offset of the POM frame O from the tag frame T: translation [m] ...
    tag_to_pom_xyz: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    # ... and roll-pitch-yaw [deg] (zeros: O = T).
    tag_to_pom_rpy_deg: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    # Initial placement of the body frame B (shape centre) in the palm frame P [m] ...
    placement_xyz: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.06])
    # ... and its roll-pitch-yaw in P [deg].
    placement_rpy_deg: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    # Friction coefficient of the object's surface (static = dynamic) [-].
    friction: float = 1.0
    # RGBA colour of the body (visual only).
    color: list[float] = field(default_factory=lambda: [0.8, 0.2, 0.15, 1.0])
    # Marble-maze extras: the radius [m] of the marble that rolls on the tag face (0: none;
    # the maze task simulates it in the plate's frame, vlr_drake.tasks.maze.MarbleMaze, so
    # the Drake model has no marble body: until 2026-11-27 it had one, posed in the model
    # frame, which fell away from the plate at the first step), and the height of a rim
    # around that face [m] (0: none). Box shape only.
    marble_radius: float = 0.0
    rim_height: float = 0.0

    def validate(self) -> "ObjectSpec":
        """Check the spec; raise ``ValueError`` naming the offending field."""
        where = f"object '{self.name}'"
        if not (isinstance(self.name, str) and re.fullmatch(r"[A-Za-z0-9_.-]+", self.name)):
            # it names the Drake model instance and the generated file
            raise ValueError(f"object: field 'name' must be letters, digits, '_', '.' or '-', got {self.name!r}")
        if self.shape not in SHAPES:
            raise ValueError(f"{where}: field 'shape' must be one of {list(SHAPES)}, got '{self.shape}'")
        n = {"sphere": 1, "box": 3, "cylinder": 2, "capsule": 2}[self.shape]
        if not isinstance(self.size, list | tuple | np.ndarray) or len(self.size) != n:
            raise ValueError(
                f"{where}: field 'size' must have {n} entries for a {self.shape} {SHAPES[self.shape]}, got {self.size}"
            )
        if not all(is_number(x) and np.isfinite(x) and x > 0 for x in self.size):
            raise ValueError(f"{where}: field 'size' must be positive numbers, got {self.size}")
        units.check_length(self.size, f"{where}: field 'size'")
        if not (is_number(self.mass) and np.isfinite(self.mass) and self.mass > 0):
            raise ValueError(f"{where}: field 'mass' must be a positive number, got {self.mass!r}")
        units.warn_if_grams(self.mass, f"{where}: field 'mass'")
        if not (is_number(self.tag_id) and np.isfinite(self.tag_id) and 0 <= self.tag_id < TAG36H11_COUNT
                and int(self.tag_id) == self.tag_id):
            raise ValueError(
                f"{where}: field 'tag_id' must be a tag36h11 id in 0..{TAG36H11_COUNT - 1}, got {self.tag_id}"
            )
        if not (is_number(self.tag_size) and np.isfinite(self.tag_size) and self.tag_size > 0):
            raise ValueError(f"{where}: field 'tag_size' must be a finite positive number, got {self.tag_size!r}")
        units.check_length(self.tag_size, f"{where}: field 'tag_size'")
        if self.tag_face not in FACES:
            raise ValueError(f"{where}: field 'tag_face' must be one of {list(FACES)}, got '{self.tag_face}'")
        plate, room = TAG_PLATE_RATIO * self.tag_size, self.face_width()
        if plate > room:
            raise ValueError(f"{where}: field 'tag_size' ({self.tag_size} m) makes a {plate:.4g} m tag plate, wider "
                             f"than the '{self.tag_face}' face ({room:.4g} m)")
        for fname in ["tag_to_pom_xyz", "tag_to_pom_rpy_deg", "placement_xyz", "placement_rpy_deg"]:
            v = getattr(self, fname)
            if not (isinstance(v, list | tuple | np.ndarray) and len(v) == 3
                    and all(is_number(x) and np.isfinite(x) for x in v)):
                raise ValueError(f"{where}: field '{fname}' must have 3 finite entries, got {v!r}")
        for fname in ["tag_to_pom_xyz", "placement_xyz"]:  # (20 for 20 mm had put the POM 20 m away)
            units.check_length(getattr(self, fname), f"{where}: field '{fname}'")
        if len(self.color) != 4 or not all(np.isfinite(c) and 0 <= c <= 1 for c in self.color):
            raise ValueError(f"{where}: field 'color' must be RGBA, 4 entries in [0, 1], got {self.color}")
        for fname in ["friction", "marble_radius", "rim_height"]:  # (NaN < 0 is False)
            if not (is_number(getattr(self, fname)) and np.isfinite(getattr(self, fname)) and getattr(self, fname) >= 0):
                raise ValueError(f"{where}: field '{fname}' must be a finite number >= 0, got {getattr(self, fname)!r}")
        for fname in ["marble_radius", "rim_height"]:
            if getattr(self, fname) > 0:
                units.check_length(getattr(self, fname), f"{where}: field '{fname}'")
        if (self.marble_radius > 0 or self.rim_height > 0) and self.shape != "box":
            raise ValueError(f"{where}: field 'shape' must be 'box' for a marble maze, got '{self.shape}'")
        # the marble rolls on the tag's face (it had been checked on the x-y face whatever the tag's)
        face = [self.size[i] for i in range(3) if i != "xyz".index(self.tag_face[1])] if len(self.size) == 3 else []
        if self.marble_radius > 0 and face and 2 * self.marble_radius >= min(face):
            raise ValueError(f"{where}: field 'marble_radius' ({self.marble_radius} m) does not fit on the "
                             f"{face[0]} x {face[1]} m {self.tag_face} face (the tag's, which it rolls on)")
        return self

    # -- geometry -------------------------------------------------------------------------

    def face_extent(self, face: str | None = None) -> float:
        """Distance from the body origin to the (flat or tangent) face along its normal [m]."""
        face = self.tag_face if face is None else face
        axis = "xyz".index(face[1])
        s = self.size
        if self.shape == "sphere":
            return s[0]
        if self.shape == "box":
            return 0.5 * s[axis]
        if self.shape == "cylinder":
            return 0.5 * s[1] if axis == 2 else s[0]
        return 0.5 * s[1] + s[0] if axis == 2 else s[0]  # capsule

    def face_width(self, face: str | None = None) -> float:
        """The narrowest width of the (flat or tangent) face across its normal [m]: what a
        square tag plate on it must fit in (a sphere's and a cylinder's curved side: their
        diameter, and the cylinder's length; a cylinder's flat end: the side of the square
        inscribed in its disc, sqrt(2) r, where its diameter had let a tag's corners hang
        over the edge)."""
        face = self.tag_face if face is None else face
        axis = "xyz".index(face[1])
        s = self.size
        if self.shape == "sphere":
            return 2 * s[0]
        if self.shape == "box":
            return min(s[i] for i in range(3) if i != axis)
        if axis == 2:  # a cylinder's flat end, or a capsule's round one
            return np.sqrt(2.0) * s[0] if self.shape == "cylinder" else 2 * s[0]
        return min(2 * s[0], s[1] + (2 * s[0] if self.shape == "capsule" else 0.0))

    def R_BT(self) -> np.ndarray:
        """Rotation of the tag frame T in the body frame B: z_T = the face's outward normal,
        x_T = the body's x (or y when the face is +-x) projected onto the face."""
        z = np.array(FACES[self.tag_face])
        ref = np.array([0.0, 1.0, 0.0]) if abs(z[0]) > 0.5 else np.array([1.0, 0.0, 0.0])
        x = ref - z * (ref @ z)
        x /= np.linalg.norm(x)
        return np.column_stack([x, np.cross(z, x), z])

    def X_BT(self):
        """Pose of the tag frame T in the body frame B (pydrake RigidTransform)."""
        from pydrake.math import RigidTransform, RotationMatrix

        z = np.array(FACES[self.tag_face])
        return RigidTransform(RotationMatrix(self.R_BT()), (self.face_extent() + TAG_STANDOFF) * z)

    def X_TO(self):
        """Pose of the POM frame O in the tag frame T."""
        from pydrake.math import RigidTransform, RollPitchYaw

        return RigidTransform(
            RollPitchYaw(np.deg2rad(self.tag_to_pom_rpy_deg)), np.asarray(self.tag_to_pom_xyz, float)
        )

    def X_BO(self):
        """Pose of the POM frame O in the body frame B."""
        return self.X_BT() @ self.X_TO()

    def X_PB(self):
        """Initial placement of the body in the palm frame."""
        from pydrake.math import RigidTransform, RollPitchYaw

        return RigidTransform(
            RollPitchYaw(np.deg2rad(self.placement_rpy_deg)), np.asarray(self.placement_xyz, float)
        )

    def inertia(self) -> tuple[float, float, float]:
        """Principal moments of inertia (uniform density) about the body origin [kg m^2]."""
        m, s = self.mass, self.size
        if self.shape == "sphere":
            i = 0.4 * m * s[0] ** 2
            return i, i, i
        if self.shape == "box":
            x, y, z = s
            return m * (y * y + z * z) / 12, m * (x * x + z * z) / 12, m * (x * x + y * y) / 12
        r, L = s[0], s[1]
        if self.shape == "cylinder":
            ixx = m * (3 * r * r + L * L) / 12
            return ixx, ixx, 0.5 * m * r * r
        # capsule: a cylinder of length L and two hemispheres of radius r, uniform density,
        # the hemispheres' moments carried from their own centres of mass (3r/8 from the flat
        # face) to the body origin by the parallel-axis theorem
        v_cyl, v_sph = np.pi * r * r * L, 4.0 / 3.0 * np.pi * r ** 3
        m_cyl, m_sph = m * v_cyl / (v_cyl + v_sph), m * v_sph / (v_cyl + v_sph)
        ixx_cyl = m_cyl * (3 * r * r + L * L) / 12
        # two hemispheres (mass m_sph together): about their centres 83/320 m r^2 each side's
        # transverse moment, then offset by L/2 + 3r/8
        ixx_sph = m_sph * (83.0 / 320.0 * r * r + (0.5 * L + 3.0 * r / 8.0) ** 2)
        izz = 0.5 * m_cyl * r * r + 0.4 * m_sph * r * r
        return ixx_cyl + ixx_sph, ixx_cyl + ixx_sph, izz


# --------------------------------------------------------------------------------------
# Presets.
# --------------------------------------------------------------------------------------


def _sphere(name, radius, mass, tag_id, tag_size, z, color) -> ObjectSpec:
    return ObjectSpec(
        name=name,
        shape="sphere",
        size=[radius],
        mass=mass,
        tag_id=tag_id,
        tag_size=tag_size,
        placement_xyz=[0.0, 0.0, z],
        color=color,
    )


def _cylinder(name, radius, length, mass, tag_id, tag_size, z, color) -> ObjectSpec:
    return ObjectSpec(
        name=name,
        shape="cylinder",
        size=[radius, length],
        mass=mass,
        tag_id=tag_id,
        tag_size=tag_size,
        placement_xyz=[0.0, 0.0, z],
        color=color,
    )


def preset(name: str) -> ObjectSpec:
    """A preset object, placed in the palm frame where the Model O's pads reach it.

    Paper objects (YCB object set sizes and masses, reduced to the part the fingers touch):
    - ``apple``: YCB 013 apple, about 75 mm across, 68 g: a sphere.
    - ``wine_glass``: the bowl of a wine glass, about 66 mm across and 70 mm tall, 133 g
      with its stem: a cylinder standing along the palm normal.
    - ``toy_block``: YCB 061 foam brick, 75 x 50 x 50 mm, 28 g: a box, long side across
      the thumb-finger direction (y), tag on the face towards the palm.
    - ``flat_screwdriver``: the handle of YCB 044 flat screwdriver, about 32 mm across and
      90 mm long, 98 g (whole tool): a cylinder lying across the fingers, tag on its side.
    - ``gelatin_box``: YCB 009 gelatin box, 89 x 73 x 28 mm, 97 g: a box with its thin
      side along the palm normal and its 89 mm side across (y).
    Task objects: ``cup_1`` .. ``cup_4`` (YCB 065 stacking cups, four in decreasing size,
    modelled as closed cylinders), ``cup_target`` (a larger cup to stack into),
    ``marble_maze`` (a 75 x 90 mm plate with a rim and a 12 mm marble on the face towards the
    palm, tag in the middle).
    """
    if name == "apple":
        return _sphere("apple", 0.0375, 0.068, 1, 0.030, 0.070, [0.8, 0.15, 0.1, 1.0])
    if name == "wine_glass":
        return _cylinder("wine_glass", 0.033, 0.070, 0.133, 2, 0.030, 0.075, [0.75, 0.85, 0.9, 1.0])
    if name == "toy_block":
        return ObjectSpec(
            name="toy_block",
            shape="box",
            size=[0.050, 0.075, 0.050],
            mass=0.028,
            tag_id=3,
            tag_size=0.030,
            placement_xyz=[0.0, 0.0, 0.075],
            color=[0.2, 0.6, 0.25, 1.0],
        )
    if name == "flat_screwdriver":
        # Lying across the fingers (axis along the palm's y), where the thumb pushes it
        # against the two fingers' proximal links (a power grasp: a 32 mm handle is narrow
        # for this hand); tag on the side facing the palm.
        return ObjectSpec(
            name="flat_screwdriver",
            shape="cylinder",
            size=[0.016, 0.090],
            mass=0.098,
            tag_id=4,
            tag_size=0.020,
            tag_face="-y",
            placement_xyz=[-0.015, 0.0, 0.07],
            placement_rpy_deg=[90.0, 0.0, 0.0],
            color=[0.9, 0.8, 0.1, 1.0],
        )
    if name == "gelatin_box":
        return ObjectSpec(
            name="gelatin_box",
            shape="box",
            size=[0.073, 0.089, 0.028],
            mass=0.097,
            tag_id=5,
            tag_size=0.030,
            placement_xyz=[0.0, 0.0, 0.085],
            color=[0.85, 0.3, 0.5, 1.0],
        )
    cups = {"cup_1": 0.0375, "cup_2": 0.035, "cup_3": 0.0325, "cup_4": 0.030, "cup_target": 0.041}
    if name in cups:
        r = cups[name]
        k = CUP_NAMES.index(name)
        return _cylinder(name, r, 0.060, 0.02, 10 + k, 0.025, 0.075, [0.2, 0.4 + 0.1 * k, 0.9, 1.0])
    if name == "marble_maze":
        return ObjectSpec(
            name="marble_maze",
            shape="box",
            size=[0.075, 0.090, 0.008],
            mass=0.06,
            tag_id=20,
            tag_size=0.025,
            placement_xyz=[0.0, 0.0, 0.09],
            color=[0.6, 0.45, 0.3, 1.0],
            marble_radius=0.006,
            rim_height=0.008,
        )
    raise ValueError(f"unknown object preset '{name}' (known: {', '.join(preset_names())})")


def preset_names() -> list[str]:
    return [*PAPER_OBJECTS, *CUP_NAMES, "marble_maze"]


# --------------------------------------------------------------------------------------
# SDFormat.
# --------------------------------------------------------------------------------------


def tag_texture_path(tag_id: int, root: Path | None = None) -> Path:
    from vlr_drake.models import models_dir

    root = models_dir() if root is None else Path(root)
    return root / "objects" / "textures" / f"tag36h11_{int(tag_id):03d}.png"


def _tag_mesh_name(tag_id: int) -> str:
    return f"tag36h11_{int(tag_id):03d}"


def _tag_obj(tag_id: int) -> str:
    """A unit quad in the tag frame's xy plane, facing +z, textured with the tag image (the
    image's top row at +y). Scaled in the SDF to the printed size with its quiet zone."""
    name = _tag_mesh_name(tag_id)
    return "\n".join(
        [
            f"mtllib {name}.mtl",
            "v -0.5 -0.5 0",
            "v 0.5 -0.5 0",
            "v 0.5 0.5 0",
            "v -0.5 0.5 0",
            "vt 0 0",
            "vt 1 0",
            "vt 1 1",
            "vt 0 1",
            "vn 0 0 1",
            f"usemtl {name}",
            "f 1/1/1 2/2/1 3/3/1",
            "f 1/1/1 3/3/1 4/4/1",
            "",
        ]
    )


def _tag_mtl(tag_id: int) -> str:
    name = _tag_mesh_name(tag_id)
    return "\n".join(
        [f"newmtl {name}", "Ka 1 1 1", "Kd 1 1 1", "Ks 0 0 0", "d 1", f"map_Kd textures/{name}.png", ""]
    )


def _fmt(*v: float) -> str:
    return " ".join(f"{x:.17g}" if abs(x) > 1e-15 else "0" for x in v)


def _pose(X) -> str:
    rpy = X.rotation().ToRollPitchYaw().vector()
    return _fmt(*X.translation(), *rpy)


def _geometry(spec: ObjectSpec) -> str:
    s = spec.size
    if spec.shape == "sphere":
        return f"<sphere><radius>{s[0]:.17g}</radius></sphere>"
    if spec.shape == "box":
        return f"<box><size>{_fmt(*s)}</size></box>"
    if spec.shape == "cylinder":
        return f"<cylinder><radius>{s[0]:.17g}</radius><length>{s[1]:.17g}</length></cylinder>"
    return f"<capsule><radius>{s[0]:.17g}</radius><length>{s[1]:.17g}</length></capsule>"


#: Hydroelastic modulus of the objects (stiff plastic), used only with the hydroelastic
#: contact model [Pa].
OBJECT_HYDROELASTIC_MODULUS = 1.0e7


def _friction(mu: float, hint: float | None = None) -> str:
    """Friction, plus compliant-hydroelastic properties (with a mesh resolution ``hint``
    [m]) that only the hydroelastic contact model uses."""
    hydro = ""
    if hint is not None:
        hydro = (
            f"<drake:compliant_hydroelastic/><drake:hydroelastic_modulus>{OBJECT_HYDROELASTIC_MODULUS:.17g}"
            f"</drake:hydroelastic_modulus><drake:mesh_resolution_hint>{hint:.17g}</drake:mesh_resolution_hint>"
        )
    return (
        f"<drake:proximity_properties><drake:mu_dynamic>{mu:.17g}</drake:mu_dynamic>"
        f"<drake:mu_static>{mu:.17g}</drake:mu_static>{hydro}</drake:proximity_properties>"
    )


def object_sdf(spec: ObjectSpec, tag_mesh_uri: str | None = None) -> str:
    """SDFormat of an object: body ``body`` (frame B at the shape centre), tag quad with the
    tag36h11 texture on ``tag_face``, frames ``tag`` (T) and ``pom`` (O). The tag mesh is
    referenced as ``package://vlr_drake/objects/tag36h11_<id>.obj`` (written by
    :func:`write_object_models`) unless ``tag_mesh_uri`` is given (see :func:`tag_mesh_uri`)."""
    spec.validate()
    if tag_mesh_uri is None:
        tag_mesh_uri = f"package://vlr_drake/objects/{_tag_mesh_name(spec.tag_id)}.obj"
    ixx, iyy, izz = spec.inertia()
    color = _fmt(*spec.color)
    X_BT = spec.X_BT()
    plate = spec.tag_size * TAG_PLATE_RATIO
    lines = [
        '<?xml version="1.0"?>',
        "<!-- Generated by `python -m vlr_drake.models --write` from vlr_drake.objects; do not edit. -->",
        '<sdf version="1.9" xmlns:drake="http://drake.mit.edu">',
        f'  <model name="{spec.name}">',
        '    <link name="body">',
        f"      <inertial><mass>{spec.mass:.17g}</mass><inertia><ixx>{ixx:.17g}</ixx><iyy>{iyy:.17g}</iyy>"
        f"<izz>{izz:.17g}</izz><ixy>0</ixy><ixz>0</ixz><iyz>0</iyz></inertia></inertial>",
        '      <collision name="collision">',
        f"        <geometry>{_geometry(spec)}</geometry>",
        f"        {_friction(spec.friction, hint=0.25 * min(spec.size))}",
        "      </collision>",
        '      <visual name="visual">',
        f"        <geometry>{_geometry(spec)}</geometry>",
        f"        <material><diffuse>{color}</diffuse></material>",
        "      </visual>",
        '      <visual name="tag_visual">',
        f"        <pose>{_pose(X_BT)}</pose>",
        f"        <geometry><mesh><uri>{tag_mesh_uri}</uri>"
        f"<scale>{_fmt(plate, plate, 1.0)}</scale></mesh></geometry>",
        "      </visual>",
    ]
    if spec.rim_height > 0:
        lines += _rim(spec)
    lines.append("    </link>")
    lines += [
        '    <frame name="tag" attached_to="body">',
        f"      <pose>{_pose(X_BT)}</pose>",
        "    </frame>",
        '    <frame name="pom" attached_to="tag">',
        f"      <pose>{_pose(spec.X_TO())}</pose>",
        "    </frame>",
    ]
    lines += ["  </model>", "</sdf>", ""]
    return "\n".join(lines)


def _rim(spec: ObjectSpec) -> list[str]:
    """Four walls around the tag face of a box (marble maze)."""
    z = np.array(FACES[spec.tag_face])
    axis = int(np.argmax(np.abs(z)))
    others = [i for i in range(3) if i != axis]
    h, t = spec.rim_height, 0.003
    s = np.asarray(spec.size)
    out = []
    for j, (ax, sign) in enumerate([(others[0], 1), (others[0], -1), (others[1], 1), (others[1], -1)]):
        c = z * (0.5 * s[axis] + 0.5 * h)
        c[ax] = sign * (0.5 * s[ax] - 0.5 * t)
        size = np.empty(3)
        size[axis] = h
        size[ax] = t
        other = others[1] if ax == others[0] else others[0]
        size[other] = s[other]
        for kind in ("collision", "visual"):
            out += [
                f'      <{kind} name="rim_{kind}{j}">',
                f"        <pose>{_fmt(*c)} 0 0 0</pose>",
                f"        <geometry><box><size>{_fmt(*size)}</size></box></geometry>",
                f"        {_friction(spec.friction, hint=0.002)}"
                if kind == "collision"
                else f"        <material><diffuse>{_fmt(*spec.color)}</diffuse></material>",
                f"      </{kind}>",
            ]
    return out


def object_model_path(name: str) -> str:
    """``package://`` URI of a generated object model."""
    return f"package://vlr_drake/objects/{name}.sdf"


def generated_object_files(names: list[str] | None = None) -> dict[str, str]:
    """Relative path under models/ -> text of each preset's SDF and its tag quad OBJ/MTL."""
    out = {}
    for name in names or preset_names():
        spec = preset(name)
        out[f"objects/{name}.sdf"] = object_sdf(spec)
        out[f"objects/{_tag_mesh_name(spec.tag_id)}.obj"] = _tag_obj(spec.tag_id)
        out[f"objects/{_tag_mesh_name(spec.tag_id)}.mtl"] = _tag_mtl(spec.tag_id)
    return out


_TAG_TEMP_DIR: Path | None = None


def tag_mesh_uri(tag_id: int) -> str:
    """URI of the textured tag quad for ``tag_id``: the package's copy under models/objects
    when it exists (the presets' tags), else one written once to a temporary directory (so a
    custom object never writes into the repository; that directory is removed when the
    process exits)."""
    from vlr_drake.models import models_dir

    name = _tag_mesh_name(tag_id)
    if (models_dir() / "objects" / f"{name}.obj").exists() and tag_texture_path(tag_id).exists():
        return f"package://vlr_drake/objects/{name}.obj"
    global _TAG_TEMP_DIR
    if _TAG_TEMP_DIR is None:
        import atexit
        import shutil
        import tempfile

        _TAG_TEMP_DIR = Path(tempfile.mkdtemp(prefix="vlr_drake_tags_"))
        atexit.register(shutil.rmtree, _TAG_TEMP_DIR, ignore_errors=True)
    root = _TAG_TEMP_DIR
    obj = root / "objects" / f"{name}.obj"
    if not obj.exists():
        obj.parent.mkdir(parents=True, exist_ok=True)
        (root / "objects" / f"{name}.mtl").write_text(_tag_mtl(tag_id))
        write_tag_texture(tag_id, root)
        obj.write_text(_tag_obj(tag_id))
    return obj.as_uri()


def write_tag_texture(tag_id: int, root: Path | None = None) -> Path:
    import cv2

    path = tag_texture_path(tag_id, root)
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), tag_image(tag_id, pixels_per_cell=32, quiet_cells=1))
    return path


def write_object_models(root: Path | None = None, specs: list[ObjectSpec] | None = None) -> list[Path]:
    """Write preset (or given) object models, tag meshes and textures under ``root``
    (default: the repository's models/)."""
    from vlr_drake.models import models_dir

    root = models_dir() if root is None else Path(root)
    written = []
    if specs is None:
        files = generated_object_files()
        ids = {preset(n).tag_id for n in preset_names()}
    else:
        files = {}
        for spec in specs:
            files[f"objects/{spec.name}.sdf"] = object_sdf(spec)
            files[f"objects/{_tag_mesh_name(spec.tag_id)}.obj"] = _tag_obj(spec.tag_id)
            files[f"objects/{_tag_mesh_name(spec.tag_id)}.mtl"] = _tag_mtl(spec.tag_id)
        ids = {s.tag_id for s in specs}
    for rel, text in files.items():
        p = root / rel
        p.parent.mkdir(parents=True, exist_ok=True)
        p.write_text(text)
        written.append(p)
    for tag_id in sorted(ids):
        written.append(write_tag_texture(tag_id, root))
    return written


def copy_spec(spec: ObjectSpec, **changes) -> ObjectSpec:
    """A copy of a spec with some fields changed."""
    out = copy.deepcopy(spec)
    for k, v in changes.items():
        if not hasattr(out, k):
            raise ValueError(f"ObjectSpec has no field '{k}'")
        setattr(out, k, v)
    return out
