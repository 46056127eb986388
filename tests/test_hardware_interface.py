"""The hardware interface system, on the Dynamixel pty emulator and a video file as camera.

No real hardware: the motors are emulated X-series servos behind a pseudo-terminal, reached
through the real dynamixel_sdk; the camera is an MJPG video of an AprilTag rendered at known
poses with a known K, played through cv2.VideoCapture.
"""

from __future__ import annotations

import json
import threading
import time
from types import SimpleNamespace

import cv2
import numpy as np
import pytest
from dynamixel_emulator import ADDR_GOAL_POSITION, ADDR_TORQUE_ENABLE, SYNC_WRITE, WRITE, DynamixelEmulator
from pydrake.common.yaml import yaml_load_typed
from pydrake.math import RigidTransform, RollPitchYaw, RotationMatrix
from pydrake.systems.analysis import Simulator
from pydrake.systems.framework import DiagramBuilder, EventStatus
from pydrake.systems.primitives import ConstantVectorSource

from vlr_drake.hand import model_o
from vlr_drake.hardware.calibrate import render_planar_target
from vlr_drake.hardware.camera import (
    CameraError,
    CameraIntrinsics,
    FrameSource,
    read_intrinsics,
    write_intrinsics,
)
from vlr_drake.hardware.config import HardwareConfig, TendonMotorMap, load_hardware_config
from vlr_drake.hardware.dynamixel import DynamixelError, TendonMotors
from vlr_drake.perception.apriltag import tag_image
from vlr_drake.systems.hardware_interface import (
    HardwareInterface,
    add_hardware_interface,
    build_hardware_diagram,
    run_hardware,
)

# Bus calls and camera reads are bounded: a hang would trip this.
pytestmark = pytest.mark.timeout(30)

IDS = [11, 12, 13]
ZERO = [1000, 2000, -500]
DIRECTION = [1, -1, 1]
W, H = 320, 240
K = np.array([[300.0, 0.0, 159.5], [0.0, 300.0, 119.5], [0.0, 0.0, 1.0]])
TAG_SIZE = 0.03
R_FACING = np.diag([1.0, -1.0, -1.0])  # tag frame facing the camera


def intrinsics() -> CameraIntrinsics:
    return CameraIntrinsics(K=K.copy(), dist=np.zeros(5), width=W, height=H)


def tag_poses(n: int) -> list[RigidTransform]:
    """Poses X_CT of the tag in the camera frame, a small wobble 0.12 m in front of it."""
    out = []
    for k in range(n):
        a = 2 * np.pi * k / n
        R = (
            RotationMatrix(R_FACING)
            @ RollPitchYaw(0.15 * np.sin(a), 0.12 * np.cos(a), 0.1 * a).ToRotationMatrix()
        )
        out.append(RigidTransform(R, [0.01 * np.cos(a), 0.008 * np.sin(a), 0.12 + 0.01 * np.sin(2 * a)]))
    return out


def write_tag_video(path, poses) -> None:
    """MJPG video, one frame per pose, of tag 0 rendered with K (a few kB per frame)."""
    ppc = 16
    tex = tag_image(0, pixels_per_cell=ppc)
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 20.0, (W, H))
    assert writer.isOpened()
    for X in poses:
        gray = render_planar_target(
            tex, TAG_SIZE / (8 * ppc), K, X.rotation().matrix(), X.translation(), (W, H), background=200
        )
        writer.write(cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR))
    writer.release()


@pytest.fixture
def emulator():
    emu = DynamixelEmulator(IDS, initial_positions=dict(zip(IDS, [1300, 1500, -100], strict=True)))
    emu.start()
    yield emu
    emu.stop()


@pytest.fixture(scope="module")
def tag_video(tmp_path_factory):
    path = tmp_path_factory.mktemp("video") / "tag.avi"
    poses = tag_poses(10)
    write_tag_video(path, poses)
    return path, poses


def make_config(emu: DynamixelEmulator, camera, **kw) -> HardwareConfig:
    cfg = HardwareConfig(
        port=emu.port_name,
        motor_ids=list(IDS),
        zero_offset_ticks=list(ZERO),
        direction=list(DIRECTION),
        spool_radius=0.005,
        camera=camera,
        camera_timeout_s=0.5,
        latency_timer_ms=30.0,
        period_s=0.05,
        # the fastest ramp allowed, 1 mm per update (its own test:
        # test_system_ports_with_fixed_input_and_forced_update)
        max_tendon_speed=0.02,
    )
    for k, v in kw.items():
        setattr(cfg, k, v)
    return cfg


def expected_ticks(l) -> list[int]:
    ticks_per_m = 4096 / (2 * np.pi * 0.005)
    return [z + d * int(np.round(x * ticks_per_m)) for z, d, x in zip(ZERO, DIRECTION, l, strict=True)]


class FakeCapture:
    """A VideoCapture stand-in: ``n`` grey frames, then ``read`` blocks until released.
    With ``gate`` (a threading.Event) the first frame waits until the gate opens."""

    def __init__(self, n: int, size=(W, H), gate: threading.Event | None = None, shape=None, dtype=np.uint8):
        self.n, self.size, self.gate = n, size, gate
        # a frame's shape beyond (height, width): (3,) BGR by default, () for a gray camera
        self.shape, self.dtype = (3,) if shape is None else tuple(shape), dtype
        self.release_event = threading.Event()

    def __call__(self, source):
        return self

    def isOpened(self):  # noqa: N802 (OpenCV name)
        return True

    def read(self):
        if self.gate is not None:
            self.gate.wait(timeout=5.0)
        if self.n > 0:
            self.n -= 1
            return True, np.full((self.size[1], self.size[0], *self.shape), 77, self.dtype)
        self.release_event.wait(timeout=30.0)
        return False, None

    def release(self):
        self.release_event.set()


