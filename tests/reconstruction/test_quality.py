"""The gates that refuse a confident wrong twin (issue 16, item 4)."""

from __future__ import annotations

import numpy as np
import pytest

from reconstruction.masks import mask_quality, subtract_background
from reconstruction.quality import QualityError, check_masks, check_registration, mask_problems
from tests.reconstruction.test_masks import scene


def test_whole_image_and_empty_masks_are_refused():
    masks = np.zeros((3, 40, 50), bool)
    masks[0, 10:30, 10:40] = True
    masks[1] = True
    assert mask_problems(masks)[0].startswith("view 1: the mask covers 100% of the image")
    assert "covers none of the image" in mask_problems(masks)[1]
    with pytest.raises(QualityError, match=r"^masks refused: view 1: the mask covers 100%.*\(1 more view\(s\) alike\)$"):
        check_masks(masks)
    check_masks(masks[:1])


def test_registration_gates():
    ring = np.zeros((2, 60, 60), bool)
    yy, xx = np.mgrid[0:60, 0:60]
    ring[:] = (xx - 30) ** 2 + (yy - 30) ** 2 < 400
    with pytest.raises(QualityError, match="every library model fits these silhouettes alike"):
        check_registration(0.80, [("b", 0.795), ("c", 0.79)], ring, 3, "a")
    check_registration(0.90, [("b", 0.6), ("c", 0.5)], ring, 3, "a")
    rect = np.zeros((2, 60, 60), bool)
    rect[:, 10:50, 5:55] = True
    with pytest.raises(QualityError, match="plain rectangles"):
        check_registration(0.99, [("b", 0.6), ("c", 0.5)], rect, 3, "imu_adis16480")
    check_registration(0.99, [("b", 0.6), ("c", 0.5)], ring, 3, "a")  # a round part fitting well is fine


def test_mask_quality_refuses_nothing_everything_and_a_lighting_change():
    image, background, _ = scene()
    good = mask_quality(image, background, subtract_background(image, background))
    assert good.problem == "" and good.score > 0.5
    empty = mask_quality(background, background, subtract_background(background, background))
    assert empty.problem.startswith("nothing differs") and empty.score == 0.0
    darker = np.clip(image * 0.6, 0, 1)
    assert "lighting or exposure changed" in mask_quality(darker, background, subtract_background(darker, background)).problem
    noise = np.random.default_rng(0).random(image.shape).astype(np.float32)
    assert mask_quality(noise, background, np.ones(image.shape[:2], bool)).problem != ""
