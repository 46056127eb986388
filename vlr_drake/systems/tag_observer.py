"""POM pose sensors as Drake LeafSystems (DESIGN section 8, "camera/AprilTag observer").

- :class:`TagObserver`: camera image in, measured POM pose X_PO out, with a valid flag. Wraps
  the pure functions of ``vlr_drake.perception.tag_pose`` (detection, PnP, X_PO = X_PC X_CT
  X_TO). Used with the physics plant's rendered camera and with a real camera.
- :class:`NoisyPoseSensor`: the true POM pose in, a noisy measurement out, with the same
  output ports; stands in for camera + observer beside the fast model plant.

Both output ``X_PO_measured`` (abstract ``RigidTransform``) and ``X_PO_valid`` (vector of
size 1: 1.0 valid, 0.0 not). The measurement is computed from the *current* input (a reader
at time t sees the image, or true pose, at t). An invalid frame (an empty image; the tag
not found, out of view, occluded or too small; its edges not measurable; the reprojection
error too large; or a dropout of the noisy sensor) outputs the last valid pose held in the
system's state (identity before the first valid one) with valid 0; it never raises and
never reports a stale pose as valid.

Held-pose update (the documented choice): an unrestricted update event stores the current
measurement in the state when it is valid. With ``update_period_sec`` the event is periodic
(use the action period, and ``update_offset_sec`` the filter's offset: the plant settles,
then the observer and the filter read the same frame, rendered and detected once; this is
the intended use beside the physics plant, and it keeps the rendered camera from being
evaluated at every simulator step); with ``update_period_sec=None`` (the constructor's
default) it is a per-step event, which evaluates the input at *every* simulator step: fine
for a discrete diagram stepping at the action period, far too slow beside a physics plant
stepping at 1 ms with a rendered camera (about 0.1 s per render). A forced unrestricted
update does the same (tests use it). So the held pose is the last valid measurement *at an
update event*. The TagObserver outputs it too (``X_PO_held``), with whether that update's
frame was valid (``X_PO_held_valid``): reading them costs no frame.
"""

from __future__ import annotations

import numpy as np
from pydrake.common.value import AbstractValue
from pydrake.math import RigidTransform, RotationMatrix
from pydrake.systems.framework import BasicVector, Context, LeafSystem, State, ValueProducer
from pydrake.systems.sensors import ImageRgba8U

from vlr_drake.kinematics import checked_offset, checked_period, checked_seed
from vlr_drake.perception.image_noise import add_pixel_noise, checked_scale, downsample_area
from vlr_drake.perception.tag_pose import (
    TagObserverConfig,
    _check_intrinsics,
    check_pose,
    make_detector,
    observe_pom,
)


def _declare_update(system: LeafSystem, update_period_sec: float | None, update, update_offset_sec: float = 0.0) -> None:
    if update_period_sec is None:
        if update_offset_sec != 0.0:
            raise ValueError(f"'update_offset_sec' needs a periodic update ('update_period_sec'), got {update_offset_sec}")
        system.DeclarePerStepUnrestrictedUpdateEvent(update=update)
    else:
        period = checked_period(update_period_sec, "update_period_sec")
        offset = checked_offset(update_offset_sec, period, "update_offset_sec", "update_period_sec")
        system.DeclarePeriodicUnrestrictedUpdateEvent(period_sec=period, offset_sec=offset, update=update)
    system.DeclareForcedUnrestrictedUpdateEvent(update=update)