# --- config --------------------------------------------------------------------------------
def test_config_loads_from_yaml(tmp_path):
    text = """
port: /dev/ttyUSB1
baud_rate: 57600
motor_ids: [4, 5, 6]
spool_radius: 0.006
zero_offset_ticks: [10, 20, 30]
direction: [1, -1, 1]
camera: rtsp://camera.local/stream
tendon_lower: [0.0, 0.0, 0.001]
tendon_upper: [0.04, 0.04, 0.03]
"""
    (tmp_path / "hw.yaml").write_text(text)
    cfg = load_hardware_config(filename=str(tmp_path / "hw.yaml"), data="camera: 2\n")
    assert cfg.motor_ids == [4, 5, 6] and cfg.baud_rate == 57600 and cfg.camera == 2
    cfg.validate(num_fingers=3)
    lo, hi = cfg.tendon_limits()
    assert lo.tolist() == [0.0, 0.0, 0.001] and hi.tolist() == [0.04, 0.04, 0.03]
    cfg = yaml_load_typed(schema=HardwareConfig, data="camera: /videos/run.avi\n")
    assert cfg.camera == "/videos/run.avi"
    # a scenario file gives its hardware section (the bring-up tool with diagrams/hardware.yaml)
    from vlr_drake.scenario import DIAGRAMS_DIR, load_scenario

    cfg = load_hardware_config(filename=str(DIAGRAMS_DIR / "hardware.yaml"), data="baud_rate: 57600\n")
    expected = load_scenario(DIAGRAMS_DIR / "hardware.yaml").hardware
    assert cfg.motor_ids == expected.motor_ids and cfg.direction == expected.direction and cfg.baud_rate == 57600
    assert cfg.calibration_file == expected.calibration_file  # relative to the scenario file, as the scenario has it
    (tmp_path / "no_hw.yaml").write_text("name: x\nplant: model\n")
    with pytest.raises(ValueError, match="no_hw.yaml': a scenario file without a 'hardware' section"):
        load_hardware_config(filename=str(tmp_path / "no_hw.yaml"))


def test_tendon_limits_default_to_the_hand():
    hand = model_o()
    lo, hi = HardwareConfig().tendon_limits(hand)
    assert lo.tolist() == [f.tendon_range[0] for f in hand.fingers]
    assert hi.tolist() == [f.tendon_range[1] for f in hand.fingers]


def test_tendon_limits_may_narrow_the_hand_s_range_not_widen_it():
    hand = model_o()
    top = hand.fingers[2].tendon_range[1]
    cfg = HardwareConfig(tendon_lower=[0.0, 0.0, 0.001], tendon_upper=[0.03, 0.03, top])
    lo, hi = cfg.tendon_limits(hand)
    assert lo.tolist() == [0.0, 0.0, 0.001] and hi.tolist() == [0.03, 0.03, top]
    cfg.tendon_upper = [0.03, 0.03, top + 0.01]
    assert cfg.tendon_limits()[1][2] == top + 0.01  # without the hand there is nothing to check against
    with pytest.raises(ValueError, match=r"motor 2 \(finger_right\) limits \[0.001, 0.055\] m reach outside the "
                                         r"hand's tendon_range \[0.0, 0.045\] m"):
        cfg.tendon_limits(hand)
    cfg = HardwareConfig(tendon_lower=[-1.0, 0.0, 0.0], tendon_upper=[0.03, 0.03, 0.03])
    with pytest.raises(ValueError, match=r"motor 0 \(thumb\) limits \[-1.0, 0.03\] m reach outside"):
        cfg.tendon_limits(hand)


@pytest.mark.parametrize(
    "field, value",
    [
        ("baud_rate", 12345),
        ("motor_ids", [1, 1, 2]),
        ("spool_radius", -0.01),
        ("zero_offset_ticks", [0, 0]),
        ("direction", [1, 0, 1]),
        ("tendon_lower", [0.0, 0.0]),
        ("operating_mode", 3),
        ("camera", ""),
        ("period_s", 0.0),
        ("protocol_version", 1.0),
        ("goal_current_raw", 0),  # mode 5 needs one: the motor's own is near the stall current
        ("goal_current_raw", 4000),
        ("max_tendon_speed", 0.0),
        ("grasp_timeout_s", float("nan")),
        ("period_s", 1.0),  # 20 mm per update, each at the motors' full speed: not a speed limit
        ("max_tendon_speed", 0.05),  # 2.5 mm per 50 ms update
        ("start_tolerance_ticks", 100_000),  # 767 mm of tendon clamped in one jump at start
        ("zero_offset_ticks", [2_000_000, 0, 0]),  # past the motors' multi-turn range
        ("camera_mode", "sequential"),  # a device read in order: a timed-out frame came late as fresh
    ],
)
def test_config_validate_names_bad_field(field, value):
    cfg = HardwareConfig()
    setattr(cfg, field, value)
    with pytest.raises(ValueError, match=f"'{field}'"):
        cfg.validate()


def test_the_goal_current_is_written_by_default(emulator):
    """Current-based position mode with the config's goal current (300 by default), which
    limits the tendons' pull; extended position mode (4) has none to give."""
    from dynamixel_emulator import ADDR_GOAL_CURRENT

    assert HardwareConfig(operating_mode=4, goal_current_raw=0).validate().goal_current_raw == 0
    cfg = make_config(emulator, 0)
    assert (cfg.operating_mode, cfg.goal_current_raw) == (5, 300)
    with TendonMotors.from_config(cfg, (np.full(3, -99999), np.full(3, 99999))):
        assert [emulator.motors[i].get(ADDR_GOAL_CURRENT, "<h") for i in IDS] == [300] * 3


def test_config_loader_errors_name_the_file(tmp_path):
    """Drake's loader raised RuntimeError for an unknown or mistyped field, which the bring-up
    tool's error handling (ValueError, FileNotFoundError) let through as a traceback."""
    (tmp_path / "hw.yaml").write_text("motor_idz: [1, 2, 3]\n")
    with pytest.raises(ValueError, match=r"hardware config file '.*hw.yaml': .*motor_idz"):
        load_hardware_config(filename=str(tmp_path / "hw.yaml"))
    with pytest.raises(ValueError, match=r"hardware config text: .*camera"):
        load_hardware_config(data="camera: true\n")
    with pytest.raises(ValueError, match=r"hardware config text: "):  # YAML that does not parse
        load_hardware_config(data="port: [1\n")


def test_bring_up_tool_refuses_no_frames(capsys):
    """--frames 0 or less read nothing and reported "0 of 0 frames" (after opening the camera)."""
    from vlr_drake.hardware.__main__ import main as bring_up

    for frames in ("0", "-3"):
        with pytest.raises(SystemExit):
            bring_up(["camera", "--frames", frames])
        assert f"--frames: must be >= 1, got {frames}" in capsys.readouterr().err


