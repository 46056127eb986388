"""The hardware interface: the real hand's tendon motors and palm camera as one Drake system.

DESIGN.md section 8: the same diagram runs on a real hand by swapping the physics plant and
the rendered camera for this system; the observer, filter and controller stay unchanged. It
has the simulated hand's ports plus the camera's:

    input  tendon_command            (N,) commanded tendon pull l [m] (0 = taut, straight finger)
    output tendon_position_measured  (N,) tendon pull measured by the motor encoders [m]
    output rgb_image                 ImageRgba8U, the latest camera frame (abstract)
    output camera_valid              (1,) 1 if the last update got a camera frame, else 0
    output tendon_command_sent       (N,) the command after the limits, as sent [m]
    output motor_current             (N,) present motor current [A]

A periodic unrestricted update (``config.period_s``) clips the command to the tendon limits
(the config's or the hand's ``tendon_range``), moves it at most ``config.max_tendon_speed``
x ``period_s`` from the command sent before (so the grasp's first command is a ramp from
where the motors start, not a jump), and never sends sooner than ``period_s`` of real time
after the last send (it waits out the rest): a Simulator that fell behind real time (a slow
filter, a stalled camera) runs its missed updates back to back, which had sent a full step
each, 19 mm in 113 ms against the 20 mm/s limit, and had taken the measurement 0.9 T after
an action a few milliseconds after it (a review). The update reads the command as it stands
before any discrete update at the same instant (Drake runs unrestricted updates first): a
policy's or controller's new command at k T goes out at the next update, ``period_s`` later
(50 ms by default; the filter reads at 0.9 T, long after). It then converts the command to motor ticks
(:class:`vlr_drake.hardware.config.TendonMotorMap`), sends it with one sync write, reads all
positions with one sync read, and takes a camera frame (a device or stream: the newest frame
if it is fresher than ``config.camera_max_frame_age_s``, without waiting; a video file: the
next frame, waiting at most ``config.camera_timeout_s``; :class:`vlr_drake.hardware.camera.FrameSource`). Without a
frame (a stalled camera, the end of a video), ``camera_valid`` is 0 and ``rgb_image`` is a
black frame, so an AprilTag observer that only sees the image reports "no tag" instead of
re-using a stale frame.

Safe start and stop: an initialization event opens the camera, then the motors (ping, first
read, goal = present position, then torque on:
:class:`vlr_drake.hardware.dynamixel.TendonMotors`), so a camera that cannot open stops the
start before any motor has torque.
Given a ``grasp_command``, the same event then closes the hand on the grasp before the run's
clock starts: the tendons are ramped there at ``config.max_tendon_speed`` until each is
within ``config.grasp_tolerance`` of its command (waiting at most ``config.grasp_timeout_s``
once the ramp has sent it; then a warning says how far they are), so that the first action
and the filter's first measurement find the grasp made. A Simulator's real-time pacing
should start after it (``Simulator.ResetStatistics`` after ``Initialize``, as
:func:`run_hardware` and the scenario builder do).
A bus failure or a non-finite command switches torque off and raises. :meth:`close` (called by
:func:`run_hardware` on the way out, also on errors and Ctrl-C, and by a finalizer as a last
resort) switches torque off and releases the camera.

The hardware is a single resource: one context per :class:`HardwareInterface` at a time.
"""

from __future__ import annotations

import logging
import time
import warnings
import weakref
from pathlib import Path

import numpy as np
from pydrake.systems.framework import DiagramBuilder, LeafSystem
from pydrake.systems.sensors import ImageRgba8U

from vlr_drake.hand import HandSpec
from vlr_drake.hardware.camera import CameraError, CameraIntrinsics, FrameSource, read_intrinsics
from vlr_drake.hardware.config import HardwareConfig, TendonMotorMap
from vlr_drake.hardware.dynamixel import TendonMotors

__all__ = ["HardwareInterface", "add_hardware_interface", "build_hardware_diagram", "run_hardware"]

log = logging.getLogger(__name__)


def _shutdown(motors, camera) -> None:
    try:
        if motors is not None:
            motors.close()
    finally:
        if camera is not None:
            camera.release()


