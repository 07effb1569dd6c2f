"""The configuration as data: presets sized from the scene, every input of the resolution (provenance,
init, ablations, overrides), the learning-rate table, and the reasons generated from the result."""

from __future__ import annotations

import json
from dataclasses import replace

import pytest

from reconstruction.presets import (
    ABLATIONS,
    PAPER,
    ConfigInputs,
    LearningRates,
    Preset,
    SceneStats,
    StageRates,
    ablation_reason,
    apply_ablations,
    reasons,
    resolve_config,
    resolve_preset,
)

STATS = SceneStats(num_views=9, width=320, height=240, foreground_px=(6000,) * 9, coverage_deg=150.0)


def resolve(name, stats, **inputs):
    """(configuration, reasons) as a reconstruction resolves and records them."""
    given = ConfigInputs(stats, **inputs)
    cfg = resolve_config(name, given)
    return cfg, reasons(cfg, given)


def test_each_ablation_switches_off_only_its_ingredient():
    cpu = resolve_preset("cpu", STATS)
    total = cpu.iters_pose + cpu.iters_deform + cpu.iters_photo
    p = apply_ablations(cpu, ["no-mask-warmup"])
    assert (p.iters_pose, p.iters_deform, p.iters_photo) == (0, 0, total)
    p = apply_ablations(cpu, ["no-deformation"])
    assert p.lr.deformation == StageRates.constant(0.0) and p.iters_deform == 0 and p.lr.pose == cpu.lr.pose
    p = apply_ablations(cpu, ["no-pose"])
    assert p.lr.pose == p.lr.pose_camera == StageRates.constant(0.0) and p.iters_pose == 0
    assert p.lr.deformation == cpu.lr.deformation
    p = apply_ablations(PAPER, ["no-sh-smoothness", "no-dropout"])
    assert p.lambda_sh == 0.0 and p.dropout_p0 == 0.0 and p.num_splats == PAPER.num_splats
    cfg, why = resolve("cpu", STATS, ablations=("no-mask-warmup",))
    assert cfg.iters_photo == total and why["ablations"]["value"] == ["no-mask-warmup"]


def test_an_ablation_that_changes_nothing_says_so():
    cpu = resolve_preset("cpu", STATS)  # the cpu preset already trains without dropout
    assert apply_ablations(cpu, ["no-dropout"]) == cpu and "already off" in ablation_reason(cpu, ["no-dropout"])


def test_unknown_ablation_is_one_sentence():
    with pytest.raises(ValueError, match="unknown ablation 'no-colour'; choose from"):
        apply_ablations(PAPER, ["no-colour"])


def test_the_cli_lists_every_ablation():
    from deploy.commands.reconstruct import ABLATION_NAMES

    assert set(ABLATION_NAMES) == set(ABLATIONS)


def test_per_camera_residuals_learn_finely_through_stage_two_unless_the_poses_are_rough():
    cpu, _ = resolve("cpu", STATS)
    rates = cpu.lr.pose_camera
    assert rates.pose == 0.0 and 0 < rates.deform == rates.photo <= cpu.lr.pose.deform / 50
    assert cpu.lr.pose.photo == 0.0  # the rig's Sim(3) stays where Stage I left it
    assert ConfigInputs(STATS, pose_source="Phone").rough_poses and not ConfigInputs(STATS, pose_source="optimized").rough_poses
    for inputs in ({}, {"calibration_id": "c", "calibration_error_px": 0.6}):
        assert resolve("cpu", STATS, **inputs)[0].lr == resolve_preset("cpu", STATS).lr
    for inputs in ({"pose_source": "rough"}, {"calibration_id": "c", "calibration_error_px": 3.9}):
        rough, why = resolve("cpu", STATS, **inputs)
        assert rough.pose_mode == "per_camera" and "per-camera residuals at the rig's rate" in why["learning_rates"]["why"]
        assert rough.lr.pose_camera == StageRates(0.0, cpu.lr.pose.deform, 0.0)


def test_the_pose_mode_is_an_input_of_the_resolution():
    assert resolve("cpu", STATS, calibration_id="cal-7")[0].pose_mode == "global"
    assert resolve("cpu", STATS, calibration_id="cal-7", calibration_error_px=3.9)[0].pose_mode == "per_camera"
    assert resolve("cpu", STATS)[0].pose_mode == "per_camera"  # nothing says how good the poses are
    cfg, why = resolve("cpu", STATS, pose_source="rough", pose_mode="global")
    assert cfg.pose_mode == "global" and why["pose_mode"]["why"] == "set by the caller"
    with pytest.raises(ValueError, match="pose mode must be one of"):
        resolve("cpu", STATS, pose_mode="bogus")


