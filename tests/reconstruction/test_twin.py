"""The twin format: save/load round trip, the Inria PLY columns read back with plyfile, GLB parts."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
from plyfile import PlyData

from calibration.camera import look_at_c2w
from calibration.sim3 import Sim3
from calibration.so3 import axis_angle_to_matrix
from reconstruction.gaussians import Gaussians
from reconstruction.mesh_io import MeshParts, read_mesh_parts
from reconstruction.twin import (
    Twin,
    TwinCamera,
    TwinError,
    load_twin,
    ply_columns,
    read_splats_ply,
    save_twin,
    splat_normals,
)


def make_twin(n: int = 50, degree: int = 2, seed: int = 0) -> Twin:
    rng = np.random.default_rng(seed)
    k = (degree + 1) ** 2
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    cam = TwinCamera(
        "images/a.png",
        "cam0",
        np.array([[100.0, 0, 32], [0, 100, 24], [0, 0, 1]]),
        64,
        48,
        look_at_c2w(np.array([0.5, 0.0, 0.2]), np.zeros(3)),
    )
    return Twin(
        model_id="m1",
        sim3_rig_to_object_init=Sim3(2.0, axis_angle_to_matrix(np.array([0.1, 0.2, 0.3])), np.array([1.0, 2, 3])),
        sim3_rig_to_object=Sim3(2.1, np.eye(3), np.array([0.5, 0, 0])),
        cameras=[cam],
        preset="cpu",
        choices={"num_splats": {"value": n, "why": "test"}},
        timings_s={"stage1": 1.5},
        losses={"mask": 0.01},
        gaussians=Gaussians.from_arrays(
            rng.normal(size=(n, 3)), q, rng.normal(size=(n, 3)) - 5, rng.normal(size=n), rng.normal(size=(n, k, 3))
        ),
        means_canonical=rng.normal(size=(n, 3)),
        face_index=rng.integers(0, 12, n),
        barycentrics=rng.dirichlet([1, 1, 1], n),
        part_label=rng.integers(0, 2, n),
        part_names=["body", "lid"],
    )


def test_round_trip_and_every_ply_column(tmp_path):
    twin = make_twin()
    mesh = MeshParts(
        np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1.0]]), np.array([[0, 1, 2], [0, 1, 3]]), np.array([0, 1]), ["body", "lid"]
    )
    out = save_twin(
        replace(twin, config={"name": "cpu"}, training={"seed": 3}),
        tmp_path / "twin",
        mesh_cad=mesh,
        mesh_deformed=mesh,
        renders={"a.png": np.ones((4, 5, 4), np.float32)},
    )
    back = load_twin(out)
    for name in ("means", "quats", "log_scales", "opacity_logits", "sh"):
        np.testing.assert_allclose(getattr(back.gaussians, name), getattr(twin.gaussians, name), rtol=1e-6, atol=1e-6)
    for name in ("means_canonical", "barycentrics"):
        np.testing.assert_allclose(getattr(back, name), getattr(twin, name), rtol=1e-6, atol=1e-6)
    np.testing.assert_array_equal(back.face_index, twin.face_index)
    np.testing.assert_array_equal(back.part_label, twin.part_label)
    assert back.part_names == ["body", "lid"] and back.gaussians.sh_degree == 2 and back.model_id == "m1"
    np.testing.assert_allclose(back.sim3_rig_to_object_init.matrix(), twin.sim3_rig_to_object_init.matrix(), atol=1e-12)
    np.testing.assert_allclose(back.cameras[0].c2w_object_opencv, twin.cameras[0].c2w_object_opencv)
    assert back.cameras[0].camera.width == 64
    assert (out / "renders" / "a.png").exists() and back.config == {"name": "cpu"} and back.training == {"seed": 3}

    # Every column, read with plyfile directly, in the Inria order and meaning: padded to degree 3
    # (what Inria's loader reads without flags), the fitted degree in a header comment.
    ply = PlyData.read(str(out / "splats.ply"))
    v = ply["vertex"]
    names = [p.name for p in v.properties]
    assert names == ply_columns(3) and "sh_degree 2" in ply.comments
    assert len(names) == 3 + 3 + 3 + 45 + 1 + 3 + 4
    assert all(p.val_dtype in ("f4", "float32") for p in v.properties)
    n, g = twin.num_splats, twin.gaussians
    np.testing.assert_allclose(np.stack([v["x"], v["y"], v["z"]], 1), g.means, atol=1e-6)
    np.testing.assert_allclose(np.stack([v["nx"], v["ny"], v["nz"]], 1), splat_normals(g.quats), atol=1e-6)
    np.testing.assert_allclose(np.stack([v[f"f_dc_{c}"] for c in range(3)], 1), g.sh[:, 0], atol=1e-6)
    # Channel-major f_rest: index c * 15 + (j - 1) holds coefficient j of channel c; degree 3 is zero.
    for c in range(3):
        for j in range(1, 16):
            want = g.sh[:, j, c] if j < 9 else 0.0
            np.testing.assert_allclose(v[f"f_rest_{c * 15 + j - 1}"], want, atol=1e-6)
    np.testing.assert_allclose(v["opacity"], g.opacity_logits, atol=1e-6)
    np.testing.assert_allclose(np.stack([v[f"scale_{i}"] for i in range(3)], 1), g.log_scales, atol=1e-6)
    np.testing.assert_allclose(np.stack([v[f"rot_{i}"] for i in range(4)], 1), g.quats, atol=1e-6)
    assert len(v["x"]) == n

    parts = read_mesh_parts(out / "mesh_deformed.glb")
    assert sorted(parts.part_names) == ["body", "lid"]
    assert len(parts.faces) == 2
    assert back.load_mesh_cad().faces.shape == (2, 3)


def test_existing_twin_is_kept_unless_overwrite(tmp_path):
    twin = make_twin()
    save_twin(twin, tmp_path / "t")
    with pytest.raises(TwinError, match="already exists"):
        save_twin(make_twin(seed=1), tmp_path / "t")
    np.testing.assert_allclose(load_twin(tmp_path / "t").gaussians.means, twin.gaussians.means, atol=1e-6)
    other = make_twin(seed=1)
    save_twin(other, tmp_path / "t", overwrite=True)
    np.testing.assert_allclose(load_twin(tmp_path / "t").gaussians.means, other.gaussians.means, atol=1e-6)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["t"]


def test_bad_inputs_are_one_sentence(tmp_path):
    with pytest.raises(TwinError, match="no twin.json"):
        load_twin(tmp_path)
    t = make_twin()
    with pytest.raises(TwinError, match="NaN"):
        Twin(**{**t.__dict__, "gaussians": replace(t.gaussians, means=np.full((50, 3), np.nan, np.float32))})
    with pytest.raises(TwinError, match="shape"):
        Twin(**{**t.__dict__, "barycentrics": np.zeros((49, 3))})


def test_the_dilation_a_twin_was_fitted_with_comes_back(tmp_path):
    twin = make_twin()
    sharp = replace(twin, gaussians=replace(twin.gaussians, eps2d=0.1))
    out = save_twin(sharp, tmp_path / "sharp")
    assert load_twin(out).gaussians.eps2d == 0.1
    # The PLY says it too, in a header comment Inria-layout readers skip.
    assert "eps2d 0.1" in PlyData.read(str(out / "splats.ply")).comments and read_splats_ply(out / "splats.ply").eps2d == 0.1
    # A twin written before the field existed was fitted with 3DGS's dilation.
    out = save_twin(twin, tmp_path / "old")
    doc = json.loads((out / "twin.json").read_text())
    del doc["eps2d"]
    (out / "twin.json").write_text(json.dumps(doc))
    assert load_twin(out, verify=False).gaussians.eps2d == 0.3
    for bad in (-1.0, None, True, "0.1", [0.1]):
        doc["eps2d"] = bad
        (out / "twin.json").write_text(json.dumps(doc))
        with pytest.raises(TwinError, match="eps2d"):
            load_twin(out, verify=False)


def test_a_manifest_entry_outside_the_twin_is_refused(tmp_path):
    """A manifest naming a file outside the twin (with that file's true digest) must not be read as part of it."""
    import json

    from calibration.fileio import sha256_file
    from reconstruction.twin import MANIFEST_JSON, TwinError, verify_twin

    root = tmp_path / "twin"
    root.mkdir()
    secret = tmp_path / "secret.txt"
    secret.write_text("not the twin's")
    (root / MANIFEST_JSON).write_text(json.dumps({"sha256": {"../secret.txt": sha256_file(secret)}}))
    with pytest.raises(TwinError, match="outside"):
        verify_twin(root)
