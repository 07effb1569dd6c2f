"""Lengths: the unit names a capture, a rig or a mesh file may state, and their size in metres.

Calibration owns the table because it is the lowest package: captures (calibration), the CAD
library and mesh files (reconstruction) and simulation all read it from here.
"""

UNIT_TO_M = {"m": 1.0, "mm": 1e-3, "cm": 1e-2, "in": 0.0254}
