"""Relative calibration without a board: structure from motion with pycolmap (the paper's COLMAP step).

Known intrinsics are held fixed (COLMAP's pixel convention is ours: pixel centres at +0.5), only
poses are solved. A rig calibration must not be half-right, so anything short of every image
registered with a small reprojection error raises SfMError naming what failed. The result is
aligned to reference poses (the rig's current calibration) by a Sim(3) fitted with Umeyama on
camera centres; without a reference the first camera is the frame and the scale is arbitrary.
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from calibration.camera import Camera, invert_rigid
from calibration.fileio import encode_png
from calibration.sim3 import DegenerateError, Sim3, umeyama
from calibration.so3 import project_to_so3


class SfMError(ValueError):
    """SfM could not produce a trustworthy rig; the message says which images or which figure."""


@dataclass(frozen=True)
class SfMResult:
    """`cameras` with c2w in the reference (rig) frame, or the first camera's frame when no reference."""

    cameras: dict[str, Camera]
    registered: int
    total: int
    reprojection_px: float
    points: int
    alignment: Sim3 | None
    alignment_rms_m: float | None


def align_to_reference(c2w: dict[str, np.ndarray], reference: dict[str, np.ndarray]) -> Sim3:
    """Sim(3) taking poses `c2w` onto `reference` (same camera names): scale from the centres
    (Umeyama), rotation from the cameras' orientations (a rig's centres often lie nearly on one arc,
    which pins the rotation poorly), translation from the centres given both.
    """
    names = list(c2w)
    src = np.stack([c2w[n][:3, 3] for n in names])
    dst = np.stack([reference[n][:3, 3] for n in names])
    scale = umeyama(src, dst).scale
    rot = project_to_so3(np.sum([reference[n][:3, :3] @ c2w[n][:3, :3].T for n in names], 0))
    t = (dst - scale * src @ rot.T).mean(0)
    return Sim3(scale, rot, t)


def _mapping_options(pycolmap, num_images: int):
    opts = pycolmap.IncrementalPipelineOptions()
    # Known intrinsics: never refine focal length, principal point or distortion.
    opts.ba_refine_focal_length = False
    opts.ba_refine_principal_point = False
    opts.ba_refine_extra_params = False
    opts.mapper.abs_pose_refine_focal_length = False
    opts.mapper.abs_pose_refine_extra_params = False
    opts.min_model_size = min(3, num_images)
    opts.multiple_models = False
    opts.mapper.init_min_num_inliers = 50
    opts.num_threads = 2
    opts.random_seed = 0
    return opts


def sfm_calibrate(
    images: dict[str, np.ndarray],
    cameras: dict[str, Camera],
    *,
    reference: dict[str, np.ndarray] | None = None,
    max_reprojection_px: float = 1.0,
    max_features: int = 4000,
) -> SfMResult:
    """Poses of pinhole `cameras` (intrinsics fixed) from `images` (one per camera, undistorted).

    reference[camera] = c2w [4, 4] to align to (at least 3 cameras with non-collinear centres).
    """
    import pycolmap

    names = list(images)
    if len(names) < 2:
        raise SfMError("SfM needs at least two images")
    with tempfile.TemporaryDirectory(prefix="cadsplat-sfm-") as tmp:
        root = Path(tmp)
        img_dir = root / "images"
        img_dir.mkdir()
        db = root / "database.db"
        extraction = pycolmap.FeatureExtractionOptions()
        extraction.sift.max_num_features = max_features
        extraction.num_threads = 2
        for n in names:
            (img_dir / f"{n}.png").write_bytes(encode_png(images[n]))
            k = cameras[n].K
            reader = pycolmap.ImageReaderOptions()
            reader.camera_model = "PINHOLE"
            reader.camera_params = f"{k[0, 0]},{k[1, 1]},{k[0, 2]},{k[1, 2]}"
            pycolmap.extract_features(
                db,
                img_dir,
                image_names=[f"{n}.png"],
                camera_mode=pycolmap.CameraMode.PER_IMAGE,
                reader_options=reader,
                extraction_options=extraction,
                device=pycolmap.Device.cpu,
            )
        matching = pycolmap.FeatureMatchingOptions()
        matching.num_threads = 2
        pycolmap.match_exhaustive(db, matching_options=matching, device=pycolmap.Device.cpu)
        (root / "sparse").mkdir()
        recs = pycolmap.incremental_mapping(db, img_dir, root / "sparse", _mapping_options(pycolmap, len(names)))
        if not recs:
            raise SfMError(
                f"SfM found no initial image pair among {len(names)} images; the views overlap too little for a board-free calibration"
            )
        rec = max(recs.values(), key=lambda r: r.num_reg_images())
        poses = {}
        for image in rec.images.values():
            if image.has_pose:
                vm = np.eye(4)
                vm[:3, :4] = image.cam_from_world().matrix()
                poses[Path(image.name).stem] = invert_rigid(vm)
        error = float(rec.compute_mean_reprojection_error())
        points = int(rec.num_points3D())
    missing = [n for n in names if n not in poses]
    if missing:
        raise SfMError(
            f"SfM registered {len(poses)}/{len(names)} images; {', '.join(missing)} could not be placed (too few matches); use a board"
        )
    if error > max_reprojection_px:
        raise SfMError(f"SfM reprojection error is {error:.2f} px (limit {max_reprojection_px} px); the result is not trustworthy")
    sim, rms = None, None
    if reference:
        common = [n for n in names if n in reference]
        try:
            sim = align_to_reference({n: poses[n] for n in common}, {n: np.asarray(reference[n]) for n in common})
        except (DegenerateError, ValueError) as e:
            raise SfMError(f"cannot align SfM to the reference: {e}") from None
        moved = {n: sim.apply_to_c2w(poses[n]) for n in names}
        rms = float(np.sqrt(np.mean([np.sum((moved[n][:3, 3] - np.asarray(reference[n])[:3, 3]) ** 2) for n in common])))
        poses = moved
    else:
        first = invert_rigid(poses[names[0]])
        poses = {n: first @ poses[n] for n in names}
    cams = {n: cameras[n].with_c2w(poses[n]) for n in names}
    return SfMResult(cams, len(names), len(names), error, points, sim, rms)
