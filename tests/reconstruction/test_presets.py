"""The paper's ablation switches on a resolved preset."""

from __future__ import annotations

import pytest

from reconstruction.presets import ABLATIONS, PAPER, SceneStats, apply_ablations, resolve_preset

STATS = SceneStats(num_views=9, width=320, height=240, foreground_px=(6000,) * 9, coverage_deg=150.0)


def test_each_ablation_switches_off_only_its_ingredient():
    cpu, _ = resolve_preset("cpu", STATS)
    total = cpu.iters_pose + cpu.iters_deform + cpu.iters_photo
    p, choice = apply_ablations(cpu, ["no-mask-warmup"])
    assert (p.iters_pose, p.iters_deform, p.iters_photo) == (0, 0, total) and choice["value"] == ["no-mask-warmup"]
    p, _ = apply_ablations(cpu, ["no-deformation"])
    assert p.lr["deformation"] == 0.0 and p.iters_deform == 0 and p.lr["pose"] == cpu.lr["pose"]
    p, _ = apply_ablations(cpu, ["no-pose"])
    assert all(p.lr[k] == 0.0 for k in ("pose", "pose_deform", "pose_photo", "pose_camera")) and p.iters_pose == 0
    assert p.lr["deformation"] == cpu.lr["deformation"]
    p, _ = apply_ablations(PAPER, ["no-sh-smoothness", "no-dropout"])
    assert p.lambda_sh == 0.0 and p.dropout_p0 == 0.0 and p.num_splats == PAPER.num_splats


def test_an_ablation_that_changes_nothing_says_so():
    cpu, _ = resolve_preset("cpu", STATS)  # the cpu preset already trains without dropout
    p, choice = apply_ablations(cpu, ["no-dropout"])
    assert p == cpu and "already off" in choice["why"]


def test_unknown_ablation_is_one_sentence():
    with pytest.raises(ValueError, match="unknown ablation 'no-colour'; choose from"):
        apply_ablations(PAPER, ["no-colour"])


def test_the_cli_lists_every_ablation():
    from deploy.commands.reconstruct import ABLATION_NAMES

    assert set(ABLATION_NAMES) == set(ABLATIONS)


def test_per_camera_residuals_learn_finely_through_stage_two_unless_the_poses_are_rough():
    from reconstruction.pose_correction import residual_rates, rough_poses
    from reconstruction.train import pose_stage_lr

    cpu, _ = resolve_preset("cpu", STATS)
    rates = {stage: pose_stage_lr(cpu.lr, "pose_camera", stage) for stage in ("pose", "deform", "photo")}
    assert rates["pose"] == 0.0 and 0 < rates["deform"] == rates["photo"] <= cpu.lr["pose"] / 50
    assert pose_stage_lr(cpu.lr, "pose", "photo") == 0.0  # the rig's Sim(3) stays where Stage I left it
    assert rough_poses({"pose_source": "Phone"}) and not rough_poses({"pose_source": "optimized"}) and not rough_poses({})
    assert residual_rates(cpu.lr, {}, None) == (cpu.lr, False)
    assert residual_rates(cpu.lr, {"calibration_id": "c"}, 0.6) == (cpu.lr, False)
    for meta, px in (({"pose_source": "rough"}, None), ({"calibration_id": "c"}, 3.9)):
        rough, changed = residual_rates(cpu.lr, meta, px)
        assert changed and pose_stage_lr(rough, "pose_camera", "deform") == cpu.lr["pose_deform"]
        assert pose_stage_lr(rough, "pose_camera", "photo") == 0.0


def test_preview_weighs_ssim_more_and_says_why():
    cpu, cpu_choices = resolve_preset("cpu", STATS)
    preview, preview_choices = resolve_preset("preview", STATS)
    assert cpu.lambda_dssim == PAPER.lambda_dssim == 0.2 and preview.lambda_dssim == 0.6
    assert cpu_choices["lambda_dssim"]["value"] == 0.2 and "preview" in preview_choices["lambda_dssim"]["why"]


def test_the_field_gets_fewer_frequency_bands_when_few_views_constrain_it():
    from dataclasses import replace

    three = replace(STATS, num_views=3, foreground_px=(6000,) * 3)
    cpu9, _ = resolve_preset("cpu", STATS)
    cpu3, choices3 = resolve_preset("cpu", three)
    assert cpu9.field.bands == PAPER.field.bands == 10
    assert cpu3.field.bands == 6 and "3 views leave finer ones unconstrained" in choices3["deformation"]["why"]
    assert resolve_preset("cpu", replace(STATS, num_views=5, foreground_px=(6000,) * 5))[0].field.bands == 10
    assert resolve_preset("preview", three)[0].field.bands == 10


def test_the_cpu_preset_dilates_splats_by_about_a_pixel_footprint_and_says_why():
    from reconstruction.gaussians import EPS2D_3DGS

    cpu, cpu_choices = resolve_preset("cpu", STATS)
    preview, preview_choices = resolve_preset("preview", STATS)
    assert cpu.eps2d == cpu_choices["eps2d"]["value"] == 0.1 and "footprint" in cpu_choices["eps2d"]["why"]
    assert PAPER.eps2d == preview.eps2d == preview_choices["eps2d"]["value"] == EPS2D_3DGS == 0.3
    assert "preview" in preview_choices["eps2d"]["why"]


def test_stage_two_runs_longer_only_with_a_full_rig_and_scales_are_bounded():
    from dataclasses import replace

    full, full_choices = resolve_preset("cpu", STATS)
    five, five_choices = resolve_preset("cpu", replace(STATS, num_views=5, foreground_px=(6000,) * 5))
    assert full.iters_photo == 200 and "8 or more views" in full_choices["iteration_caps"]["why"]
    assert five.iters_photo == 150 and "fewer than 8 views" in five_choices["iteration_caps"]["why"]
    for views, photo in ((7, 150), (8, 200)):
        assert resolve_preset("cpu", replace(STATS, num_views=views, foreground_px=(6000,) * views))[0].iters_photo == photo
    preview = resolve_preset("preview", STATS)[0]
    assert preview.iters_photo == 50
    assert full.max_scale_growth == full_choices["max_scale_growth"]["value"] == preview.max_scale_growth == 2.0
    assert PAPER.max_scale_growth is None


def test_disks_keep_their_thickness_only_below_five_views():
    from dataclasses import replace

    three, choices = resolve_preset("cpu", replace(STATS, num_views=3, foreground_px=(6000,) * 3))
    assert three.max_normal_growth == choices["max_normal_growth"]["value"] == 1.0
    assert "edge-on" in choices["max_normal_growth"]["why"]
    five, five_choices = resolve_preset("cpu", replace(STATS, num_views=5, foreground_px=(6000,) * 5))
    assert five.max_normal_growth is None and five_choices["max_normal_growth"]["value"] is None
    assert resolve_preset("cpu", STATS)[0].max_normal_growth is None
    assert resolve_preset("preview", replace(STATS, num_views=3, foreground_px=(6000,) * 3))[0].max_normal_growth is None
    assert PAPER.max_normal_growth is None
