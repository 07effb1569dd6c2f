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

import numpy as np
import torch
import torch.nn.functional as F

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


def consistency_loss(colors: torch.Tensor, weights: torch.Tensor, eps: float = ROBUST_EPS) -> torch.Tensor:
    """Robust spread of each point's colours about their weighted mean: colors [V, N, 3], weights [V, N]
    (visibility, 0 or 1). Points seen by fewer than two views carry no information and no weight."""
    wsum = weights.sum(0)
    used = (wsum >= 2).to(colors.dtype)
    mean = (weights[..., None] * colors).sum(0) / wsum.clamp_min(1)[:, None]
    r2 = ((colors - mean[None]) ** 2).sum(-1)
    rho = eps * eps * (torch.sqrt(1 + r2 / (eps * eps)) - 1)
    return (weights * used[None] * rho).sum() / (weights * used[None]).sum().clamp_min(1)


def visibility_weights(visible: np.ndarray) -> torch.Tensor:
    """visible [V, N] bool (`splats.point_visibility`) -> float weights [V, N]."""
    return torch.from_numpy(np.asarray(visible, np.float32))
