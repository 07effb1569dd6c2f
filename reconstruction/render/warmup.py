"""Compile the training loop's numba kernels once, at install time: `python -m reconstruction.render.warmup`.

The kernels are cached on disk (`cache=True`) per argument type, so the first reconstruction of a
fresh clone would otherwise spend ~20 s compiling. Rendering a few splats through the public
`rasterize` in every mode training and rendering use (alpha only; SH degrees 0-3 over a background;
with and without gradients), SSIM (the loss's SSIM + L1 sums in float32 with gradients, the metric in float64),
the silhouette losses, the photo-consistency term, the neighbour-smoothness product and the deformation field's
anchor blend (float32, with gradients) compiles exactly the specialisations a run will ask for.
"""

from __future__ import annotations

import time

import numpy as np
import torch

from reconstruction.deformation import blend_anchors
from reconstruction.losses import neighbour_graph, sh_neighbour_loss, silhouette_losses
from reconstruction.photo_consistency import consistency_loss, sample_colors
from reconstruction.render.rasterization import rasterize
from reconstruction.ssim import dssim_l1_sums, ssim_map


def compile_kernels() -> float:
    """Runs every rasterizer mode once on a tiny scene; returns the seconds it took."""
    t0 = time.perf_counter()
    n, w, h = 64, 32, 24
    gen = torch.Generator().manual_seed(0)
    means = torch.randn(n, 3, generator=gen) * 0.1 + torch.tensor([0.0, 0.0, 2.0])
    quats = torch.nn.functional.normalize(torch.randn(n, 4, generator=gen), dim=1)
    scales = torch.full((n, 3), 0.05)
    opacities = torch.full((n,), 0.9)
    viewmats = torch.eye(4).repeat(2, 1, 1)
    ks = torch.tensor([[30.0, 0, w / 2], [0, 30.0, h / 2], [0, 0, 1]]).repeat(2, 1, 1)
    backgrounds = torch.rand(2, 3, generator=gen)
    active = torch.arange(n) % 2 == 0  # splat dropout (the paper preset)
    modes = [(torch.zeros(n, 0), None, None, None)]
    modes += [(torch.rand(n, (d + 1) ** 2, 3, generator=gen), d, bg, None) for d in range(4) for bg in (None, backgrounds)]
    modes += [(torch.rand(n, 16, 3, generator=gen), 3, backgrounds, active)]
    for colors, degree, bg, keep in modes:
        for grad in (False, True):
            m = means.clone().requires_grad_(grad)
            c = colors.clone().requires_grad_(grad)
            rgb, alpha, _ = rasterize(m, quats, scales, opacities, c, viewmats, ks, w, h, sh_degree=degree, backgrounds=bg,
                                      active=keep)
            if grad:
                (rgb.sum() + alpha.sum()).backward()
    image = torch.rand(2, h, w, 3, generator=gen).requires_grad_(True)
    ssim_map(image, torch.rand(2, h, w, 3, generator=gen)).sum().backward()
    ssim_map(image.detach().double(), image.detach().double())  # the evaluation metric's float64 map
    sum(dssim_l1_sums(image, torch.rand(2, h, w, 3, generator=gen))).backward()
    alpha = torch.rand(2, h, w, 1, generator=gen).requires_grad_(True)
    sum(silhouette_losses(alpha, torch.rand(2, h, w, generator=gen), torch.ones(2, h, w, dtype=torch.bool))).backward()
    points = means.clone().requires_grad_(True)
    colors = sample_colors(image.detach(), points, viewmats.clone().requires_grad_(True), ks)
    consistency_loss(colors, torch.ones(2, n)).backward()
    ring = neighbour_graph((np.arange(n)[:, None] + np.array([1, 2])) % n)
    sh_neighbour_loss(torch.rand(n, 9, 3, generator=gen).requires_grad_(True), ring).backward()
    anchors = torch.rand(8, 3, generator=gen).requires_grad_(True)
    blend_anchors(anchors, torch.randint(0, 8, (n, 4), generator=gen), torch.full((n, 4), 0.25)).sum().backward()
    return time.perf_counter() - t0


def main() -> None:
    print(f"rasterizer, loss and deformation kernels compiled and cached in {compile_kernels():.1f} s")


if __name__ == "__main__":
    main()