def test_bring_up_tool_takes_a_hardware_sections_paths_relative_to_its_file(tag_video, tmp_path, monkeypatch):
    """A hardware section file's relative calibration_file is next to it, as a scenario's is
    (the bring-up tool had looked in the working folder, and said the file does not exist)."""
    import io

    from vlr_drake.hardware.__main__ import main as bring_up

    path, poses = tag_video
    (tmp_path / "hw").mkdir()
    write_intrinsics(tmp_path / "hw" / "cam.yaml", intrinsics())
    (tmp_path / "hw" / "hw.yaml").write_text(f"camera: {path}\ncalibration_file: cam.yaml\nmotor_record: motors.json\n")
    monkeypatch.chdir(tmp_path)
    out = io.StringIO()
    assert bring_up(["camera", "--config", "hw/hw.yaml", "--frames", "2"], out=out) == 0
    assert f"calibration {tmp_path / 'hw' / 'cam.yaml'}: {W} x {H}" in out.getvalue()
    cfg = load_hardware_config(filename="hw/hw.yaml", data="calibration_file: other.yaml\n", resolve=True)
    assert cfg.calibration_file == "other.yaml" and cfg.motor_record == str(tmp_path / "hw" / "motors.json")
    # without resolve, as add_hardware_interface takes it (with its own base_dir)
    assert load_hardware_config(filename="hw/hw.yaml").calibration_file == "cam.yaml"


def test_config_validate_checks_finger_count():
    with pytest.raises(ValueError, match="'motor_ids' has 3 motors but the hand has 4"):
        HardwareConfig().validate(num_fingers=4)


def test_tendon_motor_map_round_trip_and_clip():
    cfg = HardwareConfig(zero_offset_ticks=ZERO, direction=DIRECTION, spool_radius=0.005)
    m = TendonMotorMap(cfg, np.zeros(3), np.full(3, 0.04))
    l = np.array([0.0, 0.01, 0.0375])
    ticks = m.to_ticks(l)
    assert ticks.tolist() == expected_ticks(l)
    assert np.allclose(m.to_tendon(ticks), l, atol=2 * np.pi * 0.005 / 4096)
    c, clipped = m.clip(np.array([-0.01, 0.02, 0.05]))
    assert c.tolist() == [0.0, 0.02, 0.04] and clipped.tolist() == [True, False, True]
    lo, hi = m.tick_limits()
    assert lo.tolist() == [1000, expected_ticks([0, 0.04, 0])[1], -500]
    assert np.all(lo <= hi)
    with pytest.raises(ValueError, match="not finite"):
        m.clip(np.array([0.0, np.nan, 0.0]))
    with pytest.raises(ValueError, match="shape"):
        m.to_ticks(np.zeros(2))


# --- camera --------------------------------------------------------------------------------
def test_intrinsics_yaml_round_trip(tmp_path):
    intr = CameraIntrinsics(K=K, dist=np.array([0.1, -0.2, 0.001, 0.002, 0.05]), width=W, height=H)
    write_intrinsics(tmp_path / "cam.yaml", intr, rms_px=0.2)
    text = (tmp_path / "cam.yaml").read_text()
    assert text.startswith("%YAML") and "camera_matrix" in text and "distortion_coefficients" in text
    back = read_intrinsics(tmp_path / "cam.yaml")
    assert np.allclose(back.K, K) and np.allclose(back.dist, intr.dist)
    assert (back.width, back.height) == (W, H)
    # no coefficients (no distortion) reads back as no distortion (it had written a matrix
    # that read_intrinsics refused)
    write_intrinsics(tmp_path / "plain.yaml", CameraIntrinsics(K=K, dist=np.zeros(0), width=W, height=H))
    assert np.array_equal(read_intrinsics(tmp_path / "plain.yaml").dist, np.zeros(5))


def test_intrinsics_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.yaml"):
        read_intrinsics(tmp_path / "nope.yaml")
    (tmp_path / "bad.yaml").write_text("%YAML:1.0\n---\nimage_width: 320\nimage_height: 240\n")
    with pytest.raises(CameraError, match="no 'camera_matrix'"):
        read_intrinsics(tmp_path / "bad.yaml")
    with pytest.raises(ValueError, match="camera_matrix"):
        CameraIntrinsics(K=np.eye(2), dist=np.zeros(5), width=W, height=H).validate()


def test_frame_source_plays_a_file_then_reports_no_frame(tag_video):
    path, poses = tag_video
    with FrameSource(str(path), timeout_s=1.0, expected_size=(W, H)) as cam:
        assert cam.mode == "sequential"  # auto: an existing file
        frames = [cam.read() for _ in range(len(poses) + 3)]
    assert all(ok for ok, _ in frames[: len(poses)])
    assert frames[0][1].shape == (H, W, 3)
    assert not any(ok for ok, _ in frames[len(poses) :])
    assert cam.ended and cam.frames == len(poses) and cam.misses == 3


@pytest.mark.parametrize("mode", ["sequential", "latest"])
def test_frame_source_times_out_instead_of_hanging(mode):
    fake = FakeCapture(1)
    # a timeout long enough for a loaded machine to deliver the first frame in time (0.05 s
    # is within reach of a busy CI runner's scheduling)
    cam = FrameSource(0, timeout_s=0.3, mode=mode, capture_factory=fake).open()
    assert cam.read()[0]
    if mode == "latest":
        time.sleep(0.4)  # let the only frame grow older than timeout_s
    assert cam.read() == (False, None)
    assert cam.read() == (False, None)
    assert cam.misses == 2 and not cam.ended
    cam.release()


def test_a_stalled_camera_gives_no_frame_once_its_last_is_too_old(emulator):
    """latest mode: a frame counts while it is at most max_age_s old, however long the read
    may wait (timeout_s), so a camera that stalls gives no frame instead of one from before
    the hand's last action; the config's camera_max_frame_age_s reaches the interface."""
    cam = FrameSource(0, timeout_s=5.0, mode="latest", capture_factory=FakeCapture(1), max_age_s=0.3).open()
    try:
        assert cam.read()[0]
        time.sleep(0.4)
        assert cam.read() == (False, None) and cam.misses == 1
    finally:
        cam.release()
    with pytest.raises(ValueError, match="'max_age_s' must be positive"):
        FrameSource(0, max_age_s=0.0)
    # a NaN or infinite timeout is named (NaN had opened as "camera '0' did not open within nan
    # s"; an infinite wait overflows concurrent.futures' timeout: OverflowError)
    for bad in (float("nan"), float("inf"), 0.0):
        with pytest.raises(ValueError, match="'timeout_s' must be a positive finite time"):
            FrameSource(0, timeout_s=bad, capture_factory=FakeCapture(1))
    with pytest.raises(ValueError, match="'camera_max_frame_age_s' must be positive"):
        HardwareConfig(camera_max_frame_age_s=-1.0).validate()
    hw = HardwareInterface(model_o(), make_config(emulator, 0, camera_max_frame_age_s=0.15),
                           intrinsics=intrinsics())
    assert hw.camera.max_age_s == 0.15 and hw.camera.timeout_s == 0.5
    hw.close()


