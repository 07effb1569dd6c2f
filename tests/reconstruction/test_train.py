"""Training: a short preview-sized run stays finite and improves the silhouettes; checkpoints resume;
non-finite steps are skipped; cameras very close to the object and masks with holes are handled."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

torch.set_num_threads(1)  # the CI box is shared; one thread avoids oversubscription stalls

from calibration.camera import look_at_c2w  # noqa: E402
from calibration.capture import load_views, read_capture  # noqa: E402
from calibration.so3 import axis_angle_to_matrix  # noqa: E402
from reconstruction.deformation import FieldConfig  # noqa: E402
from reconstruction.mesh_io import read_mesh_parts  # noqa: E402
from reconstruction.pipeline import FileCheckpoint  # noqa: E402
from reconstruction.presets import PAPER, PAPER_RATES, ConfigInputs, SceneStats, reasons, resolve_preset  # noqa: E402
from reconstruction.splats import init_splats  # noqa: E402
from reconstruction.train import Plateau, Views, _grads_finite, train  # noqa: E402

SAMPLE = Path(__file__).resolve().parents[2] / "sample"


def sample_scene(n_views=5, noise_deg=3.0, size=None):
    cap = read_capture(SAMPLE / "train")
    gt = json.loads((SAMPLE / "gt.json").read_text())
    idx = list(range(0, len(cap), max(1, len(cap) // n_views)))[:n_views]
    images, masks, cams = load_views(cap, idx)
    c2w = np.array(gt["train_c2w_object"])[idx]
    # A global registration error the pose correction must remove.
    rot = axis_angle_to_matrix(np.radians([noise_deg, -noise_deg, 0.5 * noise_deg]))
    c2w_noisy = c2w.copy()
    c2w_noisy[:, :3, :3] = rot @ c2w[:, :3, :3]
    c2w_noisy[:, :3, 3] = c2w[:, :3, 3] @ rot.T
    parts = read_mesh_parts(SAMPLE / "library_meshes" / "medium_clamp_cad.ply")
    return Views(images, masks, np.stack([c.K for c in cams]), c2w_noisy), parts, c2w


def tiny_preset(pose=25, deform=15, photo=20):
    stats = SceneStats(5, 320, 240, (5000,) * 5, 120.0)
    p = resolve_preset("preview", stats)
    return replace(
        p,
        num_splats=3000,
        iters_pose=pose,
        iters_deform=deform,
        iters_photo=photo,
        dropout_p0=0.5,
        dropout_anneal=10,
        field=FieldConfig(2, 32, 10, 256),
        checkpoint_every=10,
    )


def finite_model(model) -> bool:
    return all(bool(torch.isfinite(p).all()) for p in model.parameters()) and bool(torch.isfinite(model.means()).all())


def test_short_run_is_finite_and_pose_moves_towards_truth(tmp_path):
    views, parts, c2w_true = sample_scene()
    splats = init_splats(parts.vertices, parts.faces, 3000, sh_degree=0, seed=0)
    preset = tiny_preset(pose=40)
    stages = []
    res = train(views, splats, preset, progress=lambda s, i, c, l: stages.append((s, l)), checkpoint=FileCheckpoint(tmp_path / "twin"))
    assert [s for s, _ in stages][:1] == ["pose"] and stages[-1][0] == "photo"
    assert all(np.isfinite(l) for _, l in stages)
    assert res.skipped_steps == 0 and finite_model(res.model)
    assert res.iterations == {"pose": 40, "deform": 15, "photo": 20}
    # The pose correction removed part of the injected 4.6-degree rotation error.
    with torch.no_grad():
        refined = res.model.pose(torch.tensor(views.c2w)).numpy()
    from calibration.so3 import geodesic_angle_deg

    before = np.median(geodesic_angle_deg(views.c2w[:, :3, :3], c2w_true[:, :3, :3]))
    after = np.median(geodesic_angle_deg(refined[:, :3, :3], c2w_true[:, :3, :3]))
    assert after < 0.8 * before, (before, after)
    # The Stage-II losses are all recorded (the preview preset saturates alpha inside the mask).
    assert set(res.losses["photo"]) >= {"rgb", "mask", "sh", "fill"}
    # pose_scale=False: the registration's scale is kept exactly, rotation and translation still learn.
    assert not preset.pose_scale and float(res.model.pose.rig_log_scale) == 0.0


def test_the_pose_stage_evaluates_the_frozen_splats_once(monkeypatch):
    """Only the pose learns in the first stage: the field and the splats' activations are computed once for the
    stage, not once per iteration, and the pose still moves."""
    from reconstruction.deformation import DeformationField

    views, parts, _ = sample_scene(n_views=3)
    splats = init_splats(parts.vertices, parts.faces, 1000, sh_degree=0, seed=0)
    calls = []
    forward = DeformationField.forward
    monkeypatch.setattr(DeformationField, "forward", lambda self: calls.append(1) or forward(self))
    seen = []
    res = train(
        views,
        splats,
        tiny_preset(pose=12, deform=0, photo=0),
        progress=lambda stage, it, cap, loss: seen.append(len(calls)) if stage == "pose" else None,
    )
    assert res.iterations["pose"] == 12
    assert len(seen) == 12 and seen[0] == seen[-1] <= 2  # the consistency weights' look, and the stage's one
    assert float(res.model.pose.rig_t.detach().abs().sum()) > 0


class _Stop(Exception):
    pass


def _interrupted_run(ck: FileCheckpoint):
    """A 3-view run stopped after Stage I's deformation iteration 10, which wrote `ck`: (views, splats, preset)."""
    views, parts, _ = sample_scene(n_views=3)
    splats = init_splats(parts.vertices, parts.faces, 2000, sh_degree=0, seed=0)
    preset = tiny_preset(pose=10, deform=10, photo=10)

    def interrupt(stage, it, cap, loss):
        if stage == "deform" and it == 10:
            raise _Stop

    with pytest.raises(_Stop):
        train(views, splats, preset, checkpoint=ck, progress=interrupt)
    assert ck.path.exists()
    return views, splats, preset


