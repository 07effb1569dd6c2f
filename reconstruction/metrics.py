"""Image metrics of the evaluation protocol (paper section 4.3, SPEC "Evaluation protocol").

All functions are pure: arrays in, numbers out. Images are [H, W, 3] float RGB in [0, 1] (sRGB, as
displayed), masks are [H, W] bool; numpy arrays and torch tensors (any device) are both accepted.

Protocol, per held-out view (`image_metrics`):
- Object crop -> psnr, ssim, lpips, flip (NeRS): the GT is composited on white with the GT mask,
  the prediction is taken as rendered over white, both are cropped to the same 10 %-padded square
  around the GT mask (`crop_box`) and Lanczos-resized to 256x256 (`object_crop`). The prediction
  is not masked, so geometry outside the true silhouette is penalised.
- Eroded mask -> mpsnr, mssim, mlpips, mflip (PixelNeRF/RegNeRF): both images are composited on
  white with the GT mask eroded by 5 px (`erode_mask`), full image.
- fgpsnr (CO3D): squared error averaged over the pixels inside both the rendered silhouette
  (alpha > 0.5) and the GT mask, full resolution, no compositing.
- iou: rendered silhouette (alpha > 0.5) against the un-eroded GT mask.
"""

from __future__ import annotations

import math

import cv2
import flip_evaluator
import numpy as np
import torch
from PIL import Image

from reconstruction.lpips import load_lpips
from reconstruction.ssim import ssim_map

Array = np.ndarray | torch.Tensor

CROP_SIZE = 256
ERODE_PX = 5
SSIM_WINDOW = 11
SSIM_SIGMA = 1.5
ALPHA_THRESHOLD = 0.5


def _numpy(x: Array, dtype: type = np.float32) -> np.ndarray:
    if isinstance(x, torch.Tensor):
        x = x.detach().cpu().numpy()
    return np.ascontiguousarray(x, dtype=dtype)


def _nchw(img: np.ndarray) -> torch.Tensor:
    """[H, W, 3] numpy -> [1, 3, H, W] float32 tensor."""
    return torch.from_numpy(img).permute(2, 0, 1).unsqueeze(0).float()


def composite_on_white(rgb: Array, mask: Array) -> np.ndarray:
    """`rgb` [H, W, 3] where `mask` [H, W] is true, white elsewhere; returns [H, W, 3] float32."""
    keep = _numpy(mask, bool)[..., None]
    return np.where(keep, _numpy(rgb), np.float32(1.0))


def crop_box(gt_mask: Array) -> tuple[int, int, int]:
    """The object-crop square (left, top, side) in pixels for a non-empty `gt_mask` [H, W].

    The GT mask's bounding box is [x0, x1) x [y0, y1) in pixel edges (x1 = last column + 1).
    The square's side is max(x1 - x0, y1 - y0) * 1.1 rounded half up, and its centre is the box's
    centre, with the left/top edge rounded half up to a whole pixel: the square is never resampled
    before the final resize, so an odd/even mismatch shifts it by half a pixel, never more. The
    square may leave the image; `crop_square` pads with white there.
    """
    ys, xs = np.nonzero(_numpy(gt_mask, bool))
    if xs.size == 0:
        raise ValueError("the ground-truth mask is empty: the object is not in this view")
    x0, x1 = int(xs.min()), int(xs.max()) + 1
    y0, y1 = int(ys.min()), int(ys.max()) + 1
    # Integer arithmetic so that e.g. 1.1 * 5 = 5.5 rounds to 6 on every platform.
    side = (11 * max(x1 - x0, y1 - y0) + 5) // 10
    left = (x0 + x1 - side + 1) // 2
    top = (y0 + y1 - side + 1) // 2
    return left, top, side