class CountingCapture:
    """A VideoCapture stand-in whose k-th frame carries k (blue: k mod 256, green: k // 256),
    one frame per ~2 ms."""

    def __init__(self):
        self.count = 0

    def __call__(self, source):
        return self

    def isOpened(self):  # noqa: N802 (OpenCV name)
        return True

    def read(self):
        time.sleep(0.002)
        self.count += 1
        frame = np.zeros((H, W, 3), np.uint8)
        frame[..., 0], frame[..., 1] = self.count % 256, self.count // 256
        return True, frame

    def release(self):
        pass


def test_frame_source_latest_mode_returns_the_newest_frame():
    fake = CountingCapture()
    cam = FrameSource(0, timeout_s=1.0, mode="latest", capture_factory=fake).open()
    assert cam.mode == "latest"
    try:

        def index(frame):
            return int(frame[0, 0, 0]) + 256 * int(frame[0, 0, 1])

        ok, first = cam.read()
        assert ok
        # the camera runs on ahead (count leads the published frame by at most one) ...
        while fake.count < index(first) + 11:
            time.sleep(0.001)
        ok, second = cam.read()
        # ... and the next read skips the stale frames in between
        assert ok and index(second) >= index(first) + 10
    finally:
        cam.release()
    assert FrameSource(0).mode == "latest"  # auto: a device index


def test_frame_source_errors(tmp_path):
    with pytest.raises(CameraError, match="cannot open camera"):
        FrameSource(str(tmp_path / "missing.avi")).open()
    cam = FrameSource(0, expected_size=(W, H), capture_factory=FakeCapture(2, size=(64, 48))).open()
    with pytest.raises(CameraError, match="64 x 48 frames but the calibration is for 320 x 240"):
        cam.read()
    cam.release()


# --- the system ----------------------------------------------------------------------------
def test_system_ports_with_fixed_input_and_forced_update(emulator, tag_video, monkeypatch):
    path, poses = tag_video
    cfg = make_config(emulator, str(path), max_tendon_speed=HardwareConfig().max_tendon_speed)  # the default ramp
    hw = HardwareInterface(model_o(), cfg, intrinsics=intrinsics())
    try:
        names = {hw.get_output_port(i).get_name() for i in range(hw.num_output_ports())}
        assert names == {
            "tendon_position_measured",
            "rgb_image",
            "camera_valid",
            "tendon_command_sent",
            "motor_current",
        }
        assert hw.get_input_port().get_name() == "tendon_command"
        assert np.allclose(hw.camera_matrix(), K) and hw.distortion_coefficients().shape == (5,)
        assert hw.image_size() == (W, H)
        ctx = hw.CreateDefaultContext()
        hw.ExecuteInitializationEvents(ctx)
        # measured tendons from the initial motor positions
        start = hw.motor_map.to_tendon(np.array([1300, 1500, -100]))
        assert np.allclose(hw.get_tendon_position_measured_output_port().Eval(ctx), start)
        assert all(emulator.torque_enabled(i) for i in IDS)
        assert hw.get_camera_valid_output_port().Eval(ctx)[0] == 0.0  # no frame yet
        command = np.array([0.012, 0.03, 0.02])
        hw.get_tendon_command_input_port().FixValue(ctx, command)
        # the command is approached at max_tendon_speed, one update at a time, not jumped to
        sent0 = hw.GetOutputPort("tendon_command_sent").Eval(ctx).copy()
        step = hw.config.max_tendon_speed * hw.config.period_s
        updates = int(np.ceil(np.max(np.abs(command - sent0)) / step - 1e-9))
        assert updates >= 3
        # the interface's clock, stopped: updates run back to back, as a Simulator that fell
        # behind real time runs them, and the waits it asks for are recorded
        from vlr_drake.systems import hardware_interface as hi

        now, waits = [time.monotonic()], []
        monkeypatch.setattr(hi, "time", SimpleNamespace(monotonic=lambda: now[0],
                                                        sleep=lambda s: (waits.append(s), now.__setitem__(0, now[0] + s))))
        for k in range(1, updates + 1):
            hw.ExecuteForcedEvents(ctx)
            emulator.wait_idle()
            want = np.clip(command, sent0 - k * step, sent0 + k * step)
            assert [emulator.goal_position(i) for i in IDS] == expected_ticks(want)
            if k == 1:  # the update's camera frame
                assert hw.get_camera_valid_output_port().Eval(ctx)[0] == 1.0
                image = hw.get_rgb_image_output_port().Eval(ctx)
                assert (image.width(), image.height()) == (W, H)
                rgba = np.asarray(image.data)
                assert rgba[..., 3].min() == 255 and rgba[..., :3].max() > 150  # a real frame
        assert [emulator.goal_position(i) for i in IDS] == expected_ticks(command)
        # each send after the first waited out period_s, so the ramp is a speed (each had sent a
        # full step at once)
        assert waits == pytest.approx([hw.config.period_s] * (updates - 1))
        assert hw.num_ramped == updates - 1  # the last update sends the command itself
        assert np.allclose(hw.get_tendon_position_measured_output_port().Eval(ctx), command, atol=1e-5)
    finally:
        hw.close()
    assert not any(emulator.torque_enabled(i) for i in IDS)
    assert hw.closed


