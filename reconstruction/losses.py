"""Training losses and the splat-dropout schedule (paper 3.6).

Images are [C, H, W, 3] float32 tensors in [0, 1]; alphas and masks [C, H, W] or [C, H, W, 1]
(masks may be fractional: a mask downsampled by area keeps its edge coverage).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F


def _hw(t: torch.Tensor) -> torch.Tensor:
    return t[..., 0] if t.dim() == 4 else t


def mask_l1(alpha: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """L_mask = mean |A - M| over pixels (eq. mask)."""
    return (_hw(alpha) - _hw(mask).to(alpha.dtype)).abs().mean()


def fill_loss(alpha: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean under-coverage 1 - A over the object, sum M (1 - A) / sum M: pushes the rendered alpha to
    saturate inside the mask. L_mask spreads its weight over the whole image, so the object's rim
    pixels (a few % of it) stay at alpha 0.5-0.9, and a render composited on white shows them washed out."""
    m = _hw(mask).to(alpha.dtype)
    return (m * (1 - _hw(alpha))).sum() / m.sum().clamp_min(1.0)


def composite(image: torch.Tensor, mask: torch.Tensor, background: torch.Tensor) -> torch.Tensor:
    """image [C, H, W, 3] over `background` [C, 3] or [3] where mask [C, H, W] is 0."""
    m = _hw(mask).to(image.dtype)[..., None]
    bg = background.reshape(-1, 1, 1, 3).to(image.dtype)
    return image * m + bg * (1 - m)


def _gaussian_window(size: int, sigma: float, dtype: torch.dtype) -> torch.Tensor:
    x = torch.arange(size, dtype=dtype) - (size - 1) / 2
    g = torch.exp(-(x * x) / (2 * sigma * sigma))
    return g / g.sum()


def ssim(a: torch.Tensor, b: torch.Tensor, window: int = 11, sigma: float = 1.5) -> torch.Tensor:
    """Mean SSIM of [C, H, W, 3] images (Gaussian window, as 3DGS; zero padding at the borders)."""
    x = a.permute(0, 3, 1, 2)
    y = b.permute(0, 3, 1, 2)
    ch = x.shape[1]
    g = _gaussian_window(window, sigma, x.dtype)
    # Separable blur: a row pass then a column pass, depthwise per channel.
    kx = g.reshape(1, 1, 1, -1).expand(ch, 1, 1, window)
    ky = g.reshape(1, 1, -1, 1).expand(ch, 1, window, 1)

    def blur(t):
        t = F.conv2d(t, kx, padding=(0, window // 2), groups=ch)
        return F.conv2d(t, ky, padding=(window // 2, 0), groups=ch)

    mu_x, mu_y = blur(x), blur(y)
    sxx = blur(x * x) - mu_x * mu_x
    syy = blur(y * y) - mu_y * mu_y
    sxy = blur(x * y) - mu_x * mu_y
    c1, c2 = 0.01**2, 0.03**2
    s = ((2 * mu_x * mu_y + c1) * (2 * sxy + c2)) / ((mu_x * mu_x + mu_y * mu_y + c1) * (sxx + syy + c2))
    return s.mean()


def photometric_loss(render: torch.Tensor, target: torch.Tensor, lambda_dssim: float = 0.2) -> torch.Tensor:
    """L_rgb = (1 - λ) L1 + λ D-SSIM, D-SSIM = 1 - SSIM (3DGS)."""
    l1 = (render - target).abs().mean()
    return (1 - lambda_dssim) * l1 + lambda_dssim * (1 - ssim(render, target))


def sh_neighbour_loss(sh: torch.Tensor, neighbours: torch.Tensor) -> torch.Tensor:
    """L_SH = 1/(N K) sum_i sum_{j in N(i)} ||c_i - c_j||^2 for sh [N, B, 3], neighbours [N, K] (eq. sh_smooth)."""
    n, k = neighbours.shape
    if k == 0:
        return sh.sum() * 0
    c = sh.reshape(n, -1)
    return ((c[:, None, :] - c[neighbours]) ** 2).sum(-1).mean()


def dropout_fraction(step: int, anneal_steps: int, p0: float = 0.5) -> float:
    """Fraction of splats dropped at Stage-II `step`: p0 cosine-annealed to 0 at `anneal_steps`, then 0."""
    if anneal_steps <= 0 or step >= anneal_steps:
        return 0.0
    return p0 * 0.5 * (1.0 + math.cos(math.pi * max(step, 0) / anneal_steps))


def dropout_active(n: int, fraction: float, generator: torch.Generator) -> torch.Tensor | None:
    """bool [n] keeping all but round(fraction * n) splats, dropped uniformly without replacement; None keeps all."""
    drop = int(round(fraction * n))
    if drop <= 0:
        return None
    active = torch.ones(n, dtype=torch.bool)
    active[torch.randperm(n, generator=generator)[:drop]] = False
    return active
