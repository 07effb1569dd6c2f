"""Shared helpers for the rig tests: a store + pattern-camera acquisition, and the store invariant."""

from __future__ import annotations

from pathlib import Path

import pytest

from calibration.capture import read_capture
from rig.acquisition import Acquisition, Thresholds, agree_photometry
from rig.camera import CameraSettings
from rig.store import CAPTURES, INCOMING, CaptureStore
from rig.synthetic_driver import PatternCamera


def pattern_cameras(n: int = 3, width: int = 64, height: int = 48) -> list[PatternCamera]:
    return [PatternCamera(f"cam{i}", index=i, n=n, width=width, height=height) for i in range(n)]


def make_acquisition(root: Path, cameras=None, **kw) -> Acquisition:
    cameras = cameras if cameras is not None else pattern_cameras()
    for cam in cameras:
        cam.open()
    settings = agree_photometry(cameras, CameraSettings(cameras[0].camera.width, cameras[0].camera.height))
    store = kw.pop("store", None) or CaptureStore(root, min_free_bytes=0)
    kw.setdefault("thresholds", Thresholds(sync_tolerance_ns=50_000_000))
    return Acquisition(cameras, store, settings=settings, **kw)


def assert_store_sound(root: Path, reported: list[str]) -> list[str]:
    """The acceptance invariant: captures/ holds only complete, verified captures, every id
    reported as committed is among them, and nothing is left half-written in .incoming/."""
    root = Path(root)
    stored = sorted(p.name for p in (root / CAPTURES).iterdir())
    for name in stored:
        cap = read_capture(root / CAPTURES / name, verify=True)
        assert cap.meta["capture_id"] == name
        assert set(cap.meta["sha256"]) >= {f.file_path for f in cap.frames}
    missing = sorted(set(reported) - set(stored))
    assert not missing, f"reported as captured but missing: {missing}"
    assert not any((root / INCOMING).iterdir()), "half-written entries left in .incoming/"
    return stored


@pytest.fixture
def store_root(tmp_path) -> Path:
    return tmp_path / "store"