def test_the_camera_check_counts_new_frames_not_a_stalled_one_given_again(monkeypatch):
    """In latest mode a frame still fresh is given again; the bring-up check had read its
    frames back to back and passed a camera that gave one frame and stalled (30 of 30). It
    paces its reads as a run does and needs more than one new frame (a review)."""
    import io
    import threading

    import cv2

    from vlr_drake.hardware.__main__ import main as bring_up

    class OneFrameThenStall:
        def __init__(self, source):
            self.n, self.stop = 0, threading.Event()

        def isOpened(self):
            return True

        def read(self):
            self.n += 1
            if self.n == 1:
                return True, np.zeros((480, 640, 3), np.uint8)
            self.stop.wait(2.0)  # the device stalls
            return False, None

        def set(self, *args):
            return True

        def get(self, *args):
            return 0.0

        def release(self):
            self.stop.set()

    monkeypatch.setattr(cv2, "VideoCapture", OneFrameThenStall)
    out = io.StringIO()
    assert bring_up(["camera", "--set", "camera: '0'\ncamera_max_frame_age_s: 0.2", "--frames", "10"], out=out) == 1
    assert "(1 new; latest mode gives a frame still fresh again)" in out.getvalue()


def test_end_to_end_with_tag_observer(emulator, tag_video):
    """The interface under Drake's Simulator in real time: commands reach the motors as the
    right ticks (clipped at the limits), the AprilTag observer sees the video's poses, the
    camera turns invalid when the video ends, and torque is off afterwards."""
    from vlr_drake.perception.tag_pose import TagObserverConfig
    from vlr_drake.systems.tag_observer import TagObserver

    path, poses = tag_video
    hand = model_o()
    cfg = make_config(emulator, str(path))
    lo, hi = cfg.tendon_limits(hand)
    command = np.array([0.01, -0.005, hi[2] + 0.01])  # finger 1 below, finger 2 above its limit
    # the motors start within 4 mm of the clipped command: the interface ramps at 1 mm per update
    for i, t in zip(IDS, expected_ticks(np.clip(command - 0.004, lo, hi)), strict=True):
        emulator.set_present_position(i, t)
    builder = DiagramBuilder()
    hw = add_hardware_interface(builder, hand, cfg, intrinsics=intrinsics())
    src = builder.AddNamedSystem("command", ConstantVectorSource(command))
    builder.Connect(src.get_output_port(), hw.get_tendon_command_input_port())
    observer = builder.AddNamedSystem(
        "tag_observer",
        TagObserver(
            TagObserverConfig(tag_id=0, tag_size=TAG_SIZE),
            K=hw.camera_matrix(),
            dist=hw.distortion_coefficients(),
            X_PC=RigidTransform(),
            update_period_sec=cfg.period_s,
            image_size=hw.image_size(),
        ),
    )
    builder.Connect(hw.get_rgb_image_output_port(), observer.rgb_image_input_port())
    diagram = builder.Build()

    records = []

    def monitor(root):
        ctx = hw.GetMyContextFromRoot(root)
        octx = observer.GetMyContextFromRoot(root)
        records.append(
            (
                root.get_time(),
                hw.camera.frames,
                hw.get_camera_valid_output_port().Eval(ctx)[0],
                observer.X_PO_valid_output_port().Eval(octx)[0],
                RigidTransform(
                    observer.X_PO_measured_output_port().Eval(octx)
                ),  # a copy: Eval returns the cache
                hw.get_tendon_position_measured_output_port().Eval(ctx).copy(),
            )
        )
        return EventStatus.Succeeded()

    duration = (len(poses) + 4) * cfg.period_s
    start = time.perf_counter()
    sim = run_hardware(diagram, hw, duration, realtime_rate=1.0, monitor=monitor)
    # in real time: the run took the clock's time, not less
    assert time.perf_counter() - start >= 0.9 * duration and sim.get_context().get_time() == pytest.approx(duration)
    assert hw.closed and not any(emulator.torque_enabled(i) for i in IDS)

    # ticks: the command, clipped to the limits, through spool radius, offset and direction
    sent = np.clip(command, lo, hi)
    assert sent[1] == lo[1] and sent[2] == hi[2]
    assert [emulator.goal_position(i) for i in IDS] == expected_ticks(sent)
    # where the run left the motors is recorded for the next start (a lost turn: test_dynamixel)
    record = json.loads(cfg.motor_record_path().read_text())
    assert record["port"] == emulator.port_name and list(record["ticks"].values()) == expected_ticks(sent)
    goal_writes = emulator.instructions(SYNC_WRITE, ADDR_GOAL_POSITION)
    lo_t, hi_t = hw.motor_map.tick_limits()
    for _, _, p in goal_writes:  # nothing outside the limits ever went on the bus
        for k in range(3):
            dxl_id, value = p[4 + 5 * k], int.from_bytes(p[5 + 5 * k : 9 + 5 * k], "little", signed=True)
            j = IDS.index(dxl_id)
            assert lo_t[j] <= value <= hi_t[j]
    assert hw.num_clipped == hw.num_updates > len(poses)
    assert np.allclose(records[-1][5], sent, atol=1e-5)

    # camera: valid while the video lasts, then invalid (and the observer sees no tag)
    valid = [r for r in records if r[2] == 1.0]
    invalid_after = [r for r in records if r[1] == len(poses) and r[2] == 0.0]
    assert len(valid) >= len(poses) - 1 and invalid_after
    assert all(r[3] == 0.0 for r in invalid_after)
    # the observer's pose matches the frame's rendered pose
    errors = []
    for _, frames, _, tag_ok, X, _ in valid:
        assert tag_ok == 1.0
        X_true = poses[frames - 1]
        errors.append(np.linalg.norm(X.translation() - X_true.translation()))
        angle = np.rad2deg(
            np.arccos(
                np.clip((np.trace(X.rotation().matrix().T @ X_true.rotation().matrix()) - 1) / 2, -1, 1)
            )
        )
        assert angle < 3.0
    assert max(errors) < 2e-3


def test_build_hardware_diagram_exports_ports(emulator, tag_video):
    path, _ = tag_video
    diagram, hw = build_hardware_diagram(model_o(), make_config(emulator, str(path)), intrinsics=intrinsics())
    try:
        for name in (
            "tendon_position_measured",
            "rgb_image",
            "camera_valid",
            "tendon_command_sent",
            "motor_current",
        ):
            assert diagram.HasOutputPort(name)
        assert diagram.HasInputPort("tendon_command")
        sim = Simulator(diagram)
        diagram.GetInputPort("tendon_command").FixValue(sim.get_mutable_context(), [0.005, 0.005, 0.005])
        sim.Initialize()
        sim.AdvanceTo(0.12)
        emulator.wait_idle()
        assert [emulator.goal_position(i) for i in IDS] == expected_ticks([0.005] * 3)
    finally:
        hw.close()
    assert not any(emulator.torque_enabled(i) for i in IDS)


