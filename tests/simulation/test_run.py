"""Drop every shared object and CAD part onto the floor for 2 s: it must end at rest, supported,
without NaN or more than 1 mm of penetration."""

from __future__ import annotations

import numpy as np
import pytest

from simulation.asset import choose_density, load_mesh_asset
from simulation.collision import collision_geometry, surface_points
from simulation.mjcf import BodySpec, write_mjcf_package
from simulation.run import Trajectory, load_model, rest_report, simulate, support_distance
from simulation.scene import euler_xyz_to_quat, resting_position
from tests.conftest import require_shared

YCB = [
    "011_banana",
    "033_spatula",
    "037_scissors",
    "043_phillips_screwdriver",
    "050_medium_clamp",
    "061_foam_brick",
    "072-c_toy_airplane",
    "077_rubiks_cube",
]
# Declared units of the CAD parts (the files do not say; chosen from their makers' sizes).
PARTS = {
    "1002_tray_bottom.STL": "mm",
    "ADIS16480.STL": "m",
    "angle_block.STL": "in",
    "counter.unitsmm.STL": None,
    "featuretype.STL": "in",
    "idler_riser.STL": "in",
    "large_block.STL": "mm",
    "octagonal_pocket.stl": "m",
    "plate_holes.STL": "mm",
    "round.stl": "mm",
    "torus.STL": "in",
    "busted.STL": "mm",
}


def drop(asset, collision, tmp_path, tilt=(20.0, 10.0, 0.0), height=0.05, duration=2.0):
    quat = euler_xyz_to_quat(tilt)
    pos = resting_position(asset.vertices, quat, (0.0, 0.0, 0.0), height)
    xml = write_mjcf_package(tmp_path / asset.name, [BodySpec(asset, collision, pos, quat)])
    model = load_model(xml)
    return model, simulate(model, duration, fps=50)


def check_rest(asset, collision, traj: Trajectory) -> None:
    rep = rest_report(traj, 0, asset.vertices, asset.mass.center_of_mass, surface_points(collision))
    assert rep.kinetic_ratio < 1e-4, rep
    assert rep.final_kinetic < 1e-3 * asset.mass.mass * 9.81 * 1e-3, rep  # below a 1 mm-drop's worth of energy / 1000
    assert rep.final_penetration <= 1e-4, rep  # at rest: micrometres (acceptance: <= 1 mm)
    assert rep.peak_penetration <= 1e-2, rep  # the impact itself, soft contacts at 1 m/s
    assert rep.support_margin <= 1e-3, rep
    # Enclosing collision shapes hold the mesh at or above the floor; its lowest point is no higher
    # than the shape's excess size allows.
    excess = (np.cbrt(1 + max(collision.volume_error, 0)) - 1) * float(np.ptp(asset.vertices, 0).max())
    assert -1e-3 <= rep.lowest_height <= excess + 1e-3, (rep, excess)


@pytest.mark.parametrize("name", YCB)
def test_ycb_object_drops_to_rest(name, tmp_path):
    path = require_shared("objects", "ycb", name, "textured.obj")
    asset = load_mesh_asset(path, "m", name.replace("-", "_"))
    col = collision_geometry(asset.vertices, asset.faces, asset.mass.volume, decomposition=None, measure_hausdorff=False)
    _, traj = drop(asset, col, tmp_path)
    check_rest(asset, col, traj)


@pytest.mark.parametrize("name", sorted(PARTS))
def test_cad_part_drops_to_rest(name, tmp_path):
    path = require_shared("cad", "parts", name)
    asset = load_mesh_asset(path, PARTS[name], name.split(".")[0], density=choose_density(material="aluminium"))
    col = collision_geometry(asset.vertices, asset.faces, asset.mass.volume, decomposition=None, measure_hausdorff=False)
    _, traj = drop(asset, col, tmp_path)
    check_rest(asset, col, traj)


def test_support_distance_inside_outside_and_degenerate():
    square = np.array([[0, 0], [1, 0], [1, 1], [0, 1.0]])
    assert support_distance([0.5, 0.5], square) == 0.0
    assert support_distance([2.0, 0.5], square) == pytest.approx(1.0)
    assert support_distance([0.5, 0.3], np.array([[0, 0], [1, 0.0]])) == pytest.approx(0.3)