def test_checkpoint_resumes_where_it_stopped(tmp_path):
    ck = FileCheckpoint(tmp_path / "twin")
    views, splats, preset = _interrupted_run(ck)
    seen = []
    res = train(views, splats, preset, checkpoint=ck, progress=lambda s, i, c, l: seen.append((s, i)))
    # Resumed from the checkpoint written at deform iteration 10: only Stage II is left.
    assert seen[0] == ("photo", 1) and len(seen) == 10
    assert res.iterations["pose"] == 10


def test_checkpoint_of_other_splats_is_not_resumed(tmp_path):
    # The same count in another order (an engine that lays splats out otherwise): every per-splat row of the
    # checkpoint would land on the wrong splat, so training starts over.
    ck = FileCheckpoint(tmp_path / "twin")
    views, splats, preset = _interrupted_run(ck)
    order = np.random.default_rng(0).permutation(len(splats))
    shuffled = replace(
        splats,
        gaussians=splats.gaussians.subset(order),
        normals=splats.normals[order],
        face_index=splats.face_index[order],
        barycentrics=splats.barycentrics[order],
        part_label=splats.part_label[order],
    )
    seen = []
    train(views, shuffled, preset, checkpoint=ck, progress=lambda s, i, c, l: seen.append((s, i)))
    assert seen[0] == ("pose", 1)


def test_nonfinite_steps_are_skipped_not_applied():
    views, parts, _ = sample_scene(n_views=2)
    splats = init_splats(parts.vertices, parts.faces, 1000, sh_degree=0, seed=0)
    views.images[:, 100:140, 140:180] = np.nan  # a corrupt patch poisons every Stage-II loss
    res = train(views, splats, tiny_preset(pose=5, deform=5, photo=10))
    assert res.skipped_steps > 0
    assert finite_model(res.model)


def test_cameras_very_close_and_masks_with_holes():
    views, parts, _ = sample_scene(n_views=3)
    centre = 0.5 * (parts.vertices.min(0) + parts.vertices.max(0))
    # Cameras 2 cm from the centre of a ~20 cm clamp: inside or grazing the object, near plane crossed.
    views.c2w = np.stack([look_at_c2w(centre + d, centre) for d in ([0.02, 0, 0.005], [0, 0.02, 0.005], [-0.02, 0, 0.005])])
    views.masks[:, ::4, ::4] = False  # holes in every mask
    splats = init_splats(parts.vertices, parts.faces, 1500, sh_degree=1, seed=0)
    res = train(views, splats, tiny_preset(pose=8, deform=8, photo=8))
    assert finite_model(res.model)
    for stage in ("pose", "deform", "photo"):
        assert all(np.isfinite(v) for v in res.losses[stage].values())


