"""Checks that a setting is in the package's units.

Every length here is in metres, every angle in radians, every mass in kilograms, a joint's
stiffness in N m/rad, a density in kg/m^3 and gravity in m/s^2. A hand's or an object's
value far outside what any hand of this kind has was almost surely given in another unit:
millimetres, degrees, grams, N mm/rad or g/cm^3. Left alone it runs and gives a wrong
result, such as a 48 m link "identified" from a prior in millimetres, or tendon limits a
thousand times too wide for the motors. These checks refuse such a value, naming the field
and the unit it looks like. A mass and a grasp's angles are warned about rather than
refused: a heavy object or a nearly open hand can be meant.
"""

from __future__ import annotations

import warnings

import numpy as np

#: Longer than this [m] a hand's or an object's length is taken for millimetres. The hands
#: here measure centimetres: links 30-75 mm, the palm 75 mm, tendon travel 45 mm.
LONGEST_LENGTH = 1.0
#: Larger than this [rad] a joint angle or limit is taken for degrees.
LARGEST_ANGLE = 2.0 * np.pi
#: Heavier than this [kg] an object's mass is taken for grams (a warning). The hands here
#: hold tens to hundreds of grams (the objects in vlr_drake.objects weigh 28-133 g).
HEAVY_OBJECT = 5.0
#: Lighter than this [kg/m^3] a solid's density is taken for g/cm^3 (water is 1000 kg/m^3).
LIGHTEST_DENSITY = 10.0
#: Stiffer than this [N m/rad] a finger joint's spring is taken for N mm/rad. The Model O's
#: are 0.08-0.16 N m/rad, the identified ones' prior 0.05-0.40.
STIFFEST_SPRING = 10.0
#: Stronger than this [m/s^2] a gravity vector is taken for mm/s^2 (Earth's is 9.81).
STRONGEST_GRAVITY = 30.0
#: Wider than this [m] a pose measurement's noise (a camera stand-in's, or the filter's
#: likelihood, which also stands for the model's mismatch) is taken for millimetres: a tag
#: at the hand's scale is measured to hundredths of a millimetre (the rendered camera's
#: 0.002 mm), the likelihood is 0.3 mm wide, and an action moves the object about a
#: millimetre, which a noise of centimetres would hide. (Under :data:`LONGEST_LENGTH`, 0.3
#: meant as millimetres had run.)
WIDEST_POSE_NOISE = 0.01
#: Wider than this [rad] a pose measurement's rotation noise is taken for degrees: the
#: likelihood's is 1.5 deg, the camera's 0.02 (1.5 meant as degrees is 86 deg and had run).
WIDEST_ROTATION_NOISE = np.deg2rad(15.0)
#: Longer than this [s] an action period is taken for milliseconds: the plants' periods are
#: 0.7-1 s (700 meant as ms had been taken for twelve minutes an action).
LONGEST_PERIOD = 60.0
#: Below this [deg] in every joint a grasp's angles are taken for radians (a warning): a
#: grasp bends its joints by tens of degrees.
SMALLEST_GRASP_DEG = 3.0


def check_length(value, field: str, longest: float = LONGEST_LENGTH,
                 what: str = "more than any hand here measures") -> None:
    """Raise ``ValueError`` naming ``field`` where any of ``value`` (a length or an array of
    lengths [m], or of positions) is longer than ``longest`` (:data:`LONGEST_LENGTH`,
    ``what`` says why it is too long)."""
    v = np.abs(np.asarray(value, float))
    if v.size and np.nanmax(v) > longest:
        raise ValueError(f"{field}: {_show(value)} m is longer than {longest:g} m, {what}; lengths are in metres: "
                         "was it given in millimetres?")


