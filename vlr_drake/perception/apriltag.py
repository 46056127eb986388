"""AprilTag (tag36h11) images and geometry shared by the object models and the observer.

Tag frame T (OpenCV's marker convention): origin at the tag centre, x to the right and
y up in the tag image, z out of the printed face (towards a camera that sees it). The POM
frame O of an object is the tag frame, optionally offset by a known X_TO.
"""

from __future__ import annotations

import cv2
import numpy as np

from vlr_drake.kinematics import is_number

#: Dictionary used everywhere (OpenCV's predefined tag36h11 family).
TAG_DICTIONARY = cv2.aruco.DICT_APRILTAG_36h11
#: Number of ids in tag36h11.
TAG36H11_COUNT = 587
#: Cells across the black square of a tag36h11 marker (6 data + 2 border bits).
TAG36H11_CELLS = 8


def dictionary() -> cv2.aruco.Dictionary:
    return cv2.aruco.getPredefinedDictionary(TAG_DICTIONARY)


def check_tag_id(tag_id: int) -> int:
    """``tag_id`` as an int, or a ValueError naming it: a whole number (3.5 is no tag, and
    would have been read as 3) within the tag36h11 dictionary."""
    if not (is_number(tag_id) and float(tag_id).is_integer()):
        raise ValueError(f"'tag_id' must be a whole number, got {tag_id!r}")
    if not 0 <= int(tag_id) < TAG36H11_COUNT:
        raise ValueError(f"'tag_id' {tag_id} is outside the tag36h11 dictionary (0..{TAG36H11_COUNT - 1})")
    return int(tag_id)


def tag_image(tag_id: int, pixels_per_cell: int = 32, quiet_cells: int = 1) -> np.ndarray:
    """Grayscale uint8 image of a tag36h11 marker with a white quiet zone.

    The black square (the part whose side is the tag's physical ``size``) spans
    ``8 * pixels_per_cell`` pixels; ``quiet_cells`` white cells surround it.
    """
    check_tag_id(tag_id)
    side = TAG36H11_CELLS * pixels_per_cell
    marker = cv2.aruco.generateImageMarker(dictionary(), int(tag_id), side, borderBits=1)
    q = quiet_cells * pixels_per_cell
    return cv2.copyMakeBorder(marker, q, q, q, q, cv2.BORDER_CONSTANT, value=255)


def tag_corners(size: float) -> np.ndarray:
    """The black square's corners in the tag frame (4 x 3), in OpenCV's detection order:
    top-left, top-right, bottom-right, bottom-left (as seen in the tag image)."""
    h = size / 2.0
    return np.array([[-h, h, 0.0], [h, h, 0.0], [h, -h, 0.0], [-h, -h, 0.0]])