class TagObserver(LeafSystem):
    """AprilTag observer: ``rgb_image`` in; ``X_PO_measured``, ``X_PO_valid``,
    ``reprojection_error``, ``X_PO_held``, ``X_PO_held_valid`` out (DESIGN sections 5 and 8).

    Parameters:
        config: what tag to look for and when to trust it (``TagObserverConfig``).
        K, dist: intrinsics of the image the detector sees (after ``input_scale``
            downsampling); dist None means no distortion.
        X_PC: camera pose in the palm frame; X_TO: POM frame in the tag frame (None:
            identity, the POM is the tag frame).
        update_period_sec: period of the held-pose update; None for a per-step update.
        update_offset_sec: when in that period the update comes, in [0, update_period_sec).
            The builder gives the filter's offset: an update at the same time as the
            filter's reads the same detection (one cache entry, one rendered frame), where
            an update at 0 would render and detect a second frame every period.
        input_scale: the incoming image is this many times the resolution K describes
            (a rendering at ``render_scale``); it is downsampled with INTER_AREA first.
        image_size: (width, height) the (downsampled) image must have, or None (unchecked).
        pixel_noise_std, seed: Gaussian pixel noise (0..255 scale) added after
            downsampling, drawn per frame from ``numpy.random.default_rng((seed, t_us))``
            with t_us the context time in microseconds (reproducible); 0 disables it.

    Ports: input ``rgb_image`` (abstract ``ImageRgba8U``); outputs ``X_PO_measured``
    (abstract ``RigidTransform``), ``X_PO_valid`` (size 1) and ``reprojection_error`` (size
    1, RMS px of the pose fitted to the detection; NaN where no pose was fitted: no tag,
    an empty image, a tag too small, one whose edges could not be measured or that faces
    away; finite with valid 0 where the error itself rejected the frame); ``X_PO_held``
    (abstract ``RigidTransform``) and ``X_PO_held_valid`` (size 1): the held pose and
    whether the last update's frame was valid, which a reader between updates takes
    without rendering or detecting a frame of its own (the scenario builder's controller
    and goal anchor: they act on the frame the filter read).
    """

    def __init__(
        self,
        config: TagObserverConfig,
        K: np.ndarray,
        dist: np.ndarray | None,
        X_PC: RigidTransform,
        X_TO: RigidTransform | None = None,
        update_period_sec: float | None = None,
        update_offset_sec: float = 0.0,
        input_scale: int = 1,
        image_size: tuple[int, int] | None = None,
        pixel_noise_std: float = 0.0,
        seed: int = 0,
    ):
        super().__init__()
        self._config = config.validate()
        _check_intrinsics(K, dist)  # named here, not at the first frame with a tag
        self._K = np.asarray(K, dtype=np.float64)
        self._dist = None if dist is None else np.asarray(dist, dtype=np.float64).ravel()
        self._X_PC = check_pose(X_PC, "X_PC")
        self._X_TO = check_pose(X_TO, "X_TO", optional=True)
        self._input_scale = checked_scale(input_scale, "'input_scale'")
        if image_size is not None and (len(image_size) != 2 or min(image_size) <= 0):
            raise ValueError(f"'image_size' must be (width, height) > 0, got {image_size}")
        self._image_size = None if image_size is None else (int(image_size[0]), int(image_size[1]))
        if not (np.isfinite(pixel_noise_std) and pixel_noise_std >= 0):
            raise ValueError(f"'pixel_noise_std' must be a finite number >= 0, got {pixel_noise_std}")
        self._pixel_noise_std = float(pixel_noise_std)
        self._seed = checked_seed(seed)
        self._detector = make_detector(config.corner_refinement, config.detector_overrides)

        self._rgb_image = self.DeclareAbstractInputPort(
            name="rgb_image", model_value=AbstractValue.Make(ImageRgba8U())
        )
        self._held = self.DeclareAbstractState(model_value=AbstractValue.Make(RigidTransform()))
        self._detection = self.DeclareCacheEntry(
            description="tag detection of the current image",
            value_producer=ValueProducer(
                allocate=lambda: AbstractValue.Make((None, {})), calc=self._calc_detection
            ),
            prerequisites_of_calc=(
                {self._rgb_image.ticket(), self.time_ticket()}
                if self._pixel_noise_std > 0
                else {self._rgb_image.ticket()}
            ),
        )
        depends = {self._detection.ticket(), self.abstract_state_ticket(self._held)}
        self._X_PO_measured = self.DeclareAbstractOutputPort(
            name="X_PO_measured",
            alloc=lambda: AbstractValue.Make(RigidTransform()),
            calc=self._calc_pose,
            prerequisites_of_calc=depends,
        )
        self._X_PO_valid = self.DeclareVectorOutputPort(
            name="X_PO_valid", size=1, calc=self._calc_valid, prerequisites_of_calc={self._detection.ticket()}
        )
        self._reprojection_error = self.DeclareVectorOutputPort(
            name="reprojection_error",
            size=1,
            calc=self._calc_reprojection_error,
            prerequisites_of_calc={self._detection.ticket()},
        )
        # whether the last update's frame was valid (0 before the first update)
        self._held_valid = self.DeclareDiscreteState(1)
        self._X_PO_held = self.DeclareAbstractOutputPort(
            name="X_PO_held",
            alloc=lambda: AbstractValue.Make(RigidTransform()),
            calc=lambda context, output: output.set_value(self.held_pose(context)),
            prerequisites_of_calc={self.abstract_state_ticket(self._held)},
        )
        self._X_PO_held_valid = self.DeclareStateOutputPort("X_PO_held_valid", self._held_valid)
        _declare_update(self, update_period_sec, self._update_held, update_offset_sec)

    # Port accessors (keep the handles, never look ports up by number).
    def rgb_image_input_port(self):
        return self._rgb_image

    def X_PO_measured_output_port(self):
        return self._X_PO_measured

    def X_PO_valid_output_port(self):
        return self._X_PO_valid

    def reprojection_error_output_port(self):
        return self._reprojection_error

    def X_PO_held_output_port(self):
        """The pose stored at the last update: its frame's where that frame was valid
        (``X_PO_held_valid`` 1), else the last valid one before it. Reading it renders and
        detects nothing."""
        return self._X_PO_held

    def X_PO_held_valid_output_port(self):
        """1.0 where the last update's frame was valid, 0.0 where it was not or before the
        first update."""
        return self._X_PO_held_valid

    def held_pose(self, context: Context) -> RigidTransform:
        """The last valid pose stored by an update (identity before the first); a copy."""
        return RigidTransform(context.get_abstract_state(self._held).get_value())

    def prepare_image(self, image: np.ndarray, time: float = 0.0) -> np.ndarray:
        """Downsample (``input_scale``), check ``image_size`` and add the seeded pixel noise:
        the image the detector sees."""
        image = downsample_area(image, self._input_scale)
        if self._image_size is not None and (image.shape[1], image.shape[0]) != self._image_size:
            raise ValueError(
                f"rgb_image: expected {self._image_size[0]} x {self._image_size[1]} after downsampling by "
                f"{self._input_scale}, got shape {image.shape}"
            )
        if self._pixel_noise_std > 0:
            rng = np.random.default_rng((self._seed, int(round(time * 1e6))))
            image = add_pixel_noise(image, self._pixel_noise_std, rng)
        return image

    def _calc_detection(self, context: Context, value: AbstractValue) -> None:
        image = self._rgb_image.Eval(context).data
        if image.size:  # (an empty frame is a lost one: observe_pom says so)
            image = self.prepare_image(image, context.get_time())
        X_PO, info = observe_pom(
            image, self._config, self._K, self._dist, self._X_PC, self._X_TO, self._detector
        )
        value.set_value((X_PO, info))

    def _calc_pose(self, context: Context, output: AbstractValue) -> None:
        X_PO, _ = self._detection.Eval(context)
        output.set_value(X_PO if X_PO is not None else self.held_pose(context))

    def _calc_valid(self, context: Context, output: BasicVector) -> None:
        X_PO, _ = self._detection.Eval(context)
        output.SetAtIndex(0, 1.0 if X_PO is not None else 0.0)

    def _calc_reprojection_error(self, context: Context, output: BasicVector) -> None:
        _, info = self._detection.Eval(context)
        output.SetAtIndex(0, info["reprojection_error_px"])

    def _update_held(self, context: Context, state: State) -> None:
        X_PO, _ = self._detection.Eval(context)
        if X_PO is not None:
            state.get_mutable_abstract_state(self._held).set_value(X_PO)
        state.get_mutable_discrete_state(self._held_valid).SetAtIndex(0, 0.0 if X_PO is None else 1.0)


