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

from reconstruction.render import _cpu_kernels as kernels
from reconstruction.parallel import parallel_for


class Projection(NamedTuple):
    """Per-camera screen-space Gaussians; culled entries are all zero (radii == 0)."""

    means2d: Tensor  # [C, N, 2] float64, pixels (pixel (u, v) is centred at (u + 0.5, v + 0.5))
    conics: Tensor  # [C, N, 3] float64, inverse 2D covariance (a, b, c) = [[a, b], [b, c]]
    depths: Tensor  # [C, N] float64, camera-frame z
    radii: Tensor  # [C, N, 2] int32, opacity-aware half extents of the screen box in x and y


def to_numpy(tensor: Tensor) -> np.ndarray:
    """Zero-copy contiguous numpy view of a CPU tensor, detached from autograd."""
    return tensor.detach().contiguous().numpy()


class _Float64(torch.autograd.Function):
    """float32 -> float64 cast whose gradient comes back in float32, both in numpy.

    The same roundings as `Tensor.to`, but on the calling thread: torch's copy kernel wakes its sleeping OpenMP workers
    for a few ten thousand elements, which cost ~55 us a cast against ~10 us for the copy itself.
    """

    @staticmethod
    def forward(ctx, tensor: Tensor) -> Tensor:
        return torch.from_numpy(tensor.detach().numpy().astype(np.float64))

    @staticmethod
    @once_differentiable
    def backward(ctx, grad: Tensor) -> Tensor:
        return torch.from_numpy(grad.detach().numpy().astype(np.float32))


def to_float64(tensor: Tensor) -> Tensor:
    """`tensor` as float64, differentiably (CPU float32 through numpy, anything else through `Tensor.to`)."""
    if tensor.dtype == torch.float32 and tensor.device.type == "cpu":
        return _Float64.apply(tensor)
    return tensor.to(torch.float64)


class _ProjectGaussians(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means, quats, scales, viewmats, opacities, Ks, active, width, height, near, far, eps2d):
        n_cams, n = viewmats.shape[0], means.shape[0]
        means2d = np.zeros((n_cams, n, 2))
        conics = np.zeros((n_cams, n, 3))
        depths = np.zeros((n_cams, n))
        radii = np.zeros((n_cams, n, 2), np.int32)
        n_chunks = max(1, min(kernels.GAUSSIAN_CHUNKS, n))
        parallel_for(
            kernels.project_forward, n_chunks, n_chunks,
            to_numpy(means), to_numpy(quats), to_numpy(scales), to_numpy(opacities), to_numpy(active),
            to_numpy(viewmats), to_numpy(Ks), width, height, near, far, eps2d,
            means2d, conics, depths, radii,
        )
        means2d_t, conics_t = torch.from_numpy(means2d), torch.from_numpy(conics)
        depths_t, radii_t = torch.from_numpy(depths), torch.from_numpy(radii)
        ctx.mark_non_differentiable(depths_t, radii_t)
        ctx.set_materialize_grads(False)
        ctx.save_for_backward(means, quats, scales, viewmats, Ks, conics_t, radii_t)
        ctx.image_size = (width, height)
        return means2d_t, conics_t, depths_t, radii_t

    @staticmethod
    @once_differentiable
    def backward(ctx, v_means2d, v_conics, _v_depths, _v_radii):
        means, quats, scales, viewmats, Ks, conics, radii = ctx.saved_tensors
        n, n_cams = means.shape[0], viewmats.shape[0]
        v_means2d = np.zeros((n_cams, n, 2)) if v_means2d is None else to_numpy(v_means2d)
        v_conics = np.zeros((n_cams, n, 3)) if v_conics is None else to_numpy(v_conics)
        n_chunks = max(1, min(kernels.GAUSSIAN_CHUNKS, n))
        v_means = np.zeros((n, 3))
        v_quats = np.zeros((n, 4))
        v_scales = np.zeros((n, 3))
        want_viewmats = ctx.needs_input_grad[3]
        v_view_chunks = np.zeros((n_chunks, n_cams, 3, 4))
        parallel_for(
            kernels.project_backward, n_chunks, to_numpy(means), to_numpy(quats), to_numpy(scales),
            to_numpy(viewmats), to_numpy(Ks), *ctx.image_size, to_numpy(radii), to_numpy(conics),
            v_means2d, v_conics, want_viewmats,
            v_means, v_quats, v_scales, v_view_chunks,
        )
        v_viewmats = None
        if want_viewmats:
            v_viewmats = torch.zeros(viewmats.shape, dtype=torch.float64)
            v_viewmats[:, :3, :] = torch.from_numpy(v_view_chunks.sum(axis=0))
        return (
            torch.from_numpy(v_means), torch.from_numpy(v_quats), torch.from_numpy(v_scales), v_viewmats,
            *(None,) * 8,
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

    Returns:
        `Projection` (float64); means2d and conics carry gradients to means, quats, scales and viewmats.
    """
    if not near_plane > 0.0:
        raise ValueError(f"near_plane must be positive, got {near_plane}")
    if active is None:
        active = torch.ones(means.shape[0], dtype=torch.bool)
    return Projection(
        *_ProjectGaussians.apply(
            *(to_float64(t) for t in (means, quats, scales, viewmats, opacities, Ks)),
            active, int(width), int(height), float(near_plane), float(far_plane), float(eps2d),
        )
    )
