"""Twin exports: the MJCF package of one twin, the COLMAP text model (read back by pycolmap), the export table."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from reconstruction.twin import load_twin
from simulation.asset import sh_dc_rgb
from simulation.export import DIRECTORY_MARKERS, FORMATS, PHYSICS_FORMATS, export_colmap, export_mjcf
from simulation.run import load_model, simulate
from simulation.scene import SceneError, parse_scene
from tests.simulation.twins import hammer, make_twin


@pytest.fixture(scope="module")
def twin_dir(tmp_path_factory):
    return make_twin(tmp_path_factory.mktemp("twins"), "hammer", *hammer(), n=1500)


def test_export_mjcf_loads_and_rests_on_the_floor(twin_dir, tmp_path):
    xml = export_mjcf(twin_dir, tmp_path / "mjcf", material="steel")
    model = load_model(xml)
    assert model.body(1).name == "hammer" and model.body_mass[1] == pytest.approx(
        7850 * (0.14 * 0.02 * 0.016 + 0.03 * 0.07 * 0.024), rel=1e-3
    )
    traj = simulate(model, 0.5, fps=10)
    assert traj.kinetic.max() < 1e-6  # placed resting on the floor: nothing moves
    assert traj.penetration[-1] < 1e-4


def test_export_colmap_round_trips_through_pycolmap(twin_dir, tmp_path):
    import pycolmap

    twin = load_twin(twin_dir)
    export_colmap(twin_dir, tmp_path / "colmap")
    rec = pycolmap.Reconstruction(str(tmp_path / "colmap"))
    assert rec.num_images() == len(twin.cameras) and rec.num_points3D() == twin.num_splats
    for image in rec.images.values():
        tc = twin.cameras[image.image_id - 1]
        w2c = np.eye(4)
        w2c[:3] = image.cam_from_world().matrix()
        assert w2c == pytest.approx(tc.camera.viewmat, abs=1e-9)
        cam = rec.cameras[image.camera_id]
        assert cam.model.name == "PINHOLE" and cam.calibration_matrix() == pytest.approx(tc.K)
        assert (cam.width, cam.height) == (tc.camera.width, tc.camera.height) and image.name == Path(tc.file_path).name
    ids = sorted(rec.points3D)
    xyz = np.array([rec.points3D[i].xyz for i in ids])
    rgb = np.array([rec.points3D[i].color for i in ids])
    assert xyz == pytest.approx(twin.gaussians.means, abs=1e-6)
    assert np.abs(rgb.astype(int) - np.round(sh_dc_rgb(twin.gaussians.sh[:, 0]) * 255)).max() <= 1


def test_the_export_table_names_callable_exporters_with_help():
    assert list(FORMATS) == ["ply", "glb", "spz", "mjcf", "usd", "colmap"]
    assert all(callable(fn) and help_text for fn, help_text in FORMATS.values())
    assert set(DIRECTORY_MARKERS) | set(PHYSICS_FORMATS) <= set(FORMATS)


def test_scene_parse_errors_are_plain(tmp_path):
    (tmp_path / "m.stl").write_bytes(b"")
    good = {"twin": [{"path": "m.stl", "unit": "mm", "euler_deg": [0, 0, 90]}]}
    scene = parse_scene(good, tmp_path)
    assert scene.placements[0].quat == pytest.approx([np.sqrt(0.5), 0, 0, np.sqrt(0.5)])
    assert scene.options.contact.solref == (2 * scene.options.timestep, 1.0)
    for doc, msg in [
        ({}, "no \\[\\[twin\\]\\]"),
        ({"twin": [{"path": "m.stl", "quat": [0, 0, 0, 0]}]}, "must not be zero"),
        ({"twin": [{"path": "m.stl", "pos": [0, 1]}]}, "list of 3 finite numbers"),
        ({"twin": [{"path": "m.stl"}, {"path": "m.stl"}]}, "unique"),
        ({"twin": [{"path": "m.stl"}], "timestep": -1}, "positive"),
        ({"twin": [{"path": "m.stl"}], "camera": {"mode": "orbit"}}, "fixed or turntable"),
    ]:
        with pytest.raises(SceneError, match=msg):
            parse_scene(doc, tmp_path)