def rotation_from_vector(w: np.ndarray) -> RotationMatrix:
    """Rotation matrix exp([w]x) of a rotation vector w [rad] (Rodrigues' formula)."""
    w = np.asarray(w, dtype=np.float64)
    if w.shape != (3,):
        raise ValueError(f"rotation vector: must have shape (3,), got {w.shape}")
    angle = float(np.linalg.norm(w))
    if angle < 1e-12:
        return RotationMatrix()
    k = w / angle
    Kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return RotationMatrix(np.eye(3) + np.sin(angle) * Kx + (1.0 - np.cos(angle)) * (Kx @ Kx))


class NoisyPoseSensor(LeafSystem):
    """The true POM pose plus seeded noise, with the TagObserver's output ports.

    Sample n draws, from ``numpy.random.default_rng((seed, n))``: dp ~ N(0, sigma_p^2 I_3)
    [m] (in P), w ~ N(0, sigma_r^2 I_3) [rad] (a rotation vector, applied in P) and a
    dropout with probability ``dropout_probability``; the measurement is
        p_PO_meas = p_PO + dp,   R_PO_meas = exp([w]x) R_PO,
    or, on a dropout, the held pose with valid 0. The sample index n (discrete state) advances
    at every update event (periodic with ``update_period_sec``, else per step, and forced),
    which also stores the new sample's measurement as the held pose when it is valid.

    Ports: input ``X_PO_true`` (abstract ``RigidTransform``); outputs ``X_PO_measured``
    (abstract ``RigidTransform``) and ``X_PO_valid`` (size 1).
    """

    def __init__(
        self,
        sigma_p: float,
        sigma_r: float,
        dropout_probability: float = 0.0,
        seed: int = 0,
        update_period_sec: float | None = None,
    ):
        super().__init__()
        if not (np.isfinite(sigma_p) and sigma_p >= 0):
            raise ValueError(f"'sigma_p' must be a finite number >= 0 [m], got {sigma_p}")
        if not (np.isfinite(sigma_r) and sigma_r >= 0):
            raise ValueError(f"'sigma_r' must be a finite number >= 0 [rad], got {sigma_r}")
        if not 0.0 <= dropout_probability < 1.0:
            raise ValueError(f"'dropout_probability' must be in [0, 1), got {dropout_probability}")
        self._sigma_p = float(sigma_p)
        self._sigma_r = float(sigma_r)
        self._dropout = float(dropout_probability)
        self._seed = checked_seed(seed)

        self._X_PO_true = self.DeclareAbstractInputPort(
            name="X_PO_true", model_value=AbstractValue.Make(RigidTransform())
        )
        self._sample = self.DeclareDiscreteState(1)
        self._held = self.DeclareAbstractState(model_value=AbstractValue.Make(RigidTransform()))
        self._X_PO_measured = self.DeclareAbstractOutputPort(
            name="X_PO_measured", alloc=lambda: AbstractValue.Make(RigidTransform()), calc=self._calc_pose
        )
        self._X_PO_valid = self.DeclareVectorOutputPort(
            name="X_PO_valid",
            size=1,
            calc=self._calc_valid,
            prerequisites_of_calc={self.discrete_state_ticket(self._sample)},
        )
        _declare_update(self, update_period_sec, self._update)

    def X_PO_true_input_port(self):
        return self._X_PO_true

    def X_PO_measured_output_port(self):
        return self._X_PO_measured

    def X_PO_valid_output_port(self):
        return self._X_PO_valid

    def held_pose(self, context: Context) -> RigidTransform:
        """The last valid measurement stored by an update (identity before the first); a copy."""
        return RigidTransform(context.get_abstract_state(self._held).get_value())

    def draw(self, n: int) -> tuple[np.ndarray, np.ndarray, bool]:
        """Noise of sample n: (dp [m] (3,), rotation vector w [rad] (3,), valid)."""
        rng = np.random.default_rng((self._seed, int(n)))
        dp = rng.normal(0.0, self._sigma_p, size=3)
        w = rng.normal(0.0, self._sigma_r, size=3)
        valid = bool(rng.random() >= self._dropout)
        return dp, w, valid

    def measure(self, X_PO_true: RigidTransform, n: int) -> RigidTransform | None:
        """Measurement of sample n, or None on a dropout."""
        dp, w, valid = self.draw(n)
        if not valid:
            return None
        return RigidTransform(rotation_from_vector(w) @ X_PO_true.rotation(), X_PO_true.translation() + dp)

    def _n(self, context: Context) -> int:
        return int(context.get_discrete_state(self._sample).GetAtIndex(0))

    def _calc_pose(self, context: Context, output: AbstractValue) -> None:
        X = self.measure(check_pose(self._X_PO_true.Eval(context), "input 'X_PO_true'"), self._n(context))
        output.set_value(X if X is not None else self.held_pose(context))

    def _calc_valid(self, context: Context, output: BasicVector) -> None:
        output.SetAtIndex(0, 1.0 if self.draw(self._n(context))[2] else 0.0)

    def _update(self, context: Context, state: State) -> None:
        n = self._n(context) + 1
        state.get_mutable_discrete_state(self._sample).SetAtIndex(0, float(n))
        X = self.measure(check_pose(self._X_PO_true.Eval(context), "input 'X_PO_true'"), n)
        if X is not None:
            state.get_mutable_abstract_state(self._held).set_value(X)
