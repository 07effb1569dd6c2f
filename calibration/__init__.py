"""Camera models, Sim(3), the capture format, rig calibration and the calibration keeper."""

from calibration.camera import Camera
from calibration.sim3 import Sim3

__all__ = ["Camera", "Sim3"]