def crop_square(img: Array, left: int, top: int, side: int) -> np.ndarray:
    """The [side, side, 3] window of `img` [H, W, 3] at (left, top); white where it leaves the image."""
    img = _numpy(img)
    h, w = img.shape[:2]
    out = np.ones((side, side, img.shape[2]), np.float32)
    sx0, sy0 = max(left, 0), max(top, 0)
    sx1, sy1 = min(left + side, w), min(top + side, h)
    if sx0 < sx1 and sy0 < sy1:
        out[sy0 - top : sy1 - top, sx0 - left : sx1 - left] = img[sy0:sy1, sx0:sx1]
    return out


def lanczos_resize(img: Array, size: int = CROP_SIZE) -> np.ndarray:
    """`img` [H, W, C] resized to [size, size, C] with PIL's Lanczos filter, clipped to [0, 1].

    Each channel is resampled as a 32-bit float PIL image, so no 8-bit quantisation enters the
    metric; Lanczos rings past [0, 1] at hard edges, which no display shows, hence the clip.
    """
    img = _numpy(img)
    channels = [np.asarray(Image.fromarray(img[..., c]).resize((size, size), Image.Resampling.LANCZOS)) for c in range(img.shape[2])]
    return np.clip(np.stack(channels, axis=-1), 0.0, 1.0)


def object_crop(img: Array, gt_mask: Array, size: int = CROP_SIZE) -> np.ndarray:
    """`img` [H, W, 3] cropped to `crop_box(gt_mask)` and Lanczos-resized to [size, size, 3]."""
    return lanczos_resize(crop_square(img, *crop_box(gt_mask)), size)


def erode_mask(mask: Array, pixels: int = ERODE_PX) -> np.ndarray:
    """`mask` [H, W] bool eroded by `pixels`: [H, W] bool.

    The structuring element is OpenCV's (2p+1)x(2p+1) ellipse, a digital disc of radius p, so a
    silhouette shrinks by p pixels in every direction (p iterations of a 3x3 square would shrink
    diagonals by p*sqrt(2)). Outside the image counts as inside the mask (OpenCV's default for
    erosion): where the object is cut by the image frame there is no silhouette edge to distrust.
    """
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * pixels + 1, 2 * pixels + 1))
    return cv2.erode(_numpy(mask, np.uint8), kernel).astype(bool)


def psnr(pred: Array, gt: Array, mask: Array | None = None) -> float:
    """PSNR (dB, peak 1) of `pred` vs `gt` [H, W, 3]; mean squared error over the pixels of `mask` [H, W].

    inf for identical images; nan for an empty mask.
    """
    sq = (_numpy(pred, np.float64) - _numpy(gt, np.float64)) ** 2
    if mask is not None:
        sq = sq[_numpy(mask, bool)]
    if sq.size == 0:
        return math.nan
    mse = float(sq.mean())
    return math.inf if mse == 0.0 else -10.0 * math.log10(mse)


def ssim(pred: Array, gt: Array, window: int = SSIM_WINDOW, sigma: float = SSIM_SIGMA) -> float:
    """Mean SSIM (Wang et al. 2004) of `pred` vs `gt` [H, W, 3], data range 1.

    Gaussian window (11, sigma 1.5) applied separably without padding, K1 = 0.01, K2 = 0.03,
    population (co)variances, averaged over valid positions and channels: the same number as
    pytorch-msssim's `ssim` and skimage's `structural_similarity(gaussian_weights=True,
    use_sample_covariance=False, data_range=1, channel_axis=-1)`. H and W must be >= `window`.
    """
    x = torch.from_numpy(_numpy(pred, np.float64))[None]
    y = torch.from_numpy(_numpy(gt, np.float64))[None]
    h, w = x.shape[1:3]
    if min(h, w) < window:
        raise ValueError(f"SSIM needs images of at least {window}x{window} pixels, got {h}x{w}")
    # The zero-padded map of the loss, where each window lies inside the image, is the 'valid' map.
    r = window // 2
    with torch.no_grad():
        return float(ssim_map(x, y, window, sigma)[..., r : h - r, r : w - r].mean())