def test_init_metric_scale_and_overrides_are_inputs_too():
    cad, _ = resolve("cpu", STATS)
    sphere, why = resolve("cpu", STATS, init="sphere")
    assert sphere.iters_deform == 4 * cad.iters_deform and "carve" in why["iteration_caps"]["why"]
    assert cad.field.projection_keeps_scale and not resolve("cpu", STATS, metric=False)[0].field.projection_keeps_scale
    over, why = resolve(
        "cpu", STATS, overrides={"iters_photo": 7, "field": {"num_anchors": 64}, "lr": {"sh0": 0.5, "pose": {"photo": 1e-4}}}
    )
    assert over.iters_photo == 7 and over.field.num_anchors == 64 and over.field.width == cad.field.width
    assert over.lr.sh0 == StageRates.constant(0.5) and over.lr.pose == StageRates(cad.lr.pose.pose, cad.lr.pose.deform, 1e-4)
    assert why["overrides"]["value"]["iters_photo"] == 7
    with pytest.raises(ValueError, match="unknown preset field 'iters'"):
        resolve("cpu", STATS, overrides={"iters": 3})
    with pytest.raises(ValueError, match="unknown learning-rate group 'colour'"):
        resolve("cpu", STATS, overrides={"lr": {"colour": 1.0}})


def test_the_resolved_configuration_round_trips_and_its_reasons_are_read_from_it():
    cfg, why = resolve("cpu", STATS, calibration_id="cal-7")
    doc = json.loads(json.dumps(cfg.to_dict()))
    assert Preset.from_dict(doc) == cfg and LearningRates.from_dict(doc["lr"]) == cfg.lr
    json.dumps(why, allow_nan=False)
    # Every reason's value is the configuration's own: change the configuration and the reason follows.
    assert why["num_splats"]["value"] == cfg.num_splats and why["eps2d"]["value"] == cfg.eps2d
    other = replace(cfg, num_splats=1234, eps2d=0.2)
    assert (
        reasons(other, ConfigInputs(STATS))["num_splats"]["value"] == 1234 and reasons(other, ConfigInputs(STATS))["eps2d"]["value"] == 0.2
    )
    with pytest.raises(ValueError, match="does not know"):
        Preset.from_dict({**doc, "colour": 1})


def test_preview_weighs_ssim_more_and_says_why():
    cpu, cpu_choices = resolve("cpu", STATS)
    preview, preview_choices = resolve("preview", STATS)
    assert cpu.lambda_dssim == PAPER.lambda_dssim == 0.2 and preview.lambda_dssim == 0.6
    assert cpu_choices["lambda_dssim"]["value"] == 0.2 and "preview" in preview_choices["lambda_dssim"]["why"]


def test_the_field_gets_fewer_frequency_bands_when_few_views_constrain_it():
    from dataclasses import replace

    three = replace(STATS, num_views=3, foreground_px=(6000,) * 3)
    cpu9, _ = resolve("cpu", STATS)
    cpu3, choices3 = resolve("cpu", three)
    assert cpu9.field.bands == PAPER.field.bands == 10
    assert cpu3.field.bands == 6 and "3 views leave finer ones unconstrained" in choices3["deformation"]["why"]
    assert resolve("cpu", replace(STATS, num_views=5, foreground_px=(6000,) * 5))[0].field.bands == 10
    assert resolve("preview", three)[0].field.bands == 10


def test_the_cpu_preset_dilates_splats_by_about_a_pixel_footprint_and_says_why():
    from reconstruction.gaussians import EPS2D_3DGS

    cpu, cpu_choices = resolve("cpu", STATS)
    preview, preview_choices = resolve("preview", STATS)
    assert cpu.eps2d == cpu_choices["eps2d"]["value"] == 0.1 and "footprint" in cpu_choices["eps2d"]["why"]
    assert PAPER.eps2d == preview.eps2d == preview_choices["eps2d"]["value"] == EPS2D_3DGS == 0.3
    assert "preview" in preview_choices["eps2d"]["why"]


def test_stage_two_runs_longer_only_with_a_full_rig_and_scales_are_bounded():
    from dataclasses import replace

    full, full_choices = resolve("cpu", STATS)
    five, five_choices = resolve("cpu", replace(STATS, num_views=5, foreground_px=(6000,) * 5))
    assert full.iters_photo == 200 and "8 or more views" in full_choices["iteration_caps"]["why"]
    assert five.iters_photo == 150 and "fewer than 8 views" in five_choices["iteration_caps"]["why"]
    for views, photo in ((7, 150), (8, 200)):
        assert resolve("cpu", replace(STATS, num_views=views, foreground_px=(6000,) * views))[0].iters_photo == photo
    preview = resolve("preview", STATS)[0]
    assert preview.iters_photo == 50
    assert full.max_scale_growth == full_choices["max_scale_growth"]["value"] == preview.max_scale_growth == 2.0
    assert PAPER.max_scale_growth is None


def test_disks_keep_their_thickness_only_below_five_views():
    from dataclasses import replace

    three, choices = resolve("cpu", replace(STATS, num_views=3, foreground_px=(6000,) * 3))
    assert three.max_normal_growth == choices["max_normal_growth"]["value"] == 1.0
    assert "edge-on" in choices["max_normal_growth"]["why"]
    five, five_choices = resolve("cpu", replace(STATS, num_views=5, foreground_px=(6000,) * 5))
    assert five.max_normal_growth is None and five_choices["max_normal_growth"]["value"] is None
    assert resolve("cpu", STATS)[0].max_normal_growth is None
    assert resolve("preview", replace(STATS, num_views=3, foreground_px=(6000,) * 3))[0].max_normal_growth is None
    assert PAPER.max_normal_growth is None
