"""Projection of 3D Gaussians to screen-space means and conics (gsplat's fused pinhole projection).

Everything runs in float64 whatever the input dtype (the casts are part of the autograd graph, so
gradients come back in the caller's dtype): compositing is exact to 1e-5 only if pixel-space means are
carried to well below a float32 ulp at a few hundred pixels, and a single kernel specialisation keeps
numba's compile time down.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch
from torch import Tensor
from torch.autograd.function import once_differentiable

from reconstruction.parallel import PARTS_PER_THREAD, num_threads, parallel_for
from reconstruction.render import _cpu_kernels as kernels


class TileFootprints(NamedTuple):
    """Where each visible (camera, Gaussian) pair lands on a grid of square tiles: the binning's first pass, which the
    projection kernel does while each splat is in registers (see `_cpu_kernels.project_forward`)."""

    tile_size: int
    two_logs: np.ndarray  # [N] float64, 2 ln(255 opacity) of the drawn Gaussians
    rects: np.ndarray  # [C * N, 4] int32, pixel rect (u_lo, u_hi, v_lo, v_hi) of the alpha >= 1/255 ellipse
    tile_counts: np.ndarray  # [C * N] int64, tiles each pair's rect touches (0: culled)
    hist: np.ndarray  # [n_chunks, C * tiles_per_cam] int64, slots per tile of each chunk of Gaussians


class Projection(NamedTuple):
    """Per-camera screen-space Gaussians; culled entries are all zero (radii == 0)."""

    means2d: Tensor  # [C, N, 2] float64, pixels (pixel (u, v) is centred at (u + 0.5, v + 0.5))
    conics: Tensor  # [C, N, 3] float64, inverse 2D covariance (a, b, c) = [[a, b], [b, c]]
    depths: Tensor  # [C, N] float64, camera-frame z
    radii: Tensor  # [C, N, 2] int32, opacity-aware half extents of the screen box in x and y
    footprints: TileFootprints | None = None  # with a tile size asked for


def to_numpy(tensor: Tensor) -> np.ndarray:
    """Zero-copy contiguous numpy view of a CPU tensor, detached from autograd."""
    return tensor.detach().contiguous().numpy()


class _Float64(torch.autograd.Function):
    """float32 -> float64 casts whose gradients come back in float32, all in numpy, as one graph node.

    The same roundings as `Tensor.to`, but on the calling thread: torch's copy kernel wakes its sleeping OpenMP workers
    for a few ten thousand elements, which costs more than the copy itself; one node for all the rasterizer's inputs
    also spares autograd a node per input each way (benchmarks/results/rasterizer.md).
    """

    @staticmethod
    def forward(ctx, *tensors: Tensor) -> tuple[Tensor, ...]:
        outs = tuple(torch.from_numpy(t.detach().numpy().astype(np.float64)) for t in tensors)
        ctx.mark_non_differentiable(*(o for o, t in zip(outs, tensors) if not t.requires_grad))
        ctx.set_materialize_grads(False)
        return outs

    @staticmethod
    @once_differentiable
    def backward(ctx, *grads: Tensor | None) -> tuple[Tensor | None, ...]:
        return tuple(None if g is None else torch.from_numpy(g.detach().numpy().astype(np.float32)) for g in grads)


def to_float64(*tensors: Tensor) -> tuple[Tensor, ...]:
    """`tensors` as float64, differentiably: CPU float32 ones through numpy in one graph node, float64 ones as they
    are, anything else through `Tensor.to`."""
    cast = [i for i, t in enumerate(tensors) if t.dtype == torch.float32 and t.device.type == "cpu"]
    out = [None if i in cast else t.to(torch.float64) for i, t in enumerate(tensors)]
    for i, t in zip(cast, _Float64.apply(*(tensors[i] for i in cast)) if cast else ()):
        out[i] = t
    return tuple(out)


class _ProjectGaussians(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, scales, viewmats, opacities, Ks, active, width, height, near, far, eps2d, tile_size):
        n_cams, n = viewmats.shape[0], means.shape[0]
        means2d = np.zeros((n_cams, n, 2))
        conics = np.zeros((n_cams, n, 3))
        depths = np.zeros((n_cams, n))
        radii = np.zeros((n_cams, n, 2), np.int32)
        # No sums run across Gaussians here, so the chunks follow the threads (they are the histogram's rows).
        n_chunks = max(1, min(num_threads() * PARTS_PER_THREAD, n))
        footprints = None
        if tile_size:
            tiles = n_cams * -(-width // tile_size) * -(-height // tile_size)
            footprints = TileFootprints(
                tile_size,
                np.empty(n),
                np.empty((n_cams * n, 4), np.int32),
                np.zeros(n_cams * n, np.int64),
                np.zeros((n_chunks, tiles), np.int64),
            )
        parallel_for(
            kernels.project_forward,
            n_chunks,
            n_chunks,
            to_numpy(means),
            to_numpy(quats),
            to_numpy(scales),
            to_numpy(opacities),
            to_numpy(active),
            to_numpy(viewmats),
            to_numpy(Ks),
            width,
            height,
            near,
            far,
            eps2d,
            tile_size or 0,
            means2d,
            conics,
            depths,
            radii,
            *(
                footprints[1:]
                if footprints
                else (np.empty(0), np.empty((0, 4), np.int32), np.empty(0, np.int64), np.empty((n_chunks, 0), np.int64))
            ),
        )
        means2d_t, conics_t = torch.from_numpy(means2d), torch.from_numpy(conics)
        depths_t, radii_t = torch.from_numpy(depths), torch.from_numpy(radii)
        ctx.mark_non_differentiable(depths_t, radii_t)
        ctx.set_materialize_grads(False)
        ctx.save_for_backward(means, quats, scales, viewmats, Ks, conics_t, radii_t)
        ctx.image_size = (width, height)
        return means2d_t, conics_t, depths_t, radii_t, footprints

    @staticmethod
    @once_differentiable
    def backward(ctx, v_means2d, v_conics, _v_depths, _v_radii, _v_footprints):
        means, quats, scales, viewmats, Ks, conics, radii = ctx.saved_tensors
        n, n_cams = means.shape[0], viewmats.shape[0]
        v_means2d = np.zeros((n_cams, n, 2)) if v_means2d is None else to_numpy(v_means2d)
        v_conics = np.zeros((n_cams, n, 3)) if v_conics is None else to_numpy(v_conics)
        n_chunks = max(1, min(kernels.GAUSSIAN_CHUNKS, n))
        v_means = np.zeros((n, 3))
        # Training's quaternions are fixed and its scales learn only in Stage II: without them the covariance's
        # gradient is not formed (benchmarks/results/rig_scenes.md).
        want_cov = ctx.needs_input_grad[1] or ctx.needs_input_grad[2]
        v_quats = np.zeros((n, 4)) if want_cov else np.zeros((0, 4))
        v_scales = np.zeros((n, 3)) if want_cov else np.zeros((0, 3))
        want_viewmats = ctx.needs_input_grad[3]
        v_view_chunks = np.zeros((n_chunks, n_cams, 3, 4))
        parallel_for(
            kernels.project_backward,
            n_chunks,
            to_numpy(means),
            to_numpy(quats),
            to_numpy(scales),
            to_numpy(viewmats),
            to_numpy(Ks),
            *ctx.image_size,
            to_numpy(radii),
            to_numpy(conics),
            v_means2d,
            v_conics,
            want_cov,
            want_viewmats,
            v_means,
            v_quats,
            v_scales,
            v_view_chunks,
        )
        v_viewmats = None
        if want_viewmats:
            v_viewmats = torch.zeros(viewmats.shape, dtype=torch.float64)
            v_viewmats[:, :3, :] = torch.from_numpy(v_view_chunks.sum(axis=0))
        return (
            torch.from_numpy(v_means),
            torch.from_numpy(v_quats) if want_cov else None,
            torch.from_numpy(v_scales) if want_cov else None,
            v_viewmats,
            *(None,) * 9,
        )


def project_gaussians(
    means: Tensor,
    quats: Tensor,
    scales: Tensor,
    opacities: Tensor,
    viewmats: Tensor,
    Ks: Tensor,
    width: int,
    height: int,
    *,
    near_plane: float = 0.01,
    far_plane: float = 1e10,
    eps2d: float = 0.3,
    active: Tensor | None = None,
    tile_size: int | None = None,
) -> Projection:
    """Projects Gaussians into pinhole cameras, as gsplat's `fully_fused_projection` (unpacked).

    Covariance R S S^T R^T from wxyz quaternions (normalised here) and linear scales; the perspective
    Jacobian clamps x/z and y/z to the image plus 30% of the half field of view; eps2d is added to the
    2D covariance. A Gaussian is culled (radii 0) when its depth is not in (near, far), the 2D
    determinant is <= 0, its opacity is < 1/255, it is inactive, or its box misses the image. The box
    is gsplat 1.5.3's opacity-aware one: radius_x = ceil(sqrt(2 ln(255 opacity)) sqrt(cov2d_xx)).

    Args:
        means: [N, 3] world positions.
        quats: [N, 4] wxyz rotations, any norm.
        scales: [N, 3] linear scales.
        opacities: [N] in [0, 1] (used for culling and the box only; no gradient flows here).
        viewmats: [C, 4, 4] world-to-camera (OpenCV axes).
        Ks: [C, 3, 3] intrinsics (no gradient).
        width, height: image size in pixels.
        near_plane, far_plane, eps2d: as in gsplat.
        active: optional [N] bool; inactive Gaussians are culled without copying anything.
        tile_size: with a tile edge in pixels, also the `TileFootprints` the rasterizer's binning starts from.

    Returns:
        `Projection` (float64; five fields, `footprints` last and None without a tile size); means2d and conics
        carry gradients to means, quats, scales and viewmats.
    """
    if not near_plane > 0.0:
        raise ValueError(f"near_plane must be positive, got {near_plane}")
    if tile_size is not None and not tile_size >= 1:
        raise ValueError(f"tile_size must be at least 1, got {tile_size}")
    if active is None:
        active = torch.ones(means.shape[0], dtype=torch.bool)
    return Projection(
        *_ProjectGaussians.apply(
            *to_float64(means, quats, scales, viewmats, opacities, Ks),
            active,
            int(width),
            int(height),
            float(near_plane),
            float(far_plane),
            float(eps2d),
            int(tile_size or 0),
        )
    )
