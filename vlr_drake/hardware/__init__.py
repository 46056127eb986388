"""Hardware interface pieces: scenario config, Dynamixel tendon motors, camera source, calibration.

Only ``config`` is imported eagerly; the driver and the camera import their libraries
(``dynamixel_sdk``, ``cv2``) when used.
"""

from vlr_drake.hardware.config import HardwareConfig, TendonMotorMap, load_hardware_config

__all__ = ["HardwareConfig", "TendonMotorMap", "load_hardware_config"]
