"""SDFormat models of the hand and its fingers, generated from a :class:`HandSpec`.

The hand's geometry has one source of truth, :mod:`vlr_drake.hand`; this module turns a
spec into SDFormat (DESIGN.md sections 2 and 8) and registers the ``vlr_drake`` package
(``models/package.xml``) so ``package://vlr_drake/...`` URIs resolve.

Frames of the generated hand model (all derived from the spec):

- ``palm``: the palm body, its frame is the palm frame P (origin at the palm centre, +z
  out of the palm towards the object, finger bases at z = 0).
- ``{finger}_link{k}`` (k = 1..K): link k of a finger. Its frame sits at joint k with
  x along the flexion direction u_i and y along the joint axis w_i = z x u_i when the
  finger is straight; its z axis runs along the link (e(phi_k) of DESIGN.md section 2).
  Rotating about +y by theta tilts +z towards u_i: positive angle = flexion.
- ``{finger}_joint{k}``: revolute joint about y with SDFormat ``<dynamics>``
  spring_stiffness / spring_reference / damping (Drake makes RevoluteSprings of them).
- ``{finger}_pad``: a frame on the pad surface of the last link, at ``pad_offset`` from the
  link axis (towards the flexion side) and at :data:`PAD_FRACTION` of the distal length.
- Fingertip pad: two spheres of the finger's ``pad_radius``, :data:`PAD_SPHERE_SPACING`
  apart across the finger (along the joint axis), whose surfaces touch the pad plane. Two
  spheres resist a twist of the object about the contact (DESIGN.md section 8).

Run ``python -m vlr_drake.models --write`` to regenerate ``models/hands/*.sdf`` and
``models/fingers/*.sdf``; ``tests/test_models.py`` checks the files are not stale.
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np

from vlr_drake.hand import (
    NOVEL_FINGER_NAMES,
    NOVEL_HANDS,
    FingerSpec,
    HandSpec,
    hand_by_name,
    link_mass,
    novel_finger,
)
from vlr_drake.resources import data_dir

__all__ = [
    "PACKAGE_NAME",
    "PAD_FRACTION",
    "PAD_SPHERE_SPACING",
    "package_map_path",
    "configure_parser",
    "hand_sdf",
    "finger_sdf",
    "finger_rotation",
    "pad_position",
    "generated_models",
    "write_models",
    "link_name",
    "joint_name",
    "pad_frame_name",
    "pad_geometry_name",
]

#: Name of the package in models/package.xml.
PACKAGE_NAME = "vlr_drake"
#: Distance between the two pad spheres' centres, across the finger [m] (12 mm).
PAD_SPHERE_SPACING = 0.012
#: Position of the pad along the last link, as a fraction of the distal length. Mid-pad
#: contacts, away from the fingertip's end cap (end caps make objects roll).
PAD_FRACTION = 0.6
#: Hydroelastic modulus of the finger pads and links (soft rubber), used only with the
#: hydroelastic contact model [Pa].
PAD_HYDROELASTIC_MODULUS = 1.0e6
#: Palm mass (welded in the plant; only for a well-formed model) [kg].
PALM_MASS = 0.3

_COLORS = {
    "palm": "0.25 0.25 0.28 1",
    "link": "0.85 0.85 0.8 1",
    "pad": "0.1 0.1 0.1 1",
}


def package_map_path() -> Path:
    """Path of ``models/package.xml`` (the ``vlr_drake`` package's root is ``models/``)."""
    return models_dir() / "package.xml"


def models_dir() -> Path:
    """The ``models/`` directory: the repository's, or an installed wheel's copy
    (:func:`vlr_drake.resources.data_dir`)."""
    return data_dir("models")


def configure_parser(parser) -> None:
    """Register the ``vlr_drake`` package with a ``pydrake.multibody.parsing.Parser``."""
    pm = parser.package_map()
    if not pm.Contains(PACKAGE_NAME):
        pm.AddPackageXml(str(package_map_path()))


def link_name(finger: str, k: int) -> str:
    """Name of link k (1-based) of a finger."""
    return f"{finger}_link{k}"


def joint_name(finger: str, k: int) -> str:
    """Name of joint k (1-based) of a finger."""
    return f"{finger}_joint{k}"


def pad_frame_name(finger: str) -> str:
    return f"{finger}_pad"


def pad_geometry_name(finger: str, side: int) -> str:
    """Collision geometry name of pad sphere ``side`` (0 or 1) of a finger."""
    return f"{finger}_pad_collision{side}"


def finger_rotation(u: np.ndarray) -> np.ndarray:
    """Rotation R_PF of a finger's straight-finger frame: x = u, y = z x u, z = palm z."""
    u = np.asarray(u, float)
    u = u / np.linalg.norm(u)
    z = np.array([0.0, 0.0, 1.0])
    return np.column_stack([u, np.cross(z, u), z])


def pad_position(finger: FingerSpec) -> np.ndarray:
    """Pad-surface point (pad frame origin) in the last link's frame: (n_i, 0, a_pad)."""
    return np.array([finger.pad_offset, 0.0, PAD_FRACTION * finger.distal_length])


def _fmt(*v: float) -> str:
    return " ".join(f"{x:.17g}" if abs(x) > 1e-15 else "0" for x in v)


def _rpy(R: np.ndarray) -> tuple[float, float, float]:
    """Roll-pitch-yaw (SDFormat's fixed-axis x-y-z) of a rotation matrix."""
    pitch = math.asin(-max(-1.0, min(1.0, R[2, 0])))
    if abs(math.cos(pitch)) > 1e-9:
        roll = math.atan2(R[2, 1], R[2, 2])
        yaw = math.atan2(R[1, 0], R[0, 0])
    else:  # gimbal lock: put everything in yaw
        roll = 0.0
        yaw = math.atan2(-R[0, 1], R[1, 1])
    return roll, pitch, yaw


def _capsule_inertia(f: FingerSpec, length: float) -> tuple[float, float, float, float]:
    """Mass (:func:`~vlr_drake.hand.link_mass`, ``f.link_density``) and principal inertias
    (ixx = iyy across, izz along) of a solid cylinder of the capsule's radius and total
    length (a slight overestimate)."""
    radius = f.link_radius
    total = length + 2 * radius
    m = float(link_mass(f.link_density, radius, length))
    ixx = m * (3 * radius**2 + total**2) / 12.0
    izz = 0.5 * m * radius**2
    return m, ixx, ixx, izz


def _finger_links(
    f: FingerSpec, X_root: tuple[np.ndarray, np.ndarray], parent: str, indent: str
) -> list[str]:
    """Links and joints of one finger. ``X_root`` = (R, p) of the finger frame F (at its base,
    straight-finger orientation) in the model frame; ``parent`` is the body its joint 1
    attaches to."""
    R_MF, p_MF = X_root
    rpy = _rpy(R_MF)
    K = f.num_joints
    lengths = list(f.link_lengths) + [f.distal_length]
    out: list[str] = []
    z_along = 0.0
    for k in range(1, K + 1):
        L = lengths[k - 1]
        p = p_MF + R_MF @ np.array([0.0, 0.0, z_along])
        m, ixx, iyy, izz = _capsule_inertia(f, L)
        lname = link_name(f.name, k)
        last = k == K
        out += [
            f'{indent}<link name="{lname}">',
            f"{indent}  <pose>{_fmt(*p, *rpy)}</pose>",
            f"{indent}  <inertial>",
            f"{indent}    <pose>{_fmt(0, 0, L / 2)} 0 0 0</pose>",
            f"{indent}    <mass>{m:.17g}</mass>",
            f"{indent}    <inertia><ixx>{ixx:.17g}</ixx><iyy>{iyy:.17g}</iyy><izz>{izz:.17g}</izz>"
            f"<ixy>0</ixy><ixz>0</ixz><iyz>0</iyz></inertia>",
            f"{indent}  </inertial>",
            f'{indent}  <visual name="{lname}_visual">',
            f"{indent}    <pose>{_fmt(0, 0, L / 2)} 0 0 0</pose>",
            f"{indent}    <geometry><capsule><radius>{f.link_radius:.17g}</radius>"
            f"<length>{L:.17g}</length></capsule></geometry>",
            f"{indent}    <material><diffuse>{_COLORS['link']}</diffuse></material>",
            f"{indent}  </visual>",
        ]
        if not last:
            # The proximal links touch large objects too; a capsule along the link.
            out += [
                f'{indent}  <collision name="{lname}_collision">',
                f"{indent}    <pose>{_fmt(0, 0, L / 2)} 0 0 0</pose>",
                f"{indent}    <geometry><capsule><radius>{f.link_radius:.17g}</radius>"
                f"<length>{L:.17g}</length></capsule></geometry>",
                _friction(f, indent + "    ", hint=0.5 * f.link_radius),
                f"{indent}  </collision>",
            ]
        else:
            # The last link touches objects with its pad only (two spheres across the finger,
            # their surfaces at pad_offset from the axis), so contacts sit mid-pad.
            pad = pad_position(f)
            cx = f.pad_offset - f.pad_radius  # the spheres' centres: the VLR's contact offset
            for side, y in enumerate((-0.5 * PAD_SPHERE_SPACING, 0.5 * PAD_SPHERE_SPACING)):
                out += [
                    f'{indent}  <collision name="{pad_geometry_name(f.name, side)}">',
                    f"{indent}    <pose>{_fmt(cx, y, pad[2])} 0 0 0</pose>",
                    f"{indent}    <geometry><sphere><radius>{f.pad_radius:.17g}</radius></sphere></geometry>",
                    _friction(f, indent + "    "),
                    f"{indent}  </collision>",
                    f'{indent}  <visual name="{f.name}_pad_visual{side}">',
                    f"{indent}    <pose>{_fmt(cx, y, pad[2])} 0 0 0</pose>",
                    f"{indent}    <geometry><sphere><radius>{f.pad_radius:.17g}</radius></sphere></geometry>",
                    f"{indent}    <material><diffuse>{_COLORS['pad']}</diffuse></material>",
                    f"{indent}  </visual>",
                ]
        out.append(f"{indent}</link>")
        jparent = parent if k == 1 else link_name(f.name, k - 1)
        out += [
            f'{indent}<joint name="{joint_name(f.name, k)}" type="revolute">',
            f"{indent}  <parent>{jparent}</parent>",
            f"{indent}  <child>{lname}</child>",
            f"{indent}  <axis>",
            f"{indent}    <xyz>0 1 0</xyz>",
            f"{indent}    <limit><lower>{f.joint_lower[k - 1]:.17g}</lower><upper>{f.joint_upper[k - 1]:.17g}</upper></limit>",
            f"{indent}    <dynamics><damping>{f.joint_damping[k - 1]:.17g}</damping>"
            f"<spring_stiffness>{f.stiffness[k - 1]:.17g}</spring_stiffness>"
            f"<spring_reference>{f.rest_angles[k - 1]:.17g}</spring_reference></dynamics>",
            f"{indent}  </axis>",
            f"{indent}</joint>",
        ]
        z_along += L
    pad = pad_position(f)
    out += [
        f'{indent}<frame name="{pad_frame_name(f.name)}" attached_to="{link_name(f.name, K)}">',
        f"{indent}  <pose>{_fmt(*pad)} 0 0 0</pose>",
        f"{indent}</frame>",
    ]
    return out


def _friction(f: FingerSpec, indent: str, hint: float | None = None) -> str:
    """Friction, plus compliant-hydroelastic properties that only the hydroelastic contact
    model uses (the default point contact ignores them). ``hint``: the mesh resolution
    (default: half the pad radius)."""
    hint = 0.5 * f.pad_radius if hint is None else hint
    return (
        f"{indent}<drake:proximity_properties><drake:mu_dynamic>{f.friction:.17g}</drake:mu_dynamic>"
        f"<drake:mu_static>{f.friction:.17g}</drake:mu_static>"
        f"<drake:compliant_hydroelastic/><drake:hydroelastic_modulus>{PAD_HYDROELASTIC_MODULUS:.17g}"
        f"</drake:hydroelastic_modulus><drake:mesh_resolution_hint>{hint:.17g}</drake:mesh_resolution_hint>"
        f"</drake:proximity_properties>"
    )


def _palm_links(hand: HandSpec, indent: str) -> list[str]:
    """The palm body. Its visual leaves a hole at the centre for the recessed camera."""
    r, t = hand.palm_radius, hand.palm_thickness
    hole = 0.3 * r
    out = [
        f'{indent}<link name="palm">',
        f"{indent}  <inertial><pose>0 0 {-t / 2:.17g} 0 0 0</pose><mass>{PALM_MASS}</mass>"
        f"<inertia><ixx>{PALM_MASS * r * r / 4:.17g}</ixx><iyy>{PALM_MASS * r * r / 4:.17g}</iyy>"
        f"<izz>{PALM_MASS * r * r / 2:.17g}</izz><ixy>0</ixy><ixz>0</ixz><iyz>0</iyz></inertia></inertial>",
        # Collision only (no visual): a thin disc below the finger bases.
        f'{indent}  <collision name="palm_collision">',
        f"{indent}    <pose>0 0 {-t / 2:.17g} 0 0 0</pose>",
        f"{indent}    <geometry><cylinder><radius>{r:.17g}</radius><length>{t:.17g}</length></cylinder></geometry>",
        # rigid under hydroelastic contact (strict "hydroelastic" needs every collision
        # geometry to have a representation); point contact ignores it
        f"{indent}    <drake:proximity_properties><drake:rigid_hydroelastic/><drake:mesh_resolution_hint>{r / 6:.17g}"
        f"</drake:mesh_resolution_hint></drake:proximity_properties>",
        f"{indent}  </collision>",
    ]
    # Visual: a ring of 12 blocks around the camera hole.
    n = 12
    width = r - hole
    chord = 2 * r * math.sin(math.pi / n) * 1.05
    for j in range(n):
        ang = 2 * math.pi * j / n
        c = hole + width / 2
        out += [
            f'{indent}  <visual name="palm_visual{j}">',
            f"{indent}    <pose>{_fmt(c * math.cos(ang), c * math.sin(ang), -t / 2)} 0 0 {ang:.17g}</pose>",
            f"{indent}    <geometry><box><size>{_fmt(width, chord, t)}</size></box></geometry>",
            f"{indent}    <material><diffuse>{_COLORS['palm']}</diffuse></material>",
            f"{indent}  </visual>",
        ]
    out.append(f"{indent}</link>")
    return out


def hand_sdf(spec: HandSpec) -> str:
    """SDFormat of a hand: palm (model frame = palm frame P) and N fingers of K joints."""
    spec.validate()
    ind = "    "
    lines = [
        '<?xml version="1.0"?>',
        "<!-- Generated by `python -m vlr_drake.models --write` from vlr_drake.hand; do not edit. -->",
        '<sdf version="1.9" xmlns:drake="http://drake.mit.edu">',
        f'  <model name="{spec.name}">',
    ]
    lines += _palm_links(spec, ind)
    for f in spec.fingers:
        R = finger_rotation(f.flexion_direction)
        lines += _finger_links(f, (R, np.asarray(f.base, float)), "palm", ind)
    lines += ["  </model>", "</sdf>", ""]
    return "\n".join(lines)


def finger_sdf(finger: FingerSpec) -> str:
    """SDFormat of one finger on its own: a small mount link at the base (model frame =
    finger frame F: x = flexion direction, z = palm normal), then the K links."""
    finger.validate()
    f = FingerSpec(**{**finger.__dict__, "base": [0.0, 0.0, 0.0], "flexion_direction": [1.0, 0.0, 0.0]})
    ind = "    "
    lines = [
        '<?xml version="1.0"?>',
        "<!-- Generated by `python -m vlr_drake.models --write` from vlr_drake.hand; do not edit. -->",
        '<sdf version="1.9" xmlns:drake="http://drake.mit.edu">',
        f'  <model name="{f.name}">',
        f'{ind}<link name="mount">',
        f"{ind}  <inertial><mass>0.05</mass><inertia><ixx>1e-5</ixx><iyy>1e-5</iyy><izz>1e-5</izz>"
        "<ixy>0</ixy><ixz>0</ixz><iyz>0</iyz></inertia></inertial>",
        f'{ind}  <visual name="mount_visual"><pose>0 0 -0.005 0 0 0</pose>'
        f"<geometry><box><size>0.02 0.02 0.01</size></box></geometry>"
        f"<material><diffuse>{_COLORS['palm']}</diffuse></material></visual>",
        f"{ind}</link>",
    ]
    lines += _finger_links(f, (np.eye(3), np.zeros(3)), "mount", ind)
    lines += ["  </model>", "</sdf>", ""]
    return "\n".join(lines)


def generated_models() -> dict[str, str]:
    """Relative path under models/ -> SDFormat text of every generated hand and finger."""
    out = {}
    for name in ["model_o", *NOVEL_HANDS]:
        out[f"hands/{name}.sdf"] = hand_sdf(hand_by_name(name))
    for name in NOVEL_FINGER_NAMES:
        out[f"fingers/{name}.sdf"] = finger_sdf(novel_finger(name))
    return out


def write_models(root: Path | None = None) -> list[Path]:
    """Write :func:`generated_models` under ``root`` (default: the repository's models/)."""
    root = models_dir() if root is None else Path(root)
    written = []
    for rel, text in generated_models().items():
        path = root / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(text)
        written.append(path)
    return written


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(
        description="Generate the SDFormat models of the hands, fingers and objects."
    )
    ap.add_argument(
        "--write", action="store_true", help="write models/hands, models/fingers and models/objects"
    )
    args = ap.parse_args(argv)
    if not args.write:
        for rel in generated_models():
            print(rel)
        return
    for p in write_models():
        print(p)
    from vlr_drake.objects import write_object_models

    for p in write_object_models():
        print(p)


if __name__ == "__main__":
    main()
