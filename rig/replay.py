"""Recorded captures played back as cameras: trigger `seq` shows capture `seq mod n`, every view of it.

`path` is one capture directory or a directory of them (a store's `captures/`); each camera plays
the frames with its `camera_id`. Images come back as recorded (distorted, uint8) with the
recorded camera model, so a replayed capture stores exactly like the original.
"""

from __future__ import annotations

import functools
import time
from pathlib import Path

import numpy as np

from calibration.camera import Camera
from calibration.capture import Capture, CaptureError, read_capture
from rig.camera import CameraError, CameraSettings, Frame, Health


@functools.lru_cache(maxsize=8)
def load_recordings(path: str) -> tuple[Capture, ...]:
    """The captures under `path` (itself a capture, or a directory of captures), sorted by name."""
    root = Path(path)
    if (root / "transforms.json").exists():
        dirs = [root]
    else:
        dirs = sorted(p for p in root.iterdir() if (p / "transforms.json").exists()) if root.is_dir() else []
    if not dirs:
        raise CameraError(f"{root}: no recorded captures to replay (no transforms.json here or in its sub-directories)")
    try:
        return tuple(read_capture(d, verify=False) for d in dirs)
    except CaptureError as e:
        raise CameraError(f"cannot replay {root}: {e}") from None


class ReplayCamera:
    """Camera `camera_id` of the recordings under `path`."""

    def __init__(self, camera_id: str, path: str | Path) -> None:
        self.camera_id = camera_id
        self.path = str(path)
        self._recordings: tuple[Capture, ...] = ()
        self._seq: int | None = None
        self._exposed_ns = 0
        self._frames = 0

    def _index(self, capture: Capture) -> int:
        for i, f in enumerate(capture.frames):
            if f.camera_id == self.camera_id:
                return i
        raise CameraError(f"{self.camera_id}: recording {capture.root.name} has no view from this camera")

    @property
    def camera(self) -> Camera:
        if not self._recordings:
            raise CameraError(f"{self.camera_id}: open the replay camera before asking for its model")
        return self._recordings[0].camera(self._index(self._recordings[0]), undistorted=False)

    def open(self) -> None:
        self._recordings = load_recordings(self.path)
        self._index(self._recordings[0])

    def configure(self, settings: CameraSettings) -> CameraSettings:
        cam = self.camera
        if (settings.width, settings.height) != (cam.width, cam.height):
            raise CameraError(f"{self.camera_id}: recordings are {cam.width}x{cam.height}, not {settings.width}x{settings.height}")
        recorded = self._recordings[0].meta.get("camera_settings", {}).get(self.camera_id, {})
        return CameraSettings(
            cam.width,
            cam.height,
            recorded.get("exposure_us"),
            recorded.get("iso"),
            recorded.get("white_balance_k"),
            recorded.get("focus"),
            "software",
        )

    def arm(self, seq: int) -> None:
        self._seq = seq
        self._exposed_ns = time.monotonic_ns()

    def grab(self, timeout_s: float) -> Frame:
        if not self._recordings or self._seq is None:
            raise CameraError(f"{self.camera_id}: grab before open and arm")
        capture = self._recordings[self._seq % len(self._recordings)]
        i = self._index(capture)
        try:
            image = capture.image(i, undistort=False)
        except CaptureError as e:
            raise CameraError(f"{self.camera_id}: recording unreadable ({e})") from None
        self._frames += 1
        settings = {**capture.meta.get("camera_settings", {}).get(self.camera_id, {}), "replayed_from": capture.root.name}
        return Frame(self.camera_id, (np.clip(image, 0, 1) * 255 + 0.5).astype(np.uint8), self._exposed_ns, settings)

    def close(self) -> None:
        self._recordings = ()

    def health(self) -> Health:
        ok = bool(self._recordings)
        return Health(self.camera_id, ok, f"replaying {len(self._recordings)} captures from {self.path}" if ok else "closed", self._frames)
