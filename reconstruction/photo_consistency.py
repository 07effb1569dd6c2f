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
    """images [V, H, W, 3] Gaussian-blurred by `sigma_px` (none at 0), contiguous, ready for `sample_colors`."""
    if sigma_px <= 0:
        return images.contiguous()
    x = images.permute(0, 3, 1, 2).contiguous()
    radius = max(1, int(round(3 * sigma_px)))
    t = torch.arange(-radius, radius + 1, dtype=x.dtype)
    g = torch.exp(-0.5 * (t / sigma_px) ** 2)
    g = g / g.sum()
    c = x.shape[1]
    x = F.conv2d(F.pad(x, (radius, radius, 0, 0), mode="replicate"), g.reshape(1, 1, 1, -1).expand(c, 1, 1, -1), groups=c)
    x = F.conv2d(F.pad(x, (0, 0, radius, radius), mode="replicate"), g.reshape(1, 1, -1, 1).expand(c, 1, -1, 1), groups=c)
    return x.permute(0, 2, 3, 1).contiguous()


@njit(inline="always", cache=True, nogil=True, error_model="numpy")
def _pixel_of(point, viewmat, K, width, height):
    """(camera-frame X, Y, clamped z, x, y, gx, gy) of a point: x, y its continuous pixel coordinates (pixel centres
    at integers) clipped to the image as grid_sample's border padding does, gx, gy 1 where unclipped (else 0)."""
    cx = viewmat[0, 0] * point[0] + viewmat[0, 1] * point[1] + viewmat[0, 2] * point[2] + viewmat[0, 3]
    cy = viewmat[1, 0] * point[0] + viewmat[1, 1] * point[1] + viewmat[1, 2] * point[2] + viewmat[1, 3]
    cz = viewmat[2, 0] * point[0] + viewmat[2, 1] * point[1] + viewmat[2, 2] * point[2] + viewmat[2, 3]
    z = max(cz, 1e-9)
    xn, yn = cx / z, cy / z
    x = K[0, 0] * xn + K[0, 1] * yn + K[0, 2] - 0.5
    y = K[1, 0] * xn + K[1, 1] * yn + K[1, 2] - 0.5
    gx, gy = 1.0, 1.0
    if not x > 0.0:
        x, gx = 0.0, 0.0
    elif x >= width - 1:
        x, gx = width - 1.0, 0.0
    if not y > 0.0:
        y, gy = 0.0, 0.0
    elif y >= height - 1:
        y, gy = height - 1.0, 0.0
    return cx, cy, z if cz > 1e-9 else -1.0, x, y, gx, gy


@njit(cache=True, nogil=True, error_model="numpy")
def _sample_forward(view_lo, view_hi, images, points, viewmats, Ks, out) -> None:
    """out [V, N, C] = bilinear samples of images [V, H, W, C] at points [N, 3] seen by viewmats [V, 4, 4], Ks [V, 3, 3],
    one view at a time (its image stays in cache); corners off the image count as 0, as in grid_sample."""
    _, height, width, n_ch = images.shape
    for v in range(view_lo, view_hi):
        img, K, vm = images[v], Ks[v], viewmats[v]
        for i in range(points.shape[0]):
            _, _, _, x, y, _, _ = _pixel_of(points[i], vm, K, width, height)
            x0, y0 = int(math.floor(x)), int(math.floor(y))
            fx, fy = x - x0, y - y0
            in_x1, in_y1 = x0 + 1 < width, y0 + 1 < height
            for ch in range(n_ch):
                value = (1.0 - fx) * (1.0 - fy) * img[y0, x0, ch]
                if in_x1:
                    value += fx * (1.0 - fy) * img[y0, x0 + 1, ch]
                if in_y1:
                    value += (1.0 - fx) * fy * img[y0 + 1, x0, ch]
                    if in_x1:
                        value += fx * fy * img[y0 + 1, x0 + 1, ch]
                out[v, i, ch] = value


