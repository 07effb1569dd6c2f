"""Atomic, verified file writes: temp file + fsync + rename, and sha256 digests; image headers read before decoding.

Every file the appliance writes goes through here so a crash or a full disk never leaves a
half-written file under its final name. Every image it reads has its declared size checked against
a pixel cap first, so a decompression bomb (a small PNG declaring a huge canvas) is never decoded.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import tempfile
import warnings
from pathlib import Path

import numpy as np

# The largest image decoded by default: a 12 MP sensor (4056x3040) four times over. rig.toml's
# [limits] max_image_pixels changes it for a rig (rig.config); its bound stays under PIL's own bomb limit.
MAX_IMAGE_PIXELS = 50_000_000


class ImageTooLarge(ValueError):
    """An image whose header declares more pixels than the cap; it was not decoded."""


def image_header_size(data: bytes, max_pixels: int = MAX_IMAGE_PIXELS) -> tuple[int, int]:
    """(width, height) that the encoded image `data` declares, read from its header (PIL opens lazily, no
    pixel is decoded) and checked against `max_pixels`. Raises ImageTooLarge over the cap, ValueError
    when no image format is recognised."""
    from PIL import Image, UnidentifiedImageError

    cap = f"the cap of {max_pixels / 1e6:g} MP (rig.toml [limits] max_image_pixels); it was not decoded"
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", Image.DecompressionBombWarning)
        try:
            with Image.open(io.BytesIO(data)) as im:
                w, h = im.size
        except Image.DecompressionBombError:
            raise ImageTooLarge(f"declares more than {2 * Image.MAX_IMAGE_PIXELS / 1e6:.0f} MP, above {cap}") from None
        except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as e:
            raise ValueError(f"no image header recognised ({type(e).__name__})") from None
    if w * h > max_pixels:
        raise ImageTooLarge(f"declares {w}x{h} pixels ({w * h / 1e6:.0f} MP), above {cap}")
    return w, h


def sha256_bytes(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def sha256_file(path: str | os.PathLike, chunk: int = 1 << 20) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        while block := f.read(chunk):
            h.update(block)
    return h.hexdigest()


def fsync_dir(path: str | os.PathLike) -> None:
    """Make a rename or a new entry in `path` durable."""
    fd = os.open(path, os.O_RDONLY)
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def _durable_temp(path: Path, data: bytes) -> str:
    """`data` in a fsynced temporary file beside `path`; returns the temporary file's name."""
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
    except BaseException:
        os.unlink(tmp)
        raise
    return tmp


def atomic_write_bytes(path: str | os.PathLike, data: bytes) -> str:
    """Write `data` to `path` atomically (replacing it); returns its sha256. The parent directory must exist."""
    path = Path(path)
    tmp = _durable_temp(path, data)
    try:
        os.replace(tmp, path)
    except BaseException:
        os.unlink(tmp)
        raise
    fsync_dir(path.parent)
    return sha256_bytes(data)


def atomic_create_bytes(path: str | os.PathLike, data: bytes) -> str:
    """Write `data` to a new file `path` atomically; FileExistsError if it exists (link(2) never replaces)."""
    path = Path(path)
    tmp = _durable_temp(path, data)
    try:
        os.link(tmp, path)
    finally:
        os.unlink(tmp)
    fsync_dir(path.parent)
    return sha256_bytes(data)


def json_default(o):
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, (np.floating, np.integer, np.bool_)):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"cannot write {type(o).__name__} to JSON")


def atomic_write_json(path: str | os.PathLike, obj) -> str:
    """Write `obj` as indented JSON atomically; returns its sha256."""
    text = json.dumps(obj, indent=2, default=json_default, allow_nan=False)
    return atomic_write_bytes(path, (text + "\n").encode())


def encode_png(image: np.ndarray) -> bytes:
    """uint8/uint16 [H, W] or [H, W, 3|4] (RGB order) or float in [0, 1] (-> uint8) to lossless PNG bytes."""
    import cv2

    img = np.asarray(image)
    if img.dtype.kind == "f":
        img = (np.clip(img, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    if img.ndim == 3 and img.shape[2] == 3:
        img = img[..., ::-1]
    elif img.ndim == 3 and img.shape[2] == 4:
        img = img[..., [2, 1, 0, 3]]
    ok, buf = cv2.imencode(".png", np.ascontiguousarray(img))
    if not ok:
        raise ValueError("PNG encoding failed")
    return buf.tobytes()


def atomic_write_png(path: str | os.PathLike, image: np.ndarray) -> str:
    """Write an image (see `encode_png`) atomically; returns its sha256."""
    return atomic_write_bytes(path, encode_png(image))


def publish_dir(tmp: Path, out: Path) -> None:
    """Move the finished directory `tmp` to `out` (a sibling), replacing what `out` held: the old one
    steps aside first and is removed only once the new one is in place, so a crash leaves one whole."""
    import shutil

    old = None
    if out.exists():
        old = out.parent / f".{out.name}.replaced"
        shutil.rmtree(old, ignore_errors=True)
        os.rename(out, old)
    os.rename(tmp, out)
    fsync_dir(out.parent)
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)
