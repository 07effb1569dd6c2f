"""Object masks for a capture: its masks/ when present, else background subtraction against background/.

Masks are computed once per capture and handed forward (the service keeps them beside the
registration; `reconstruct` takes them as given), so nothing masks the same capture twice.

A static rig sees the same empty scene in every capture, so the per-camera empty frame makes the
object the set of pixels that changed. The threshold adapts to each view's noise (median absolute
difference), then small specks are removed and holes closed so the bounding box the silhouette
matcher normalises by is the object's.

Every background-difference view gets a quality score (`MaskQuality`), and a view whose difference
is implausible is refused in one sentence: nothing changed (no part, or a reference taken with the
part on the belt), nearly everything changed, or the whole frame shifted (lighting or exposure
changed since the reference was taken).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import cv2
import numpy as np

from calibration.capture import Capture, CaptureError, on_canvas


def subtract_background(
    image: np.ndarray, background: np.ndarray, *, min_diff: float = 0.08, noise_k: float = 6.0, min_area_frac: float = 0.002
) -> np.ndarray:
    """Foreground bool [H, W] of RGB float `image` [H, W, 3] against the empty-rig `background` [H, W, 3].

    A pixel is foreground when its colour distance exceeds max(min_diff, noise_k * MAD of the
    distances); connected components smaller than `min_area_frac` of the image are dropped.
    """
    if image.shape != background.shape:
        raise ValueError(f"image {image.shape} and background {background.shape} differ in size")
    diff = np.linalg.norm(image.astype(np.float32) - background.astype(np.float32), axis=-1)
    mad = float(np.median(np.abs(diff - np.median(diff))))
    fg = diff > max(min_diff, noise_k * 1.4826 * mad)
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (3, 3))
    fg = cv2.morphologyEx(fg.astype(np.uint8), cv2.MORPH_OPEN, kernel)
    fg = cv2.morphologyEx(fg, cv2.MORPH_CLOSE, kernel, iterations=2)
    return remove_specks(fg.astype(bool), min_area_frac)


def remove_specks(mask: np.ndarray, min_area_frac: float) -> np.ndarray:
    """Drop connected components smaller than `min_area_frac` of the image from a bool mask."""
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    keep = np.zeros(n, dtype=bool)
    keep[1:] = stats[1:, cv2.CC_STAT_AREA] >= min_area_frac * mask.size
    return keep[labels]


@dataclass(frozen=True)
class MaskQuality:
    """How plausible one view's background difference is. `cover`: foreground fraction; `frame_shift`:
    median colour difference over the whole frame (0 for a static scene); `score` in [0, 1]; `problem`:
    the sentence that refuses the view, or ""."""

    cover: float
    frame_shift: float
    score: float
    problem: str = ""


def mask_quality(
    image: np.ndarray,
    background: np.ndarray,
    mask: np.ndarray,
    *,
    min_cover: float = 0.0005,
    max_cover: float = 0.9,
    max_shift: float = 0.06,
) -> MaskQuality:
    """Quality of the mask [H, W] `subtract_background(image [H, W, 3], background [H, W, 3])` returned."""
    diff = np.linalg.norm(image.astype(np.float32) - background.astype(np.float32), axis=-1)
    shift = float(np.median(diff))
    cover = float(np.mean(mask))
    problem = ""
    if shift > max_shift:
        problem = (
            f"the whole frame differs from the empty-rig reference (median colour change {shift:.2f}): the lighting or "
            "exposure changed since it was taken; take a new reference with the belt empty"
        )
    elif cover > max_cover:
        problem = f"{100 * cover:.0f}% of the frame differs from the empty-rig reference, far more than a part covers"
    elif cover < min_cover:
        problem = "nothing differs from the empty-rig reference: no part in view, or the reference was taken with the part on the belt"
    in_range = min(1.0, cover / (10 * min_cover)) * min(1.0, (1.0 - cover) / (1.0 - max_cover))
    score = 0.0 if problem else float(np.clip(in_range * (1.0 - shift / max_shift), 0.0, 1.0))
    return MaskQuality(cover, shift, score, problem)


def capture_masks(
    capture: Capture, images: np.ndarray | Sequence[np.ndarray] | None = None, indices: Sequence[int] | None = None
) -> tuple[np.ndarray, str]:
    """Undistorted bool masks [V, H, W] of the views `indices` (default all) and where they came from
    ("masks" or "background").

    Views of mixed sizes come on one canvas, as `load_views` gives them.

    `images`: those views' undistorted images ([V, H, W, 3], or one [H, W, 3] each) when the caller
    already decoded them (`load_views`), so background subtraction decodes none again; each empty-rig
    frame is decoded once. Raises CaptureError when the capture has neither masks/ nor background/
    frames for every camera.
    """
    idx = list(range(len(capture))) if indices is None else list(indices)
    if capture.has_masks:
        return on_canvas([capture.mask(i) for i in idx]), "masks"
    backgrounds = capture.meta.get("background", {})
    missing = sorted({f.camera_id for f in capture.frames} - set(backgrounds))
    if not backgrounds:
        raise CaptureError(f"{capture.root}: has neither masks/ nor background/ frames, so no object mask can be made")
    if missing:
        raise CaptureError(f"{capture.root}: has no masks/ and no background frame for camera {missing[0]}")
    out, decoded = [], {}
    for j, i in enumerate(idx):
        frame = capture.frames[i]
        image = capture.image(i) if images is None else capture.camera(i).crop(images[j])
        if frame.camera_id not in decoded:
            decoded[frame.camera_id] = capture.background(frame.camera_id)
        background = decoded[frame.camera_id]
        if image.shape != background.shape:
            raise CaptureError(
                f"{capture.root}: the background frame of {frame.camera_id} is {background.shape[1]}x{background.shape[0]}, "
                f"its image {image.shape[1]}x{image.shape[0]}"
            )
        mask = subtract_background(image, background)
        quality = mask_quality(image, background, mask)
        if quality.problem:
            raise CaptureError(f"{capture.root}: view {i} ({frame.camera_id}) refused: {quality.problem}")
        out.append(mask)
    return on_canvas(out), "background"