def _run_with_fault(hw, diagram, inject, at_time=0.15, duration=1.0):
    def monitor(root):
        if root.get_time() >= at_time:
            inject()
        return EventStatus.Succeeded()

    with pytest.raises(DynamixelError) as info:
        run_hardware(diagram, hw, duration, realtime_rate=0.0, monitor=monitor)
    assert hw.closed
    return info.value


def test_corrupt_packets_stop_the_run_with_torque_off(emulator, tag_video):
    path, _ = tag_video
    diagram, hw = build_hardware_diagram(
        model_o(),
        make_config(emulator, str(path)),
        command_source=ConstantVectorSource([0.01] * 3),
        intrinsics=intrinsics(),
    )
    err = _run_with_fault(hw, diagram, lambda: emulator.corrupt_ids.add(12))
    assert "Incorrect status packet" in str(err) and "motor id 12" in str(err)
    assert not any(emulator.torque_enabled(i) for i in IDS)
    assert hw.camera._cap is None  # camera released too


def test_motor_that_stops_answering_stops_the_run(emulator, tag_video):
    path, _ = tag_video
    diagram, hw = build_hardware_diagram(
        model_o(),
        make_config(emulator, str(path)),
        command_source=ConstantVectorSource([0.01] * 3),
        intrinsics=intrinsics(),
    )
    err = _run_with_fault(hw, diagram, lambda: emulator.missing_ids.add(13))
    assert "motor id 13" in str(err)
    assert not emulator.torque_enabled(11) and not emulator.torque_enabled(12)


def test_disconnected_port_stops_the_run(emulator, tag_video):
    path, _ = tag_video
    diagram, hw = build_hardware_diagram(
        model_o(),
        make_config(emulator, str(path)),
        command_source=ConstantVectorSource([0.01] * 3),
        intrinsics=intrinsics(),
    )
    err = _run_with_fault(hw, diagram, emulator.disconnect)
    assert "failed" in str(err)


def test_missing_motor_at_start_is_named(emulator, tag_video):
    path, _ = tag_video
    emulator.missing_ids.add(12)
    diagram, hw = build_hardware_diagram(model_o(), make_config(emulator, str(path)), intrinsics=intrinsics())
    with pytest.raises(DynamixelError, match="motor id 12 does not answer"):
        run_hardware(diagram, hw, 0.5, realtime_rate=0.0)
    assert hw.closed and not any(emulator.torque_enabled(i) for i in IDS)


@pytest.mark.parametrize("mode", ["sequential", "latest"])
def test_camera_that_stops_delivering_gives_invalid_frames(emulator, mode):
    # latest mode keeps a frame valid for camera_timeout_s of wall time after it arrived: the
    # frames arrive once the run has started (the gate), and stay valid for 0.1 s, so that a
    # loaded machine's slow first steps do not age them before the loop looks (it did in CI,
    # with 30 ms and frames grabbed while the diagram was still being set up)
    latest = mode == "latest"
    gate = threading.Event() if latest else None
    fake = FakeCapture(3, gate=gate)
    cfg = make_config(emulator, 0, camera_timeout_s=0.1 if latest else 0.03)
    for i, t in zip(IDS, expected_ticks([0.018] * 3), strict=True):  # 2 mm from the command: two updates
        emulator.set_present_position(i, t)
    camera = FrameSource(
        0, timeout_s=cfg.camera_timeout_s, expected_size=(W, H), mode=mode, capture_factory=fake
    )
    diagram, hw = build_hardware_diagram(
        model_o(),
        cfg,
        command_source=ConstantVectorSource([0.02] * 3),
        intrinsics=intrinsics(),
        camera=camera,
    )
    flags = []

    def monitor(root):
        if gate is not None:
            gate.set()
        ctx = hw.GetMyContextFromRoot(root)
        flags.append(
            (
                hw.get_camera_valid_output_port().Eval(ctx)[0],
                np.asarray(hw.get_rgb_image_output_port().Eval(ctx).data)[..., :3].max(),
            )
        )
        return EventStatus.Succeeded()

    # real time: in latest mode a frame counts as valid for camera_timeout_s after it arrived
    run_hardware(diagram, hw, 0.5, realtime_rate=1.0, monitor=monitor)
    valid = [f for f, _ in flags]
    assert 1.0 in valid and valid[-1] == 0.0
    assert all(m == 0 for f, m in flags if f == 0.0)  # invalid frames are black
    assert all(m == 77 for f, m in flags if f == 1.0)
    # sequential: each of the 3 frames once; latest: the newest of them while it is fresh
    assert (camera.frames == 3) if mode == "sequential" else (camera.frames >= 1)
    # misses: sequential, each read after the third frame; latest, each read once the frames
    # have aged past 0.1 s of wall time (3-4 of the run's 10 on a quiet machine, 1 under load)
    assert camera.misses >= (5 if mode == "sequential" else 1)
    assert [emulator.goal_position(i) for i in IDS] == expected_ticks([0.02] * 3)  # motors kept running
    assert hw.closed and not any(emulator.torque_enabled(i) for i in IDS)


def test_nonfinite_command_stops_with_torque_off(emulator, tag_video):
    path, _ = tag_video
    hw = HardwareInterface(model_o(), make_config(emulator, str(path)), intrinsics=intrinsics())
    ctx = hw.CreateDefaultContext()
    hw.ExecuteInitializationEvents(ctx)
    n_writes = len(emulator.instructions(SYNC_WRITE, ADDR_GOAL_POSITION))
    hw.get_tendon_command_input_port().FixValue(ctx, [0.01, np.nan, 0.01])
    with pytest.raises(ValueError, match="not finite"):
        hw.ExecuteForcedEvents(ctx)
    emulator.wait_idle()
    assert len(emulator.instructions(SYNC_WRITE, ADDR_GOAL_POSITION)) == n_writes
    assert hw.closed and not any(emulator.torque_enabled(i) for i in IDS)


