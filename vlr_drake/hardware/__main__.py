"""Bring-up tool for the real hand: check the motors and the camera, measure zero offsets.

    python -m vlr_drake.hardware status --config hw.yaml   # ping, read, torque stays off
    python -m vlr_drake.hardware zero   --config hw.yaml   # zero_offset_ticks to paste
    python -m vlr_drake.hardware camera --config hw.yaml --frames 30
    python -m vlr_drake.hardware reboot --config hw.yaml   # clear a motor's hardware error

``--config`` is a hardware section (:class:`vlr_drake.hardware.config.HardwareConfig`) or a
scenario file with one (``diagrams/hardware.yaml``);
``--set 'port: /dev/ttyUSB1'`` overrides fields as YAML text. Relative paths in the file
(``calibration_file``, ``motor_record``) are relative to its folder. No command enables torque.
``zero``: straighten every finger by hand with its tendon just taut, then run it; it prints
the present positions as ``zero_offset_ticks`` (measure again after a motor power cycle, which
resets the multi-turn count; a run refuses a motor that lost turns, against the positions
the last run recorded, ``HardwareConfig.motor_record``, and ``status`` says so; ``zero``
starts the record again). ``reboot``: a motor that stopped on a hardware error
(overload, overheating) keeps it, and its torque off, until it is rebooted; find the cause
first, then reboot, then ``zero`` again (a reboot may reset the multi-turn count as well).
"""

import argparse
import sys
import time
from collections.abc import Sequence

import numpy as np

from vlr_drake.entry import count
from vlr_drake.hardware.config import load_hardware_config

__all__ = ["main"]

#: The camera check's pause between reads in latest mode [s]: the hardware interface's update
#: period, so that a camera delivering frames gives a new one at most reads.
LATEST_READ_PERIOD_S = 0.05


def _motors(config):
    from vlr_drake.hardware.dynamixel import EXTENDED_POSITION_LIMIT, TendonMotors

    unlimited = (
        np.full(config.num_motors, -EXTENDED_POSITION_LIMIT),
        np.full(config.num_motors, EXTENDED_POSITION_LIMIT),
    )
    return TendonMotors.from_config(config, unlimited)


def main(argv: Sequence[str] | None = None, out=None) -> int:
    """Command line entry (see the module docstring). Returns the exit status."""
    out = out or sys.stdout
    p = argparse.ArgumentParser(prog="python -m vlr_drake.hardware", description=__doc__.split("\n")[0])
    p.add_argument("command", choices=["status", "zero", "camera", "reboot"])
    p.add_argument("--config", help="hardware section YAML file, or a scenario file with a hardware section")
    p.add_argument("--set", action="append", default=None,
                   help="YAML text overriding config fields; repeatable, applied in order")
    p.add_argument("--frames", type=count(1), default=30, help="camera: frames to read")
    p.add_argument("--hand", default="model_o",
                   help="status: the hand whose tendon_range gives the limits where the config gives none "
                        "(default model_o)")
    a = p.parse_args(argv)
    # a hardware section's relative paths (calibration_file, motor_record) as a scenario's: relative
    # to its file (they had been taken relative to the working folder)
    config = load_hardware_config(filename=a.config, data=a.set, resolve=True).validate()

    if a.command == "reboot":
        from vlr_drake.hardware.dynamixel import hardware_error_text

        had = _motors(config).reboot()
        for i, status in zip(config.motor_ids, had, strict=True):
            cause = f"had {hardware_error_text(status)}" if status else "had no hardware error"
            print(f"  motor {i}: {cause}; rebooted, torque off", file=out)
        print("measure zero_offset_ticks again (python -m vlr_drake.hardware zero): a reboot may reset the "
              "multi-turn count", file=out)
        return 0

    if a.command in ("status", "zero"):
        from vlr_drake.hardware.config import TendonMotorMap

        motors = _motors(config)
        try:
            ticks = motors.open(enable_torque=False)
            _, current = motors.read()
            if a.command == "zero":  # the record starts again from the positions zeroed at
                motors.accept_positions()
        finally:
            motors.close()
        if a.command == "zero":
            print(f"zero_offset_ticks: {ticks.tolist()}", file=out)
            if motors.record_path is not None:
                print(f"(the motors' record {motors.record_path} starts from these positions)", file=out)
            return 0
        from vlr_drake.hand import hand_by_name

        # the limits a run takes: the config's, else the hand's tendon_range (status had checked
        # only a config's own, and said nothing of a motor the run then refused; a review)
        lower, upper = config.tendon_limits(hand_by_name(a.hand))
        tendon_map = TendonMotorMap(config, lower, upper)
        tendon = tendon_map.to_tendon(ticks)
        slack = config.start_tolerance_ticks / tendon_map.ticks_per_m  # [m] a run's start allows this far out
        print(f"port {config.port} at {config.baud_rate} baud: motors {config.motor_ids} answer", file=out)
        for k, (i, t, l, c) in enumerate(zip(config.motor_ids, ticks, tendon, current, strict=True)):
            line = f"  motor {i}: {int(t)} ticks, tendon {l * 1000:.2f} mm, current {c * config.current_unit_a:.3f} A"
            out_by = max(lower[k] - l, l - upper[k])
            if out_by > 0:
                line += (f"  (outside the tendon limits [{1e3 * lower[k]:.1f}, {1e3 * upper[k]:.1f}] mm"
                         + ("; a run refuses to start: zero again?" if out_by > slack else "") + ")")
            print(line, file=out)
        for finding in motors.record_findings:  # a lost turn: a run refuses to start
            print(f"  {finding}", file=out)
        return 0

    from vlr_drake.hardware.camera import FrameSource, read_intrinsics

    size = None
    try:
        intr = read_intrinsics(config.calibration_file)
        size = (intr.width, intr.height)
        print(
            f"calibration {config.calibration_file}: {intr.width} x {intr.height}, fx {intr.K[0, 0]:.1f}",
            file=out,
        )
    except (FileNotFoundError, RuntimeError) as e:
        print(f"calibration: {e}", file=out)
    # the size a run asks the device for (a device left at another size had been reported as a
    # mismatch here, while a run got the calibrated one)
    # (a frame of another size than the calibration's is the read's CameraError, named)
    with FrameSource(config.camera, config.camera_timeout_s, expected_size=size, mode=config.camera_mode,
                     max_age_s=config.camera_max_frame_age_s) as cam:
        shapes = set()
        for _ in range(a.frames):
            ok, frame = cam.read()
            if ok:
                shapes.add((frame.shape[1], frame.shape[0]))
            if cam.mode == "latest":  # paced as a run reads it: a frame still fresh comes again, counted
                time.sleep(LATEST_READ_PERIOD_S)
    new = cam.frames - cam.repeats
    print(f"camera {config.camera!r}: {cam.frames} of {a.frames} frames ({new} new; latest mode gives a frame "
          f"still fresh again), sizes {sorted(shapes)}" if cam.mode == "latest" else
          f"camera {config.camera!r}: {cam.frames} of {a.frames} frames, sizes {sorted(shapes)}", file=out)
    # a camera that gave one frame and stalled had passed on that frame given again (a review)
    return 0 if new > (1 if a.frames > 1 else 0) else 1


if __name__ == "__main__":
    from vlr_drake.entry import run

    raise SystemExit(run("python -m vlr_drake.hardware", main, hardware=True))