def _to_rgba(frame: np.ndarray) -> np.ndarray:
    """A camera frame as RGBA uint8: OpenCV's BGR (H, W, 3), BGRA (H, W, 4), or gray (H, W)
    or (H, W, 1), as monochrome cameras deliver; another shape or dtype is a CameraError
    that names it."""
    import cv2

    frame = np.asarray(frame)
    codes = {1: cv2.COLOR_GRAY2RGBA, 3: cv2.COLOR_BGR2RGBA, 4: cv2.COLOR_BGRA2RGBA}
    channels = 1 if frame.ndim == 2 else frame.shape[2] if frame.ndim == 3 else 0
    if frame.dtype != np.uint8 or channels not in codes or min(frame.shape[:2], default=0) < 1:
        raise CameraError(f"camera: frames must be uint8 BGR, BGRA or gray images, got shape {frame.shape} "
                          f"of {frame.dtype}")
    return cv2.cvtColor(np.ascontiguousarray(frame), codes[channels])


class HardwareInterface(LeafSystem):
    """Tendon motors and camera of a real hand, with the simulated hand's ports (module doc).

    Args:
        hand: the hand (finger count and, unless the config narrows them, tendon limits).
        config: the scenario's hardware section.
        intrinsics: camera intrinsics; default: read ``config.calibration_file``.
        motors: a motor driver with ``open/read/write_goal_ticks/close`` (default
            :class:`TendonMotors` from the config).
        camera: a frame source with ``open/read/release`` (default :class:`FrameSource`).
        grasp_command: tendon commands (N,) [m] to close the hand on before the run starts
            (module doc); None: the run starts where the motors are.
    """

    def __init__(
        self,
        hand: HandSpec,
        config: HardwareConfig,
        intrinsics: CameraIntrinsics | None = None,
        motors=None,
        camera=None,
        grasp_command=None,
    ):
        super().__init__()
        N = hand.num_fingers
        config.validate(num_fingers=N)
        self.config = config
        self.num_tendons = N
        lower, upper = config.tendon_limits(hand)
        self.motor_map = TendonMotorMap(config, lower, upper)
        if grasp_command is not None:
            grasp_command = np.asarray(grasp_command, float)
            if grasp_command.shape != (N,) or not np.all(np.isfinite(grasp_command)):
                raise ValueError(f"hardware interface: 'grasp_command' must be {N} finite tendon commands [m], "
                                 f"got {grasp_command.tolist()}")
            if np.any(self.motor_map.clip(grasp_command)[1]):  # never close on a grasp cut short at a limit
                raise ValueError(
                    f"hardware interface: 'grasp_command' {np.round(1e3 * grasp_command, 3).tolist()} mm is outside "
                    f"the tendon limits [{np.round(1e3 * lower, 3).tolist()}, {np.round(1e3 * upper, 3).tolist()}] mm")
        self.grasp_command = grasp_command
        #: How the start's closing on the grasp went: updates, seconds, the largest distance
        #: of a tendon from its command at the end [m], and whether it got within tolerance.
        self.grasp_report: dict | None = None
        self.intrinsics = (intrinsics or read_intrinsics(config.calibration_file)).validate()
        w, h = self.intrinsics.width, self.intrinsics.height
        self.motors = (
            motors if motors is not None else TendonMotors.from_config(config, self.motor_map.tick_limits())
        )
        self.camera = (
            camera
            if camera is not None
            else FrameSource(
                config.camera, config.camera_timeout_s, expected_size=(w, h), mode=config.camera_mode,
                max_age_s=config.camera_max_frame_age_s,
            )
        )
        self._finalizer = weakref.finalize(self, _shutdown, self.motors, self.camera)
        self._blank = np.zeros((h, w, 4), np.uint8)
        self._blank[..., 3] = 255

        self._command_port = self.DeclareVectorInputPort(name="tendon_command", size=N)
        self._measured_index = self.DeclareDiscreteState(N)
        self._sent_index = self.DeclareDiscreteState(N)
        self._current_index = self.DeclareDiscreteState(N)
        self._valid_index = self.DeclareDiscreteState(1)
        self._image_index = self.DeclareAbstractState(model_value=self._image_value(self._blank))
        self._measured_port = self.DeclareStateOutputPort(
            name="tendon_position_measured", state_index=self._measured_index
        )
        self._image_port = self.DeclareStateOutputPort(name="rgb_image", state_index=self._image_index)
        self._valid_port = self.DeclareStateOutputPort(name="camera_valid", state_index=self._valid_index)
        self._sent_port = self.DeclareStateOutputPort(
            name="tendon_command_sent", state_index=self._sent_index
        )
        self._current_port = self.DeclareStateOutputPort(
            name="motor_current", state_index=self._current_index
        )
        self.DeclareInitializationUnrestrictedUpdateEvent(update=self._initialize)
        self.DeclarePeriodicUnrestrictedUpdateEvent(
            period_sec=config.period_s, offset_sec=0.0, update=self._update
        )
        self.DeclareForcedUnrestrictedUpdateEvent(update=self._update)
        #: Updates done, how many of them had a command clipped at a limit, and how many sent
        #: a command ramped towards the one asked for (config.max_tendon_speed).
        self.num_updates = 0
        self.num_clipped = 0
        self.num_ramped = 0
        self._last_send: float | None = None  # time.monotonic() of the last goal sent to the motors

    # --- the camera's calibration, for the AprilTag observer ----------------------------------
    def camera_matrix(self) -> np.ndarray:
        """3 x 3 intrinsic matrix K of ``rgb_image`` (OpenCV pixel convention)."""
        return np.array(self.intrinsics.K, float)

    def distortion_coefficients(self) -> np.ndarray:
        """OpenCV distortion coefficients of ``rgb_image``."""
        return np.array(self.intrinsics.dist, float)

    def image_size(self) -> tuple[int, int]:
        """(width, height) of ``rgb_image`` [px] (the calibration's image size)."""
        return self.intrinsics.width, self.intrinsics.height

    # --- life cycle ---------------------------------------------------------------------------
    def close(self) -> None:
        """Torque off, close the bus and release the camera (idempotent)."""
        self._finalizer()

    @property
    def closed(self) -> bool:
        return not self._finalizer.alive

    # --- events -------------------------------------------------------------------------------
    @staticmethod
    def _image_value(rgba: np.ndarray):
        from pydrake.common.value import Value

        image = ImageRgba8U(rgba.shape[1], rgba.shape[0])
        image.mutable_data[:] = rgba
        return Value(image)

    def _initialize(self, context, state) -> None:
        if self.closed:
            raise RuntimeError("hardware interface: already closed; build a new one to run again")
        try:
            self.camera.open()  # first: a camera that cannot open stops the start before any torque
            ticks = self.motors.open()
            l = self.motor_map.to_tendon(ticks)
            sent = np.clip(l, self.motor_map.lower, self.motor_map.upper)
            if self.grasp_command is not None:
                l, sent = self._close_on_grasp(l, sent)
        except BaseException:
            self.close()
            raise
        state.get_mutable_discrete_state(self._measured_index).set_value(l)
        state.get_mutable_discrete_state(self._sent_index).set_value(sent)
        log.info("hardware interface started: tendons %s m", np.round(l, 5))

    def _pace(self) -> None:
        """Wait until ``period_s`` of real time has passed since the last send, so that the
        ramp's step per update is a speed (``max_tendon_speed``) whatever the Simulator does."""
        if self._last_send is not None:
            wait = self.config.period_s - (time.monotonic() - self._last_send)
            if wait > 0:
                time.sleep(wait)

    def _ramped(self, command: np.ndarray, last: np.ndarray) -> np.ndarray:
        """``command`` moved at most ``max_tendon_speed * period_s`` from ``last`` [m]."""
        step = self.config.max_tendon_speed * self.config.period_s
        return np.clip(command, last - step, last + step)

    def _close_on_grasp(self, l: np.ndarray, sent: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Ramp the tendons from ``sent`` to the grasp's commands, then wait up to
        ``grasp_timeout_s`` for the motors to get within ``grasp_tolerance`` of them (module
        doc); returns the measured and the sent tendons at the end."""
        cfg = self.config
        target = self.grasp_command  # within the limits (checked when the interface was made)
        updates, start, arrived = 0, time.monotonic(), None
        while True:
            sent = self._ramped(target, sent)
            self._pace()
            self.motors.write_goal_ticks(self.motor_map.to_ticks(sent))
            self._last_send = time.monotonic()
            ticks, _ = self.motors.read()
            l = self.motor_map.to_tendon(ticks)
            updates += 1
            off = float(np.max(np.abs(l - target)))
            if arrived is None and np.all(sent == target):  # the ramp is done; the motors follow
                arrived = time.monotonic()
            reached = arrived is not None and off <= cfg.grasp_tolerance
            if reached or (arrived is not None and time.monotonic() - arrived >= cfg.grasp_timeout_s):
                break  # (the next send waits out period_s: _pace)
        self.grasp_report = {"updates": updates, "seconds": time.monotonic() - start, "largest_offset_m": off,
                             "reached": reached}
        if not reached:
            warnings.warn(
                f"hardware interface: {cfg.grasp_timeout_s} s after the grasp's commands were sent the tendons "
                f"are {np.round(1e3 * (l - target), 2).tolist()} mm from them (grasp_tolerance "
                f"{1e3 * cfg.grasp_tolerance} mm): an object that stops the fingers short under the goal current, "
                f"or a motor that cannot follow; the run starts there", stacklevel=2)
        return l, sent

    def _update(self, context, state) -> None:
        if self.closed:
            raise RuntimeError("hardware interface: closed (torque is off); the run cannot continue")
        try:
            last = np.array(context.get_discrete_state(self._sent_index).get_value())
            if self._command_port.HasValue(context):
                command = np.asarray(self._command_port.Eval(context), float)
            else:  # nothing connected: hold the last command
                command = last
            sent, clipped = self.motor_map.clip(command)
            ramped = self._ramped(sent, last)
            self.num_ramped += bool(np.any(ramped != sent))
            sent = ramped
            self._pace()
            self.motors.write_goal_ticks(self.motor_map.to_ticks(sent))
            self._last_send = time.monotonic()
            ticks, current = self.motors.read()
            ok, frame = self.camera.read()
            rgba = _to_rgba(frame) if ok else self._blank
        except BaseException:
            self.close()
            raise
        self.num_updates += 1
        self.num_clipped += bool(np.any(clipped))
        state.get_mutable_discrete_state(self._sent_index).set_value(sent)
        state.get_mutable_discrete_state(self._measured_index).set_value(self.motor_map.to_tendon(ticks))
        state.get_mutable_discrete_state(self._current_index).set_value(
            np.asarray(current, float) * self.config.current_unit_a
        )
        state.get_mutable_discrete_state(self._valid_index).set_value([1.0 if ok else 0.0])
        state.get_mutable_abstract_state(self._image_index).set_value(self._image_value(rgba).get_value())

    # --- port handles -------------------------------------------------------------------------
    def get_tendon_command_input_port(self):
        return self._command_port

    def get_tendon_position_measured_output_port(self):
        return self._measured_port

    def get_rgb_image_output_port(self):
        return self._image_port

    def get_camera_valid_output_port(self):
        return self._valid_port


def add_hardware_interface(
    builder: DiagramBuilder,
    hand: HandSpec,
    config: HardwareConfig,
    name: str = "hardware",
    base_dir: str | Path | None = None,
    **kwargs,
) -> HardwareInterface:
    """Add a :class:`HardwareInterface` named ``name`` to ``builder`` (what the scenario
    builder calls for a hardware run). A relative ``config.calibration_file`` is resolved
    against ``base_dir`` (the scenario file's folder) when given; ``kwargs`` go to the
    constructor (e.g. ``intrinsics=``)."""
    if base_dir is not None and not Path(config.calibration_file).is_absolute():
        import copy

        config = copy.deepcopy(config)
        config.calibration_file = str(Path(base_dir) / config.calibration_file)
    return builder.AddNamedSystem(name, HardwareInterface(hand, config, **kwargs))


def build_hardware_diagram(
    hand: HandSpec,
    config: HardwareConfig,
    command_source=None,
    **kwargs,
):
    """A diagram of the hardware interface alone, for bring-up and tests.

    ``command_source`` (a System with one N-vector output, e.g. a ConstantVectorSource or a
    TrajectorySource) is connected to ``tendon_command``; without it that input is exported.
    The interface's outputs are exported under their own names. Returns (diagram, interface).
    """
    builder = DiagramBuilder()
    hw = add_hardware_interface(builder, hand, config, **kwargs)
    if command_source is not None:
        src = builder.AddNamedSystem("tendon_command_source", command_source)
        builder.Connect(src.get_output_port(), hw.get_tendon_command_input_port())
    else:
        builder.ExportInput(hw.get_tendon_command_input_port(), "tendon_command")
    for port in (
        hw.get_tendon_position_measured_output_port(),
        hw.get_rgb_image_output_port(),
        hw.get_camera_valid_output_port(),
        hw.GetOutputPort("tendon_command_sent"),
        hw.GetOutputPort("motor_current"),
    ):
        builder.ExportOutput(port, port.get_name())
    diagram = builder.Build()
    diagram.set_name("hardware_diagram")
    return diagram, hw


def run_hardware(
    diagram, interface: HardwareInterface, duration: float, realtime_rate: float = 1.0, monitor=None
):
    """Run ``diagram`` in (scaled) real time with Drake's Simulator for ``duration`` [s];
    the interface is closed (torque off) on the way out, also on errors. Returns the
    simulator. ``monitor`` (optional) is passed to ``Simulator.set_monitor``."""
    from pydrake.systems.analysis import Simulator

    simulator = Simulator(diagram)
    simulator.set_target_realtime_rate(realtime_rate)
    if monitor is not None:
        simulator.set_monitor(monitor)
    try:
        simulator.Initialize()
        simulator.ResetStatistics()  # real time from here: the start (opening, the grasp) took its own
        simulator.AdvanceTo(duration)
    finally:
        interface.close()
    return simulator