@pytest.mark.parametrize("shape", [(), (1,), (4,)])
def test_gray_and_bgra_cameras_give_rgba_images(emulator, shape):
    """A monochrome camera's (H, W) or (H, W, 1) frames and BGRA frames become the RGBA
    image (they used to fail in cvtColor's BGR conversion)."""
    camera = FrameSource(0, timeout_s=1.0, expected_size=(W, H), mode="sequential",
                         capture_factory=FakeCapture(3, shape=shape))
    hw = HardwareInterface(model_o(), make_config(emulator, 0), intrinsics=intrinsics(), camera=camera)
    ctx = hw.CreateDefaultContext()
    hw.ExecuteInitializationEvents(ctx)
    hw.ExecuteForcedEvents(ctx)
    image = np.asarray(hw.get_rgb_image_output_port().Eval(ctx).data)
    assert hw.get_camera_valid_output_port().Eval(ctx)[0] == 1.0
    alpha = 77 if shape == (4,) else 255  # a BGRA frame keeps its own alpha
    assert image.shape == (H, W, 4) and np.all(image[..., :3] == 77) and np.all(image[..., 3] == alpha)
    hw.close()


@pytest.mark.parametrize("shape, dtype", [((3,), np.uint16), ((2,), np.uint8)])
def test_unreadable_frames_stop_with_torque_off(emulator, shape, dtype):
    """A frame that is not a uint8 BGR, BGRA or gray image is named, and the motors stop."""
    camera = FrameSource(0, timeout_s=1.0, expected_size=(W, H), mode="sequential",
                         capture_factory=FakeCapture(3, shape=shape, dtype=dtype))
    hw = HardwareInterface(model_o(), make_config(emulator, 0), intrinsics=intrinsics(), camera=camera)
    ctx = hw.CreateDefaultContext()
    hw.ExecuteInitializationEvents(ctx)
    with pytest.raises(CameraError, match=f"got shape \\({H}, {W}(, {shape[0]})?\\) of {np.dtype(dtype).name}"):
        hw.ExecuteForcedEvents(ctx)
    emulator.wait_idle()
    assert hw.closed and not any(emulator.torque_enabled(i) for i in IDS)


def test_example_files_load_and_build(emulator, tmp_path):
    """The example hardware section and intrinsics in tests/data load; a relative
    calibration file is resolved against the scenario folder by add_hardware_interface."""
    from pathlib import Path

    data = Path(__file__).parent / "data"
    cfg = load_hardware_config(filename=str(data / "hardware_model_o.yaml"))
    cfg.validate(num_fingers=3)
    assert cfg.calibration_file == "camera_intrinsics.yaml" and cfg.camera == 0
    # run it against the emulator with a stand-in camera
    cfg.port, cfg.motor_ids, cfg.latency_timer_ms = emulator.port_name, list(IDS), 30.0
    for i in IDS:
        emulator.set_present_position(i, 2048)  # taut and straight: at the zero offsets
    builder = DiagramBuilder()
    camera = FrameSource(
        0, timeout_s=0.05, expected_size=(640, 480), capture_factory=FakeCapture(5, size=(640, 480))
    )
    hw = add_hardware_interface(builder, model_o(), cfg, base_dir=data, camera=camera)
    try:
        assert cfg.calibration_file == "camera_intrinsics.yaml"  # the caller's config is untouched
        assert hw.camera_matrix()[0, 0] == pytest.approx(612.4)
        assert hw.distortion_coefficients().tolist() == pytest.approx([0.082, -0.154, 0.0007, -0.0011, 0.061])
        ctx = hw.CreateDefaultContext()
        hw.ExecuteInitializationEvents(ctx)
        hw.get_tendon_command_input_port().FixValue(ctx, [0.001, 0.001, 0.001])  # one update's step
        hw.ExecuteForcedEvents(ctx)
        emulator.wait_idle()
        # direction [1, -1, 1] and zero offsets 2048 from the file
        ticks = int(np.round(0.001 * 4096 / (2 * np.pi * 0.005)))
        assert [emulator.goal_position(i) for i in IDS] == [2048 + ticks, 2048 - ticks, 2048 + ticks]
    finally:
        hw.close()
    with pytest.raises(FileNotFoundError, match="camera_intrinsics.yaml"):
        HardwareInterface(model_o(), load_hardware_config(filename=str(data / "hardware_model_o.yaml")))


def test_measured_position_lags_the_goal():
    """With a first-order motor lag the measured tendon trails the command."""
    with DynamixelEmulator(IDS, lag_s=0.5) as emu:
        cfg = make_config(emu, 0, zero_offset_ticks=[0, 0, 0], direction=[1, 1, 1])
        camera = FrameSource(0, timeout_s=0.05, expected_size=(W, H), capture_factory=FakeCapture(5))
        hw = HardwareInterface(model_o(), cfg, intrinsics=intrinsics(), camera=camera)
        try:
            ctx = hw.CreateDefaultContext()
            hw.ExecuteInitializationEvents(ctx)
            hw.get_tendon_command_input_port().FixValue(ctx, [0.002, 0.002, 0.002])  # two updates' steps
            hw.ExecuteForcedEvents(ctx)
            time.sleep(0.1)  # the motors follow 1 mm with a 0.5 s lag: about 0.18 mm by now
            hw.ExecuteForcedEvents(ctx)
            measured = hw.get_tendon_position_measured_output_port().Eval(ctx)
            assert np.all(measured > 0.0) and np.all(measured < 0.002)
            assert np.allclose(hw.GetOutputPort("tendon_command_sent").Eval(ctx), 0.002)
            assert np.all(hw.GetOutputPort("motor_current").Eval(ctx) > 0.0)  # pulling towards the goal
        finally:
            hw.close()


