"""The real palm camera: an OpenCV VideoCapture frame source and OpenCV YAML intrinsics.

:class:`FrameSource` reads frames from a device index, a video file or a stream URL
(``cv2.VideoCapture``). A read never waits longer than ``timeout_s``: the capture runs on one
worker thread, and a frame that does not arrive in time, or the end of a file, is reported as
"no frame" (the hardware interface turns that into ``camera_valid = 0``), never as a hang.
Two modes: "sequential" (every frame in order, one capture read per :meth:`FrameSource.read`,
waiting up to ``timeout_s``; for video files) and "latest" (a grabber thread reads
continuously and :meth:`FrameSource.read` returns at once the newest frame if it is at most
``max_age_s`` old (default ``timeout_s``), so the control loop never waits on the camera
and never reads a stale buffer; for devices and streams). "auto" picks sequential for an
existing file, latest otherwise.

Intrinsics use OpenCV's own YAML format (``cv2.FileStorage``), the one ``calibrateCamera``
tools write: nodes ``camera_matrix`` (3 x 3), ``distortion_coefficients`` (1 x n, OpenCV's
order k1 k2 p1 p2 k3 ...), ``image_width``, ``image_height``. The pose observer gets K and
the distortion from here (DESIGN.md section 5: solvePnP with the camera intrinsics).
"""

from __future__ import annotations

import concurrent.futures as cf
import logging
import queue
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

__all__ = ["CameraError", "CameraIntrinsics", "FrameSource", "read_intrinsics", "write_intrinsics"]

#: Frame source modes (:class:`FrameSource`).
CAMERA_MODES = ("auto", "sequential", "latest")


def resolved_mode(mode: str, source) -> str:
    """``mode`` with "auto" resolved for ``source``: "sequential" for an existing file (a
    video), "latest" for a device or a stream."""
    if mode == "auto":
        return "sequential" if isinstance(source, str) and Path(source).is_file() else "latest"
    return mode
#: The least time a capture gets to open, or to take a setting, before a CameraError [s]
#: (a device may take a few seconds; ``timeout_s`` if that is longer).
OPEN_WAIT_S = 5.0

log = logging.getLogger(__name__)


class CameraError(RuntimeError):
    """The camera cannot be opened, or its frames do not match its calibration."""


@dataclass
class CameraIntrinsics:
    """Pinhole intrinsics with OpenCV distortion, for images of ``width`` x ``height``."""

    # 3 x 3 camera matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] [px], OpenCV pixel centres.
    K: np.ndarray
    # Distortion coefficients in OpenCV's order (k1, k2, p1, p2[, k3, ...]).
    dist: np.ndarray
    # Image size the calibration holds for [px].
    width: int
    height: int

    def validate(self) -> CameraIntrinsics:
        K = np.asarray(self.K, float)
        if K.shape != (3, 3) or not np.all(np.isfinite(K)):
            raise ValueError(
                f"intrinsics: 'camera_matrix' must be a finite 3 x 3 matrix, got shape {K.shape}"
            )
        if K[0, 0] <= 0 or K[1, 1] <= 0 or not np.allclose(K[2], [0, 0, 1]) or K[1, 0] != 0:
            raise ValueError(f"intrinsics: 'camera_matrix' is not a pinhole matrix: {K.tolist()}")
        d = np.asarray(self.dist, float).ravel()
        if d.size not in (0, 4, 5, 8, 12, 14) or not np.all(np.isfinite(d)):
            raise ValueError(
                f"intrinsics: 'distortion_coefficients' must have 4, 5, 8, 12 or 14 finite entries, got {d.size}"
            )
        if self.width <= 0 or self.height <= 0:
            raise ValueError(
                f"intrinsics: 'image_width' and 'image_height' must be positive, got {self.width} x {self.height}"
            )
        if not (0 <= K[0, 2] <= self.width and 0 <= K[1, 2] <= self.height):  # (a calibration had cy -33.5)
            raise ValueError(f"intrinsics: the principal point ({K[0, 2]:.1f}, {K[1, 2]:.1f}) px lies outside the "
                             f"{self.width} x {self.height} image: not a calibration of this camera")
        self.K, self.dist = K, d
        return self