def check_pose_noise(position, field: str, rotation=None, rotation_field: str = "") -> None:
    """Raise ``ValueError`` naming the field where a pose measurement's position noise [m]
    (``field``) is wider than :data:`WIDEST_POSE_NOISE`, or its rotation noise [rad]
    (``rotation_field``; None: not given) than :data:`WIDEST_ROTATION_NOISE`."""
    check_length(position, field, WIDEST_POSE_NOISE,
                 "wider than any tag camera's noise at a hand's scale (an action moves the object about a mm)")
    if rotation is not None:
        check_angle(rotation, rotation_field, WIDEST_ROTATION_NOISE,
                    f"{np.rad2deg(WIDEST_ROTATION_NOISE):g} deg, wider than any tag camera's rotation noise")


def check_angle(value, field: str, largest: float = LARGEST_ANGLE, what: str = "a full turn") -> None:
    """Raise ``ValueError`` naming ``field`` where any of ``value`` [rad] exceeds
    ``largest`` (:data:`LARGEST_ANGLE`, ``what`` names it) in size."""
    v = np.abs(np.asarray(value, float))
    if v.size and np.nanmax(v) > largest:
        raise ValueError(f"{field}: {_show(value)} rad is more than {what}; angles are in radians: "
                         "was it given in degrees?")


def check_period(value, field: str) -> None:
    """Raise ``ValueError`` naming ``field`` where a period [s] is longer than
    :data:`LONGEST_PERIOD`."""
    if value > LONGEST_PERIOD:
        raise ValueError(f"{field}: {value:g} s is longer than {LONGEST_PERIOD:g} s, more than any action period "
                         "here (the plants' are 0.7-1 s); periods are in seconds: was it given in milliseconds?")


def check_stiffness(value, field: str) -> None:
    """Raise ``ValueError`` naming ``field`` where any of ``value`` (a joint spring's
    stiffness [N m/rad], or an array of them) is stiffer than :data:`STIFFEST_SPRING`."""
    v = np.abs(np.asarray(value, float))
    if v.size and np.nanmax(v) > STIFFEST_SPRING:
        raise ValueError(f"{field}: {_show(value)} N m/rad is stiffer than any finger joint's spring here (the Model "
                         "O's are 0.08-0.16); stiffness is in N m/rad: was it given in N mm/rad?")


def check_density(value, field: str) -> None:
    """Raise ``ValueError`` naming ``field`` where a density [kg/m^3] is below
    :data:`LIGHTEST_DENSITY`."""
    if value < LIGHTEST_DENSITY:
        raise ValueError(f"{field}: {value:g} kg/m^3 is lighter than any solid (water is 1000); densities are "
                         "in kg/m^3: was it given in g/cm^3?")


def check_gravity(value, field: str) -> None:
    """Raise ``ValueError`` naming ``field`` where a gravity vector [m/s^2] is stronger
    than :data:`STRONGEST_GRAVITY`."""
    if np.linalg.norm(np.asarray(value, float)) > STRONGEST_GRAVITY:
        raise ValueError(f"{field}: {_show(value)} is stronger than any gravity a hand works in (Earth's is "
                         "9.81 m/s^2); gravity is in m/s^2: was it given in mm/s^2?")


def warn_if_grams(mass, field: str, stacklevel: int = 3) -> None:
    """Warn where an object's mass [kg] is above :data:`HEAVY_OBJECT`."""
    if mass > HEAVY_OBJECT:
        warnings.warn(f"{field}: {mass:g} kg is more than any object these hands hold (the objects here "
                      f"weigh 28-133 g); masses are in kilograms: was it given in grams?", stacklevel=stacklevel)


def warn_if_radians(angles_deg, field: str, stacklevel: int = 3) -> None:
    """Warn where every one of a grasp's joint angles [deg] is under :data:`SMALLEST_GRASP_DEG`."""
    if np.abs(np.asarray(angles_deg, float)).max() < SMALLEST_GRASP_DEG:
        warnings.warn(f"{field} {_show(angles_deg)}: every angle under {SMALLEST_GRASP_DEG:g} deg, an open hand "
                      "rather than a grasp; the angles are in degrees: were they given in radians?",
                      stacklevel=stacklevel)


def _show(value):
    """A value as a reader wrote it: a list of plain floats, not of np.float64."""
    arr = np.asarray(value, float)
    return float(arr) if arr.ndim == 0 else arr.tolist()