def lpips(pred: Array, gt: Array) -> float:
    """LPIPS (AlexNet, v0.1) of `pred` vs `gt` [H, W, 3] in [0, 1] (scaled to [-1, 1] as upstream)."""
    with torch.no_grad():
        x0 = _nchw(_numpy(pred)) * 2.0 - 1.0
        x1 = _nchw(_numpy(gt)) * 2.0 - 1.0
        return float(load_lpips()(x0, x1)[0])


def flip(pred: Array, gt: Array) -> float:
    """Mean LDR-FLIP error (NVIDIA `flip-evaluator`, default 67 pixels per degree) of `pred` vs reference `gt`."""
    _, mean_error, _ = flip_evaluator.evaluate(_numpy(gt), _numpy(pred), "LDR", applyMagma=False)
    return float(mean_error)


def iou(pred_alpha: Array, gt_mask: Array) -> float:
    """IoU of the rendered silhouette (`pred_alpha` [H, W] > 0.5) and `gt_mask` [H, W]; nan if both are empty."""
    a = _numpy(pred_alpha) > ALPHA_THRESHOLD
    b = _numpy(gt_mask, bool)
    union = int((a | b).sum())
    return math.nan if union == 0 else int((a & b).sum()) / union


def image_metrics(pred_rgb: Array, pred_alpha: Array, gt_rgb: Array, gt_mask: Array) -> dict[str, float]:
    """Every image metric of the protocol for one held-out view.

    Args:
        pred_rgb: [H, W, 3] float in [0, 1], the render composited over a white background.
            Clamped to [0, 1] first: rasterizer outputs overshoot by float error.
        pred_alpha: [H, W] float in [0, 1], the render's accumulated opacity.
        gt_rgb: [H, W, 3] float in [0, 1], the photograph (its background is ignored).
        gt_mask: [H, W] bool, the object's ground-truth mask; must be non-empty.

    Returns:
        psnr, ssim, lpips, flip (object crop); mpsnr, mssim, mlpips, mflip (5-px eroded GT mask,
        full image; nan when the eroded mask is empty, as there is nothing left to score); fgpsnr
        (nan when the silhouettes do not overlap); iou.
    """
    pred = np.clip(_numpy(pred_rgb), 0.0, 1.0)
    gt = _numpy(gt_rgb)
    mask = _numpy(gt_mask, bool)
    alpha = _numpy(pred_alpha)
    if pred.shape != gt.shape or pred.shape[:2] != mask.shape or alpha.shape != mask.shape:
        raise ValueError(f"shapes disagree: pred_rgb {pred.shape}, pred_alpha {alpha.shape}, gt_rgb {gt.shape}, gt_mask {mask.shape}")

    box = crop_box(mask)
    crop_pred = lanczos_resize(crop_square(pred, *box))
    crop_gt = lanczos_resize(crop_square(composite_on_white(gt, mask), *box))
    out = {
        "psnr": psnr(crop_pred, crop_gt),
        "ssim": ssim(crop_pred, crop_gt),
        "lpips": lpips(crop_pred, crop_gt),
        "flip": flip(crop_pred, crop_gt),
    }

    eroded = erode_mask(mask)
    if eroded.any():
        m_pred, m_gt = composite_on_white(pred, eroded), composite_on_white(gt, eroded)
        out |= {
            "mpsnr": psnr(m_pred, m_gt),
            "mssim": ssim(m_pred, m_gt),
            "mlpips": lpips(m_pred, m_gt),
            "mflip": flip(m_pred, m_gt),
        }
    else:
        out |= dict.fromkeys(("mpsnr", "mssim", "mlpips", "mflip"), math.nan)

    out["fgpsnr"] = psnr(pred, gt, mask=(alpha > ALPHA_THRESHOLD) & mask)
    out["iou"] = iou(alpha, mask)
    return out
