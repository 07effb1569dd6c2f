"""The service's steps hand forward what they computed: a job decodes each image file once, masks and
registers its capture once, and a job resumed after a crash still finishes."""

from __future__ import annotations

import json
from collections import Counter
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
import torch

torch.set_num_threads(1)  # the CI box is shared; one thread avoids oversubscription stalls

import calibration.capture  # noqa: E402
from calibration.capture import FrameData, read_capture, write_capture  # noqa: E402
from deploy.commands.demo import bundled_sample_dir  # noqa: E402
from deploy.service import PipelineService  # noqa: E402
from deploy.steps import MASKS_NPZ, REGISTRATION_JSON, PipelineConfig, make_step_runner  # noqa: E402
from reconstruction import presets  # noqa: E402

SAMPLE = bundled_sample_dir()
VIEWS = (0, 2, 4, 6, 8)


@pytest.fixture
def short_preview(monkeypatch):
    original = presets.resolve_preset

    def resolve(name, stats):
        return replace(original(name, stats), iters_pose=20, iters_deform=10, iters_photo=20, dropout_anneal=10)

    monkeypatch.setattr("reconstruction.presets.resolve_preset", resolve)


def rig_capture(root: Path, *, masks: bool) -> Path:
    """Five views of the sample with its empty-rig frames, and with (`masks`) or without masks/."""
    cap = read_capture(SAMPLE / "train")
    frames = [
        FrameData(
            Path(cap.frames[i].file_path).stem,
            (cap.image(i, undistort=False) * 255).round().astype(np.uint8),
            cap.camera(i, undistorted=False),
            cap.frames[i].camera_id,
            None,
            cap.mask(i, undistort=False) if masks else None,
        )
        for i in VIEWS
    ]
    backgrounds = {
        cap.frames[i].camera_id: (cap.background(cap.frames[i].camera_id, undistort=False) * 255).round().astype(np.uint8) for i in VIEWS
    }
    meta = {k: cap.meta[k] for k in ("units", "rig_id", "calibration_id")}
    return write_capture(root, frames, backgrounds=backgrounds, meta=meta).root


@pytest.fixture
def decodes(monkeypatch):
    """Every image file decoded through the capture reader, counted by path."""
    counts: Counter = Counter()
    original = calibration.capture.read_image

    def counting(path, *args):
        counts[Path(path).resolve()] += 1
        return original(path, *args)

    monkeypatch.setattr(calibration.capture, "read_image", counting)
    return counts


