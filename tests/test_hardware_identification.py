"""The full identification diagram on the hardware interface: the Dynamixel emulator on a
pseudo-terminal for the motors and a video file of the object's tag for the camera. The
filter initialises from the first frame with the tag and then runs one iteration per action."""

from pathlib import Path

import cv2
import numpy as np
import pytest
from pydrake.math import RigidTransform, RollPitchYaw, RotationMatrix
from pydrake.systems.analysis import Simulator

from vlr_drake.builder import build_diagram, initialize, run
from vlr_drake.hardware.calibrate import render_planar_target
from vlr_drake.hardware.camera import read_intrinsics
from vlr_drake.objects import preset
from vlr_drake.perception.apriltag import tag_image
from vlr_drake.scenario import DIAGRAMS_DIR, load_scenario


def _tag_video(path: Path, K, size, tag_id: int, tag_size: float, frames: int = 200) -> None:
    """The tag 0.1 m in front of the camera, facing it, wobbling a little frame by frame."""
    ppc = 16
    tex = tag_image(tag_id, pixels_per_cell=ppc)
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 20.0, size)
    facing = RotationMatrix(np.diag([1.0, -1.0, -1.0]))
    for k in range(frames):
        a = 0.2 * k
        X = RigidTransform(facing @ RollPitchYaw(0.05 * np.sin(a), 0.04 * np.cos(a), 0.0).ToRotationMatrix(),
                           [0.002 * np.sin(a), 0.001 * np.cos(a), 0.10])
        gray = render_planar_target(tex, tag_size / (8 * ppc), K, X.rotation().matrix(), X.translation(), size,
                                    background=200)
        writer.write(cv2.cvtColor(gray, cv2.COLOR_GRAY2BGR))
    writer.release()


def _apple_tag_video(tmp_path: Path, frames: int = 200) -> Path:
    """The apple's tag, seen by hardware.yaml's calibrated camera, as a video file."""
    intr = read_intrinsics(DIAGRAMS_DIR / "hardware" / "camera_intrinsics.yaml")
    obj = preset("apple")
    video = tmp_path / "tag.avi"
    _tag_video(video, intr.K, (intr.width, intr.height), obj.tag_id, obj.tag_size, frames=frames)
    return video


def _hardware_overrides(emu, video, period_sec: float | None = 0.25) -> str:
    """hardware.yaml's overrides for the emulated bus and the video camera, 500 particles."""
    exploration = "" if period_sec is None else f"exploration: {{period_sec: {period_sec}}}\n"
    return ("filter: {particles: 500}\n" + exploration
            + f"hardware: {{port: '{emu.port_name}', camera: '{video}', latency_timer_ms: 30.0}}\n")


def test_identification_diagram_runs_on_the_hardware_interface(tmp_path):
    from dynamixel_emulator import DynamixelEmulator

    video = _apple_tag_video(tmp_path)
    ids = [1, 2, 3]
    with DynamixelEmulator(ids, initial_positions={i: 2048 for i in ids}) as emu:
        s = load_scenario(DIAGRAMS_DIR / "hardware.yaml", _hardware_overrides(emu, video))
        b = build_diagram(s)
        sim = Simulator(b.diagram)
        ctx = sim.get_mutable_context()
        try:
            initialize(b, sim)
            sim.AdvanceTo(4.5 * b.period_sec)
            assert b.diagram.GetOutputPort("tag_observer.X_PO_valid").Eval(ctx)[0] == 1.0  # the tag is seen
            f = b.filter.filter(b.filter.GetMyContextFromRoot(ctx))
            assert f is not None, "the filter never initialised from the tag"
            assert f.iteration >= 2  # and it keeps stepping with the motors' actions
            theta = b.diagram.GetOutputPort("self_identification.theta_estimate").Eval(ctx)
            assert np.all(np.isfinite(theta))
            # the tag 0.1 m in front of the recessed camera, within the video's wobble (2 mm
            # and 0.06 rad) and the detection's error; the camera's pose in the palm from the
            # scenario
            X = b.diagram.GetOutputPort("tag_observer.X_PO_measured").Eval(ctx)
            X_CO = s.camera.X_PC().inverse() @ X
            assert np.linalg.norm(X_CO.translation() - [0.0, 0.0, 0.10]) < 0.004, X_CO.translation()
            facing = RotationMatrix(np.diag([1.0, -1.0, -1.0]))
            tilt = (facing.inverse() @ X_CO.rotation()).ToAngleAxis().angle()
            assert tilt < 0.08, tilt
        finally:
            b.plant.close()


