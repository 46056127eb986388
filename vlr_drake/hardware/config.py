"""The hardware section of a scenario: tendon motors (Dynamixel) and the palm camera.

A :class:`HardwareConfig` is a plain dataclass, loadable with Drake's YAML loader
(``pydrake.common.yaml.yaml_load_typed``), with a comment on every field. It holds what the
hardware interface (DESIGN.md section 8) needs to swap the simulated hand plant and rendered
camera for the real Yale Model O: the serial bus, one Dynamixel X-series servo per tendon
(protocol 2.0), the spool that turns motor angle into tendon pull, and the camera source and
its calibration file.

Tendon pull ``l_i`` [m] (0 = taut at a straight finger, DESIGN.md section 2) and motor ticks
are related through the spool radius ``r`` and a per-motor zero offset and direction sign:

    ticks_i = zero_offset_ticks_i + direction_i * round(l_i / r * ticks_per_rev / (2 pi))

Tendon limits default to the hand's ``tendon_range`` (:class:`vlr_drake.hand.HandSpec`), so
the hand's numbers stay in one place; a hardware build may narrow them here.
"""

# No ``from __future__ import annotations``: Drake's yaml_load_typed reads the dataclass
# field types at run time.
import math
import os
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from vlr_drake import units
from vlr_drake.hardware.dynamixel import EXTENDED_POSITION_LIMIT, GOAL_CURRENT_MAX

__all__ = ["HardwareConfig", "TendonMotorMap", "load_hardware_config"]

#: Baud rates accepted by the Dynamixel SDK's PortHandler.
SUPPORTED_BAUD_RATES = (
    9600, 19200, 38400, 57600, 115200, 230400, 460800, 500000, 576000, 921600,
    1000000, 1152000, 2000000, 2500000, 3000000, 3500000, 4000000,
)  # fmt: skip
#: X-series operating modes that allow a tendon to wind more than one turn.
MULTI_TURN_MODES = (4, 5)  # 4: extended position, 5: current-based position
#: The largest tendon step one update of the hardware interface may send [m]: the motors
#: take each step at their full speed (their profile velocity is left at 0), so
#: ``max_tendon_speed * period_s`` is a speed limit only while each step is small.
MAX_UPDATE_STEP = 1.0e-3
#: The farthest a motor may start outside its tendon limits [m] (``start_tolerance_ticks``
#: in tendon pull): the first goal clamps it into the limits in one jump at full speed.
MAX_START_OFFSET = 5.0e-3


def default_record_path(port: str) -> Path:
    """Where the motors of bus ``port`` keep their last positions between runs
    (``motor_record: auto``): ``$XDG_STATE_HOME/vlr_drake/motors_<port>.json``, with
    ``~/.local/state`` for ``$XDG_STATE_HOME`` where it is not set."""
    base = os.environ.get("XDG_STATE_HOME") or os.path.join(os.path.expanduser("~"), ".local", "state")
    name = re.sub(r"[^A-Za-z0-9._-]+", "_", str(port)).strip("_") or "port"
    return Path(base) / "vlr_drake" / f"motors_{name}.json"


