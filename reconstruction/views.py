"""The views of one capture as the engine takes them: decoded once, then handed forward in memory.

`capture_views` is the one place a capture's images are decoded and its masks made; registration,
reconstruction, the fit score and inspection take the `CaptureViews` it returns instead of reading
the capture again.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from calibration.camera import Camera
from calibration.capture import Capture, CaptureError, load_views, rig_metres_per_unit


@dataclass(frozen=True)
class CaptureViews:
    """Undistorted views of a capture on one canvas (views of mixed sizes sit top-left, as `load_views` places them).

    images: [V, H, W, 3] float32 in [0, 1]
    masks: [V, H, W] bool
    cameras: V pinhole cameras in the rig frame
    indices: which capture frames these are
    metres_per_unit: the rig frame's metric scale (None: unknown, e.g. an SfM calibration)
    mask_source: "masks" (the capture's own), "background" (subtracted) or "given" (handed in)
    """

    capture: Capture
    indices: tuple[int, ...]
    images: np.ndarray
    masks: np.ndarray
    cameras: tuple[Camera, ...]
    metres_per_unit: float | None
    mask_source: str

    def __len__(self) -> int:
        return len(self.indices)

    @property
    def names(self) -> list[str]:
        """ "view i (camera id)" for each view, as messages name them."""
        return [f"view {i} ({self.capture.frames[i].camera_id})" for i in self.indices]

    @property
    def sizes(self) -> np.ndarray:
        """[V, 2] each view's own (width, height)."""
        return np.array([(c.width, c.height) for c in self.cameras])

    def subset(self, positions: Sequence[int]) -> CaptureViews:
        """The views at `positions` (into this object's views, not the capture's frames)."""
        pos = list(positions)
        return CaptureViews(
            self.capture,
            tuple(self.indices[p] for p in pos),
            self.images[pos],
            self.masks[pos],
            tuple(self.cameras[p] for p in pos),
            self.metres_per_unit,
            self.mask_source,
        )


def capture_views(capture: Capture, indices: Sequence[int] | None = None, *, masks: np.ndarray | None = None) -> CaptureViews:
    """Decode the views `indices` (default all) of `capture` once and make their masks.

    masks: [V, H, W] bool for those views when already made (recorded as "given"); otherwise the
        capture's own masks, or background subtraction against its empty-rig frames.
    Raises CaptureError on a view that does not exist or masks that do not match the views.
    """
    from reconstruction.masks import capture_masks

    idx = list(range(len(capture))) if indices is None else list(indices)
    images, own, cameras = load_views(capture, idx, with_masks=masks is None)
    if masks is not None:
        if masks.shape != images.shape[:3]:
            raise CaptureError(f"{capture.root}: the given masks are {masks.shape}, the views {images.shape[:3]}")
        source = "given"
    elif own is not None:
        masks, source = own, "masks"
    else:
        masks, source = capture_masks(capture, images, idx)
    return CaptureViews(capture, tuple(idx), images, masks, tuple(cameras), rig_metres_per_unit(capture.meta, capture.root), source)
