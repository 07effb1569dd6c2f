"""CUDA backend: `gsplat.rasterization` in classic, unpacked, pinhole mode (the `[cuda]` extra)."""

from __future__ import annotations

from typing import Any

import torch
from torch import Tensor


def _import_gsplat():
    try:
        import gsplat
    except ImportError as exc:
        raise ImportError("CUDA tensors are rasterized by gsplat, which is not installed: pip install 'cadsplat[cuda]'") from exc
    return gsplat


@torch.no_grad()
def _visibility_counts(gsplat, meta: dict[str, Any], render_alphas: Tensor) -> Tensor:
    """Pixels each Gaussian shaded, [C, N]: gsplat enumerates the contributing (Gaussian, pixel) pairs.

    Every tile's whole list is one range of at most ceil(len / tile_size^2) batches of tile_size^2
    Gaussians, so [0, that + 1) covers everything; transmittances start at 1 for each pixel.
    """
    n_cams, n = meta["radii"].shape[:2]
    offsets = meta["isect_offsets"].flatten()
    ends = torch.cat([offsets[1:], offsets.new_tensor([meta["flatten_ids"].shape[0]])])
    block = meta["tile_size"] ** 2
    n_batches = int(((ends - offsets).max().item() + block - 1) // block) + 1 if offsets.numel() else 1
    gaussian_ids, _, _ = gsplat.rasterize_to_indices_in_range(
        0,
        n_batches,
        torch.ones_like(render_alphas[..., 0]),
        meta["means2d"],
        meta["conics"],
        meta["opacities"],
        meta["width"],
        meta["height"],
        meta["tile_size"],
        meta["isect_offsets"],
        meta["flatten_ids"],
    )
    return torch.bincount(gaussian_ids.long(), minlength=n_cams * n)[: n_cams * n].view(n_cams, n)


def rasterize_gsplat(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    colors: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    *,
    near_plane: float,
    far_plane: float,
    eps2d: float,
    sh_degree: int | None,
    backgrounds: Tensor | None,
    tile_size: int,
    active: Tensor | None,
    visibility_counts: bool = False,
) -> tuple[Tensor, Tensor, dict[str, Any]]:
    """Same contract as `reconstruction.render.rasterize`, on CUDA tensors."""
    gsplat = _import_gsplat()
    if active is not None:
        # Zero opacity is culled exactly like an inactive Gaussian, and passes no gradient to the rest.
        opacities = opacities * active.to(opacities.dtype)
    if backgrounds is not None and backgrounds.dim() == 1:
        backgrounds = backgrounds.expand(viewmats.shape[0], -1)
    # gsplat has no kernel for zero channels: an alphas-only render draws one zero channel and drops it.
    alphas_only = sh_degree is None and colors.shape[-1] == 0
    if alphas_only:
        colors = colors.new_zeros(*colors.shape[:-1], 1)
        backgrounds = None
    render_colors, render_alphas, meta = gsplat.rasterization(
        means,
        quats,
        scales,
        opacities,
        colors,
        viewmats,
        Ks,
        width,
        height,
        near_plane=near_plane,
        far_plane=far_plane,
        eps2d=eps2d,
        sh_degree=sh_degree,
        packed=False,
        tile_size=tile_size,
        backgrounds=backgrounds,
        rasterize_mode="classic",
        camera_model="pinhole",
    )
    if alphas_only:
        render_colors = render_colors[..., :0]
    if visibility_counts:
        meta["visibility_counts"] = _visibility_counts(gsplat, meta, render_alphas)
    meta["n_isects"] = int(meta["flatten_ids"].shape[0])
    meta["n_cameras"] = viewmats.shape[0]
    return render_colors, render_alphas, meta