def test_plateau_detector():
    p = Plateau(window=10, rel_tol=0.01)
    assert not any(p.update(1.0 / (i + 1)) for i in range(40))  # still falling fast
    q = Plateau(window=10, rel_tol=0.01)
    flags = [q.update(0.5) for _ in range(20)]
    assert flags[-1] and not any(flags[:-1])


def test_cpu_preset_sizes_from_the_scene():
    small = SceneStats(3, 320, 240, (2000,) * 3, 20.0)
    big = SceneStats(12, 640, 480, (60000,) * 12, 300.0)
    ps = resolve_preset("cpu", small)
    pb = resolve_preset("cpu", big)
    cb = reasons(pb, ConfigInputs(big))
    assert ps.num_splats < pb.num_splats <= 15_000
    assert ps.sh_degree == 0 and pb.sh_degree == 2
    assert pb.image_scale == 0.6 and ps.image_scale == 1.0
    assert pb.views_per_iter == 0 and pb.init_opacity == 0.9
    assert all("why" in c and "value" in c for c in cb.values())
    paper = resolve_preset("paper", big)
    assert (paper.num_splats, paper.sh_degree, paper.iters_pose, paper.iters_deform, paper.iters_photo) == (600_000, 3, 3000, 3000, 24_000)
    assert paper.lr == PAPER_RATES and paper.lr.at("deformation", "photo") == 1.6e-5 and paper.lr.at("pose", "deform") == 5e-4
    with pytest.raises(ValueError, match="unknown preset"):
        resolve_preset("fast", big)


def test_one_random_view_per_iteration_as_the_paper():
    views, parts, _ = sample_scene(n_views=3)
    splats = init_splats(parts.vertices, parts.faces, 1000, sh_degree=0, seed=0)
    res = train(views, splats, replace(tiny_preset(pose=6, deform=4, photo=6), views_per_iter=1))
    assert res.iterations == {"pose": 6, "deform": 4, "photo": 6} and finite_model(res.model)


def test_stage_without_iterations_reports_null_loss_not_nan():
    """An ablation that skips a stage (no mask warm-up) still yields strict-JSON losses."""
    import json

    views, parts, _ = sample_scene(n_views=2)
    splats = init_splats(parts.vertices, parts.faces, 1000, sh_degree=0, seed=0)
    res = train(views, splats, tiny_preset(pose=0, deform=0, photo=4))
    assert res.losses["pose"]["total_last_window"] is None and res.losses["deform"]["total_last_window"] is None
    json.dumps(res.losses, allow_nan=False)
    assert finite_model(res.model)


def test_splats_move_along_their_normals_and_the_mesh_follows_them():
    from reconstruction.losses import neighbour_graph, neighbour_smoothness
    from reconstruction.splats import knn_indices
    from reconstruction.train import SplatModel

    _, parts, _ = sample_scene()
    splats = init_splats(parts.vertices, parts.faces, 2000, sh_degree=0, seed=0)
    model = SplatModel(splats, replace(tiny_preset(), field=FieldConfig(2, 16, 4, 128), pose_scale=False), 3, "global")
    with torch.no_grad():
        still = model.means().clone()
        model.displacement.fill_(0.01)  # a hundredth of the object's radius, outwards along every normal
        moved = model.means()
    step = float(model.field.radius) * 0.01
    # An outward move is not a rigid motion: it survives the projection, less the small rigid part that the splats'
    # uneven spacing gives it, along the normals.
    along = np.einsum("nd,nd->n", (moved - still).numpy(), splats.normals)
    np.testing.assert_allclose((moved - still).numpy(), along[:, None] * splats.normals, atol=1e-7)
    assert abs(along.mean() - step) < 0.02 * step and np.abs(along - step).max() < 0.25 * step
    # A point on a splat takes that splat's move (and the field's offset there).
    np.testing.assert_allclose(model.offsets_at(splats.means[:50]), (moved - model.means_canonical).numpy()[:50], atol=1e-6)
    # The smoothness of the moves costs nothing for a uniform move and pulls an outlier back to its neighbours.
    graph = neighbour_graph(knn_indices(splats.means, 8))
    assert float(neighbour_smoothness(model.normal_moves().detach(), graph)) < 1e-6
    with torch.no_grad():
        model.displacement[7] = 0.05
    loss = neighbour_smoothness(model.normal_moves(), graph)
    loss.backward()
    assert float(loss.detach()) > 0 and model.displacement.grad[7] > 0 and model.displacement.grad.abs().argmax() == 7


