"""Camera image post-processing for the simulated camera path (DESIGN section 8): area
downsampling of images rendered at ``render_scale`` times the delivered resolution, and
seeded Gaussian pixel noise. Pure functions on uint8 numpy images, no Drake systems.

Downsampling by an integer factor s with ``cv2.INTER_AREA`` averages s x s blocks: the
delivered pixel i covers rendered pixels s i .. s i + s - 1, so in OpenCV's integer-centred
pixel coordinates x_delivered = (x_rendered - (s - 1) / 2) / s, which maps a rendered
principal point s c + (s - 1) / 2 back to c (the same c that ``CameraConfig`` gives).
"""

from __future__ import annotations

import cv2
import numpy as np

from vlr_drake.kinematics import is_number


def _check_image(image: np.ndarray, name: str = "image") -> np.ndarray:
    image = np.asarray(image)
    if image.dtype != np.uint8:
        raise ValueError(f"{name}: dtype must be uint8, got {image.dtype}")
    if image.ndim not in (2, 3) or (image.ndim == 3 and image.shape[2] not in (1, 3, 4)):
        raise ValueError(
            f"{name}: shape must be (H, W), (H, W, 1), (H, W, 3) or (H, W, 4), got {image.shape}"
        )
    return image


def checked_scale(scale, name: str = "scale") -> int:
    """A downsampling factor as an int: a whole number >= 1 (2.0 too), or a ValueError that
    names it (NaN and inf had ended in int()'s own errors, which name nothing)."""
    if not (is_number(scale) and np.isfinite(scale) and float(scale).is_integer() and scale >= 1):
        raise ValueError(f"{name}: must be a positive integer, got {scale!r}")
    return int(scale)


def downsample_area(image: np.ndarray, scale: int) -> np.ndarray:
    """Shrink an image by the integer factor ``scale`` with ``cv2.INTER_AREA`` (block mean).
    Height and width must be multiples of ``scale``; scale 1 returns the image unchanged."""
    image = _check_image(image)
    scale = checked_scale(scale)
    if scale == 1:
        return image
    h, w = image.shape[:2]
    if h % scale or w % scale:
        raise ValueError(f"image: shape {image.shape} is not a multiple of scale {scale}")
    out = cv2.resize(np.ascontiguousarray(image), (w // scale, h // scale), interpolation=cv2.INTER_AREA)
    if image.ndim == 3 and image.shape[2] == 1:
        out = out[:, :, None]
    return out


def add_pixel_noise(
    image: np.ndarray, std: float, rng: np.random.Generator, noise_alpha: bool = False
) -> np.ndarray:
    """Copy of ``image`` with independent Gaussian noise N(0, std^2) (0..255 scale) added
    to every pixel and channel, rounded and clipped to uint8. An RGBA image keeps its alpha
    channel unless ``noise_alpha``. ``std`` 0 returns a copy unchanged."""
    image = _check_image(image)
    if not (np.isfinite(std) and std >= 0):
        raise ValueError(f"std: pixel noise standard deviation must be a finite number >= 0, got {std}")
    if not isinstance(rng, np.random.Generator):
        raise TypeError(f"rng: must be a numpy.random.Generator, got {type(rng).__name__}")
    out = image.copy()
    if std == 0:
        return out
    channels = slice(None)
    if image.ndim == 3 and image.shape[2] == 4 and not noise_alpha:
        channels = slice(0, 3)
    view = out[..., channels] if image.ndim == 3 else out
    noisy = view.astype(np.float64) + rng.normal(0.0, std, size=view.shape)
    view[...] = np.clip(np.rint(noisy), 0, 255).astype(np.uint8)
    return out
