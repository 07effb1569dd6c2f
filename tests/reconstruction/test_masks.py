"""Masks from the capture's masks/ or by background subtraction; neither is a clear error."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.camera import Camera
from calibration.capture import CaptureError, FrameData, write_capture
from reconstruction.masks import capture_masks, subtract_background
from reconstruction.silhouette import iou


def scene(seed=0):
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:120, 0:160]
    background = np.stack([0.3 + 0.2 * xx / 160, 0.5 + 0.1 * yy / 120, np.full_like(xx, 0.4, dtype=float)], -1)
    truth = (xx - 80) ** 2 / 30**2 + (yy - 60) ** 2 / 20**2 < 1
    image = background.copy()
    image[truth] = [0.8, 0.2, 0.1]
    image[truth & (xx < 70)] = [0.32, 0.52, 0.42]  # a patch close to the background colour
    noisy = np.clip(image + rng.normal(0, 0.01, image.shape), 0, 1)
    return noisy.astype(np.float32), np.clip(background + rng.normal(0, 0.01, image.shape), 0, 1).astype(np.float32), truth


def test_background_subtraction_recovers_the_object():
    image, background, truth = scene()
    mask = subtract_background(image, background)
    assert iou(mask, truth) > 0.6  # the camouflaged half is the hard part
    assert not mask[:, :20].any()  # no specks in the empty rig


def test_background_subtraction_distinct_object():
    image, background, truth = scene()
    image[truth] = [0.8, 0.2, 0.1]
    assert iou(subtract_background(image, background), truth) > 0.95


def _capture(tmp_path, name, with_masks, with_bg):
    image, background, truth = scene()
    cam = Camera.from_fov(1.0, 160, 120)
    frames = [FrameData("v0", image, cam, "cam0", mask=truth if with_masks else None)]
    return write_capture(tmp_path / name, frames, backgrounds={"cam0": background} if with_bg else None), truth


def test_capture_masks_sources(tmp_path):
    cap, truth = _capture(tmp_path, "a", True, True)
    masks, source = capture_masks(cap)
    assert source == "masks" and np.array_equal(masks[0], truth)
    cap, truth = _capture(tmp_path, "b", False, True)
    masks, source = capture_masks(cap)
    assert source == "background" and iou(masks[0], truth) > 0.6
    cap, _ = _capture(tmp_path, "c", False, False)
    with pytest.raises(CaptureError, match="neither masks/ nor background/"):
        capture_masks(cap)