def test_a_service_job_decodes_each_image_once_and_masks_and_registers_once(tmp_path, library, short_preview, decodes, monkeypatch):
    store = tmp_path / "store"
    captures = [
        rig_capture(store / "captures" / "000001-background", masks=False),
        rig_capture(store / "captures" / "000002-masks", masks=True),
    ]
    registered: list[int] = []
    masked: list[int] = []
    import reconstruction.masks
    import reconstruction.registration

    for module, name, calls in (
        (reconstruction.registration, "register_views", registered),
        (reconstruction.masks, "capture_masks", masked),
    ):
        original = getattr(module, name)
        monkeypatch.setattr(module, name, lambda *a, _o=original, _c=calls, **k: (_c.append(1), _o(*a, **k))[1])
    import PIL.Image

    import reconstruction.twin

    verified: list[Path] = []
    png_reads: list[str] = []
    original_verify, original_open = reconstruction.twin.verify_twin, PIL.Image.open
    monkeypatch.setattr(reconstruction.twin, "verify_twin", lambda root: (verified.append(root), original_verify(root))[1])
    monkeypatch.setattr(PIL.Image, "open", lambda fp, *a, **k: (png_reads.append(str(fp)), original_open(fp, *a, **k))[1])
    cfg = PipelineConfig(library=str(library), preset="preview", export_formats=("ply", "glb"), inspection_tolerance_mm=1.0)
    svc = PipelineService(store, tmp_path / "work", make_step_runner(cfg), min_free_bytes=0)
    assert svc.run_once() and svc.run_once()
    assert [j.status for j in svc.jobs.jobs()] == ["done", "done"]
    # The twin trained in the job stays in memory through inspection and export: no step loads or verifies it again,
    # and the fit is scored from the renders in memory, not from the PNGs just written.
    assert verified == [] and not any("renders" in p for p in png_reads)
    for job in svc.jobs.jobs():
        assert {Path(p).name for p in job.steps["export"]["output"].values()} == {"twin.ply", "twin.glb"}
        assert job.steps["reconstruct"]["output"]["inspection"]["status"] in ("PASS", "FAIL", "UNCERTAIN")
    for cap in captures:
        files = [(cap / f).resolve() for f in json.loads((cap / "transforms.json").read_text())["cadsplat"]["sha256"]]
        # With masks/, the empty-rig frames are not needed at all.
        expected = {p: 0 if cap.name.endswith("masks") and "background" in p.parts else 1 for p in files}
        assert {p: decodes[p] for p in files} == expected
    # One registration per job; background subtraction only for the capture without masks/.
    assert len(registered) == 2 and len(masked) == 1
    for job in svc.jobs.jobs():
        twin = json.loads((Path(job.steps["reconstruct"]["output"]["twin"]) / "twin.json").read_text())
        assert twin["choices"]["masks"]["value"] == "given" and twin["choices"]["registration"]["source"] == "given"
        reg = json.loads((svc.job_dir(job) / REGISTRATION_JSON).read_text())["registration"]
        used = twin["choices"]["registration"]["value"]["sim3_rig_to_object"]
        for key in ("scale", "rotation", "translation"):
            np.testing.assert_allclose(used[key], reg["sim3_rig_to_object"][key], atol=1e-12)
        assert reg["scale"]["metric"] and reg["scale"]["rig_metres_per_unit"] == 1.0
        assert 0.5 < job.steps["reconstruct"]["output"]["fit_iou"] <= 1.0


def test_a_job_resumed_after_register_reads_its_masks_and_registration(tmp_path, library, short_preview, decodes):
    store = tmp_path / "store"
    cap = rig_capture(store / "captures" / "000001-background", masks=False)
    cfg = PipelineConfig(library=str(library), preset="preview", export_formats=("ply",))
    first = PipelineService(store, tmp_path / "work", make_step_runner(cfg), min_free_bytes=0)
    first.scan()
    job = first.jobs.claim_next()
    work = first.job_dir(job)
    work.mkdir(parents=True)
    first.jobs.start_step(job.id, "register")
    first.jobs.finish_step(job.id, "register", make_step_runner(cfg)("register", job, work, {}))
    first.jobs.start_step(job.id, "reconstruct")  # the process dies here, mid-reconstruction
    first.jobs.close()
    assert (work / MASKS_NPZ).exists() and (work / REGISTRATION_JSON).exists()
    decodes.clear()
    again = PipelineService(store, tmp_path / "work", make_step_runner(cfg), min_free_bytes=0)
    again.jobs.requeue_interrupted()
    assert again.run_once()
    job = again.jobs.get(job.id)
    assert job.status == "done" and job.steps["register"]["output"]["model_id"] == job.steps["reconstruct"]["output"]["model_id"]
    # The new process decodes the photos once (for the colours) and neither the backgrounds nor any mask.
    assert sorted(p.name for p in decodes) == sorted(f"{Path(read_capture(cap).frames[i].file_path).name}" for i in range(len(VIEWS)))
    assert set(decodes.values()) == {1}


KNOWN_PART_RIG_TOML = """rig_id = "line"

[[cameras]]
id = "a"
driver = "pattern"

[registration]
known_part = "medium_clamp_cad"
scale_tolerance = 0.05
"""


def _spy_known_part(monkeypatch) -> list[bool]:
    """Calls of the known-part registration, each True when it was handed the photographs for the near-tie break."""
    import reconstruction.registration.entry as entry

    calls: list[bool] = []
    original = entry.known_part_register
    monkeypatch.setattr(entry, "known_part_register", lambda *a, **k: (calls.append(k["images"] is not None), original(*a, **k))[1])
    return calls


