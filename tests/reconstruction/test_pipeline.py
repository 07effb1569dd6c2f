"""The engine's edge: a metric rig fixes the registration's scale about the object's centre."""

from __future__ import annotations

import numpy as np

from calibration.sim3 import Sim3
from calibration.so3 import axis_angle_to_matrix
from reconstruction.pipeline import metres_per_rig_unit, metric_sim3


def test_metric_rig_fixes_the_scale_and_keeps_the_object_in_place():
    reg = Sim3(1.06, axis_angle_to_matrix(np.array([0.2, -0.1, 0.4])), np.array([0.01, 0.2, -0.3]))
    centre = np.array([0.02, -0.01, 0.03])
    snapped = metric_sim3(reg, 1e-3, centre)  # a rig calibrated in millimetres, CAD in metres
    assert snapped.scale == 1e-3
    np.testing.assert_allclose(snapped.rotation, reg.rotation)
    # The object's centre sits where the registration put it in the rig.
    np.testing.assert_allclose(snapped.inverse().apply(centre[None]), reg.inverse().apply(centre[None]), atol=1e-12)


def test_only_a_capture_that_states_units_is_metric():
    assert metres_per_rig_unit({"units": "mm"}) == 1e-3
    assert metres_per_rig_unit({"units": "m"}) == 1.0
    assert metres_per_rig_unit({}) is None
    assert metres_per_rig_unit({"units": "furlong"}) is None
