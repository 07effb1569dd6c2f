"""The twin-physics benchmark's ground truth: the true solid of a closed or open mesh (`true_solid`,
the acceptance's 1 mm voxel fill for open ones) and the true mesh taken into a twin's frame through
the cameras (`true_to_twin`)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from benchmarks.bench_twin_physics import pushed_out, true_solid, true_to_twin


def plate() -> trimesh.Trimesh:
    """A 60 x 40 x 6 mm box, fine enough (edges under the 1 mm pitch) that one missing face is a small hole."""
    box = trimesh.creation.box(extents=[0.06, 0.04, 0.006])
    for _ in range(6):
        box = box.subdivide()
    return box


def test_closed_mesh_is_exact_and_open_one_is_voxel_filled_without_the_surface_layer_bias():
    box = plate()
    volume, inertia, how = true_solid(box)
    assert how == "closed mesh" and volume == pytest.approx(0.06 * 0.04 * 0.006)
    open_volume, open_inertia, how = true_solid(trimesh.Trimesh(box.vertices, box.faces[1:], process=False))
    assert how.startswith("voxels")
    # Whole surface voxels would read about area x 0.5 mm high: +12 % on this plate.
    assert open_volume == pytest.approx(volume, rel=0.02)
    assert np.linalg.eigvalsh(open_inertia) == pytest.approx(np.linalg.eigvalsh(inertia), rel=0.03)


def test_an_open_mesh_whose_fill_leaks_is_refused():
    box = trimesh.creation.box(extents=[0.06, 0.04, 0.006])
    with pytest.raises(ValueError, match="leaks"):
        true_solid(trimesh.Trimesh(box.vertices, box.faces[2:], process=False))  # a whole side missing


def test_true_to_twin_recovers_the_frame_change_from_the_cameras():
    rng = np.random.default_rng(0)
    true_to_twin_frame = np.eye(4)
    true_to_twin_frame[:3, :3] = Rotation.from_euler("xyz", [170, -20, 35], degrees=True).as_matrix()
    true_to_twin_frame[:3, 3] = [0.02, -0.01, 0.04]
    names = [f"images/cam_{i:02d}.png" for i in range(5)]
    true_c2w = []
    for _ in names:
        c2w = np.eye(4)
        c2w[:3, :3] = Rotation.random(random_state=rng).as_matrix()
        c2w[:3, 3] = rng.normal(size=3)
        true_c2w.append(c2w)
    twin = {"cameras": [{"file_path": n, "c2w_object_opencv": (true_to_twin_frame @ c).tolist()} for n, c in zip(names, true_c2w)][::-1]}
    gt = {"train": {"c2w_opencv_object": [c.tolist() for c in true_c2w]}}
    transforms = {"frames": [{"file_path": n} for n in names]}
    assert true_to_twin(twin, gt, transforms) == pytest.approx(true_to_twin_frame)


def test_pushed_out_box_grows_by_its_area_times_the_distance():
    box = plate()
    grown = pushed_out(box, 1e-4)
    assert grown.volume - box.volume == pytest.approx(box.area * 1e-4, rel=0.05)
