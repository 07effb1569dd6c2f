"""The capture format: a directory with a nerfstudio-compatible `transforms.json` (SPEC "Capture").

We write a superset of nerfstudio's format (so other 3DGS/NeRF tools read our captures) and read
nerfstudio datasets (per-frame or shared intrinsics, OpenCV distortion) and the Blender
NeRF-synthetic variant (`camera_angle_x`). `transform_matrix` is camera-to-world with OpenGL camera
axes as nerfstudio defines it; in memory every pose is OpenCV (`Camera.c2w`).

Writes build the whole capture in a hidden sibling directory and rename it into place, so a
capture is either complete, with the sha256 of every file in its manifest, or absent.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import tempfile
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from calibration.camera import Camera, c2w_opencv_to_opengl, c2w_opengl_to_opencv, undistort_image
from calibration.fileio import (
    MAX_IMAGE_PIXELS,
    ImageTooLarge,
    atomic_write_bytes,
    atomic_write_json,
    encode_png,
    fsync_dir,
    image_header_size,
    sha256_bytes,
    sha256_file,
)
from calibration.guard import PathOutside, contained
from calibration.so3 import project_to_so3
from calibration.units import UNIT_TO_M

TRANSFORMS = "transforms.json"


class CaptureError(ValueError):
    """A capture that cannot be read as it is; the message names the file and the problem."""


@dataclass(frozen=True)
class CaptureFrame:
    """One view: image path (relative to the capture root), its camera (OpenCV c2w, with distortion)."""

    file_path: str
    camera: Camera
    camera_id: str
    timestamp_ns: int | None = None
    mask_path: str | None = None


@dataclass(frozen=True)
class Capture:
    root: Path
    frames: tuple[CaptureFrame, ...]
    meta: dict = field(default_factory=dict)
    missing: tuple[str, ...] = ()
    max_pixels: int = MAX_IMAGE_PIXELS  # the largest image decoded (fileio.image_header_size)

    def __len__(self) -> int:
        return len(self.frames)

    @property
    def has_masks(self) -> bool:
        return all(f.mask_path for f in self.frames)

    def camera(self, i: int, *, undistorted: bool = True) -> Camera:
        cam = self.frames[i].camera
        return cam.pinhole() if undistorted else cam

    def image(self, i: int, *, undistort: bool = True) -> np.ndarray:
        """RGB float32 [H, W, 3] in [0, 1], undistorted to the pinhole camera by default."""
        frame = self.frames[i]
        img = read_image(self.root / frame.file_path, self.max_pixels)[..., :3]
        self._check_size(frame, img)
        return undistort_image(frame.camera, img)[0] if undistort else img

    def mask(self, i: int, *, undistort: bool = True) -> np.ndarray | None:
        """Object mask bool [H, W] from masks/ (or the image's alpha channel); None when the capture has none."""
        frame = self.frames[i]
        return self._mask(frame, None if frame.mask_path else read_image(self.root / frame.file_path, self.max_pixels), undistort)

    def view(self, i: int, *, undistort: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
        """`image(i)` and `mask(i)` with the image file decoded once (its alpha is the mask without masks/)."""
        frame = self.frames[i]
        img = read_image(self.root / frame.file_path, self.max_pixels)
        self._check_size(frame, img)
        rgb = img[..., :3]
        return (undistort_image(frame.camera, rgb)[0] if undistort else rgb), self._mask(frame, img, undistort)

    def _mask(self, frame: CaptureFrame, img: np.ndarray | None, undistort: bool) -> np.ndarray | None:
        """The mask of `frame` from its masks/ file, else from the alpha of its decoded image `img`."""
        if frame.mask_path:
            m = read_image(self.root / frame.mask_path, self.max_pixels)
            m = m[..., 0] if m.ndim == 3 else m
        elif img.ndim == 3 and img.shape[2] == 4:
            m = img[..., 3]
        else:
            return None
        self._check_size(frame, m)
        m = (m > 0.5).astype(np.uint8)
        if undistort:
            m = undistort_image(frame.camera, m, nearest=True)[0]
        return m.astype(bool)

    def background(self, camera_id: str, *, undistort: bool = True) -> np.ndarray | None:
        """The empty-rig frame of `camera_id` (RGB float32), or None when the capture has none."""
        rel = self.meta.get("background", {}).get(camera_id)
        if rel is None:
            return None
        frame = next((f for f in self.frames if f.camera_id == camera_id), None)
        if frame is None:
            return None
        img = read_image(self.root / rel, self.max_pixels)[..., :3]
        return undistort_image(frame.camera, img)[0] if undistort else img

    def _check_size(self, frame: CaptureFrame, img: np.ndarray) -> None:
        h, w = img.shape[:2]
        if (w, h) != (frame.camera.width, frame.camera.height):
            raise CaptureError(f"{frame.file_path}: image is {w}x{h} but transforms.json says {frame.camera.width}x{frame.camera.height}")


def read_image(path: Path, max_pixels: int = MAX_IMAGE_PIXELS) -> np.ndarray:
    """Decode an image file to float32 in [0, 1]: [H, W] gray, or [H, W, 3|4] RGB(A). Truncated or corrupt files,
    and images whose header declares more than `max_pixels` (checked before decoding), raise CaptureError."""
    data = _encoded(path)
    _header_size(path, data, max_pixels)
    img = cv2.imdecode(data, cv2.IMREAD_UNCHANGED)
    if img is None:
        raise CaptureError(f"{path}: not a readable image (corrupt or unsupported format)")
    if img.ndim == 3 and img.shape[2] == 3:
        img = img[..., ::-1]
    elif img.ndim == 3 and img.shape[2] == 4:
        img = img[..., [2, 1, 0, 3]]
    scale = 65535.0 if img.dtype == np.uint16 else 255.0
    return np.ascontiguousarray(img, dtype=np.float32) / np.float32(scale)


def _encoded(path: Path) -> np.ndarray:
    """The bytes of image file `path`, refused when missing, empty or a truncated PNG."""
    try:
        data = np.fromfile(path, dtype=np.uint8)
    except FileNotFoundError:
        raise CaptureError(f"{path}: file is missing") from None
    if data.size == 0:
        raise CaptureError(f"{path}: file is empty")
    if path.suffix.lower() == ".png" and not _png_complete(data):
        raise CaptureError(f"{path}: PNG is truncated (no IEND chunk)")
    return data


def _header_size(path: Path, data: np.ndarray, max_pixels: int) -> tuple[int, int]:
    try:
        return image_header_size(data.tobytes(), max_pixels)
    except ImageTooLarge as e:
        raise CaptureError(f"{path}: image {e}") from None
    except ValueError:
        raise CaptureError(f"{path}: not a readable image (corrupt or unsupported format)") from None


def _png_complete(data: np.ndarray) -> bool:
    return data.size >= 12 and bytes(data[-8:-4]) == b"IEND"


def _intrinsics(src: dict, fallback: dict, where: str, image_size) -> tuple[np.ndarray, int, int, np.ndarray]:
    """K, w, h, dist from a frame dict with the top-level dict as fallback (nerfstudio's sharing rule)."""

    def get(key):
        return src.get(key, fallback.get(key))

    w, h = get("w"), get("h")
    if w is None or h is None:
        w, h = image_size()
    w, h = int(round(float(w))), int(round(float(h)))
    fl_x, fl_y = get("fl_x"), get("fl_y")
    if fl_x is None:
        angle_x = get("camera_angle_x")
        if angle_x is None:
            raise CaptureError(f"{where}: no focal length (neither fl_x nor camera_angle_x)")
        fl_x = 0.5 * w / math.tan(0.5 * float(angle_x))
    if fl_y is None:
        angle_y = get("camera_angle_y")
        fl_y = 0.5 * h / math.tan(0.5 * float(angle_y)) if angle_y is not None and get("fl_x") is None else fl_x
    cx = get("cx")
    cy = get("cy")
    cx = w / 2.0 if cx is None else float(cx)
    cy = h / 2.0 if cy is None else float(cy)
    k = np.array([[float(fl_x), 0.0, cx], [0.0, float(fl_y), cy], [0.0, 0.0, 1.0]])
    if get("dist") is not None:
        dist = np.array(get("dist"), dtype=np.float64)
    else:
        k1, k2, p1, p2, k3 = (float(get(n) or 0.0) for n in ("k1", "k2", "p1", "p2", "k3"))
        dist = np.array([k1, k2, p1, p2, k3]) if k3 else np.array([k1, k2, p1, p2])
        if not np.any(dist):
            dist = np.zeros(0)
    if not (np.all(np.isfinite(k)) and np.all(np.isfinite(dist))):
        raise CaptureError(f"{where}: intrinsics or distortion contain NaN or inf")
    return k, w, h, dist


def _pose(matrix, where: str) -> np.ndarray:
    m = np.asarray(matrix, dtype=np.float64)
    if m.shape == (3, 4):
        m = np.vstack([m, [0, 0, 0, 1]])
    if m.shape != (4, 4):
        raise CaptureError(f"{where}: transform_matrix must be 4x4, got shape {m.shape}")
    if not np.all(np.isfinite(m)):
        raise CaptureError(f"{where}: transform_matrix contains NaN or inf")
    r = m[:3, :3]
    if np.abs(r @ r.T - np.eye(3)).max() > 1e-3 or np.linalg.det(r) < 0:
        raise CaptureError(f"{where}: transform_matrix rotation is not rigid (scaled, sheared or reflected)")
    m[:3, :3] = project_to_so3(r)
    return c2w_opengl_to_opencv(m)


def read_capture(
    path: str | os.PathLike, *, verify: bool = True, allow_missing: bool = False, max_pixels: int = MAX_IMAGE_PIXELS
) -> Capture:
    """Read a capture directory (or a transforms.json path).

    verify: check every sha256 the manifest records. allow_missing: frames whose image file is
    absent are dropped and listed in `Capture.missing` instead of raising. max_pixels: no image
    whose header declares more is decoded (rig.toml [limits] max_image_pixels).
    """
    path = Path(path)
    tf_path = path if path.is_file() else path / TRANSFORMS
    root = tf_path.parent
    if not tf_path.exists():
        raise CaptureError(f"{tf_path}: no transforms.json here; is this a capture directory?")
    try:
        doc = json.loads(tf_path.read_text())
    except json.JSONDecodeError as e:
        raise CaptureError(f"{tf_path}: invalid JSON ({e.msg} at line {e.lineno})") from None
    except UnicodeDecodeError:
        raise CaptureError(f"{tf_path}: not a text file") from None
    check_document(doc, tf_path)
    frames_doc = doc["frames"]
    meta = doc.get("cadsplat", {})
    digests = meta.get("sha256", {})
    frames: list[CaptureFrame] = []
    missing: list[str] = []
    for i, fd in enumerate(frames_doc):
        rel = _resolve_image_path(root, fd["file_path"])
        _inside(root, rel, f"{tf_path}: frame {i} file_path")
        if fd.get("mask_path"):
            _inside(root, fd["mask_path"], f"{tf_path}: frame {i} mask_path")
        where = f"{tf_path.name} frame {i} ({rel})"
        if not (root / rel).exists():
            missing.append(rel)
            continue
        k, w, h, dist = _intrinsics(fd, doc, where, lambda: _image_size(root / rel, max_pixels))
        c2w = _pose(fd.get("transform_matrix"), where)
        frames.append(
            CaptureFrame(
                file_path=rel,
                camera=Camera(k, w, h, dist, c2w),
                camera_id=str(fd.get("camera_id", Path(rel).stem)),
                timestamp_ns=fd.get("timestamp_ns"),
                mask_path=fd.get("mask_path"),
            )
        )
    if missing and not allow_missing:
        shown = ", ".join(missing[:3]) + (", ..." if len(missing) > 3 else "")
        raise CaptureError(
            f"{tf_path}: lists {len(frames_doc)} frames but {len(missing)} image files are missing ({shown}); "
            f"read with allow_missing to load the {len(frames)} present"
        )
    if not frames:
        raise CaptureError(f"{tf_path}: none of its {len(frames_doc)} image files exist")
    for f in frames:
        if f.mask_path and not (root / f.mask_path).exists():
            raise CaptureError(f"{root / f.mask_path}: mask file is missing")
    for cam_id, rel in meta.get("background", {}).items():
        _inside(root, rel, f"{tf_path}: cadsplat.background.{cam_id}")
    if verify:
        for rel, digest in digests.items():
            p = _inside(root, rel, f"{tf_path}: cadsplat.sha256 entry")
            if not p.exists():
                raise CaptureError(f"{p}: listed in the manifest but missing")
            if sha256_file(p) != digest:
                raise CaptureError(f"{p}: sha256 does not match the manifest (file changed or corrupt)")
    return Capture(root=root, frames=tuple(frames), meta=meta, missing=tuple(missing), max_pixels=max_pixels)


# The keys a reader of a capture uses, by the JSON type each must have; other keys are carried as they are.
_NUMBER_KEYS = ("w", "h", "fl_x", "fl_y", "cx", "cy", "k1", "k2", "k3", "p1", "p2", "camera_angle_x", "camera_angle_y")
_META_TABLES = ("sha256", "background", "calibration_uncertainty", "camera_settings", "up_rig")


def check_document(doc, tf_path: Path) -> None:
    """Raise CaptureError naming `tf_path` and the key when a transforms.json document has a wrong JSON type
    where a reader relies on one (frames, their paths, poses and intrinsics, the cadsplat block)."""

    def bad(key: str, want: str, got) -> CaptureError:
        shown = repr(got) if len(repr(got)) <= 40 else f"a {type(got).__name__}"
        return CaptureError(f"{tf_path}: {key} must be {want}, got {shown}")

    def is_number(x) -> bool:
        return isinstance(x, (int, float)) and not isinstance(x, bool)

    def intrinsics(d: dict, where: str) -> None:
        for key in _NUMBER_KEYS:
            if d.get(key) is not None and not is_number(d[key]):
                raise bad(f"{where}{key}", "a number", d[key])
        for key in ("w", "h"):
            if d.get(key) is not None and not d[key] > 0:
                raise bad(f"{where}{key}", "a positive number of pixels", d[key])
        dist = d.get("dist")
        if dist is not None and not (isinstance(dist, list) and all(is_number(x) for x in dist)):
            raise bad(f"{where}dist", "a list of numbers", dist)

    if not isinstance(doc, dict):
        raise bad("the document", "a JSON object", doc)
    frames = doc.get("frames")
    if not isinstance(frames, list) or not frames:
        raise CaptureError(f"{tf_path}: has no frames (frames must be a non-empty list of objects)")
    intrinsics(doc, "")
    for i, fd in enumerate(frames):
        where = f"frames[{i}]"
        if not isinstance(fd, dict):
            raise bad(where, "an object", fd)
        if not isinstance(fd.get("file_path"), str) or not fd["file_path"]:
            raise bad(f"{where}.file_path", "a non-empty string", fd.get("file_path"))
        if fd.get("mask_path") is not None and not isinstance(fd["mask_path"], str):
            raise bad(f"{where}.mask_path", "a string", fd["mask_path"])
        m = fd.get("transform_matrix")
        if m is None:
            raise CaptureError(f"{tf_path}: {where}.transform_matrix is missing")
        if not (isinstance(m, list) and all(isinstance(row, list) and all(is_number(x) for x in row) for row in m)):
            raise bad(f"{where}.transform_matrix", "a 4x4 list of numbers", m)
        if fd.get("camera_id") is not None and not isinstance(fd["camera_id"], (str, int)):
            raise bad(f"{where}.camera_id", "a string", fd["camera_id"])
        if fd.get("timestamp_ns") is not None and (isinstance(fd["timestamp_ns"], bool) or not isinstance(fd["timestamp_ns"], int)):
            raise bad(f"{where}.timestamp_ns", "an integer", fd["timestamp_ns"])
        intrinsics(fd, f"{where}.")
    meta = doc.get("cadsplat", {})
    if not isinstance(meta, dict):
        raise bad("cadsplat", "an object", meta)
    for key in _META_TABLES:
        if key in meta and not isinstance(meta[key], dict):
            raise bad(f"cadsplat.{key}", "an object", meta[key])
    if meta.get("units") is not None and not isinstance(meta["units"], str):
        raise bad("cadsplat.units", "a string", meta["units"])
    for key in ("sha256", "background"):
        for name, value in meta.get(key, {}).items():
            if not isinstance(value, str):
                raise bad(f"cadsplat.{key}.{name}", "a string", value)
    for name, value in meta.get("calibration_uncertainty", {}).items():
        if value is not None and not is_number(value):
            raise bad(f"cadsplat.calibration_uncertainty.{name}", "a number", value)
    for name, value in meta.get("camera_settings", {}).items():
        if not isinstance(value, dict):
            raise bad(f"cadsplat.camera_settings.{name}", "an object", value)
    up = meta.get("up_rig", {}).get("vector", [0, 0, 1])
    if not (isinstance(up, list) and len(up) == 3 and all(is_number(x) and math.isfinite(x) for x in up) and any(x != 0 for x in up)):
        raise bad("cadsplat.up_rig.vector", "3 finite numbers, not all zero", up)


def _inside(root: Path, rel: str, what: str) -> Path:
    """`root`/`rel` resolved, or CaptureError when a capture names a file outside its own folder."""
    try:
        return contained(root, rel, what=what)
    except PathOutside as e:
        raise CaptureError(str(e)) from None


def _resolve_image_path(root: Path, rel: str) -> str:
    """Blender NeRF-synthetic lists paths without extension ("./train/r_0")."""
    rel = os.path.normpath(rel)
    if Path(rel).suffix == "" and not (root / rel).exists():
        for ext in (".png", ".jpg", ".jpeg"):
            if (root / (rel + ext)).exists():
                return rel + ext
    return rel


def _image_size(path: Path, max_pixels: int) -> tuple[int, int]:
    """(width, height) from the image's header, for a document that states no size; no pixel is decoded."""
    return _header_size(path, _encoded(path), max_pixels)


@dataclass
class FrameData:
    """A view to write: `image` RGB [H, W, 3] (uint8/uint16, or float in [0, 1]), optional `mask` bool [H, W]."""

    name: str
    image: np.ndarray
    camera: Camera
    camera_id: str
    timestamp_ns: int | None = None
    mask: np.ndarray | None = None


def capture_document(frames: Sequence[CaptureFrame], meta: dict) -> dict:
    """The transforms.json content for `frames` (nerfstudio keys + ours)."""
    out = []
    for f in frames:
        cam = f.camera
        d = np.zeros(5)
        d[: min(5, cam.dist.size)] = cam.dist[:5]
        entry = {
            "file_path": f.file_path,
            "transform_matrix": c2w_opencv_to_opengl(cam.c2w).tolist(),
            "fl_x": cam.K[0, 0],
            "fl_y": cam.K[1, 1],
            "cx": cam.K[0, 2],
            "cy": cam.K[1, 2],
            "w": cam.width,
            "h": cam.height,
            "k1": d[0],
            "k2": d[1],
            "p1": d[2],
            "p2": d[3],
            "camera_id": f.camera_id,
        }
        if cam.dist.size > 4:
            entry["dist"] = cam.dist.tolist()
        if f.timestamp_ns is not None:
            entry["timestamp_ns"] = int(f.timestamp_ns)
        if f.mask_path:
            entry["mask_path"] = f.mask_path
        out.append(entry)
    return {"camera_model": "OPENCV", "frames": out, "cadsplat": meta}


def write_capture(
    root: str | os.PathLike,
    frames: Sequence[FrameData],
    *,
    backgrounds: dict[str, np.ndarray] | None = None,
    meta: dict | None = None,
) -> Capture:
    """Write a new capture directory atomically and return it as read back (verified).

    The capture is assembled in a hidden sibling directory, every file fsynced, then renamed into
    place; an existing `root` is never overwritten.
    """
    root = Path(root)
    if root.exists():
        raise CaptureError(f"{root}: already exists; captures are never overwritten")
    if not frames:
        raise CaptureError(f"{root}: a capture needs at least one frame")
    names = [f.name for f in frames]
    if len(set(names)) != len(names):
        raise CaptureError(f"{root}: frame names must be unique")
    root.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{root.name}.", suffix=".incoming", dir=root.parent))
    try:
        digests: dict[str, str] = {}
        written: list[CaptureFrame] = []
        (tmp / "images").mkdir()
        for f in frames:
            h, w = f.image.shape[:2]
            if (w, h) != (f.camera.width, f.camera.height):
                raise CaptureError(f"{f.name}: image is {w}x{h} but its camera says {f.camera.width}x{f.camera.height}")
            rel = f"images/{f.name}.png"
            digests[rel] = atomic_write_bytes(tmp / rel, encode_png(f.image))
            mask_rel = None
            if f.mask is not None:
                (tmp / "masks").mkdir(exist_ok=True)
                mask_rel = f"masks/{f.name}.png"
                digests[mask_rel] = atomic_write_bytes(tmp / mask_rel, encode_png(np.asarray(f.mask, bool).astype(np.uint8) * 255))
            written.append(CaptureFrame(rel, f.camera, f.camera_id, f.timestamp_ns, mask_rel))
        # `units` only when the caller's calibration is metric: no units = unknown scale.
        meta = dict(meta or {})
        if "units" in meta:
            rig_metres_per_unit(meta, root)
        if backgrounds:
            (tmp / "background").mkdir()
            meta["background"] = {}
            for cam_id, img in backgrounds.items():
                rel = f"background/{cam_id}.png"
                digests[rel] = atomic_write_bytes(tmp / rel, encode_png(img))
                meta["background"][cam_id] = rel
        meta["sha256"] = digests
        atomic_write_json(tmp / TRANSFORMS, capture_document(written, meta))
        for sub in ("images", "masks", "background"):
            if (tmp / sub).exists():
                fsync_dir(tmp / sub)
        os.rename(tmp, root)
        fsync_dir(root.parent)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return read_capture(root)


def rig_metres_per_unit(meta: dict, where: str | os.PathLike = "capture") -> float | None:
    """Metres per rig-frame unit from a capture's `cadsplat` block (`"units": "m"`: metric rig);
    None when it states no units (another tool's capture, an SfM calibration: scale unknown)."""
    units = meta.get("units")
    if units is None:
        return None
    if units not in UNIT_TO_M:
        raise CaptureError(f"{where}: units {units!r} is not one of {', '.join(UNIT_TO_M)}")
    return UNIT_TO_M[units]


def capture_fingerprint(capture: Capture) -> str:
    """sha256 of what the capture states (views, cameras, manifest digests): what a result computed
    from it (a registration) records, so it is never applied to another capture."""
    return sha256_bytes(json.dumps(capture_document(capture.frames, capture.meta), sort_keys=True).encode())


def load_views(
    capture: Capture, indices: Sequence[int] | None = None, *, with_masks: bool = True
) -> tuple[np.ndarray, np.ndarray | None, list[Camera]]:
    """Undistorted images [V, H, W, 3] float32, masks [V, H, W] bool (None without masks, or not
    `with_masks`) and pinhole cameras, each file decoded once: what a caller decodes here it hands
    forward (to `capture_masks`, `reconstruct`) instead of decoding it again.

    Views of different sizes (a photo taken in portrait among landscape ones) share one canvas of the
    largest width and height, each at its top-left corner so its K holds; the rest of its canvas is
    black and outside its mask, and `Camera.crop` takes the view's own pixels back.
    """
    idx = list(range(len(capture))) if indices is None else list(indices)
    for i in idx:
        if not 0 <= i < len(capture):
            raise CaptureError(f"{capture.root}: view {i} does not exist (capture has {len(capture)} views)")
    decoded = [capture.view(i) if with_masks else (capture.image(i), None) for i in idx]
    images = on_canvas([image for image, _ in decoded])
    masks = None if any(m is None for _, m in decoded) else on_canvas([m for _, m in decoded])
    return images, masks, [capture.camera(i) for i in idx]


def on_canvas(arrays: Sequence[np.ndarray]) -> np.ndarray:
    """[V, H, W, ...] of arrays [h_i, w_i, ...] placed top-left on zeros of the largest h and w."""
    h, w = max(a.shape[0] for a in arrays), max(a.shape[1] for a in arrays)
    out = np.zeros((len(arrays), h, w, *arrays[0].shape[2:]), dtype=arrays[0].dtype)
    for o, a in zip(out, arrays):
        o[: a.shape[0], : a.shape[1]] = a
    return out
