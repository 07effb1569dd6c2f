"""The engine's edge: a metric rig fixes the registration's scale about the object's centre."""

from __future__ import annotations

import numpy as np

from calibration.sim3 import Sim3
from calibration.so3 import axis_angle_to_matrix
from reconstruction.pipeline import metric_sim3


def test_metric_rig_fixes_the_scale_and_keeps_the_object_in_place():
    reg = Sim3(1.06, axis_angle_to_matrix(np.array([0.2, -0.1, 0.4])), np.array([0.01, 0.2, -0.3]))
    centre = np.array([0.02, -0.01, 0.03])
    snapped = metric_sim3(reg, 1e-3, centre)  # a rig calibrated in millimetres, CAD in metres
    assert snapped.scale == 1e-3
    np.testing.assert_allclose(snapped.rotation, reg.rotation)
    # The object's centre sits where the registration put it in the rig.
    np.testing.assert_allclose(snapped.inverse().apply(centre[None]), reg.inverse().apply(centre[None]), atol=1e-12)