@njit(cache=True, nogil=True, error_model="numpy")
def _sample_backward(view_lo, view_hi, images, points, viewmats, Ks, grad, v_points_per_view, v_views) -> None:
    """VJP of `_sample_forward` for grad [V, N, C], one view at a time (its image stays in cache and its pose gradient
    in registers): v_points_per_view [V, N, 3] and v_views [V, 3, 4] (d/d of each viewmat's top rows), both written."""
    _, height, width, n_ch = images.shape
    n = points.shape[0]
    for v in range(view_lo, view_hi):
        img, K, vm = images[v], Ks[v], viewmats[v]
        a00, a01, a02, a03, a10, a11, a12, a13, a20, a21, a22, a23 = 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
        for i in range(n):
            p = points[i]
            cx, cy, z, x, y, gx, gy = _pixel_of(p, vm, K, width, height)
            x0, y0 = int(math.floor(x)), int(math.floor(y))
            fx, fy = x - x0, y - y0
            in_x1, in_y1 = x0 + 1 < width, y0 + 1 < height
            d_x, d_y = 0.0, 0.0
            for ch in range(n_ch):
                g = grad[v, i, ch]
                v00 = img[y0, x0, ch]
                v01 = img[y0, x0 + 1, ch] if in_x1 else 0.0
                v10 = img[y0 + 1, x0, ch] if in_y1 else 0.0
                v11 = img[y0 + 1, x0 + 1, ch] if in_x1 and in_y1 else 0.0
                d_x += g * ((v01 - v00) * (1.0 - fy) + (v11 - v10) * fy)
                d_y += g * ((v10 - v00) * (1.0 - fx) + (v11 - v01) * fx)
            d_x *= gx
            d_y *= gy
            if z < 0.0:
                # Behind the camera the clamped depth carries no gradient.
                d_x, d_y = 0.0, 0.0
            d_xn = K[0, 0] * d_x + K[1, 0] * d_y
            d_yn = K[0, 1] * d_x + K[1, 1] * d_y
            inv_z = 1.0 / z
            g_cx, g_cy = d_xn * inv_z, d_yn * inv_z
            g_cz = -(d_xn * cx + d_yn * cy) * inv_z * inv_z
            v_points_per_view[v, i, 0] = vm[0, 0] * g_cx + vm[1, 0] * g_cy + vm[2, 0] * g_cz
            v_points_per_view[v, i, 1] = vm[0, 1] * g_cx + vm[1, 1] * g_cy + vm[2, 1] * g_cz
            v_points_per_view[v, i, 2] = vm[0, 2] * g_cx + vm[1, 2] * g_cy + vm[2, 2] * g_cz
            a00 += g_cx * p[0]
            a01 += g_cx * p[1]
            a02 += g_cx * p[2]
            a03 += g_cx
            a10 += g_cy * p[0]
            a11 += g_cy * p[1]
            a12 += g_cy * p[2]
            a13 += g_cy
            a20 += g_cz * p[0]
            a21 += g_cz * p[1]
            a22 += g_cz * p[2]
            a23 += g_cz
        v_views[v, 0, 0], v_views[v, 0, 1], v_views[v, 0, 2], v_views[v, 0, 3] = a00, a01, a02, a03
        v_views[v, 1, 0], v_views[v, 1, 1], v_views[v, 1, 2], v_views[v, 1, 3] = a10, a11, a12, a13
        v_views[v, 2, 0], v_views[v, 2, 1], v_views[v, 2, 2], v_views[v, 2, 3] = a20, a21, a22, a23


class _SampleColors(torch.autograd.Function):
    """`sample_colors` on the CPU: projection and bilinear sampling in one numba pass each way, one view per task,
    where a dozen torch ops (batched matmuls, divisions, permutes, grid_sample and its backward) ran (measured:
    benchmarks/results/profile.md)."""

    @staticmethod
    def forward(ctx, images: torch.Tensor, points: torch.Tensor, viewmats: torch.Tensor, Ks: torch.Tensor) -> torch.Tensor:
        arrays = [t.detach().to(torch.float64).contiguous().numpy() for t in (points, viewmats, Ks)]
        imgs = images.detach().contiguous().numpy()
        out = np.empty((imgs.shape[0], arrays[0].shape[0], imgs.shape[3]), imgs.dtype)
        parallel_for(_sample_forward, imgs.shape[0], imgs, *arrays, out)
        ctx.arrays, ctx.imgs, ctx.dtypes = arrays, imgs, (points.dtype, viewmats.dtype)
        return torch.from_numpy(out)

    @staticmethod
    @once_differentiable
    def backward(ctx, grad: torch.Tensor):
        points, viewmats, Ks = ctx.arrays
        n_views = viewmats.shape[0]
        v_points_per_view = np.empty((n_views, points.shape[0], 3))
        v_views = np.empty((n_views, 3, 4))
        parallel_for(
            _sample_backward, n_views, ctx.imgs, points, viewmats, Ks, grad.detach().contiguous().numpy(), v_points_per_view, v_views
        )
        v_points = v_points_per_view.sum(0)
        v_viewmats = np.zeros_like(viewmats)
        v_viewmats[:, :3, :] = v_views
        return (None, torch.from_numpy(v_points).to(ctx.dtypes[0]), torch.from_numpy(v_viewmats).to(ctx.dtypes[1]), None)


def sample_colors(images: torch.Tensor, points: torch.Tensor, viewmats: torch.Tensor, Ks: torch.Tensor) -> torch.Tensor:
    """Bilinear colours [V, N, 3] of points [N, 3] in images [V, H, W, 3] seen by viewmats [V, 4, 4], Ks [V, 3, 3].

    Pixel centres at +0.5, border padding (as `grid_sample` with align_corners=False); differentiable in points and
    viewmats (on CPU tensors, not in the images or Ks, which training holds fixed; elsewhere through `grid_sample`,
    in all four). Points behind a camera sample the border (callers weigh them out) and pass no gradient.
    """
    if images.device.type == "cpu" and not images.requires_grad and not Ks.requires_grad and images.dtype in (torch.float32, torch.float64):
        return _SampleColors.apply(images, points, viewmats, Ks)
    h, w = images.shape[1:3]
    images = images.permute(0, 3, 1, 2)
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
    ran (measured: benchmarks/results/profile.md)."""

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