def test_a_service_job_on_a_known_part_line_registers_the_known_part(tmp_path, library, short_preview, monkeypatch):
    from deploy.steps import registration_config

    rig = tmp_path / "rig.toml"
    rig.write_text(KNOWN_PART_RIG_TOML)
    store = tmp_path / "store"
    rig_capture(store / "captures" / "000001-masks", masks=True)
    calls = _spy_known_part(monkeypatch)
    # What `service run --rig-config rig.toml` builds.
    cfg = PipelineConfig(library=str(library), preset="preview", export_formats=("ply",), registration=registration_config(rig))
    svc = PipelineService(store, tmp_path / "work", make_step_runner(cfg), min_free_bytes=0)
    assert svc.run_once()
    (job,) = svc.jobs.jobs()
    assert job.status == "done" and job.steps["register"]["output"]["method"] == "known_part"
    reg = json.loads((svc.job_dir(job) / REGISTRATION_JSON).read_text())["registration"]
    assert reg["method"] == "known_part" and reg["model_id"] == "medium_clamp_cad" and reg["config"]["known_part"] == "medium_clamp_cad"
    # The scale tolerance reaches the band of the metric capture (1 m per rig unit), and the photographs the tie-break.
    np.testing.assert_allclose(reg["scale"]["band"], [1 / 1.05, 1 / 0.95])
    assert calls == [True]


def test_a_kiosk_capture_on_a_known_part_line_registers_the_known_part(tmp_path, library, monkeypatch):
    from deploy.appliance import kiosk_pipeline_config
    from deploy.steps import register_step
    from rig.config import load_config

    rig = tmp_path / "rig.toml"
    rig.write_text(KNOWN_PART_RIG_TOML)
    cap = rig_capture(tmp_path / "store" / "captures" / "000001-masks", masks=True)
    calls = _spy_known_part(monkeypatch)
    # What `Appliance.from_config(rig.toml, ...)` builds for its pipeline.
    cfg = kiosk_pipeline_config(library, "preview", load_config(rig), rig)
    work = tmp_path / "work"
    work.mkdir()
    assert register_step(cap, work, cfg)["method"] == "known_part"
    assert json.loads((work / REGISTRATION_JSON).read_text())["registration"]["method"] == "known_part" and calls == [True]


def test_the_pipeline_config_of_a_line_is_its_rig_toml_with_the_flags_over_it(tmp_path):
    """One place reads rig.toml for the service and the kiosk: [registration], [inspection] and [limits]."""
    from deploy.steps import pipeline_config
    from rig.config import load_config

    toml = tmp_path / "rig.toml"
    toml.write_text(
        'rig_id = "line-3"\n[[cameras]]\nid = "cam00"\ndriver = "pattern"\n'
        '[registration]\nknown_part = "bracket_v3"\nscale_tolerance = 0.05\n'
        "[inspection]\ntolerance_mm = 0.5\nmax_unseen_pct = 30.0\n[limits]\nmax_image_pixels = 20000000\n"
    )
    rig = load_config(toml)
    cfg = pipeline_config("lib", "cpu", rig=rig, rig_toml=toml)
    assert cfg.registration.known_part == "bracket_v3" and cfg.registration.scale_tolerance == 0.05
    assert (cfg.inspection_tolerance_mm, cfg.inspection_max_unseen_pct, cfg.max_image_pixels) == (0.5, 30.0, 20_000_000)
    flagged = pipeline_config("lib", "cpu", rig=rig, rig_toml=toml, inspection_tolerance_mm=1.5, inspection_max_unseen_pct=None)
    assert flagged.inspection_tolerance_mm == 1.5 and flagged.inspection_max_unseen_pct == 30.0
    assert pipeline_config("lib").registration.known_part in ("", None) and pipeline_config("lib").inspection_tolerance_mm is None