@pytest.mark.parametrize("lag_s", [0.0, 5.0])
def test_closing_on_the_grasp_that_the_motors_cannot_reach_in_time_warns(lag_s):
    """Motors too slow for grasp_timeout_s: the start says how far the tendons are and the
    run starts there; motors that follow reach the grasp, however long the ramp takes
    (10 updates of 50 ms here, longer than the 0.3 s timeout, which counts from the ramp's
    end); a grasp_command of the wrong size is refused by name."""
    with DynamixelEmulator(IDS, lag_s=lag_s) as emu:
        cfg = make_config(emu, 0, zero_offset_ticks=[0, 0, 0], direction=[1, 1, 1], max_tendon_speed=0.02,
                          grasp_timeout_s=0.3)
        camera = FrameSource(0, timeout_s=0.05, expected_size=(W, H), capture_factory=FakeCapture(5))
        with pytest.raises(ValueError, match="'grasp_command' must be 3 finite tendon commands"):
            HardwareInterface(model_o(), cfg, intrinsics=intrinsics(), camera=camera, grasp_command=[0.01, 0.01])
        hw = HardwareInterface(model_o(), cfg, intrinsics=intrinsics(), camera=camera, grasp_command=[0.01] * 3)
        try:
            ctx = hw.CreateDefaultContext()
            measured = hw.get_tendon_position_measured_output_port()
            if lag_s == 0.0:
                hw.ExecuteInitializationEvents(ctx)
                assert hw.grasp_report["reached"] and hw.grasp_report["updates"] == 10
                assert np.allclose(measured.Eval(ctx), 0.01, atol=cfg.grasp_tolerance)
                return
            with pytest.warns(UserWarning, match=r"0.3 s after the grasp's commands were sent the tendons are "):
                hw.ExecuteInitializationEvents(ctx)
            rep = hw.grasp_report
            assert not rep["reached"] and rep["seconds"] >= 0.3 + 9 * 0.05
            assert rep["largest_offset_m"] > cfg.grasp_tolerance
            assert np.all(measured.Eval(ctx) < 0.01 - cfg.grasp_tolerance)  # where the motors got to
            assert all(emu.torque_enabled(i) for i in IDS)  # and the run goes on from there
        finally:
            hw.close()


def test_a_camera_that_cannot_open_stops_the_start_before_any_torque(emulator, tmp_path):
    cfg = make_config(emulator, str(tmp_path / "missing.avi"))
    hw = HardwareInterface(model_o(), cfg, intrinsics=intrinsics())
    with pytest.raises(CameraError, match="cannot open camera"):
        hw.ExecuteInitializationEvents(hw.CreateDefaultContext())
    assert hw.closed and emulator.instructions(WRITE, ADDR_TORQUE_ENABLE) == []


class SizedCapture(FakeCapture):
    """A device stand-in that starts at 640 x 480 and takes the size it is set to."""

    def __init__(self, n):
        super().__init__(n, size=(640, 480))
        self.asked = {}

    def set(self, prop, value):
        import cv2

        self.asked[prop] = value
        w, h = self.size
        self.size = (int(value), h) if prop == cv2.CAP_PROP_FRAME_WIDTH else (w, int(value))
        return True


def test_a_device_is_asked_for_the_calibrated_size():
    import cv2

    fake = SizedCapture(2)
    cam = FrameSource(0, timeout_s=0.5, expected_size=(W, H), mode="sequential", capture_factory=fake).open()
    try:
        assert fake.asked == {cv2.CAP_PROP_FRAME_WIDTH: W, cv2.CAP_PROP_FRAME_HEIGHT: H}
        ok, frame = cam.read()
        assert ok and frame.shape[:2] == (H, W)
    finally:
        cam.release()


def test_a_device_that_hangs_while_opening_or_taking_its_size_is_named(monkeypatch):
    import vlr_drake.hardware.camera as camera_module

    monkeypatch.setattr(camera_module, "OPEN_WAIT_S", 0.2)
    release = threading.Event()

    class Hanging(SizedCapture):
        def set(self, prop, value):
            release.wait(5.0)
            return True

    try:
        with pytest.raises(CameraError, match=r"camera '0' did not take the frame size 320 x 240 within 0.2 s"):
            FrameSource(0, timeout_s=0.1, expected_size=(W, H), capture_factory=Hanging(1)).open()
        with pytest.raises(CameraError, match=r"camera '0' did not open within 0.2 s"):
            FrameSource(0, timeout_s=0.1, capture_factory=lambda source: release.wait(5.0)).open()
    finally:
        release.set()


def test_bring_up_tool(emulator, tag_video, tmp_path):
    import io

    from vlr_drake.hardware.__main__ import main as bring_up

    path, poses = tag_video
    write_intrinsics(tmp_path / "cam.yaml", intrinsics())
    override = (
        f"port: {emulator.port_name}\nmotor_ids: {IDS}\nzero_offset_ticks: {ZERO}\ndirection: {DIRECTION}\n"
        f"tendon_lower: [0.0, 0.0, 0.0]\ntendon_upper: [0.01, 0.01, 0.01]\nlatency_timer_ms: 30.0\n"
        f"camera: {path}\ncalibration_file: {tmp_path / 'cam.yaml'}\n"
    )
    out = io.StringIO()
    assert bring_up(["zero", "--set", override], out=out) == 0
    lines = out.getvalue().splitlines()
    assert lines[0] == "zero_offset_ticks: [1300, 1500, -100]" and "the motors' record" in lines[1]
    out = io.StringIO()
    assert bring_up(["status", "--set", override], out=out) == 0
    text = out.getvalue()
    assert "motor 12: 1500 ticks" in text and "motors [11, 12, 13] answer" in text
    assert "outside" not in text
    # with the hand's tendon_range as the limits (no tendon_lower/upper: the run's default), a
    # motor a turn off its zero (a reset multi-turn count) is named; status had said nothing
    # and the run refused to start
    turn = ("\ntendon_lower: [0.0, 0.0, 0.0]\ntendon_upper: [0.01, 0.01, 0.01]",
            "")
    shifted = override.replace(turn[0], turn[1]).replace(f"zero_offset_ticks: {ZERO}",
                                                         f"zero_offset_ticks: {[ZERO[0] + 4096, *ZERO[1:]]}")
    out = io.StringIO()
    assert bring_up(["status", "--set", shifted], out=out) == 0
    lines = out.getvalue().splitlines()
    assert "outside the tendon limits [0.0, 45.0] mm; a run refuses to start" in lines[1] and "outside" not in lines[2]
    assert not any(emulator.torque_enabled(i) for i in IDS)  # the tool never enables torque
    # a motor whose multi-turn count was reset since zero recorded it: status says a run refuses it
    emulator.set_present_position(IDS[0], 1300 - 4096)
    out = io.StringIO()
    assert bring_up(["status", "--set", override], out=out) == 0
    assert f"motor id {IDS[0]} reads -2796 ticks, -1 turn from the 1300" in out.getvalue()
    emulator.set_present_position(IDS[0], 1300)
    out = io.StringIO()
    assert bring_up(["camera", "--set", override, "--frames", str(len(poses) + 2)], out=out) == 0
    assert f"{len(poses)} of {len(poses) + 2} frames, sizes [({W}, {H})]" in out.getvalue()
