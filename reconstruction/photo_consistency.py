"""Multi-view photo-consistency of the surface: the pose and shape signal in the texture.

Silhouettes of a CAD model that is not quite the photographed object pull a pose to a biased
optimum, and they say nothing about a surface inside the outline. Calibrated views that see the
same textured point must agree on its colour: for points on the (deformed) surface, the colours
that the views sample at the points' projections should match, and their spread, differentiable
in the camera poses and in the points, is the objective (the data term of multi-view stereo). It
pins the surface along its normal wherever the object is textured, which the silhouette cannot,
and the silhouette pins what texture cannot (a slide along a flat face).

Images are blurred before sampling so the objective reaches a few pixels of misalignment
(bilinear samples of a sharp texture give gradients only within a pixel).
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F
from numba import njit
from torch.autograd.function import once_differentiable

from reconstruction.parallel import parallel_for

# Charbonnier scale (colour units): a specular highlight or a wrongly visible point weighs like an
# outlier, not quadratically (render noise of a rig is ~0.01-0.02).
ROBUST_EPS = 0.05


def blurred(images: torch.Tensor, sigma_px: float) -> torch.Tensor:
    """images [V, H, W, 3] -> [V, 3, H, W] Gaussian-blurred by `sigma_px` (none at 0), ready for sampling."""
    x = images.permute(0, 3, 1, 2).contiguous()
    if sigma_px <= 0:
        return x
    radius = max(1, int(round(3 * sigma_px)))
    t = torch.arange(-radius, radius + 1, dtype=x.dtype)
    g = torch.exp(-0.5 * (t / sigma_px) ** 2)
    g = g / g.sum()
    c = x.shape[1]
    x = F.conv2d(F.pad(x, (radius, radius, 0, 0), mode="replicate"), g.reshape(1, 1, 1, -1).expand(c, 1, 1, -1), groups=c)
    return F.conv2d(F.pad(x, (0, 0, radius, radius), mode="replicate"), g.reshape(1, 1, -1, 1).expand(c, 1, -1, 1), groups=c)


def sample_colors(images: torch.Tensor, points: torch.Tensor, viewmats: torch.Tensor, Ks: torch.Tensor) -> torch.Tensor:
    """Bilinear colours [V, N, 3] of points [N, 3] in images [V, 3, H, W] seen by viewmats [V, 4, 4], Ks [V, 3, 3].

    Pixel centres at +0.5 (`grid_sample` with align_corners=False); differentiable in points,
    viewmats and Ks. Points behind a camera sample the border (callers weigh them out).
    """
    h, w = images.shape[-2:]
    cam = points[None] @ viewmats[:, :3, :3].transpose(1, 2) + viewmats[:, None, :3, 3]
    z = cam[..., 2:].clamp_min(1e-9)
    uv = (cam[..., :2] / z) @ Ks[:, :2, :2].transpose(1, 2) + Ks[:, None, :2, 2]
    grid = torch.stack([uv[..., 0] / w, uv[..., 1] / h], -1) * 2 - 1
    out = F.grid_sample(images, grid[:, :, None, :].to(images.dtype), mode="bilinear", padding_mode="border", align_corners=False)
    return out[..., 0].permute(0, 2, 1)


@njit(cache=True, nogil=True, error_model="numpy")
def _robust_spread(lo, hi, colors, weights, eps, point_loss, point_weight, grad) -> None:
    """Points lo..hi-1 of colors [V, N, C], weights [V, N]: point_loss [N] = sum_v w rho(|c_v - mean|^2),
    point_weight [N] = sum_v w (both 0 for a point seen by fewer than two views) and grad [V, N, C], the
    gradient of point_loss with respect to the colours (the mean included)."""
    n_views, _, n_ch = colors.shape
    mean = np.empty(n_ch)
    pull = np.empty(n_ch)
    for n in range(lo, hi):
        wsum = 0.0
        for v in range(n_views):
            wsum += weights[v, n]
        point_loss[n] = 0.0
        point_weight[n] = 0.0
        if not wsum >= 2.0:
            for v in range(n_views):
                for ch in range(n_ch):
                    grad[v, n, ch] = 0.0
            continue
        mean[:] = 0.0
        for v in range(n_views):
            for ch in range(n_ch):
                mean[ch] += weights[v, n] * colors[v, n, ch]
        for ch in range(n_ch):
            mean[ch] /= wsum
        # rho(r2) = eps^2 (sqrt(1 + r2 / eps^2) - 1), rho' = 1 / (2 sqrt(1 + r2 / eps^2)); through the mean,
        # colour v also pulls on every other view's residual by w_v / wsum.
        pull[:] = 0.0
        total = 0.0
        for v in range(n_views):
            r2 = 0.0
            for ch in range(n_ch):
                d = colors[v, n, ch] - mean[ch]
                r2 += d * d
            root = math.sqrt(1.0 + r2 / (eps * eps))
            total += weights[v, n] * eps * eps * (root - 1.0)
            a = weights[v, n] / root
            for ch in range(n_ch):
                grad[v, n, ch] = a * (colors[v, n, ch] - mean[ch])
                pull[ch] += grad[v, n, ch]
        for v in range(n_views):
            share = weights[v, n] / wsum
            for ch in range(n_ch):
                grad[v, n, ch] -= share * pull[ch]
        point_loss[n] = total
        point_weight[n] = wsum


class _ConsistencyLoss(torch.autograd.Function):
    """`consistency_loss` in one pass with its gradient, where a dozen torch ops over [V, N, 3] and their backward
    ran: the term (sampling included) 10-12 -> 7.5 ms forward+backward for 10 views x 15k points."""

    @staticmethod
    def forward(ctx, colors: torch.Tensor, weights: torch.Tensor, eps: float) -> torch.Tensor:
        c = colors.detach().contiguous().numpy()
        w = weights.detach().to(colors.dtype).contiguous().numpy()
        n = c.shape[1]
        point_loss, point_weight, grad = np.empty(n), np.empty(n), np.empty_like(c)
        parallel_for(_robust_spread, n, c, w, float(eps), point_loss, point_weight, grad, grain=4096)
        norm = max(float(point_weight.sum()), 1.0)
        ctx.save_for_backward(torch.from_numpy(grad).div_(norm))
        return torch.tensor(point_loss.sum() / norm, dtype=colors.dtype)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad_out: torch.Tensor):
        (grad,) = ctx.saved_tensors
        return grad * grad_out, None, None


def consistency_loss(colors: torch.Tensor, weights: torch.Tensor, eps: float = ROBUST_EPS) -> torch.Tensor:
    """Robust spread of each point's colours about their weighted mean: colors [V, N, 3], weights [V, N]
    (visibility, 0 or 1). Points seen by fewer than two views carry no information and no weight.

    sum over points seen twice or more and their views of w rho(|c - mean|^2) / sum of those w, with the
    Charbonnier rho(r2) = eps^2 (sqrt(1 + r2 / eps^2) - 1); differentiable in the colours."""
    if colors.is_cuda or colors.dtype not in (torch.float32, torch.float64):
        wsum = weights.sum(0)
        used = (wsum >= 2).to(colors.dtype)
        mean = (weights[..., None] * colors).sum(0) / wsum.clamp_min(1)[:, None]
        r2 = ((colors - mean[None]) ** 2).sum(-1)
        rho = eps * eps * (torch.sqrt(1 + r2 / (eps * eps)) - 1)
        return (weights * used[None] * rho).sum() / (weights * used[None]).sum().clamp_min(1)
    return _ConsistencyLoss.apply(colors, weights, eps)


def visibility_weights(visible: np.ndarray) -> torch.Tensor:
    """visible [V, N] bool (`splats.point_visibility`) -> float weights [V, N]."""
    return torch.from_numpy(np.asarray(visible, np.float32))
