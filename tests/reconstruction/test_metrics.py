"""Image metrics of the evaluation protocol against values worked out by hand on tiny scenes."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from reconstruction import metrics as M


def _box_mask(h: int, w: int, rows: tuple[int, int], cols: tuple[int, int]) -> np.ndarray:
    mask = np.zeros((h, w), bool)
    mask[rows[0] : rows[1], cols[0] : cols[1]] = True
    return mask


# --- object crop --------------------------------------------------------------------------------


def test_crop_box_is_the_10_percent_padded_square_centred_on_the_mask() -> None:
    # Box [20, 40) x [10, 20): 20 wide, 10 tall -> side 22, centre (30, 15) -> left 19, top 4.
    assert M.crop_box(_box_mask(40, 60, (10, 20), (20, 40))) == (19, 4, 22)
    # 5 x 5 at the origin: 5 * 1.1 = 5.5 rounds half up to 6; centre 2.5 -> left edge -0.5 -> 0.
    assert M.crop_box(_box_mask(10, 10, (0, 5), (0, 5))) == (0, 0, 6)
    # A flat strip in the top rows: the square sticks out above the image.
    assert M.crop_box(_box_mask(20, 20, (0, 2), (0, 10))) == (0, -4, 11)
    # Only the mask's extent matters, not its shape.
    mask = np.zeros((40, 60), bool)
    mask[10, 20] = mask[19, 39] = True
    assert M.crop_box(mask) == (19, 4, 22)


def test_crop_box_rejects_an_empty_mask() -> None:
    with pytest.raises(ValueError, match="empty"):
        M.crop_box(np.zeros((8, 8), bool))


def test_crop_square_pads_with_white_outside_the_image() -> None:
    img = np.full((20, 20, 3), 0.5, np.float32)
    crop = M.crop_square(img, 0, -4, 11)
    assert crop.shape == (11, 11, 3)
    assert np.all(crop[:4] == 1.0) and np.all(crop[4:] == 0.5)
    crop = M.crop_square(img, 15, 15, 8)  # 5 x 5 inside, the rest white
    assert np.all(crop[:5, :5] == 0.5) and crop.sum() == 25 * 3 * 0.5 + (64 - 25) * 3


def test_lanczos_resize_gives_256_square_keeps_flat_images_and_clips_ringing() -> None:
    flat = np.full((37, 23, 3), 0.3, np.float32)
    out = M.lanczos_resize(flat)
    assert out.shape == (256, 256, 3) and out.dtype == np.float32
    np.testing.assert_allclose(out, 0.3, atol=1e-6)
    edge = np.zeros((40, 40, 3), np.float32)
    edge[:, 20:] = 1.0
    up = M.lanczos_resize(edge)
    assert up.min() == 0.0 and up.max() == 1.0  # Lanczos overshoots a step edge; clipped back
    # A crop that is already 256 px wide is not resampled at all.
    rng = np.random.default_rng(0)
    same = rng.random((256, 256, 3)).astype(np.float32)
    assert np.array_equal(M.lanczos_resize(same), same)


# --- erosion, PSNR, SSIM, IoU -------------------------------------------------------------------


def test_erode_mask_removes_5_px_along_edges_and_an_11x11_disc_around_a_hole() -> None:
    eroded = M.erode_mask(_box_mask(50, 50, (10, 40), (10, 40)))
    assert np.array_equal(eroded, _box_mask(50, 50, (15, 35), (15, 35)))
    holed = np.ones((41, 41), bool)
    holed[20, 20] = False
    eroded = M.erode_mask(holed)
    # OpenCV's 11x11 ellipse has rows of 1, 7, 9, 11, 11, 11, 11, 11, 9, 7, 1 pixels.
    assert (~eroded).sum() == 89
    assert not eroded[15, 20] and eroded[14, 20] and not eroded[20, 25] and eroded[20, 26]
    assert eroded[15, 19] and not eroded[16, 17]  # a disc, not a square
    # The image frame is not a silhouette edge: a full mask stays full.
    assert M.erode_mask(np.ones((12, 12), bool)).all()


def test_psnr_by_hand() -> None:
    a = np.full((4, 4, 3), 0.5, np.float32)
    b = np.full((4, 4, 3), 0.6, np.float32)
    assert M.psnr(a, b) == pytest.approx(20.0, abs=1e-5)  # mse 0.01
    b[:2] = 0.5
    assert M.psnr(a, b) == pytest.approx(-10 * math.log10(0.005), abs=1e-5)
    mask = np.zeros((4, 4), bool)
    mask[:2] = True
    assert M.psnr(a, b, mask) == math.inf
    assert M.psnr(a, b, ~mask) == pytest.approx(20.0, abs=1e-5)
    assert math.isnan(M.psnr(a, b, np.zeros((4, 4), bool)))


def test_ssim_of_flat_images_is_the_luminance_term() -> None:
    # No variance anywhere, so SSIM = (2ab + C1) / (a^2 + b^2 + C1).
    a = np.full((16, 16, 3), 0.2, np.float32)
    b = np.full((16, 16, 3), 0.6, np.float32)
    assert M.ssim(a, b) == pytest.approx((2 * 0.2 * 0.6 + 1e-4) / (0.2**2 + 0.6**2 + 1e-4), abs=1e-6)
    assert M.ssim(a, a) == pytest.approx(1.0, abs=1e-12)
    with pytest.raises(ValueError, match="11x11"):
        M.ssim(a[:10], b[:10])


def test_ssim_matches_skimage_gaussian_ssim() -> None:
    # skimage 0.26 structural_similarity(a, b, gaussian_weights=True, sigma=1.5,
    # use_sample_covariance=False, data_range=1, channel_axis=-1) on this pair: 0.9447624.
    rng = np.random.default_rng(0)
    a = rng.random((40, 33, 3)).astype(np.float32)
    b = np.clip(a + 0.1 * rng.standard_normal(a.shape), 0, 1).astype(np.float32)
    assert M.ssim(a, b) == pytest.approx(0.9447624, abs=1e-6)


def test_iou_thresholds_alpha_strictly_above_half() -> None:
    gt = _box_mask(10, 10, (0, 10), (0, 4))  # 40 px
    alpha = np.zeros((10, 10), np.float32)
    alpha[:, 2:6] = 0.9  # 40 px, 20 shared
    alpha[:, 6] = 0.5  # not rendered: alpha must exceed 0.5
    assert M.iou(alpha, gt) == pytest.approx(20 / 60)
    assert math.isnan(M.iou(np.zeros((3, 3)), np.zeros((3, 3), bool)))


def test_flip_of_identical_images_is_zero() -> None:
    rng = np.random.default_rng(1)
    img = rng.random((48, 40, 3)).astype(np.float32)
    assert M.flip(img, img.copy()) == 0.0
    assert 0.0 < M.flip(img, np.clip(img + 0.2, 0, 1)) < 1.0


# --- the whole protocol on one view ----------------------------------------------------------


def _scene() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """260x260 view: a 233 px GT square (so the object crop is exactly 256 px and Lanczos is the
    identity) of colour 0.2 on a noisy background, and a render of colour 0.3 shifted 4 px right."""
    h = w = 260
    gt_mask = _box_mask(h, w, (10, 243), (10, 243))
    rng = np.random.default_rng(2)
    gt = rng.random((h, w, 3)).astype(np.float32)  # background: must never be scored
    gt[gt_mask] = 0.2
    alpha = _box_mask(h, w, (10, 243), (14, 247)).astype(np.float32)
    pred = np.where(alpha[..., None] > 0, np.float32(0.3), np.float32(1.0)).repeat(3, axis=-1)
    return pred, alpha, gt, gt_mask


def test_image_metrics_by_hand() -> None:
    # Torch tensors in (as a trainer hands them over); the numpy path is the perfect-render test's.
    m = M.image_metrics(*(torch.from_numpy(x) for x in _scene()))
    assert set(m) == {"psnr", "ssim", "lpips", "flip", "mpsnr", "mssim", "mlpips", "mflip", "fgpsnr", "iou"}

    # Object crop: the square [-1, 255)^2 holds the whole scene; per channel, 229 x 233 shared pixels
    # differ by 0.1, 4 x 233 render-only pixels by 0.7 (0.3 vs white), 4 x 233 GT-only by 0.8.
    sq = 229 * 233 * 0.1**2 + 4 * 233 * 0.7**2 + 4 * 233 * 0.8**2
    assert m["psnr"] == pytest.approx(-10 * math.log10(sq / 256**2), abs=1e-4)

    # Eroded mask [15, 238)^2 lies inside the render: 223^2 pixels differ by 0.1, the rest is white.
    assert m["mpsnr"] == pytest.approx(-10 * math.log10(0.01 * 223**2 / 260**2), abs=1e-4)
    # fgPSNR scores only the 229 x 233 overlap, no background, no white: exactly 0.1 everywhere.
    assert m["fgpsnr"] == pytest.approx(20.0, abs=1e-4)
    assert m["iou"] == pytest.approx(229 / 237)

    for key in ("ssim", "mssim"):
        assert 0.0 < m[key] < 1.0
    for key in ("lpips", "mlpips", "flip", "mflip"):
        assert 0.0 < m[key] < 1.0
    # The eroded-mask metrics never see the misaligned band, so they score higher than the crop ones.
    assert m["mpsnr"] > m["psnr"] and m["mssim"] > m["ssim"] and m["mlpips"] < m["lpips"]


def test_image_metrics_of_a_perfect_render() -> None:
    _, _, gt, gt_mask = _scene()
    pred = M.composite_on_white(gt, gt_mask)
    m = M.image_metrics(pred, gt_mask.astype(np.float32), gt, gt_mask)
    assert m["psnr"] == m["mpsnr"] == m["fgpsnr"] == math.inf
    assert m["ssim"] == pytest.approx(1.0) and m["mssim"] == pytest.approx(1.0)
    assert m["lpips"] == pytest.approx(0.0, abs=1e-6) and m["mlpips"] == pytest.approx(0.0, abs=1e-6)
    assert m["flip"] == 0.0 and m["mflip"] == 0.0
    assert m["iou"] == 1.0


def test_image_metrics_reports_degenerate_views() -> None:
    # A 6 px object erodes to nothing and a render beside it shares no pixel with it.
    small = _box_mask(40, 40, (10, 16), (10, 16))
    gt = np.full((40, 40, 3), 0.2, np.float32)
    apart = _box_mask(40, 40, (30, 36), (30, 36)).astype(np.float32)
    m = M.image_metrics(np.ones((40, 40, 3), np.float32), apart, gt, small)
    assert all(math.isnan(m[k]) for k in ("mpsnr", "mssim", "mlpips", "mflip", "fgpsnr"))
    assert m["iou"] == 0.0
    with pytest.raises(ValueError, match="shapes"):
        M.image_metrics(np.ones((39, 40, 3), np.float32), apart, gt, small)
