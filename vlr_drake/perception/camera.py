"""The in-hand camera's configuration: intrinsics and its pose X_PC in the palm frame.

Camera frame C follows Drake's and OpenCV's convention: +z along the optical axis, +x to
the right of the image, +y down. The default camera sits at the palm centre, recessed
below the palm surface, looking along the palm normal (+z of P), so the tag on the bottom
of a grasped object stays in view as the object moves.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from vlr_drake.kinematics import is_count, is_number


@dataclass
class CameraConfig:
    """Pinhole camera fixed to the palm."""

    # Image width of the delivered (downsampled) image [px].
    width: int = 640
    # Image height of the delivered (downsampled) image [px].
    height: int = 480
    # Vertical field of view [deg].
    fov_y_deg: float = 70.0
    # Camera position in the palm frame [m] (negative z: recessed below the palm surface).
    xyz: list[float] = field(default_factory=lambda: [0.0, 0.0, -0.02])
    # Camera orientation in the palm frame, roll-pitch-yaw [deg] (zeros: C axes = P axes).
    rpy_deg: list[float] = field(default_factory=lambda: [0.0, 0.0, 0.0])
    # Render at this many times the resolution and downsample (INTER_AREA): sharper corners.
    render_scale: int = 2
    # Clipping planes of the renderer [m].
    near: float = 0.005
    far: float = 1.0
    # Standard deviation of additive Gaussian pixel noise (0..255 scale); 0 disables it.
    pixel_noise_std: float = 0.0

    def validate(self) -> CameraConfig:
        if not (is_count(self.width, 1) and is_count(self.height, 1)):
            raise ValueError(f"camera: 'width' and 'height' must be positive integers, got {self.width!r} x {self.height!r}")
        for name in ("fov_y_deg", "near", "far", "pixel_noise_std"):  # (a string had ended in a TypeError)
            if not is_number(getattr(self, name)):
                raise ValueError(f"camera: '{name}' must be a number, got {getattr(self, name)!r}")
        if not 1.0 < self.fov_y_deg < 170.0:
            raise ValueError(f"camera: 'fov_y_deg' must be in (1, 170), got {self.fov_y_deg}")
        if len(self.xyz) != 3 or len(self.rpy_deg) != 3:
            raise ValueError("camera: 'xyz' and 'rpy_deg' must have 3 entries each")
        for name in ("xyz", "rpy_deg"):
            if not np.all(np.isfinite(np.asarray(getattr(self, name), float))):
                raise ValueError(f"camera: '{name}' must be finite, got {list(getattr(self, name))}")
        if not is_count(self.render_scale, 1):
            raise ValueError(f"camera: 'render_scale' must be an integer >= 1, got {self.render_scale!r}")
        if not 0 < self.near < self.far < np.inf:
            raise ValueError(f"camera: need 0 < near < far, both finite, got near {self.near}, far {self.far}")
        if not (np.isfinite(self.pixel_noise_std) and self.pixel_noise_std >= 0):
            raise ValueError(f"camera: 'pixel_noise_std' must be a finite number >= 0, got {self.pixel_noise_std}")
        return self

    def intrinsic_matrix(self) -> np.ndarray:
        """3 x 3 pinhole matrix of the delivered image (principal point at the centre,
        Drake's convention: pixel centres at half-integers, so c = size / 2 - 0.5 in
        OpenCV's integer-centred pixel coordinates)."""
        fy = 0.5 * self.height / np.tan(0.5 * np.deg2rad(self.fov_y_deg))
        return np.array([[fy, 0.0, self.width / 2.0 - 0.5], [0.0, fy, self.height / 2.0 - 0.5], [0.0, 0.0, 1.0]])

    def X_PC(self):
        """Pose of the camera in the palm frame (pydrake RigidTransform)."""
        from pydrake.math import RigidTransform, RollPitchYaw

        return RigidTransform(RollPitchYaw(np.deg2rad(self.rpy_deg)), np.asarray(self.xyz, float))
