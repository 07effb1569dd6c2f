"""The rasterizer's kernels compiled in every mode training and rendering use (`reconstruction.warmup` runs this)."""

from __future__ import annotations

import torch

from reconstruction.render.rasterization import rasterize


def compile_render_kernels() -> None:
    """Renders a few splats through `rasterize` in every mode: alpha only; SH degrees 0-3, with and without a
    background; splat dropout (the paper preset); each with and without gradients."""
    n, w, h = 64, 32, 24
    gen = torch.Generator().manual_seed(0)
    means = torch.randn(n, 3, generator=gen) * 0.1 + torch.tensor([0.0, 0.0, 2.0])
    quats = torch.nn.functional.normalize(torch.randn(n, 4, generator=gen), dim=1)
    scales = torch.full((n, 3), 0.05)
    opacities = torch.full((n,), 0.9)
    viewmats = torch.eye(4).repeat(2, 1, 1)
    ks = torch.tensor([[30.0, 0, w / 2], [0, 30.0, h / 2], [0, 0, 1]]).repeat(2, 1, 1)
    backgrounds = torch.rand(2, 3, generator=gen)
    active = torch.arange(n) % 2 == 0
    modes = [(torch.zeros(n, 0), None, None, None)]
    modes += [(torch.rand(n, (d + 1) ** 2, 3, generator=gen), d, bg, None) for d in range(4) for bg in (None, backgrounds)]
    modes += [(torch.rand(n, 16, 3, generator=gen), 3, backgrounds, active)]
    for colors, degree, bg, keep in modes:
        for grad in (False, True):
            m = means.clone().requires_grad_(grad)
            c = colors.clone().requires_grad_(grad)
            rgb, alpha, _ = rasterize(m, quats, scales, opacities, c, viewmats, ks, w, h, sh_degree=degree, backgrounds=bg, active=keep)
            if grad:
                (rgb.sum() + alpha.sum()).backward()
