"""Import the NeRS datasets (real phone photographs) as captures.

NeRS stores PyTorch3D cameras: row-vector world-to-view `X_view = X_world @ R + T` with view axes
+X left, +Y up, +Z forward, and a field of view that spans the image's longer side around the
image centre (NeRS's crop cameras with the full image as the crop). Masks are COCO-style
uncompressed RLE (column-major). The MVMC cars' `camera_optimized` are NeRS's cameras after its
joint fit of shape and cameras: the masks' visual hull re-projects onto every mask
(benchmarks/results/real_photos_cpu.md), so they are marked `pose_source: optimized` and the engine applies one global
correction, as NeRS's "fixed optimized cameras" setting does; `camera_initial` (PoseFromShape
estimates, whose hull fits the masks worse) stay `rough`. The NeRS "misc" objects only have rough azimuth/elevation, so their
poses are built on a sphere (PyTorch3D's look_at_view_transform, world +Y up) with each view's
distance set from its mask size, and the capture is marked `pose_source: rough` so the engine
corrects every camera independently.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from calibration.camera import Camera, look_at_c2w
from calibration.capture import Capture, CaptureError, FrameData, read_image, write_capture
from calibration.so3 import rotation_between

# PyTorch3D view axes (x left, y up, z forward) -> OpenCV (x right, y down, z forward).
_P3D_TO_CV = np.diag([-1.0, -1.0, 1.0])


def decode_coco_rle(counts: str | list[int], size: tuple[int, int]) -> np.ndarray:
    """Uncompressed COCO RLE (alternating background/foreground run lengths, column-major) -> bool [H, W]."""
    runs = np.array([int(c) for c in counts.split()] if isinstance(counts, str) else counts, dtype=np.int64)
    h, w = size
    if runs.sum() != h * w:
        raise CaptureError(f"RLE mask covers {int(runs.sum())} pixels but its size is {h}x{w}")
    values = np.zeros(len(runs), dtype=bool)
    values[1::2] = True
    return np.repeat(values, runs).reshape(w, h).T


def pytorch3d_camera(rotation: np.ndarray, translation: np.ndarray, fov_deg: float, width: int, height: int) -> Camera:
    """A NeRS/PyTorch3D camera (R [3,3] row-vector convention, T [3], fov over the longer side) as our Camera."""
    r = np.asarray(rotation, np.float64)
    t = np.asarray(translation, np.float64)
    viewmat = np.eye(4)
    viewmat[:3, :3] = _P3D_TO_CV @ r.T
    viewmat[:3, 3] = _P3D_TO_CV @ t
    f = 0.5 * max(width, height) / np.tan(np.radians(fov_deg) / 2)
    k = np.array([[f, 0, width / 2], [0, f, height / 2], [0, 0, 1.0]])
    c2w = np.linalg.inv(viewmat)
    return Camera(k, width, height, np.zeros(0), c2w)


def import_ners_mvmc(src: str | Path, out: str | Path, *, cameras: str = "camera_optimized") -> Capture:
    """One NeRS MVMC car (`annotations.json` + `images/`) -> a capture with masks and the chosen cameras
    (`camera_optimized`: NeRS's fitted cameras, marked optimized; `camera_initial`: marked rough)."""
    src = Path(src)
    doc = json.loads((src / "annotations.json").read_text())
    frames = []
    for ann in doc["annotations"]:
        img = read_image(src / "images" / ann["filename"])[..., :3]
        h, w = img.shape[:2]
        mask = decode_coco_rle(ann["mask"]["counts"], tuple(ann["mask"]["size"]))
        if mask.shape != (h, w):
            raise CaptureError(f"{ann['filename']}: mask is {mask.shape[1]}x{mask.shape[0]} but the image is {w}x{h}")
        cam = ann[cameras]
        name = Path(ann["filename"]).stem
        frames.append(
            FrameData(name, img, pytorch3d_camera(np.array(cam["R"]), np.array(cam["T"]), float(cam["fov"]), w, h), name, None, mask)
        )
    source = "optimized" if cameras == "camera_optimized" else "rough"
    meta = {
        "rig_id": f"ners-mvmc-{doc['id']}",
        "calibration_id": f"ners:{cameras}",
        "pose_source": source,
        "object": doc.get("car_model", ""),
    }
    return write_capture(out, frames, meta=meta)


def mask_from_png(m: np.ndarray) -> np.ndarray:
    """bool [H, W] of a mask image [H, W] or [H, W, 3|4] in [0, 1]: the alpha channel where it varies, else
    the colour (NeRS's espresso masks are white-on-black RGB with an opaque alpha)."""
    if m.ndim == 2:
        return m > 0.5
    if m.shape[2] == 4 and np.ptp(m[..., 3]) > 0:
        return m[..., 3] > 0.5
    return m[..., :3].mean(axis=2) > 0.5


def import_ners_misc(src: str | Path, out: str | Path, *, fov_deg: float = 60.0) -> Capture:
    """A NeRS misc object (`metadata.json` azimuths/elevations/extents + images/ + masks/) -> a capture with rough poses."""
    src = Path(src)
    meta_doc = json.loads((src / "metadata.json").read_text())
    names = sorted(p.stem for p in (src / "images").iterdir())
    azim, elev = meta_doc["azimuths"], meta_doc["elevations"]
    if not len(names) == len(azim) == len(elev):
        raise CaptureError(f"{src}: {len(names)} images but {len(azim)} azimuths and {len(elev)} elevations")
    extent = float(np.linalg.norm(meta_doc.get("extents", [1.0, 1.0, 1.0])))
    frames = []
    for name, a, e in zip(names, azim, elev):
        img = read_image(next((src / "images").glob(name + ".*")))[..., :3]
        mask = mask_from_png(read_image(src / "masks" / f"{name}.png"))
        h, w = img.shape[:2]
        f = 0.5 * max(w, h) / np.tan(np.radians(fov_deg) / 2)
        ys, xs = np.nonzero(mask)
        if len(xs) == 0:
            raise CaptureError(f"{src / 'masks' / name}.png: mask is empty")
        # Distance at which an object of the metadata's extent spans the mask's diagonal.
        diag_px = float(np.hypot(xs.max() - xs.min(), ys.max() - ys.min()))
        dist = f * extent / max(diag_px, 1.0)
        a_r, e_r = np.radians(a), np.radians(e)
        eye = dist * np.array([np.cos(e_r) * np.sin(a_r), np.sin(e_r), np.cos(e_r) * np.cos(a_r)])
        up = np.array([0.0, 1.0, 0.0]) if abs(e) < 89 else np.array([0.0, 0.0, -1.0])
        k = np.array([[f, 0, w / 2], [0, f, h / 2], [0, 0, 1.0]])
        cam = Camera(k, w, h, np.zeros(0), look_at_c2w(eye, np.zeros(3), up))
        # The photographer did not centre the object: turn the camera so the object's centre lies on the
        # ray through the mask's box centre (measured: benchmarks/results/real_photos_cpu.md).
        centre_uv = np.array([[0.5 * (xs.min() + xs.max() + 1), 0.5 * (ys.min() + ys.max() + 1)]])
        c2w = cam.c2w.copy()
        c2w[:3, :3] = cam.c2w[:3, :3] @ rotation_between(cam.pixel_rays_camera(centre_uv)[0], np.array([0.0, 0.0, 1.0]))
        frames.append(FrameData(name, img, cam.with_c2w(c2w), name, None, mask))
    meta = {"rig_id": f"ners-misc-{src.name}", "calibration_id": "ners:azimuth-elevation", "pose_source": "rough"}
    return write_capture(out, frames, meta=meta)
