"""The synthetic rig: camera layouts, MuJoCo renders against exact geometry, and the dataset it writes."""

from __future__ import annotations

import json

import cv2
import numpy as np
import pytest

from calibration.camera import Camera, look_at_c2w
from calibration.capture import CaptureError, read_capture
from calibration.sim3 import Sim3
from calibration.so3 import axis_angle_to_matrix, geodesic_angle_deg
from rig.synthetic import Light, SyntheticScene, TexturedMesh, ring_rig, synth_dataset
from tests.conftest import require_shared


def textured_torus(major: float = 0.05, minor: float = 0.018, n: int = 48, m: int = 24, tilt_deg: float = 35.0) -> TexturedMesh:
    """A tilted torus (non-convex, self-occluding) with a seam-split UV grid and a colour-checker texture."""
    u, v = np.meshgrid(np.linspace(0, 2 * np.pi, n + 1), np.linspace(0, 2 * np.pi, m + 1), indexing="ij")
    pts = np.stack([(major + minor * np.cos(v)) * np.cos(u), (major + minor * np.cos(v)) * np.sin(u), minor * np.sin(v)], -1)
    pts = pts.reshape(-1, 3) @ axis_angle_to_matrix(np.radians([tilt_deg, 0.0, 0.0])).T + [0.01, -0.02, 0.03]
    idx = np.arange((n + 1) * (m + 1)).reshape(n + 1, m + 1)
    a, b, c, d = idx[:-1, :-1], idx[1:, :-1], idx[1:, 1:], idx[:-1, 1:]
    faces = np.concatenate([np.stack([a, b, c], -1).reshape(-1, 3), np.stack([a, c, d], -1).reshape(-1, 3)])
    uv = np.stack([u.ravel() / (2 * np.pi), v.ravel() / (2 * np.pi)], 1)
    cells = (np.add.outer(np.arange(256) // 32, np.arange(256) // 32) % 2).astype(bool)
    tex = np.where(cells[..., None], [220, 60, 40], [40, 90, 210]).astype(np.uint8)
    tex[:128] = tex[:128] // 2 + 100  # the top half (v > 0.5) differs from the bottom half: a flipped texture shows
    return TexturedMesh(pts, faces, uv, tex)


@pytest.fixture(scope="module")
def torus_scene():
    with SyntheticScene(textured_torus()) as scene:
        yield scene


def off_centre_camera(target: np.ndarray, eye_dir, dist: float = 0.25, w: int = 160, h: int = 120) -> Camera:
    k = np.array([[190.0, 0.0, w / 2 + 9.3], [0.0, 176.0, h / 2 - 6.1], [0.0, 0.0, 1.0]])
    eye = target + dist * np.asarray(eye_dir, float) / np.linalg.norm(eye_dir)
    return Camera(k, w, h, c2w=look_at_c2w(eye, target))


def silhouette_coverage(camera: Camera, vertices: np.ndarray, faces: np.ndarray, ss: int = 8) -> np.ndarray:
    """Per-pixel fraction [H, W] covered by the projected triangles (8x8 supersampled exact rasterisation)."""
    uv, _ = camera.project(vertices)
    img = np.zeros((camera.height * ss, camera.width * ss), np.uint8)
    pts = np.round((uv[faces] * ss - 0.5) * 16).astype(np.int32)  # cv2 pixel centres are integers; 4 fractional bits
    for tri in pts:
        cv2.fillConvexPoly(img, tri, 1, shift=4)
    return img.reshape(camera.height, ss, camera.width, ss).mean((1, 3))


def test_ring_rig_geometry():
    target = np.array([0.1, -0.2, 0.05])
    cams = ring_rig(10, radius=0.4, elevations_deg=(10.0, 40.0, 70.0), target=target, width=200, height=100, fov_deg=60.0)
    assert len(cams) == 10
    centres = np.stack([c.center for c in cams])
    np.testing.assert_allclose(np.linalg.norm(centres - target, axis=1), 0.4, atol=1e-12)
    elev = np.degrees(np.arcsin((centres[:, 2] - target[2]) / 0.4))
    np.testing.assert_allclose(elev, [10] * 4 + [40] * 3 + [70] * 3, atol=1e-9)
    for c in cams:
        uv, depth = c.project(target[None])
        np.testing.assert_allclose(uv[0], [100.0, 50.0], atol=1e-9)  # target on the optical axis
        assert depth[0] == pytest.approx(0.4)
        assert c.K[0, 0] == pytest.approx(100.0 / np.tan(np.radians(30.0)))
        assert c.c2w[:3, 1] @ [0, 0, 1] < 0  # image "down" points down in the world: cameras are upright
    az = np.degrees(np.arctan2(centres[:4, 1] - target[1], centres[:4, 0] - target[0])) % 360
    np.testing.assert_allclose(az, [0.0, 90.0, 180.0, 270.0], atol=1e-9)  # azimuth 0 on +x, counter-clockwise about up


def test_masks_are_exact_silhouettes_with_off_centre_principal_point(torus_scene):
    mesh = torus_scene.mesh
    target = mesh.bounds.mean(0)
    cams = [off_centre_camera(target, d) for d in ([1, 0.3, 0.6], [-0.4, 1, 0.2], [0.2, -0.5, -1])]
    _, masks = torus_scene.render(cams)
    for cam, mask in zip(cams, masks):
        cov = silhouette_coverage(cam, mesh.vertices, mesh.faces)
        iou = np.minimum(mask, cov).sum() / np.maximum(mask, cov).sum()
        assert iou > 0.97, iou
        yy, xx = np.mgrid[: cam.height, : cam.width]
        c_mask = np.array([(xx * mask).sum(), (yy * mask).sum()]) / mask.sum()
        c_cov = np.array([(xx * cov).sum(), (yy * cov).sum()]) / cov.sum()
        assert np.abs(c_mask - c_cov).max() < 0.1, (c_mask, c_cov)  # principal point and focal lengths exact
        # Every projected vertex lands inside the 1-px dilated mask: the mask is the whole silhouette.
        uv, _ = cam.project(mesh.vertices)
        dil = cv2.dilate(mask.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
        px = np.floor(uv).astype(int)
        assert dil[px[:, 1], px[:, 0]].all()


def test_distorted_camera_gets_a_distorted_silhouette(torus_scene):
    mesh = torus_scene.mesh
    cam = off_centre_camera(mesh.bounds.mean(0), [1, 0.2, 0.5], dist=0.17)
    cam = Camera(cam.K, cam.width, cam.height, np.array([-0.25, 0.08, 0.001, -0.002]), cam.c2w)
    _, masks = torus_scene.render([cam])
    uv, _ = cam.project(mesh.vertices)  # projection through the distortion model
    dil = cv2.dilate(masks[0].astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    px = np.floor(uv).astype(int)
    inside = (px >= 0).all(1) & (px[:, 0] < cam.width) & (px[:, 1] < cam.height)
    assert inside.mean() > 0.9  # barrel distortion pulls the corners in: most of the torus is in view
    assert dil[px[inside, 1], px[inside, 0]].all()
    # The whole distorted silhouette, also where the image's corners see past the pinhole frame (no smeared border).
    cov = silhouette_coverage(cam, mesh.vertices, mesh.faces)  # small triangles: straight edges are fine
    assert np.minimum(masks[0], cov).sum() / np.maximum(masks[0], cov).sum() > 0.97
    _, undistorted = torus_scene.render([cam.pinhole()])
    assert (masks[0] != undistorted[0]).sum() > 50  # the warp did something


def test_texture_is_mapped_the_right_way_up(torus_scene):
    """Rendered colours at visible vertices follow the texture sampled at their UVs (a flipped v breaks this)."""
    mesh = torus_scene.mesh
    cam = off_centre_camera(mesh.bounds.mean(0), [0.3, 0.2, 1.0], dist=0.2, w=320, h=240)
    images, masks = torus_scene.render([cam], light=Light(diffuse=0.0, ambient=1.0, headlight=0.0))
    uv, depth = cam.project(mesh.vertices)
    # Visible: vertex normal faces the camera and its pixel's 3x3 neighbourhood is all object.
    tm_normals = _vertex_normals(mesh)
    facing = np.einsum("ij,ij->i", tm_normals, cam.center - mesh.vertices) > 0.7 * np.linalg.norm(cam.center - mesh.vertices, axis=1)
    px = np.floor(uv).astype(int)
    inner = cv2.erode(masks[0].astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
    sel = facing & inner[px[:, 1], px[:, 0]]
    tex = mesh.texture
    # Vertices sit on checker corners; sample a little inside the cell towards the face centroid instead.
    centroid_uv = mesh.uv[mesh.faces].mean(1)
    centroid_xyz = mesh.vertices[mesh.faces].mean(1)
    fuv, _ = cam.project(centroid_xyz)
    fsel = np.isin(mesh.faces, np.where(sel)[0]).all(1)
    want = tex[
        ((1 - centroid_uv[fsel, 1]) * tex.shape[0]).astype(int).clip(0, tex.shape[0] - 1),
        (centroid_uv[fsel, 0] * tex.shape[1]).astype(int).clip(0, tex.shape[1] - 1),
    ]
    got = images[0][np.floor(fuv[fsel, 1]).astype(int), np.floor(fuv[fsel, 0]).astype(int)]
    assert fsel.sum() > 100
    agree = np.mean(np.abs(got.astype(float) - want.astype(float)).max(1) < 40)
    assert agree > 0.8, agree


def _vertex_normals(mesh: TexturedMesh) -> np.ndarray:
    v, f = mesh.vertices, mesh.faces
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    n = np.zeros_like(v)
    for k in range(3):
        np.add.at(n, f[:, k], fn)
    # Seam duplicates share positions: pool their normals so seams do not look one-sided.
    _, inv = np.unique(np.round(v, 9), axis=0, return_inverse=True)
    pooled = np.zeros((inv.max() + 1, 3))
    np.add.at(pooled, inv.ravel(), n)
    n = pooled[inv.ravel()]
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def test_background_noise_and_backdrop(torus_scene):
    cam = off_centre_camera(torus_scene.mesh.bounds.mean(0), [1, 0, 0.4])
    empty, empty_masks = torus_scene.render([cam], object_visible=False)
    assert not empty_masks.any()
    assert np.ptp(empty[0].reshape(-1, 3), axis=0).max() <= 1  # no backdrop: a flat background
    clean, masks = torus_scene.render([cam])
    noisy, _ = torus_scene.render([cam], noise_std=0.02, seed=3)
    diff = noisy[0].astype(float) - clean[0].astype(float)
    assert np.std(diff[~masks[0]]) == pytest.approx(0.02 * 255, rel=0.1)
    far = cv2.dilate(masks[0].astype(np.uint8), np.ones((3, 3), np.uint8)) == 0  # RGB edges are antialiased, masks are not
    np.testing.assert_array_equal(clean[0][far], empty[0][far])  # the empty rig is the same rig
    with SyntheticScene(textured_torus(), backdrop=True) as scene:
        back, back_masks = scene.render([cam], object_visible=False)
        img, m = scene.render([cam])
    assert back[0].reshape(-1, 3).std(0).max() > 10  # textured floor and sky, not a flat colour
    np.testing.assert_array_equal(m, masks)  # the backdrop never leaks into the object mask


@pytest.fixture(scope="module")
def small_dataset(tmp_path_factory):
    """A 5-view + 6-held-out dataset of a real YCB scan, with calibration error on the recorded train poses."""
    mesh_path = require_shared("objects", "ycb", "011_banana", "textured.obj")
    out = tmp_path_factory.mktemp("synth") / "banana"
    gt = synth_dataset(
        mesh_path, out, views=5, heldout=6, size=(128, 96), seed=4, calib_noise_deg=0.5, calib_noise_mm=2.0, texture_size=256
    )
    return mesh_path, out, gt


def test_dataset_files_and_ground_truth(small_dataset):
    mesh_path, out, gt = small_dataset
    assert json.loads((out / "gt.json").read_text()) == gt
    train, held = read_capture(out / "train"), read_capture(out / "heldout")
    assert (len(train), len(held)) == (5, 6)
    assert train.has_masks and held.has_masks
    assert all(train.background(f.camera_id) is not None for f in train.frames)
    assert gt["size"] == [128, 96] and gt["seed"] == 4
    sim3 = Sim3.from_dict(gt["sim3_rig_to_object"])
    assert geodesic_angle_deg(sim3.rotation, np.eye(3)) > 1.0 or np.linalg.norm(sim3.translation) > 1e-3  # not the identity
    # Held-out poses are recorded true: rig poses mapped by the Sim(3) are the object-frame truth.
    held_obj = sim3.apply_to_c2w(np.stack([f.camera.c2w for f in held.frames]))
    np.testing.assert_allclose(held_obj, gt["heldout_c2w_object"], atol=1e-9)
    # Train poses carry the recorded calibration error, and gt.json says exactly which.
    rec = np.stack([f.camera.c2w for f in train.frames])
    true_rig = np.array(gt["train_c2w_rig_true"])
    ang = geodesic_angle_deg(true_rig[:, :3, :3], rec[:, :3, :3])
    np.testing.assert_allclose(ang, np.linalg.norm(gt["calib_noise"]["rotvec_deg"], axis=1), atol=1e-6)
    np.testing.assert_allclose(rec[:, :3, 3] - true_rig[:, :3, 3], gt["calib_noise"]["centre_shift_rig"], atol=1e-9)
    assert 0.05 < ang.mean() < 2.0
    np.testing.assert_allclose(sim3.apply_to_c2w(true_rig), gt["train_c2w_object"], atol=1e-9)
    # The train capture states that uncertainty, as a keeper's calibration would; the exact held-out one does not.
    assert train.meta["calibration_uncertainty"] == {"rotation_deg": 0.5, "translation_mm": 2.0}
    assert "calibration_uncertainty" not in held.meta


def test_true_poses_project_the_mesh_into_the_masks(small_dataset):
    from rig.synthetic import load_textured_mesh

    mesh_path, out, gt = small_dataset
    mesh = load_textured_mesh(mesh_path, texture_size=16)
    for name, key in (("train", "train_c2w_object"), ("heldout", "heldout_c2w_object")):
        cap = read_capture(out / name)
        for i, c2w in enumerate(gt[key]):
            cam = cap.camera(i).with_c2w(np.array(c2w))
            mask = cap.mask(i)
            uv, depth = cam.project(mesh.vertices)
            assert (depth > 0).all()
            px = np.floor(uv).astype(int)
            dil = cv2.dilate(mask.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
            assert dil[px[:, 1], px[:, 0]].all()
            assert 0.03 < mask.mean() < 0.6  # the object is framed, neither lost nor cropped


def test_captures_are_never_overwritten(small_dataset, tmp_path):
    mesh_path, out, _ = small_dataset
    before = (out / "train" / "transforms.json").read_bytes()
    with pytest.raises(CaptureError, match="already exists"):
        synth_dataset(mesh_path, out, views=3, heldout=0, size=(64, 48), texture_size=64)
    assert (out / "train" / "transforms.json").read_bytes() == before


def test_given_sim3_with_scale_and_explicit_cameras(tmp_path):
    """A rig calibrated in another unit (scale 2.5) with explicit cameras: images depend only on object-frame poses."""
    mesh = textured_torus()
    import trimesh
    from PIL import Image

    tm = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    tm.visual = trimesh.visual.TextureVisuals(uv=mesh.uv, image=Image.fromarray(mesh.texture))
    tm.export(tmp_path / "torus.obj")
    sim3 = Sim3(2.5, axis_angle_to_matrix([0.3, -0.2, 1.0]), [0.1, 0.0, -0.05])
    target_obj = mesh.bounds.mean(0)
    cams_obj = [off_centre_camera(target_obj, d, w=96, h=72) for d in ([1, 0, 0.5], [0, 1, 0.3], [-1, -1, 0.8])]
    cams_rig = [c.with_c2w(sim3.inverse().apply_to_c2w(c.c2w)) for c in cams_obj]
    gt = synth_dataset(tmp_path / "torus.obj", tmp_path / "out", cameras=cams_rig, heldout=4, rig_to_object=sim3, seed=1)
    np.testing.assert_allclose(gt["train_c2w_object"], [c.c2w for c in cams_obj], atol=1e-9)
    train = read_capture(tmp_path / "out" / "train")
    np.testing.assert_allclose(train.frames[0].camera.K, cams_obj[0].K)
    with SyntheticScene(mesh) as scene:
        _, direct = scene.render(cams_obj)
    np.testing.assert_array_equal(np.stack([train.mask(i) for i in range(3)]), direct)
    # The held-out orbit in rig units sits at the metric distance divided by the scale.
    held = read_capture(tmp_path / "out" / "heldout")
    d_rig = np.linalg.norm(held.frames[0].camera.center - sim3.inverse().apply(target_obj))
    d_obj = np.linalg.norm(np.array(gt["heldout_c2w_object"])[0, :3, 3] - target_obj)
    assert d_rig * 2.5 == pytest.approx(d_obj, rel=1e-9)


def test_bad_inputs_are_one_sentence(tmp_path):
    with pytest.raises(ValueError, match="does not exist"):
        synth_dataset(tmp_path / "nope.obj", tmp_path / "o")
    (tmp_path / "junk.obj").write_text("this is not a mesh\n")
    with pytest.raises(ValueError, match="junk.obj"):
        synth_dataset(tmp_path / "junk.obj", tmp_path / "o")
    with pytest.raises(ValueError, match="too small"):
        synth_dataset(tmp_path / "junk.obj", tmp_path / "o", size=(4, 4))
    with pytest.raises(ValueError, match="at least one view"):
        ring_rig(0, radius=1.0)