def write_intrinsics(path: str | Path, intrinsics: CameraIntrinsics, rms_px: float | None = None) -> None:
    """Write intrinsics as an OpenCV YAML file (``cv2.FileStorage``)."""
    import cv2

    intrinsics.validate()
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    if not fs.isOpened():
        raise ValueError(f"cannot write intrinsics file '{path}' (a folder, or not writable)")
    try:
        fs.write("image_width", int(intrinsics.width))
        fs.write("image_height", int(intrinsics.height))
        fs.write("camera_matrix", np.asarray(intrinsics.K, np.float64))
        # no coefficients is no distortion: written as five zeros (OpenCV writes an empty
        # matrix it cannot read back)
        dist = np.asarray(intrinsics.dist, np.float64).ravel()
        fs.write("distortion_coefficients", (dist if dist.size else np.zeros(5)).reshape(1, -1))
        if rms_px is not None:
            fs.write("avg_reprojection_error", float(rms_px))
    finally:
        fs.release()


def _matrix(node) -> np.ndarray | None:
    """A FileNode's matrix: an OpenCV one (``!!opencv-matrix``), or a mapping of rows, cols
    and a flat data list, as ROS's camera_calibration writes them; None if it is neither."""
    import cv2

    try:
        m = node.mat()
        if m is not None:
            return m
    except (cv2.error, SystemError):  # (OpenCV raises on a mapping without the matrix tag)
        pass
    if not node.isMap():
        return None
    rows, cols, data = node.getNode("rows"), node.getNode("cols"), node.getNode("data")
    if rows.empty() or cols.empty() or data.empty() or not data.isSeq():
        return None
    values = np.array([data.at(i).real() for i in range(data.size())], np.float64)
    shape = (int(rows.real()), int(cols.real()))
    return values.reshape(shape) if values.size == shape[0] * shape[1] else None


def read_intrinsics(path: str | Path) -> CameraIntrinsics:
    """Read an intrinsics file: OpenCV YAML (as ``python -m vlr_drake.hardware calibrate``
    writes it) or a ROS camera_calibration YAML (its matrices as rows, cols and data); a
    missing file or node is an error naming it."""
    import cv2

    if not Path(path).is_file():
        raise FileNotFoundError(f"camera calibration file '{path}' does not exist")
    expected = ("OpenCV YAML expected, as python -m vlr_drake.hardware calibrate writes, or ROS's "
                "camera_calibration YAML: each matrix with rows, cols and data")
    try:  # OpenCV raises on an empty or malformed file, and on a matrix without its tag (a review)
        fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    except (cv2.error, SystemError) as e:
        raise CameraError(f"cannot parse camera calibration file '{path}' ({expected}): {e}") from None
    if not fs.isOpened():
        raise CameraError(f"cannot parse camera calibration file '{path}' ({expected})")
    try:
        nodes = {}
        for name in ("camera_matrix", "distortion_coefficients", "image_width", "image_height"):
            node = fs.getNode(name)
            if node.empty():
                raise CameraError(f"camera calibration file '{path}' has no '{name}'")
            nodes[name] = node
        K, dist = _matrix(nodes["camera_matrix"]), _matrix(nodes["distortion_coefficients"])
        width, height = int(nodes["image_width"].real()), int(nodes["image_height"].real())
    finally:
        fs.release()
    if K is None or dist is None:
        raise CameraError(
            f"camera calibration file '{path}': 'camera_matrix' and 'distortion_coefficients' must be matrices "
            f"({expected})"
        )
    try:
        return CameraIntrinsics(K=K, dist=dist.ravel(), width=width, height=height).validate()
    except ValueError as e:
        raise CameraError(f"camera calibration file '{path}': {e}") from e