def test_a_hardware_scenario_runs_in_real_time(tmp_path):
    """builder.run keeps a hardware scenario to the clock: the motors get each action period
    to move and the camera's frames are of now (a Simulator left to itself ran 5.9 s of the
    hand's time in 0.4 s, the filter reading tendons that had not moved yet)."""
    from dynamixel_emulator import DynamixelEmulator

    video = _apple_tag_video(tmp_path, frames=60)
    ids = [1, 2, 3]
    with DynamixelEmulator(ids, initial_positions={i: 2048 for i in ids}) as emu:
        r = run(load_scenario(DIAGRAMS_DIR / "hardware.yaml", _hardware_overrides(emu, video)), iterations=3,
                draws=2)
        assert r["iterations"] >= 2
        # its measurements pooled under two draws of the filter, offline (no truths on hardware)
        assert r["pooled"]["draws"] == 2 and r["pooled"]["steps"] == r["iterations"] and "errors" not in r["pooled"]
        assert r["sim_time"] == pytest.approx(3.95 * 0.25)
        assert 0.0 < r["realtime_rate"] <= 1.05  # sim time over wall time, from the end of the grasp
        assert not any(emu.torque_enabled(i) for i in ids)  # closed at the end
        hw = r["hardware"]  # the interface's counts: every update, none clipped, the grasp ramped in
        assert hw["updates"] >= 3 * 0.25 / 0.05 and hw["clipped"] == 0 and hw["grasp"]["reached"]


def test_a_grasp_the_hand_cannot_make_is_refused_before_any_motor_moves(tmp_path):
    """A hardware grasp past the joint limits, with contacts in millimetres, or needing more
    tendon than the limits allow is an error that names the grasp section before the
    interface exists (it had been clipped to the limits and closed on, 'reached'); the
    interface itself refuses a grasp command outside the limits instead of clipping it."""
    from vlr_drake.hand import model_o
    from vlr_drake.hardware.config import HardwareConfig
    from vlr_drake.systems.hardware_interface import HardwareInterface

    base = DIAGRAMS_DIR / "hardware.yaml"
    with pytest.raises(ValueError, match=r"grasp: 'theta_deg' of finger 0 \(thumb\) joint 1, 300.0 deg, is outside"):
        load_scenario(base, "grasp: {theta_deg: [[10, 300], [12, 35], [12, 35]]}")
    with pytest.raises(ValueError, match=r"grasp: 'contact' of finger 0 \(thumb\), 29.0 m, is past its last link"):
        load_scenario(base, "grasp: {contact: [29, 29, 29]}")
    s = load_scenario(base, "hardware: {tendon_lower: [0, 0, 0], tendon_upper: [0.025, 0.045, 0.045]}")
    with pytest.raises(ValueError, match=r"grasp: the grasp needs finger 0 \(thumb\)'s tendon at 3\d\.\d\d mm, "
                                         r"outside its limits \[0.00, 25.00\] mm"):
        build_diagram(s)
    cfg = HardwareConfig(tendon_lower=[0.0] * 3, tendon_upper=[0.025, 0.045, 0.045])
    with pytest.raises(ValueError, match=r"'grasp_command' \[31.0, 18.0, 18.0\] mm is outside the tendon limits"):
        HardwareInterface(model_o(), cfg, grasp_command=[0.031, 0.018, 0.018])


def test_a_hardware_update_period_too_long_for_the_actions_is_refused():
    """An interface that updates once a second under 0.25 s actions sent only one action in
    four to the motors, and the filter stepped on the rest as if they had moved."""
    with pytest.raises(ValueError, match=r"hardware: 'period_s' 0.1 s must be at most 1/4 of the action period "
                                         r"\(0.25 s\)"):
        load_scenario(DIAGRAMS_DIR / "hardware.yaml", "exploration: {period_sec: 0.25}\n"
                                                      "hardware: {period_s: 0.1, max_tendon_speed: 0.01}")
    load_scenario(DIAGRAMS_DIR / "hardware.yaml", "exploration: {period_sec: 0.4}\n"
                                                  "hardware: {period_s: 0.1, max_tendon_speed: 0.01, "
                                                  "camera_max_frame_age_s: 0.15}")


def test_a_camera_frame_from_before_the_action_cannot_count():
    """A live camera ("latest" frames) frozen as an action reached the motors had its frame
    from before the action, 0.18 s old and within camera_max_frame_age_s, taken as the
    action's measurement at T = 0.25 s: the age must stay under 0.9 T - 2 period_s. A
    video file is read frame by frame and is not held to it."""
    with pytest.raises(ValueError, match=r"hardware: 'camera_max_frame_age_s' 0.2 s lets a frame from before the "
                                         r"action count as its measurement: at most 0.9 T - 2 period_s = 0.125 s"):
        load_scenario(DIAGRAMS_DIR / "hardware.yaml", "exploration: {period_sec: 0.25}\n")
    load_scenario(DIAGRAMS_DIR / "hardware.yaml", "exploration: {period_sec: 0.25}\n"
                                                  "hardware: {camera_max_frame_age_s: 0.12}\n")