def test_scales_grow_to_at_most_the_preset_multiple_of_their_start():
    from reconstruction.train import SplatModel

    _, parts, _ = sample_scene()
    splats = init_splats(parts.vertices, parts.faces, 2000, sh_degree=0, seed=0)
    preset = replace(tiny_preset(), field=FieldConfig(2, 16, 4, 128))
    assert preset.max_scale_growth == 2.0
    model = SplatModel(splats, preset, 3, "global")
    start = model.log_scales.detach().clone()
    with torch.no_grad():
        model.log_scales.add_(torch.linspace(-1.0, 3.0, len(start))[:, None])
        model.clamp_()
    limit = start.amax(1, keepdim=True) + np.log(2.0)
    assert bool((model.log_scales <= limit + 1e-6).all())
    # Shrinking and growth below the bound are untouched; only the axes past it are cut, to it.
    grown = start + torch.linspace(-1.0, 3.0, len(start))[:, None]
    np.testing.assert_allclose(model.log_scales.detach().numpy(), torch.minimum(grown, limit).numpy(), atol=1e-6)
    # Without a bound (the paper) only the object-relative range applies.
    free = SplatModel(splats, replace(preset, max_scale_growth=None), 3, "global")
    with torch.no_grad():
        free.log_scales.add_(1.0)
        free.clamp_()
    assert bool((free.log_scales > start.amax(1, keepdim=True) + np.log(2.0)).any())


def test_a_disk_keeps_its_thickness_when_the_preset_bounds_its_normal_axis():
    from reconstruction.train import SplatModel

    _, parts, _ = sample_scene()
    splats = init_splats(parts.vertices, parts.faces, 2000, sh_degree=0, seed=0)
    preset = replace(tiny_preset(), field=FieldConfig(2, 16, 4, 128), max_normal_growth=1.0)
    model = SplatModel(splats, preset, 3, "global")
    start = model.log_scales.detach().clone()
    with torch.no_grad():
        model.log_scales.add_(torch.tensor([0.2, -0.3, 0.5]))
        model.clamp_()
    got = model.log_scales.detach()
    # The normal axis (local z) may thin but not thicken; the tangent axes grow freely below the 2x bound.
    torch.testing.assert_close(got[:, 2], start[:, 2])
    torch.testing.assert_close(got[:, :2], start[:, :2] + torch.tensor([0.2, -0.3]))
    with torch.no_grad():
        model.log_scales.copy_(start - 0.4)
        model.clamp_()
    torch.testing.assert_close(model.log_scales.detach(), start - 0.4)
    # Without the scale bound the normal axis is still held, and only it.
    free = SplatModel(splats, replace(preset, max_scale_growth=None), 3, "global")
    with torch.no_grad():
        free.log_scales.add_(3.0)
        free.clamp_()
    torch.testing.assert_close(free.log_scales.detach()[:, 2], start[:, 2])
    assert bool((free.log_scales.detach()[:, :2] > start.amax(1, keepdim=True) + np.log(2.0)).all())