class _Worker:
    """One daemon thread running submitted calls in order (a hung capture cannot block the
    interpreter's exit, unlike ``concurrent.futures.ThreadPoolExecutor``)."""

    def __init__(self, name: str):
        self._jobs: queue.Queue = queue.Queue()
        threading.Thread(target=self._run, name=name, daemon=True).start()

    def submit(self, fn, *args) -> cf.Future:
        fut: cf.Future = cf.Future()
        self._jobs.put((fut, fn, args))
        return fut

    def shutdown(self, wait: bool = False) -> None:
        self._jobs.put(None)

    def _run(self) -> None:
        while (job := self._jobs.get()) is not None:
            fut, fn, args = job
            if fut.set_running_or_notify_cancel():
                try:
                    fut.set_result(fn(*args))
                except BaseException as e:
                    fut.set_exception(e)


class FrameSource:
    """Frames from ``cv2.VideoCapture`` with a bounded wait per frame.

    Args:
        source: device index (int), or a video file path or stream URL (str).
        timeout_s: longest wait for one frame [s]; then :meth:`read` reports no frame.
        expected_size: (width, height) that frames must have (from the calibration);
            another size raises :class:`CameraError` (the intrinsics would be wrong).
        mode: "sequential", "latest" or "auto" (module docstring).
        max_age_s: latest mode: the oldest a frame may be and still be returned [s] (a
            camera that stalled for longer gives no frame, not a frame from before the
            hand's last move); None: ``timeout_s``.
        capture_factory: builds the capture object from ``source`` (default
            ``cv2.VideoCapture``); tests pass a stand-in.
    """

    def __init__(
        self,
        source: int | str,
        timeout_s: float = 1.0,
        expected_size: tuple[int, int] | None = None,
        mode: str = "auto",
        capture_factory=None,
        max_age_s: float | None = None,
    ):
        if not (timeout_s > 0 and np.isfinite(timeout_s)):  # (NaN had said "did not open within nan s")
            raise ValueError(f"camera: 'timeout_s' must be a positive finite time [s], got {timeout_s}")
        if max_age_s is not None and not max_age_s > 0:
            raise ValueError(f"camera: 'max_age_s' must be positive, got {max_age_s}")
        if mode not in CAMERA_MODES:
            raise ValueError(f"camera: 'mode' must be one of {CAMERA_MODES}, got {mode!r}")
        self.mode = resolved_mode(mode, source)
        self.source = source
        self.timeout_s = float(timeout_s)
        self.max_age_s = self.timeout_s if max_age_s is None else float(max_age_s)
        self.expected_size = expected_size
        self._factory = capture_factory
        self._cap = None
        self._pool: _Worker | None = None
        self._pending: cf.Future | None = None
        #: Frames delivered, and reads that delivered nothing (timeout or end of stream).
        self.frames = 0
        self.misses = 0
        #: latest mode: reads that returned an already returned (still fresh) frame again.
        self.repeats = 0
        #: True once the capture reported the end of the stream (a file ran out).
        self.ended = False
        # latest mode: the grabber's newest frame and its sequence number
        self._cond = threading.Condition()
        self._latest: np.ndarray | None = None
        self._latest_time = 0.0
        self._seq = 0
        self._taken = 0
        self._grab_failed = False
        self._stop = threading.Event()

    def open(self) -> FrameSource:
        import cv2

        factory = self._factory or cv2.VideoCapture
        self._pool = _Worker(name=f"camera-{self.source}")
        cap = self._on_worker(lambda: factory(self.source), "did not open")
        if cap is None or not cap.isOpened():
            self._pool.shutdown(wait=False)
            raise CameraError(f"cannot open camera '{self.source}' (device index, file or URL)")
        self._cap = cap
        if isinstance(self.source, int) and self.expected_size is not None and hasattr(cap, "set"):
            # a device: ask for the calibration's size (a camera may start in another mode;
            # read() still refuses frames of another size)
            w, h = self.expected_size
            self._on_worker(lambda: (cap.set(cv2.CAP_PROP_FRAME_WIDTH, w), cap.set(cv2.CAP_PROP_FRAME_HEIGHT, h)),
                            f"did not take the frame size {w} x {h}")
        if self.mode == "latest":
            self._pool.submit(self._grab_loop, cap)
            with self._cond:  # give the first frame up to timeout_s to arrive
                self._cond.wait_for(lambda: self._seq > 0 or self._grab_failed, timeout=self.timeout_s)
        return self

    def _on_worker(self, fn, failure: str):
        """``fn()`` on the capture's worker thread, waiting at most max(timeout_s,
        :data:`OPEN_WAIT_S`); a CameraError "camera '...' <failure> within ... s" (and the
        worker let go) if it takes longer."""
        wait = max(self.timeout_s, OPEN_WAIT_S)
        try:
            return self._pool.submit(fn).result(timeout=wait)
        except cf.TimeoutError as e:
            self._pool.shutdown(wait=False)
            raise CameraError(f"camera '{self.source}' {failure} within {wait} s") from e

    def _grab_loop(self, cap) -> None:
        """latest mode: read frames continuously, keep the newest (runs on the worker)."""
        while not self._stop.is_set():
            try:
                ok, frame = cap.read()
            except Exception as e:
                log.warning("camera '%s': read failed: %s", self.source, e)
                ok, frame = False, None
            with self._cond:
                if ok and frame is not None:
                    self._latest, self._seq, self._grab_failed = frame, self._seq + 1, False
                    self._latest_time = time.monotonic()
                else:
                    self._grab_failed = True
                self._cond.notify_all()
            if not ok:
                time.sleep(0.01)  # a dead device fails at once: do not spin

    def _read_latest(self) -> tuple[bool, np.ndarray | None]:
        """latest mode, without waiting: the newest frame if it arrived within ``max_age_s``
        (a frame already returned is returned again while it is that fresh)."""
        with self._cond:
            fresh = self._latest is not None and time.monotonic() - self._latest_time <= self.max_age_s
            if fresh:
                self.repeats += self._seq == self._taken
                self._taken = self._seq
                return True, self._latest
            self.ended = self._grab_failed
        return False, None

    def read(self) -> tuple[bool, np.ndarray | None]:
        """(True, BGR frame), or (False, None) when no frame came within ``timeout_s`` (module
        docstring: sequential waits for the next frame, latest takes the newest fresh one)."""
        if self._cap is None:
            raise CameraError(f"camera '{self.source}' is not open")
        if self.mode == "latest":
            ok, frame = self._read_latest()
            if not ok:
                self.misses += 1
                return False, None
            return self._accept(frame)
        if self._pending is None:
            self._pending = self._pool.submit(self._cap.read)
        try:
            ok, frame = self._pending.result(timeout=self.timeout_s)
        except cf.TimeoutError:
            self.misses += 1
            log.warning("camera '%s': no frame within %.3f s", self.source, self.timeout_s)
            return False, None  # the read stays pending; the next call waits on it again
        except Exception as e:
            self._pending = None
            self.misses += 1
            log.warning("camera '%s': read failed: %s", self.source, e)
            return False, None
        self._pending = None
        if not ok or frame is None:
            self.misses += 1
            self.ended = True
            return False, None
        self.ended = False
        return self._accept(frame)

    def _accept(self, frame: np.ndarray) -> tuple[bool, np.ndarray]:
        if self.expected_size is not None and (frame.shape[1], frame.shape[0]) != tuple(self.expected_size):
            raise CameraError(
                f"camera '{self.source}' delivers {frame.shape[1]} x {frame.shape[0]} frames but the "
                f"calibration is for {self.expected_size[0]} x {self.expected_size[1]}"
            )
        self.frames += 1
        return True, frame

    def release(self) -> None:
        """Release the capture on its worker thread (after any pending read), waiting for it
        at most ``timeout_s``: a process that exits while its capture is still being read or
        released can abort in OpenCV's teardown ("terminate called without an active
        exception", seen when a hardware run was stopped), while a hung capture must not
        hold the exit either."""
        self._stop.set()
        if self._cap is not None and self._pool is not None:
            done = self._pool.submit(self._cap.release)
            self._pool.shutdown(wait=False)
            try:
                done.result(timeout=self.timeout_s)
            except Exception:  # timed out, or the release failed: the capture is let go either way
                pass
        self._cap = None

    def __enter__(self) -> FrameSource:
        return self.open()

    def __exit__(self, *exc) -> None:
        self.release()
