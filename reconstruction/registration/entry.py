"""The one registration entry: a capture's views, the library and the line's `RegistrationConfig` -> a checked result.

The `register` command, the service's register step, the kiosk and `reconstruct` all register through
`register_views`, so each takes the same path for the same rig.toml: the known part when the config
names one, else the library search, with the photographs' near-tie break and the scale tolerance.
"""

from __future__ import annotations

from collections.abc import Sequence

from reconstruction.library import Library
from reconstruction.quality import check_masks, check_registration
from reconstruction.registration.config import RegistrationConfig
from reconstruction.registration.known_part import known_part_register
from reconstruction.registration.result import RegistrationError, RegistrationResult, provenance
from reconstruction.registration.search import register
from reconstruction.views import CaptureViews


def register_views(
    views: CaptureViews,
    library: Library,
    config: RegistrationConfig = RegistrationConfig(),
    *,
    model_id: str | Sequence[str] | None = None,
    seed: int = 0,
) -> RegistrationResult:
    """The library model in `views` and the rig-to-object Sim(3), refused (QualityError, one sentence) when the
    masks are no object's silhouettes or the fit cannot be trusted (below the silhouette floor, `MaskGate.fit_floor`).

    `config.known_part` set: that model alone (`known_part_register`, about `config.prior` when given);
    otherwise the library search, restricted to `model_id` (one id or several) when given. The scale is a
    measurement within `config.scale_tolerance` when the views' calibration is metric (`views.metres_per_unit`).
    """
    check_masks(views.masks, names=views.names)
    masks, cameras = views.masks, list(views.cameras)
    images = views.images if config.photo_tie_break else None
    wanted = None if model_id is None else [model_id] if isinstance(model_id, str) else list(model_id)
    if config.known_part is not None:
        if wanted is not None and wanted != [config.known_part]:
            raise RegistrationError(f"the line's known part is {config.known_part!r}; asking for {', '.join(wanted)} contradicts it")
        res = known_part_register(
            masks,
            cameras,
            library,
            config.known_part,
            config.prior,
            rig_metres_per_unit=views.metres_per_unit,
            scale_tolerance=config.scale_tolerance,
            seed=seed,
            images=images,
        )
    else:
        res = register(
            masks,
            cameras,
            library,
            top_k=config.top_k,
            iou_threshold=config.iou_threshold,
            seed=seed,
            model_ids=wanted,
            rig_metres_per_unit=views.metres_per_unit,
            scale_tolerance=config.scale_tolerance,
            images=images,
        )
    check_registration(
        res.score, res.alternatives, masks, len(library.models), res.model_id, per_view_iou=res.per_view_iou, names=views.names
    )
    return res


def registration_document(res: RegistrationResult, views: CaptureViews, library: Library, config: RegistrationConfig) -> dict:
    """What reg.json and the service's registration.json hold: the result, its `provenance`, the config it was
    made with, where the masks came from, and each camera pose named by its view and camera id."""
    doc = {
        **res.to_dict(),
        **provenance(views.capture, library, res.model_id),
        "config": config.to_dict(),
        "mask_source": views.mask_source,
    }
    frames = [views.capture.frames[i] for i in views.indices]
    doc["camera_poses"] = [{**pose, "view": f.file_path, "camera_id": f.camera_id} for pose, f in zip(doc["camera_poses"], frames)]
    return doc
