"""The rig's empty-rig reference: one frame per camera of the belt with no part on it, versioned.

Background-difference masks compare every capture with this reference, so it is kept like the
calibration: every version ever taken stays, never overwritten, and every capture records which
version it was taken against (`background_id` in its transforms.json, with a copy of the frames
in its own background/ so the capture stays self-contained).

Layout under the capture store:

    references/v0001/<camera>.png     the empty-rig frame of each camera (RGB uint8)
    references/v0001/reference.json   version, time, why it was taken, cameras, sha256 of every frame
    references/.v0002.<rand>.incoming a version being written (removed on the next open)

A version directory is assembled beside its final name and renamed into place, so a version is
complete and verifying, or absent.
"""

from __future__ import annotations

import datetime as dt
import json
import os
import re
import shutil
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from calibration.capture import CaptureError, read_image
from calibration.fileio import atomic_write_bytes, atomic_write_json, encode_png, fsync_dir, sha256_file

REFERENCE_JSON = "reference.json"
_VERSION = re.compile(r"^v(\d{4,})$")


class ReferenceError(ValueError):
    """An empty-rig reference that cannot be read or written; one plain sentence."""


def reference_id(version: int) -> str:
    return f"reference-v{version:04d}"


@dataclass(frozen=True)
class Reference:
    """One version: `frames` camera id -> RGB uint8 [H, W, 3]."""

    version: int
    frames: dict[str, np.ndarray]
    reason: str
    created: str

    @property
    def reference_id(self) -> str:
        return reference_id(self.version)


class ReferenceStore:
    """The versions of the empty-rig reference under `root` (write-once, like calibration versions)."""

    def __init__(self, root: str | os.PathLike) -> None:
        self.root = Path(root)

    def versions(self) -> list[int]:
        if not self.root.is_dir():
            return []
        return sorted(int(m.group(1)) for p in self.root.iterdir() if p.is_dir() and (m := _VERSION.match(p.name)))

    def clean(self) -> None:
        """Remove versions an interrupted write left half-assembled (never published under a version name)."""
        if self.root.is_dir():
            for p in self.root.glob(".v*.incoming"):
                shutil.rmtree(p, ignore_errors=True)

    def load(self, version: int) -> Reference:
        """A version, every frame's sha256 verified."""
        folder = self.root / f"v{version:04d}"
        try:
            doc = json.loads((folder / REFERENCE_JSON).read_text())
            digests = doc["sha256"]
            frames = {}
            for cam, rel in doc["cameras"].items():
                if sha256_file(folder / rel) != digests[rel]:
                    raise ReferenceError(f"{folder / rel}: sha256 does not match {REFERENCE_JSON} (file changed or corrupt)")
                frames[cam] = (read_image(folder / rel)[..., :3] * 255.0).round().astype(np.uint8)
        except FileNotFoundError as e:
            raise ReferenceError(f"{folder}: empty-rig reference is incomplete ({Path(e.filename).name} is missing)") from None
        except (ValueError, KeyError, TypeError, CaptureError) as e:
            if isinstance(e, ReferenceError):
                raise
            raise ReferenceError(f"{folder}: empty-rig reference is unreadable ({e})") from None
        return Reference(version, frames, str(doc.get("reason", "")), str(doc.get("created", "")))

    def current(self) -> Reference | None:
        """The newest version, or None when none was ever taken."""
        versions = self.versions()
        return self.load(versions[-1]) if versions else None

    def verify(self) -> list[str]:
        """One sentence per version that does not verify (empty list: all good)."""
        problems = []
        for v in self.versions():
            try:
                self.load(v)
            except ReferenceError as e:
                problems.append(str(e))
        return problems

    def commit(self, frames: dict[str, np.ndarray], reason: str) -> Reference:
        """Store `frames` (camera id -> RGB [H, W, 3]) as the next version; returns it."""
        if not frames:
            raise ReferenceError("an empty-rig reference needs a frame from at least one camera")
        self.root.mkdir(parents=True, exist_ok=True)
        version = max(self.versions(), default=0) + 1
        final = self.root / f"v{version:04d}"
        tmp = Path(tempfile.mkdtemp(prefix=f".v{version:04d}.", suffix=".incoming", dir=self.root))
        created = dt.datetime.now(dt.timezone.utc).isoformat(timespec="seconds")
        try:
            digests, cameras = {}, {}
            for cam, img in sorted(frames.items()):
                rel = f"{cam}.png"
                digests[rel] = atomic_write_bytes(tmp / rel, encode_png(np.asarray(img)[..., :3]))
                cameras[cam] = rel
            atomic_write_json(
                tmp / REFERENCE_JSON, {"version": version, "created": created, "reason": reason, "cameras": cameras, "sha256": digests}
            )
            os.rename(tmp, final)
            fsync_dir(self.root)
        except BaseException:
            shutil.rmtree(tmp, ignore_errors=True)
            raise
        return Reference(version, {k: np.asarray(v)[..., :3].astype(np.uint8) for k, v in frames.items()}, reason, created)