@dataclass
class HardwareConfig:
    """Tendon motors and camera of a real hand (one scenario's ``hardware`` section)."""

    # Serial device of the Dynamixel bus (e.g. /dev/ttyUSB0 for a U2D2).
    port: str = "/dev/ttyUSB0"
    # Bus baud rate [bit/s]; one of the rates the Dynamixel SDK supports.
    baud_rate: int = 1000000
    # Dynamixel protocol version; only 2.0 (X-series) is supported.
    protocol_version: float = 2.0
    # Dynamixel ids of the tendon motors, one per finger in the hand's finger order.
    motor_ids: list[int] = field(default_factory=lambda: [1, 2, 3])
    # Spool (pulley) radius on each motor horn: tendon pull = radius * motor angle [m].
    spool_radius: float = 0.005
    # Motor position [ticks] at which each tendon is taut with the finger straight (l = 0).
    # The filter reads the absolute pull (FilterConfig.tendon_reference "commanded"): a wrong
    # zero is a wrong tendon stretch for every hypothesis (on the physics plant the model's
    # own offset of ~1.3 mm of thumb pull was tolerated). Where it is not known to about a
    # millimetre of pull, run the filter with tendon_reference "implied" (the paper's).
    zero_offset_ticks: list[int] = field(default_factory=lambda: [0, 0, 0])
    # Winding direction of each motor: +1 if increasing ticks pull the tendon, else -1.
    direction: list[int] = field(default_factory=lambda: [1, 1, 1])
    # Encoder ticks per motor revolution (X-series: 4096).
    ticks_per_rev: int = 4096
    # Lower tendon limits per motor [m]; empty: take them from the hand's tendon_range.
    tendon_lower: list[float] = field(default_factory=list)
    # Upper tendon limits per motor [m]; empty: take them from the hand's tendon_range.
    tendon_upper: list[float] = field(default_factory=list)
    # Operating mode written to address 11: 4 extended position, 5 current-based position.
    operating_mode: int = 5
    # Goal current (address 102) in current-based position mode [raw units]: what limits the
    # tendon's pull, and so the grip. Required (1..2047) in mode 5: the motor's own value is
    # its current limit after a power cycle, close to the stall current (XM430-W350: 1193,
    # 3.2 A). 300 (0.8 A on an XM430) as diagrams/hardware.yaml. Mode 4 has no current limit
    # at all (the ROBOTIS e-manual's Current Limit applies to the current modes only).
    goal_current_raw: int = 300
    # Size of one raw current unit [A] (XM430: 2.69 mA), for the motor_current output.
    current_unit_a: float = 0.00269
    # Camera: an int device index, or a str file path or stream URL (OpenCV VideoCapture).
    camera: int | str = 0
    # Intrinsics file (camera_matrix, distortion_coefficients, image size): OpenCV YAML, as
    # python -m vlr_drake.hardware.calibrate writes it, or a ROS camera_calibration YAML;
    # relative paths are resolved against the scenario file's folder by the caller.
    calibration_file: str = "camera_intrinsics.yaml"
    # Longest wait for one camera frame before the frame is reported invalid [s].
    camera_timeout_s: float = 1.0
    # "latest" mode: the oldest a frame may be and still count [s]. A camera that stalled for
    # longer gives camera_valid 0, not a frame from before the hand's last action (the filter
    # measures 0.9 of an action period after it). A 30 fps camera's frames are 33 ms apart.
    camera_max_frame_age_s: float = 0.2
    # "sequential" (every frame in order: video files), "latest" (newest frame from a
    # grabber thread: devices and streams) or "auto" (sequential for an existing file).
    camera_mode: str = "auto"
    # Status-packet timeout slack added by the bus adapter (USB latency timer) [ms]; the
    # SDK waits 2 * this + 2 ms plus the transfer time for each reply.
    latency_timer_ms: float = 16.0
    # Retries of a failed bus transaction (timeout or corrupt reply) before giving up.
    comm_retries: int = 2
    # A motor found farther than this outside its tendon limits at start [ticks] stops the
    # start (a wrong zero offset); within it, the first goal is clamped into the limits. It
    # cannot catch a lost turn: a power cycle or a reboot resets a motor's multi-turn count,
    # and the Model O's 45 mm of tendon is only 1.43 turns of its spool, so a motor that lost
    # a turn usually still reads inside its limits (a review: tendons then driven 17 mm past
    # their travel): motor_record catches that. After either, measure zero_offset_ticks again
    # (python -m vlr_drake.hardware zero) before a run.
    start_tolerance_ticks: int = 256
    # A JSON file where the end of each run records the motors' positions; the next start
    # compares them and refuses a motor a whole number of turns (within start_tolerance_ticks)
    # from where it was left: its multi-turn count was reset, and the zero offset is wrong by
    # those turns. "auto": $XDG_STATE_HOME/vlr_drake/motors_<port>.json (~/.local/state
    # without it); "": no record. A relative path is resolved against the scenario file's
    # folder. python -m vlr_drake.hardware zero records the positions it zeroes at.
    motor_record: str = "auto"
    # Period of the hardware interface's update: send commands, read motors and camera [s].
    period_s: float = 0.05
    # Fastest the interface moves a tendon's goal [m/s]: a command further from the last one
    # sent is approached at this speed, one update at a time. The first command (the grasp)
    # is otherwise a jump from where the motors start, at the motors' full speed (their
    # profile velocity is left at 0, no limit). 20 mm/s takes a tendon through the Model O's
    # grasp (about 31 mm of pull) in 1.6 s and through an exploration action (0.5 mm) within
    # one update. The filter reads the pull the motors reached (tendon_position_measured).
    max_tendon_speed: float = 0.02
    # Closing on the grasp before the run's clock starts (HardwareInterface's grasp_command,
    # which the scenario builder sets to the grasp section's commands): the tendons are
    # ramped there at max_tendon_speed, then the motors get up to grasp_timeout_s [s] to come
    # within grasp_tolerance [m] of them (else a warning names how far they are: an object
    # that stops the fingers short under the goal current, or a motor that cannot).
    grasp_tolerance: float = 0.5e-3
    grasp_timeout_s: float = 10.0

    @property
    def num_motors(self) -> int:
        return len(self.motor_ids)

    def validate(self, num_fingers: int | None = None) -> "HardwareConfig":
        """Check the config and raise ``ValueError`` naming the offending field.

        ``num_fingers`` (optional) is the hand's finger count that ``motor_ids`` must match.
        """
        where = "hardware config"
        if not self.port:
            raise ValueError(f"{where}: 'port' is empty")
        if self.baud_rate not in SUPPORTED_BAUD_RATES:
            raise ValueError(f"{where}: 'baud_rate' {self.baud_rate} is not one of {SUPPORTED_BAUD_RATES}")
        if self.protocol_version != 2.0:
            raise ValueError(f"{where}: 'protocol_version' must be 2.0, got {self.protocol_version}")
        n = len(self.motor_ids)
        if n == 0:
            raise ValueError(f"{where}: 'motor_ids' is empty")
        if len(set(self.motor_ids)) != n:
            raise ValueError(f"{where}: 'motor_ids' has duplicates: {self.motor_ids}")
        if any(not 0 <= int(i) <= 252 for i in self.motor_ids):
            raise ValueError(f"{where}: 'motor_ids' must be in 0..252, got {self.motor_ids}")
        if num_fingers is not None and n != num_fingers:
            raise ValueError(f"{where}: 'motor_ids' has {n} motors but the hand has {num_fingers} fingers")
        if not (math.isfinite(self.spool_radius) and self.spool_radius > 0):
            raise ValueError(f"{where}: 'spool_radius' must be positive, got {self.spool_radius}")
        units.check_length(self.spool_radius, f"{where}: 'spool_radius'")
        if len(self.zero_offset_ticks) != n:
            raise ValueError(
                f"{where}: 'zero_offset_ticks' must have {n} entries (one per motor), got {len(self.zero_offset_ticks)}"
            )
        if len(self.direction) != n or any(d not in (1, -1) for d in self.direction):
            raise ValueError(f"{where}: 'direction' must have {n} entries of +1 or -1, got {self.direction}")
        if self.ticks_per_rev <= 0:
            raise ValueError(f"{where}: 'ticks_per_rev' must be positive, got {self.ticks_per_rev}")
        for name in ("tendon_lower", "tendon_upper"):
            v = getattr(self, name)
            if len(v) not in (0, n):
                raise ValueError(f"{where}: '{name}' must be empty or have {n} entries, got {len(v)}")
            if not np.all(np.isfinite(v)):
                raise ValueError(f"{where}: '{name}' is not finite: {v}")
            units.check_length(v, f"{where}: '{name}'")
        if (len(self.tendon_lower) == 0) != (len(self.tendon_upper) == 0):
            raise ValueError(f"{where}: give both 'tendon_lower' and 'tendon_upper', or neither")
        if self.tendon_lower and not np.all(np.asarray(self.tendon_lower) < np.asarray(self.tendon_upper)):
            raise ValueError(f"{where}: 'tendon_lower' must be below 'tendon_upper'")
        if self.operating_mode not in MULTI_TURN_MODES:
            raise ValueError(
                f"{where}: 'operating_mode' must be 4 (extended position) or 5 (current-based position), got {self.operating_mode}"
            )
        least = 1 if self.operating_mode == 5 else 0
        if not least <= self.goal_current_raw <= GOAL_CURRENT_MAX:
            raise ValueError(f"{where}: 'goal_current_raw' must be in {least}..{GOAL_CURRENT_MAX}"
                             + (" in current-based position mode (5): it limits the tendon's pull" if least else "")
                             + f", got {self.goal_current_raw}")
        if not isinstance(self.camera, int | str) or (isinstance(self.camera, str) and not self.camera):
            raise ValueError(
                f"{where}: 'camera' must be an int device index or a non-empty path/URL, got {self.camera!r}"
            )
        if self.camera_mode not in ("auto", "sequential", "latest"):
            raise ValueError(
                f"{where}: 'camera_mode' must be auto, sequential or latest, got {self.camera_mode!r}"
            )
        if self.camera_mode == "sequential" and not (isinstance(self.camera, str) and Path(self.camera).is_file()):
            # a live camera read in order hands over frames that waited in its buffer, and one
            # that timed out as the next read's fresh frame (a review: 0.8 s old, reported valid)
            raise ValueError(f"{where}: 'camera_mode' sequential is for a video file; camera {self.camera!r} is a "
                             "device or a stream: use latest (or auto)")
        for name in ("camera_timeout_s", "camera_max_frame_age_s", "latency_timer_ms", "period_s", "current_unit_a", "max_tendon_speed",
                     "grasp_tolerance", "grasp_timeout_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v > 0):
                raise ValueError(f"{where}: '{name}' must be positive, got {v}")
        # metres: 0.5 meant as mm had been taken as half a metre, any grasp "within" it
        units.check_length(self.grasp_tolerance, f"{where}: 'grasp_tolerance'", 0.01,
                           "a grasp missed by centimetres is no grasp")
        step = self.max_tendon_speed * self.period_s
        if step > MAX_UPDATE_STEP * (1 + 1e-9):
            raise ValueError(
                f"{where}: 'max_tendon_speed' * 'period_s' = {1e3 * step:.3g} mm per update is more than "
                f"{1e3 * MAX_UPDATE_STEP:g} mm: each update's step is taken at the motors' full speed, so lower "
                "'period_s' or 'max_tendon_speed'"
            )
        if self.start_tolerance_ticks < 0:
            raise ValueError(
                f"{where}: 'start_tolerance_ticks' must be >= 0, got {self.start_tolerance_ticks}"
            )
        ticks_per_m = self.ticks_per_rev / (2.0 * math.pi * self.spool_radius)
        if self.start_tolerance_ticks > MAX_START_OFFSET * ticks_per_m:
            raise ValueError(
                f"{where}: 'start_tolerance_ticks' {self.start_tolerance_ticks} is "
                f"{1e3 * self.start_tolerance_ticks / ticks_per_m:.3g} mm of tendon, more than "
                f"{1e3 * MAX_START_OFFSET:g} mm: a motor that far outside its limits would be clamped into them in "
                "one jump at full speed when torque comes on"
            )
        if any(abs(int(z)) > EXTENDED_POSITION_LIMIT for z in self.zero_offset_ticks):
            raise ValueError(
                f"{where}: 'zero_offset_ticks' must be within +-{EXTENDED_POSITION_LIMIT:,} (the motors' "
                f"multi-turn range), got {self.zero_offset_ticks}"
            )
        if self.comm_retries < 0:
            raise ValueError(f"{where}: 'comm_retries' must be >= 0, got {self.comm_retries}")
        return self

    def resolve_paths(self, folder) -> None:
        """Take the relative file paths (``calibration_file``, ``motor_record``) as relative to
        ``folder`` (a scenario file's)."""
        for name in ("calibration_file", "motor_record"):
            v = getattr(self, name)
            if v and not (name == "motor_record" and v == "auto") and not Path(v).is_absolute():
                setattr(self, name, str(Path(folder) / v))

    def motor_record_path(self) -> Path | None:
        """The file of ``motor_record`` (None: no record)."""
        if not self.motor_record:
            return None
        return default_record_path(self.port) if self.motor_record == "auto" else Path(self.motor_record)

    def tendon_limits(self, hand=None) -> tuple[np.ndarray, np.ndarray]:
        """Lower and upper tendon limits (N,) [m]: this config's, else the hand's tendon_range.

        ``hand`` is a :class:`vlr_drake.hand.HandSpec`, needed when the config gives none. A
        config may narrow the hand's range, not widen it: given the hand, limits outside its
        ``tendon_range`` are refused (they would let the motors pull past the tendon's travel).
        """
        if self.tendon_lower:
            lower, upper = np.asarray(self.tendon_lower, float), np.asarray(self.tendon_upper, float)
        elif hand is None:
            raise ValueError(
                "hardware config: no 'tendon_lower'/'tendon_upper' given and no hand to take tendon_range from"
            )
        if hand is None:
            return lower, upper
        rng = np.array([f.tendon_range for f in hand.fingers], float)
        if len(rng) != self.num_motors:
            raise ValueError(
                f"hardware config: 'motor_ids' has {self.num_motors} motors but the hand has {len(rng)} fingers"
            )
        if not self.tendon_lower:
            return rng[:, 0].copy(), rng[:, 1].copy()
        for k, finger in enumerate(hand.fingers):
            if not rng[k, 0] <= lower[k] < upper[k] <= rng[k, 1]:
                raise ValueError(
                    f"hardware config: motor {k} ({finger.name}) limits [{lower[k]}, {upper[k]}] m reach outside the "
                    f"hand's tendon_range [{rng[k, 0]}, {rng[k, 1]}] m ('tendon_lower'/'tendon_upper' may only narrow it)"
                )
        return lower, upper


class TendonMotorMap:
    """Tendon pull [m] <-> motor ticks through spool radius, zero offset and direction.

    ticks = zero_offset + direction * round(l / r * ticks_per_rev / (2 pi)); the inverse is
    exact up to one tick (2 pi r / ticks_per_rev of tendon: 7.7 um for r = 5 mm).
    """

    def __init__(self, config: HardwareConfig, lower: np.ndarray, upper: np.ndarray):
        self.zero = np.asarray(config.zero_offset_ticks, np.int64)
        self.sign = np.asarray(config.direction, np.int64)
        self.ticks_per_m = config.ticks_per_rev / (2.0 * math.pi * config.spool_radius)
        self.lower = np.asarray(lower, float)
        self.upper = np.asarray(upper, float)
        n = len(self.zero)
        if self.lower.shape != (n,) or self.upper.shape != (n,):
            raise ValueError(
                f"tendon limits must have shape ({n},), got {self.lower.shape} and {self.upper.shape}"
            )

    def to_ticks(self, l: np.ndarray) -> np.ndarray:
        """Goal ticks (N,) int64 for tendon pulls ``l`` (N,) [m] (no clipping here)."""
        l = np.asarray(l, float)
        if l.shape != self.zero.shape:
            raise ValueError(f"tendon command must have shape {self.zero.shape}, got {l.shape}")
        return self.zero + self.sign * np.round(l * self.ticks_per_m).astype(np.int64)

    def to_tendon(self, ticks: np.ndarray) -> np.ndarray:
        """Tendon pulls (N,) [m] for motor positions ``ticks`` (N,)."""
        ticks = np.asarray(ticks, np.int64)
        return (self.sign * (ticks - self.zero)).astype(float) / self.ticks_per_m

    def clip(self, l: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Tendon command clipped to the limits, and a bool mask of entries that were clipped.
        A non-finite command is an error (never sent)."""
        l = np.asarray(l, float)
        if l.shape != self.lower.shape:
            raise ValueError(f"tendon command must have shape {self.lower.shape}, got {l.shape}")
        if not np.all(np.isfinite(l)):
            raise ValueError(f"tendon command is not finite: {l}")
        c = np.clip(l, self.lower, self.upper)
        return c, c != l

    def tick_limits(self) -> tuple[np.ndarray, np.ndarray]:
        """Lowest and highest allowed goal ticks per motor (the driver's last check)."""
        a, b = self.to_ticks(self.lower), self.to_ticks(self.upper)
        return np.minimum(a, b), np.maximum(a, b)


def load_hardware_config(filename: str | None = None, data: str | list[str] | None = None, *,
                         resolve: bool = False) -> HardwareConfig:
    """Load a :class:`HardwareConfig` from a YAML file and/or text (text overrides the file;
    a list of texts, each in order).
    The file is a hardware section, or a scenario file (:class:`vlr_drake.scenario.Scenario`,
    e.g. ``diagrams/hardware.yaml``) whose ``hardware`` section is taken; a scenario file's
    relative paths are taken as relative to its folder, and with ``resolve`` a hardware
    section file's too (the text's stay as given). A missing file
    raises ``FileNotFoundError``; an unknown or mistyped field ``ValueError`` naming the
    file or the text."""
    import yaml
    from pydrake.common.yaml import yaml_load_typed

    errors = (RuntimeError, ValueError, TypeError, yaml.YAMLError)  # what the loader raises on bad input
    config = HardwareConfig()
    if filename is not None:
        if not Path(filename).is_file():
            raise FileNotFoundError(f"hardware config file '{filename}' not found (or not a file)")
        try:
            with open(filename) as f:
                doc = yaml.safe_load(f)
            scenario = isinstance(doc, dict) and "plant" in doc  # a scenario names its plant
            if scenario and "hardware" not in doc:
                raise ValueError("a scenario file without a 'hardware' section")
            config = yaml_load_typed(schema=HardwareConfig, filename=filename,
                                     child_name="hardware" if scenario else None, defaults=config)
            if scenario or resolve:  # relative to the scenario file, as the scenario loader has it
                config.resolve_paths(Path(filename).resolve().parent)
        except errors as e:
            raise ValueError(f"hardware config file '{filename}': {e}") from e
    for text in [data] if isinstance(data, str) else data or []:  # (a second --set had replaced the first)
        try:
            config = yaml_load_typed(schema=HardwareConfig, data=text, defaults=config)
        except errors as e:
            raise ValueError(f"hardware config text: {e}") from e
    return config
