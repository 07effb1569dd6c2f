"""The evaluation harness: frozen twin, test-time pose refinement, frames, registration, averaging."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import trimesh

from calibration.camera import Camera, look_at_c2w
from calibration.sim3 import Sim3
from calibration.so3 import axis_angle_to_matrix
from reconstruction.evaluation import (
    average_metrics,
    cameras_to_object,
    evaluate_twin,
    evaluate_views,
    gt_train_poses,
    half_turn,
    refine_camera_pose,
    select_views,
)
from reconstruction.gaussians import Gaussians, camera_batch, render
from reconstruction.splats import init_splats
from reconstruction.twin import Twin, TwinCamera

W, H = 80, 60


def make_twin(n: int = 2500, seed: int = 0) -> Twin:
    """A 5 cm sphere of opaque splats whose colour varies smoothly with position (photometric signal)."""
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=0.05)
    pts = mesh.triangles_center
    rgb_face = 0.5 + 0.45 * pts / 0.05 * np.array([1.0, -1.0, 0.6])
    s = init_splats(mesh.vertices, mesh.faces, n, sh_degree=1, seed=seed)
    g = s.gaussians
    g.sh[:, 0] = (np.clip(rgb_face[s.face_index], 0, 1) - 0.5) / 0.28209479177387814
    g.log_scales[:, :2] += np.log(1.6)  # overlap the disks so the silhouette has no holes
    cam = TwinCamera("images/cam00.png", "cam00", orbit_camera(0.0).K, W, H, orbit_camera(0.0).c2w)
    return Twin(
        model_id="sphere",
        sim3_rig_to_object_init=Sim3.identity(),
        sim3_rig_to_object=Sim3.identity(),
        cameras=[cam],
        preset="test",
        choices={},
        timings_s={},
        losses={},
        gaussians=replace(g, opacity_logits=np.full(n, 4.0, np.float32)),
        means_canonical=s.means,
        face_index=s.face_index,
        barycentrics=s.barycentrics,
        part_label=s.part_label,
        part_names=["body"],
    )


def orbit_camera(azimuth_deg: float, elevation_deg: float = 20.0, distance: float = 0.25) -> Camera:
    a, e = np.radians(azimuth_deg), np.radians(elevation_deg)
    eye = distance * np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
    return Camera.from_fov(np.radians(40.0), W, H, look_at_c2w(eye, np.zeros(3)))


def photograph(g: Gaussians, cam: Camera, background=(0.0, 0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """A 'photo' of the twin: by default over black (a background the metrics must ignore), mask alpha > 0.5."""
    rgb, alpha = render(g, *camera_batch(cam), background=background)
    return rgb[0].numpy(), alpha[0].numpy() > 0.5


def shifted(cam: Camera, deg: float, metres: float) -> Camera:
    """The camera turned about its own y axis and slid along its own x axis: a mis-calibrated view."""
    c2w = cam.c2w.copy()
    c2w[:3, :3] = c2w[:3, :3] @ axis_angle_to_matrix(np.radians([0.0, deg, 0.0]))
    c2w[:3, 3] += metres * c2w[:3, 0]
    return cam.with_c2w(c2w)


@pytest.fixture(scope="module")
def twin() -> Twin:
    return make_twin(n=1500)


def test_perfect_view_scores_perfectly(twin):
    g = twin.gaussians
    cams = [orbit_camera(a) for a in (0.0, 120.0)]
    # Over white, as the prediction is rendered: the semi-transparent rim then matches pixel for pixel.
    shots = [photograph(g, c, background=(1.0, 1.0, 1.0)) for c in cams]
    report = evaluate_views(g, cams, np.stack([s[0] for s in shots]), np.stack([s[1] for s in shots]), refine_steps=0)
    mean = report["mean"]
    assert mean["iou"] == 1.0
    assert mean["fgpsnr"] is None or mean["fgpsnr"] > 60.0  # identical pixels: inf, reported as None
    # Inside the eroded mask the images are identical (inf dB, reported as None); the object crop
    # differs only where the rendered rim (alpha < 0.5) falls outside the GT mask the GT is cut with.
    assert mean["mpsnr"] is None and mean["mlpips"] < 1e-4 and mean["mflip"] == 0.0
    assert mean["psnr"] > 22.0 and mean["ssim"] > 0.9
    assert "mean_refined" not in report and len(report["views"]) == 2


def test_refinement_recovers_a_shifted_camera_and_leaves_the_twin_bit_identical(twin):
    before = {k: getattr(twin.gaussians, k).copy() for k in ("means", "quats", "log_scales", "opacity_logits", "sh")}
    g = twin.gaussians
    true_cam = orbit_camera(40.0)
    img, mask = photograph(g, true_cam)
    nominal = shifted(true_cam, 1.5, 0.003)  # ~4 px of misalignment at this focal length
    report = evaluate_twin(twin, [nominal], img[None], mask[None], refine_steps=40, refine_lr=3e-3)
    plain, refined = report["mean"], report["mean_refined"]
    assert refined["iou"] > plain["iou"] + 0.05, (plain["iou"], refined["iou"])
    assert refined["iou"] > 0.95
    assert refined["psnr"] > plain["psnr"] + 3.0
    ref = report["views"][0]["refine"]
    assert ref["loss_last"] < 0.5 * ref["loss_first"]
    # Rotation and sideways motion trade off for a round object; what must come back is where it lands.
    refined_cam = nominal.with_c2w(np.array(ref["c2w_object"]))
    landmarks = np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.05], [0.05, 0.0, 0.0]])
    px = lambda c: c.project(landmarks)[0]  # noqa: E731
    assert np.abs(px(nominal) - px(true_cam)).max() > 4.0
    assert np.abs(px(refined_cam) - px(true_cam)).max() < 1.0
    for k, v in before.items():
        assert np.array_equal(getattr(twin.gaussians, k), v), k  # bit-identical: refinement never touched the twin


def test_refinement_only_optimises_the_pose():
    """The refined pose is what the loss improved; the frozen splats never require grad."""
    twin = make_twin(n=800, seed=1)
    g = twin.gaussians
    assert not any(t.requires_grad for t in g.activated())
    cam = orbit_camera(200.0)
    img, mask = photograph(g, cam)
    ref = refine_camera_pose(g, shifted(cam, 1.5, 0.0), img, mask, steps=40, lr=1e-3)
    assert ref.c2w.shape == (4, 4) and np.allclose(ref.c2w[:3, :3] @ ref.c2w[:3, :3].T, np.eye(3), atol=1e-9)
    assert ref.losses.shape == (40,) and ref.losses[-1] < ref.losses[0]


def test_heldout_cameras_go_through_the_refined_registration(twin):
    """A capture in a rig frame (scaled, turned, moved) evaluates exactly like the object-frame one."""
    g = twin.gaussians
    cam_obj = orbit_camera(75.0)
    img, mask = photograph(g, cam_obj)
    rig_to_obj = Sim3(0.5, axis_angle_to_matrix(np.array([0.1, -0.4, 0.9])), np.array([0.3, -0.1, 0.05]))
    cam_rig = cam_obj.with_c2w(rig_to_obj.inverse().apply_to_c2w(cam_obj.c2w))
    assert np.allclose(cameras_to_object([cam_rig], rig_to_obj)[0].c2w, cam_obj.c2w, atol=1e-12)
    registered = make_twin(n=1500)
    registered.sim3_rig_to_object = rig_to_obj
    report = evaluate_twin(registered, [cam_rig], img[None], mask[None], refine_steps=0)
    assert report["mean"]["iou"] == 1.0
    registered.sim3_rig_to_object = Sim3.identity()  # the init/unrefined frame would put the camera elsewhere
    assert evaluate_twin(registered, [cam_rig], img[None], mask[None], refine_steps=0)["mean"]["iou"] < 0.5


def test_registration_against_gt_matches_cameras_by_name(twin):
    truth = [orbit_camera(a).c2w for a in (0.0, 90.0, 180.0, 270.0)]
    off = truth[2].copy()
    off[:3, :3] = off[:3, :3] @ axis_angle_to_matrix(np.radians([0.0, 0.0, 3.0]))
    cams = [
        TwinCamera("images/cam02.png", "cam02", twin.cameras[0].K, W, H, off),
        TwinCamera("images/cam00.png", "cam00", twin.cameras[0].K, W, H, truth[0]),
    ]
    est, ref, names = gt_train_poses(cams, {"train_c2w_object": [c.tolist() for c in truth]})
    assert names == ["cam02", "cam00"] and np.array_equal(ref[0], truth[2])
    twin2 = make_twin(n=500)
    twin2.cameras = cams
    g = twin2.gaussians
    img, mask = photograph(g, orbit_camera(10.0))
    rep = evaluate_twin(
        twin2, [orbit_camera(10.0)], img[None], mask[None], refine_steps=0, gt={"train_c2w_object": [c.tolist() for c in truth]}
    )["registration"]
    assert rep["rotation_deg"] == pytest.approx([3.0, 0.0], abs=1e-9)
    assert rep["center_pct"] == pytest.approx([0.0, 0.0], abs=1e-9)
    # A registration turned 180 deg about the object's z axis is right for a z-symmetric object.
    flipped = [TwinCamera(c.file_path, c.camera_id, c.K, W, H, np.diag([-1.0, -1.0, 1.0, 1.0]) @ truth[int(c.camera_id[3:])]) for c in cams]
    twin2.cameras = flipped
    gt = {"train_c2w_object": [c.tolist() for c in truth]}
    plain = evaluate_twin(twin2, [orbit_camera(10.0)], img[None], mask[None], refine_steps=0, gt=gt)["registration"]
    sym = evaluate_twin(
        twin2, [orbit_camera(10.0)], img[None], mask[None], refine_steps=0, gt=gt, symmetries=[half_turn("x"), half_turn("z")]
    )["registration"]
    assert plain["rotation_deg_median"] == pytest.approx(180.0) and plain["symmetry"] is None
    assert sym["rotation_deg_median"] == pytest.approx(0.0, abs=1e-9) and sym["symmetry"] == 1
    assert sym["center_pct_median"] == pytest.approx(0.0, abs=1e-9)
    with pytest.raises(ValueError, match="no ground-truth pose"):
        gt_train_poses([TwinCamera("images/x.png", "left", twin.cameras[0].K, W, H, truth[0])], {"train_c2w_object": truth})


def test_average_skips_undefined_metrics():
    views = [{"psnr": 20.0, "iou": 0.5, "fgpsnr": None}, {"psnr": 30.0, "iou": 1.0, "fgpsnr": 25.0}]
    mean = average_metrics(views)
    assert mean["psnr"] == 25.0 and mean["iou"] == 0.75 and mean["fgpsnr"] == 25.0 and mean["lpips"] is None


def test_select_views_and_bad_input(twin):
    assert select_views(36, None) == list(range(36))
    assert select_views(36, 4) == [0, 12, 23, 35]
    assert select_views(3, 10) == [0, 1, 2]
    g = twin.gaussians
    cam = orbit_camera(0.0)
    img = np.zeros((1, H, W, 3), np.float32)
    with pytest.raises(ValueError, match="empty mask"):
        evaluate_views(g, [cam], img, np.zeros((1, H, W), bool), refine_steps=0)
    with pytest.raises(ValueError, match="must match"):
        evaluate_views(g, [cam, cam], img, np.ones((1, H, W), bool), refine_steps=0)
    assert math.isfinite(select_views(5, 5)[-1])


def test_run_protocol_record_on_the_bundled_sample(tmp_path):
    """reconstruct -> held-out views -> registration error, on the sample: preview preset cut to a few
    iterations, a library of the true model and one distractor; then the same twin scored again (reuse)."""
    import json
    import shutil
    from pathlib import Path

    from reconstruction.evaluation import METRIC_KEYS, run_protocol
    from reconstruction.library import build_library

    sample = Path(__file__).resolve().parents[2] / "sample"
    meshes = tmp_path / "meshes"
    meshes.mkdir()
    for name in ("medium_clamp_cad.ply", "scissors.ply"):
        shutil.copy(sample / "library_meshes" / name, meshes / name)
    build_library(meshes, tmp_path / "library", progress=False, log=lambda _m: None)
    gt = json.loads((sample / "gt.json").read_text())
    scored: list[tuple[int, int]] = []
    run = run_protocol(
        sample / "train",
        sample / "heldout",
        tmp_path / "library",
        tmp_path / "twin",
        preset="preview",
        overrides={
            "num_splats": 1000,
            "iters_pose": 5,
            "iters_deform": 3,
            "iters_photo": 5,
            "dropout_anneal": 3,
            "field": {"num_anchors": 256},
            "lr": {"pose": 1e-3},
        },
        heldout_views=2,
        refine_steps=3,
        gt=gt,
        heldout_progress=lambda done, n: scored.append((done, n)),
    )
    assert run.twin.model_id == run.registration.model_id == "medium_clamp_cad"
    # Nested overrides merge into the resolved preset: the rest of the field and of the rates stay.
    field = run.twin.config["field"]
    assert field["num_anchors"] == 256 and field["project_similarity"]
    assert run.heldout_views == [0, 35] and scored == [(0, 2), (1, 2), (2, 2)]
    assert [v["name"] for v in run.report["views"]] == ["orbit00", "orbit35"]
    assert set(run.mean) == set(run.mean_refined) == set(METRIC_KEYS) and run.mean["iou"] > 0.7
    assert run.report["views"][0]["refine"]["steps"] == 3
    assert run.timings_s["reconstruct"] == run.twin.timings_s["total"] and run.timings_s["evaluate"] > 0
    # Without symmetries the registration error of the trained cameras is the raw one.
    assert {k: v for k, v in run.reg_refined.items() if k != "cameras"} == run.reg_raw
    assert len(run.reg_init["rotation_deg"]) == len(gt["train_c2w_object"])
    assert run.reg_init["rotation_deg_median"] < 10 and run.reg_refined["rotation_deg_median"] < 10

    written = (tmp_path / "twin" / "twin.json").stat().st_mtime_ns
    again = run_protocol(
        sample / "train", sample / "heldout", tmp_path / "library", tmp_path / "twin", heldout_views=[3], refine_steps=0, reuse=True
    )
    assert (tmp_path / "twin" / "twin.json").stat().st_mtime_ns == written and again.registration is None
    assert again.heldout_views == [3] and again.mean_refined is None and again.reg_init is None
    assert again.timings_s["reconstruct"] == run.timings_s["reconstruct"] and again.twin.num_splats == run.twin.num_splats
    with pytest.raises(FileExistsError):
        run_protocol(sample / "train", sample / "heldout", tmp_path / "library", tmp_path / "twin")