def test_the_commanded_action_on_hardware_is_what_the_motors_were_sent(tmp_path):
    """filter_action 'commanded' on hardware reads the interface's tendon_command_sent (after
    its clipping and ramp), not the policy's command, which a limit may have cut short
    (building opens no motor or camera)."""
    b = build_diagram(load_scenario(DIAGRAMS_DIR / "hardware.yaml", "filter_action: commanded"))
    try:
        assert b.diagram.AreConnected(b.plant.GetOutputPort("tendon_command_sent"), b.filter.tendon_command_input_port())
        assert not b.diagram.AreConnected(b.policy.GetOutputPort("tendon_command"), b.filter.tendon_command_input_port())
    finally:
        b.plant.close()


@pytest.mark.slow
@pytest.mark.parametrize("sig, when", [("SIGTERM", "running"), ("SIGINT", "running"), ("SIGTERM", "grasping")])
def test_a_killed_hardware_run_switches_the_torque_off(tmp_path, sig, when):
    """A kill or a closed terminal (SIGTERM, SIGHUP) had ended the process at once with the
    motors holding their goals; now they unwind the run as Ctrl-C does, whether it comes
    while the hand closes on the grasp or during the run's actions, its clean-up switches
    the torque off, and the command ends with one line and the shell's status (not as a bus
    error: the signal may come in the middle of the motors' I/O)."""
    import os
    import signal
    import subprocess
    import sys
    import time

    from dynamixel_emulator import DynamixelEmulator

    video = _apple_tag_video(tmp_path, frames=60)
    ids = [1, 2, 3]
    with DynamixelEmulator(ids, initial_positions={i: 2048 for i in ids}, lag_s=0.1) as emu:
        p = subprocess.Popen([sys.executable, "-m", "vlr_drake.builder", "--run", str(DIAGRAMS_DIR / "hardware.yaml"),
                              "--iterations", "100000", "--set", _hardware_overrides(emu, video, None)],
                             stdout=subprocess.PIPE,
                             stderr=subprocess.PIPE, text=True, env={**os.environ, "PYTHONWARNINGS": "ignore"})
        try:
            deadline = time.monotonic() + 120
            while not all(emu.torque_enabled(i) for i in ids):
                assert p.poll() is None and time.monotonic() < deadline, p.communicate()
                time.sleep(0.05)
            if when == "grasping":  # the ramp to the grasp takes about 1.6 s
                time.sleep(0.5)
                assert 2048 < emu.goal_position(1) < 2048 + 3000, "not in the middle of the grasp"
            else:  # the grasp made (the thumb's goal still for 0.4 s: 8 updates), then the run
                last, still = emu.goal_position(1), time.monotonic()
                while time.monotonic() - still < 0.4:
                    assert p.poll() is None and time.monotonic() < deadline, p.communicate()
                    time.sleep(0.02)
                    if emu.goal_position(1) != last:
                        last, still = emu.goal_position(1), time.monotonic()
                time.sleep(1.0)  # running: actions and frames
            p.send_signal(getattr(signal, sig))
            _, err = p.communicate(timeout=60)
        finally:
            p.kill()
        assert not any(emu.torque_enabled(i) for i in ids)
        assert p.returncode == 128 + int(getattr(signal, sig)), err
        assert err.strip().splitlines()[-1] == (
            f"python -m vlr_drake.builder: stopped by {sig} (closed on the way out: a real hand's torque is off)")


def test_a_hardware_scenario_with_a_control_section_wires_the_controller_through_the_switch():
    """The same control section on hardware: the motors get the switch's command (the
    exploration's, then the controller's), the controller starts from what was sent, and
    'commanded' still reads what the motors were sent (building opens no motor or camera)."""
    b = build_diagram(load_scenario(DIAGRAMS_DIR / "hardware.yaml", "filter_action: commanded\n"
                                    "control: {after_iterations: 5, goals_mm: [[0.3, 0.0, 0.0]]}"))
    try:
        d = b.diagram
        switch, controller = d.GetSubsystemByName("command_switch"), d.GetSubsystemByName("controller")
        assert d.AreConnected(switch.get_output_port(), b.plant.get_tendon_command_input_port())
        # the controller steps from what the motors were sent (clipped at their limits, ramped)
        assert d.AreConnected(b.plant.GetOutputPort("tendon_command_sent"),
                              controller.tendon_command_applied_input_port())
        assert d.AreConnected(d.GetSubsystemByName("trajectory").ready_output_port(), controller.enabled_input_port())
        assert d.AreConnected(b.policy.GetOutputPort("tendon_command"), switch.GetInputPort("exploration"))
        assert d.AreConnected(controller.tendon_command_output_port(), switch.GetInputPort("control"))
        assert d.AreConnected(b.plant.GetOutputPort("tendon_command_sent"), b.filter.tendon_command_input_port())
        assert d.HasOutputPort("controller.has_model") and d.HasOutputPort("trajectory.done")
    finally:
        b.plant.close()