def test_normal_moves_that_a_pose_could_make_are_projected_out():
    """A translation or a rotation of the whole part written as moves along the normals is the pose's to make:
    left in, the splats and the cameras drift together (per-camera rig scenes: screwdriver held-out IoU 0.852)."""
    from reconstruction.train import SplatModel

    _, parts, _ = sample_scene()
    splats = init_splats(parts.vertices, parts.faces, 2000, sh_degree=0, seed=0)
    for pose_scale in (False, True):
        model = SplatModel(splats, replace(tiny_preset(), field=FieldConfig(2, 16, 4, 128), pose_scale=pose_scale), 3, "global")
        radius, center = float(model.field.radius), model.field.center.double().numpy()
        x = splats.means - center
        rigid = np.array([0.003, -0.002, 0.001]) + np.cross([0.01, 0.02, -0.01], x)  # infinitesimal: t + w x (x - c)
        moves = [rigid] + ([0.02 * x] if pose_scale else [])
        for move in moves:
            with torch.no_grad():
                model.displacement.copy_(torch.tensor(np.einsum("nd,nd->n", move, splats.normals) / radius))
                assert float(model.displacement_offsets().abs().max()) < 1e-3 * float(model.displacement.abs().max()) * radius


def test_views_mark_the_pixels_each_photo_has():
    """On a shared canvas each photo's own pixels are valid at every scale; photos that fill it need no mark."""
    images, masks = np.zeros((2, 40, 40, 3), np.float32), np.zeros((2, 40, 40), bool)
    ks, c2w = np.tile(np.eye(3), (2, 1, 1)), np.tile(np.eye(4), (2, 1, 1))
    assert Views(images, masks, ks, c2w, np.array([(40, 40), (40, 40)])).resized(0.5).valid is None
    valid = Views(images, masks, ks, c2w, np.array([(40, 30), (30, 40)])).resized(0.5).valid
    assert valid.shape == (2, 20, 20)
    assert valid[0, :15].all() and not valid[0, 15:].any() and valid[1, :, :15].all() and not valid[1, :, 15:].any()


def test_gradient_finiteness_check():
    params = [torch.nn.Parameter(torch.zeros(1000)), torch.nn.Parameter(torch.zeros(3)), torch.nn.Parameter(torch.zeros(2))]
    params[0].grad = torch.full((1000,), 3e38)  # finite, though its float32 sum would overflow
    params[1].grad = torch.tensor([1.0, -2.0, 0.5])
    assert _grads_finite(params)  # the third has no gradient: frozen this stage
    for bad in (float("nan"), float("inf"), float("-inf")):
        params[1].grad[1] = bad
        assert not _grads_finite(params)
    params[1].grad = torch.tensor([float("inf"), float("-inf"), 0.0])  # cancelling infinities sum to nan
    assert not _grads_finite(params)
    assert _grads_finite([torch.nn.Parameter(torch.zeros(1))])


def test_view_dependent_colour_decays_towards_none_only_when_the_preset_says_so():
    """`shn_decay` pulls the higher SH bands towards zero in Stage II (decoupled, per unit of their rate): a colour
    that the views do not show to change with direction is drawn without one."""
    views, parts, _ = sample_scene()
    splats = init_splats(parts.vertices, parts.faces, 1500, sh_degree=1, seed=0)
    base = tiny_preset(pose=2, deform=2, photo=8)
    plain = train(views, splats, base).model
    decayed = train(views, splats, replace(base, shn_decay=50.0)).model

    def norm(m):
        return float(m.shN.detach().norm())

    assert norm(plain) > 0 and norm(decayed) < 0.5 * norm(plain)
    assert bool(torch.isfinite(decayed.sh0).all())
    stats = SceneStats(10, 320, 240, (5000,) * 10, 120.0)
    assert resolve_preset("cpu", stats).shn_decay == 1.0 and resolve_preset("preview", stats).shn_decay == 0.0
    assert PAPER.shn_decay == 0.0


def test_training_leaves_torch_dynamo_unimported():
    # torch.optim's classes import torch._dynamo at their first call (1.6 s a process on a slow machine); the
    # training's Adam must not (see reconstruction.adam).
    import subprocess
    import sys

    code = (
        "import sys\n"
        "from tests.reconstruction.test_train import init_splats, sample_scene, tiny_preset, train\n"
        "views, parts, _ = sample_scene(n_views=3)\n"
        "train(views, init_splats(parts.vertices, parts.faces, 500, sh_degree=0, seed=0), tiny_preset(pose=2, deform=2, photo=2))\n"
        "print('torch._dynamo' in sys.modules)\n"
    )
    out = subprocess.run(
        [sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=Path(__file__).resolve().parents[2]
    ).stdout.split()
    assert out[-1] == "False"
